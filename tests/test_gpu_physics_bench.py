"""bench/gpu_physics.py: its refusal of bad arguments, its tables from fabricated rows, and a smoke run end to end."""

import json
import subprocess
import sys

import pytest

from paths import REPO, bench_script

SCRIPT = REPO / "bench" / "gpu_physics.py"


@pytest.fixture(scope="module")
def bench():
    return bench_script("gpu_physics")


@pytest.mark.parametrize("argv, message", [
    (["--parts", "1,5"], "--parts: expected a comma list of 1, 2, 3, 4"),
    (["--batches", "1,x"], "expected comma lists of integers"),
    (["--objects", "2", "--cpu-objects", "3"], "--cpu-objects (3) must not exceed --objects (2)"),
    (["--grasps", "16", "--latency-grasps", "32"], "--latency-grasps (32) must not exceed --grasps (16)"),
    (["--protocols", "lift-shake,wobble"], "unknown protocol 'wobble'"),
    (["--first-n", "0"], "--first-n must be between 1 and 100000"),
])
def test_bad_input_is_one_line_and_exit_2(bench, capsys, argv, message):
    with pytest.raises(SystemExit) as e:
        bench.parse_args(argv)
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("gpu_physics.py: error: ") and message in err[0]


def test_smoke_sizes_fill_only_what_was_not_given(bench):
    a = bench.parse_args(["--smoke", "--grasps", "3"])
    assert a.grasps == 3 and a.objects == bench.SMOKE["objects"] and a.parts == [1, 2, 3, 4]
    assert bench.parse_args([]).batches == [1, 8, 32]


def test_nominal_steps_are_the_programmes_lengths(bench):
    from ffcgs_jax.physics.config import PhysicsConfig

    cfg = PhysicsConfig(timestep=0.004, close_time=0.2, settle_time=0.1, push_time=0.2)
    close = 50 + 25
    assert bench.nominal_steps("six-dir", cfg, 9) == close + 6 * 50
    assert bench.nominal_steps("lift-shake", cfg, 9) > close
    assert bench.nominal_steps("dexgraspbench", cfg, 9) > 6 * 50  # its own 2 s pushes, whatever cfg's push_time


def test_part3_table_counts_the_first_round_once(bench):
    rows = [{"backend": "warp", "object": "a", "geometry": 0.5, "whole": 2.0, "upload": 0.6, "setup": 0.5,
             "simulation": 1.2, "copy_back": 0.1, "other": 0.1, "objects_uploaded": 1, "engines": 1},
            {"backend": "warp", "object": "b", "geometry": 0.7, "whole": 3.0, "upload": 0.2, "setup": 0.1,
             "simulation": 2.0, "copy_back": 0.1, "other": 0.1, "objects_uploaded": 0, "engines": 1},
            {"backend": "cpu", "object": "a", "geometry": 0.4, "whole": 1.0, "simulation": 0.6, "other": 0.0}]

    class B:
        args = bench.parse_args(["--latency-objects", "2"])
        no_gpu = None

    md = bench.table3(rows, B)

    def line(label):
        row = next(x for x in md.splitlines() if x.startswith(f"| {label}"))
        return [c.strip() for c in row.split("|")[2:-1]]

    assert line("geometry") == ["0.600", "0.700", "0.400", "0.400"]
    assert line("upload") == ["0.400", "0.600", "-", "-"]
    assert line("**whole call**") == ["2.500", "3.000", "1.000", "1.000"]
    assert "objects uploaded per call: [0, 1]" in md


def test_table2_without_the_gpu_engine_keeps_the_cpu_columns(bench):
    row = {"protocols": "six-dir", "objects": 4, "cpu_objects": 1, "grasps": 8, "cpu_wall_s": 2.0,
           "cpu_geometry_s": 0.5, "cpu_gps": 4.0, "cpu_wall_scaled_s": 8.0, "cpu_pass": 0.25}

    class B:
        args = bench.parse_args(["--objects", "4", "--cpu-objects", "1"])
        cores, no_gpu = 2, "no CUDA device"

    md = bench.table2([row], B)
    assert "| six-dir | - | - | - | - | 4.00 | 8.0 | - | - | 25.0 % | - |" in md
    assert "No GPU engine: no CUDA device." in md


@pytest.mark.slow  # compiles the synthesis and runs Warp on the CPU: 2-3 minutes on a 2-core CPU
def test_smoke_run_prints_every_table(tmp_path):
    out = tmp_path / "gpu.json"
    r = subprocess.run([sys.executable, str(SCRIPT), "--smoke", "--out", str(out)], capture_output=True, text=True,
                       timeout=600, cwd=REPO)
    assert r.returncode == 0, r.stderr[-3000:]
    text = r.stdout
    assert text.startswith("machine: ") and " cores (" in text.splitlines()[0]
    for head in ("### 1. World-steps per second", "### 2. Labelled grasps per second", "### 3. Checking 1 grasps",
                 "### 4. New object to a physics-checked first grasp"):
        assert head in text
    report = json.loads(out.read_text())
    assert sorted(report["parts"]) == ["1", "2", "3", "4"]
    part2 = report["parts"]["2"]["rows"]
    assert [x["protocols"] for x in part2] == ["lift-shake", "six-dir", "lift-shake+six-dir"]
    assert all(x["cpu_gps"] > 0 for x in part2)
    if report["machine"]["engine_device"] != "none":  # Warp installed: the engine's rows beside the CPU's
        gpu = [x for x in report["parts"]["1"]["rows"] if "world_steps" in x]
        assert gpu and all(x["world_steps"] >= x["busy_steps"] > 0 for x in gpu)
        assert all(x["gpu_gps"] > 0 for x in part2)
    assert {x["backend"] for x in report["parts"]["4"]["rows"]} == {"auto", "cpu"}
