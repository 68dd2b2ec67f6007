"""`ffcgs bench`: the report it measures, the Markdown block, and how it updates bench/RESULTS.md."""

import json

import pytest

from ffcgs_jax.cli import benchmark
from ffcgs_jax.cli.main import main


@pytest.mark.e2e  # ffcgs bench end to end
def test_bench_command_measures_and_writes_its_block(tmp_path, capsys):
    results, js = tmp_path / "RESULTS.md", tmp_path / "r.json"
    results.write_text("# Benchmark results\n\nEarlier sections stay.\n")
    # the settings of test_cli_grasp's run: in one session the two share a compiled executable
    argv = ["bench", "--object", "box", "--res", "16", "--iters", "5", "--batches", "4", "--lp-solvers", "jax",
            "--repeats", "3", "--no-cli-start", "--results", str(results), "--json", str(js)]
    assert main(argv) == 0
    report = json.loads(js.read_text())
    (row,) = report["rows"]
    assert (row["solver"], row["batch"], row["devices"]) == ("jax", 4, 1)
    assert 0 < row["min_s"] <= row["median_s"] and row["compile_s"] > 0 and 0 <= row["lp_ok"] <= 1
    assert row["with_eval_s"] > 0  # the device part and its evaluation (the evaluation alone is tiny at B = 4)
    assert report["machine"]["backend"] == "cpu" and report["machine"]["versions"]["jax"] != "-"
    assert report["cli"] is None
    w = report["whole"]  # the whole call, in parts: each part took time and the total holds them
    assert (w["batch"], w["faces"], w["object"]) == (4, 12, "box")
    for kind in ("first", "cached"):
        t = w[kind]
        assert min(t["synthesis_s"], t["evaluation_s"]) > 0 and t["wall_s"] >= 0.95 * t["total_s"]
        assert t["total_s"] >= 0.95 * (t["sdf_s"] + t["synthesis_s"] + t["evaluation_s"])  # medians of each
    assert w["cached"]["sdf_s"] < w["first"]["sdf_s"]  # the grid came from the cache
    text = results.read_text()
    assert "Whole call, `box` (12 faces) to 4 ranked" in text and "| grid cached |" in text
    assert text.startswith("# Benchmark results\n\nEarlier sections stay.\n")
    key = benchmark.machine_key(report["machine"])
    assert text.count(f"<!-- ffcgs bench: {key} -->") == 1
    assert f"| jax | 1 | 4 | {row['compile_s']:.1f} | {row['median_s'] * 1e3:.1f} |" in text
    assert report["command"] == ("ffcgs bench --object box --res 16 --iters 5 --batches 4 --lp-solvers jax "
                                 "--repeats 3 --no-cli-start")
    assert "wrote" in capsys.readouterr().out


def _report(device="H100", medians=(0.010, 0.0055)):
    machine = {"backend": "gpu", "device": device, "device_count": 2, "host_cpu": "x", "host_cores": 16,
               "versions": {"jax": "0.11"}, "date": "2026-11-21"}
    rows = [{"solver": "jax", "batch": 65536, "devices": d, "compile_s": 40.0, "median_s": m, "min_s": m,
             "lp_ok": 1.0} for d, m in zip((1, 2), medians)]
    params = {"object": "mug", "res": 32, "sampler": "cvae", "iters": 50, "repeats": 5, "latency_batch": 32}
    return {"command": "ffcgs bench", "machine": machine, "params": params, "rows": rows, "cli": None}


def test_results_block_is_replaced_per_machine_and_others_kept(tmp_path):
    path = tmp_path / "RESULTS.md"
    benchmark.write_results(path, _report())
    benchmark.write_results(path, _report(device="H200", medians=(0.010, 0.008)))
    benchmark.write_results(path, _report(medians=(0.010, 0.004)))  # H100 again: its block is replaced
    text = path.read_text()
    assert text.count("<!-- ffcgs bench: gpu · H100 × 2 -->") == 1
    assert text.count("<!-- ffcgs bench: gpu · H200 × 2 -->") == 1
    assert "2 devices run 2.50× as fast as one" in text and "1.82×" not in text and "1.25×" in text
    assert text.count(benchmark.SECTION) == 1
    assert text.index("H100 × 2 -->") < text.index("H200 × 2 -->")  # replaced in place, not moved to the end


def test_scaling_line_is_the_ratio_of_medians():
    md = benchmark.markdown(_report(medians=(0.010, 0.0055)))
    assert "Scaling at B = 65536: 2 devices run 1.82× as fast as one." in md
    assert "| jax | 2 | 65536 | 40.0 | 5.5 | 5.5 | 11,915,636 | - | - | 1.000 |" in md  # no evaluation timed


@pytest.mark.parametrize("argv, message", [
    (["--lp-solvers", "highs"], "unknown LP solver 'highs'; solvers: jax, proxsuite"),
    (["--batches", "0"], "--batches must be integers in [1, 1000000], got 0"),
    (["--backend", "tpu"], "--backend must be default, cpu or gpu, got 'tpu'"),
    (["--devices", "1", "64", "--object", "box"], "--devices 64 asked for, but this machine has 1 cpu device(s)"),
    (["--sampler", "grid"], "unknown sampler 'grid'"),
])
def test_bad_options_exit_2_with_one_line(argv, message, capsys):
    assert main(["bench", *argv]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err


def test_failed_cli_run_is_reported_by_its_exception_line():
    stderr = ("Traceback (most recent call last):\n  File x\nRuntimeError: Unable to initialize backend 'rocm'\n"
              "--------------------\nFor simplicity, JAX has removed its internal frames from the traceback.\n")
    assert benchmark.last_error(stderr) == "RuntimeError: Unable to initialize backend 'rocm'"
    assert benchmark.last_error("ffcgs: error: object not found: cup\n") == "ffcgs: error: object not found: cup"
    assert benchmark.last_error("just a line\n") == "just a line"


@pytest.mark.slow
def test_cli_start_cold_then_warm(tmp_path):
    """The second process loads the first one's executables: it compiles much less."""
    c = benchmark.cli_start("box", 2, "cpu", n=2)
    assert c["cold"]["compile_s"] > 2 * c["warm"]["compile_s"] and c["warm"]["wall_s"] < c["cold"]["wall_s"]
