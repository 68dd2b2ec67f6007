"""bench/depth.py: its bad-input errors, its figures from a fabricated report, its RESULTS block, and tiny runs."""

import json
import subprocess
import sys

import pytest

from paths import REPO, bench_script

SCRIPT = REPO / "bench" / "depth.py"


@pytest.fixture(scope="module")
def depth():
    return bench_script("depth")


def _rec(obj, condition, tested=(), ls=(), sd=(), valid=2, surface=None, error=None):
    return {"object": obj, "group": "builtin", "condition": condition, "views": None, "noise": False,
            "error": error, "surface": surface, "fuse_s": None if surface is None else 0.1, "table_err_mm": None,
            "n": 4, "valid": valid, "tested": list(tested),
            "physics": {"lift_shake_success": list(ls), "six_dir_success": list(sd)} if tested else {},
            "filters": {"not all tips touching": 1, "no force closure": 0, "median |tip distance| mm": 0.5},
            "wall_s": 1.0, "compile_s": 0.0, "physics_s": 2.0 if tested else 0.0}


def _surf(med, p95, h=0.004):
    return {"median_vox": med, "p95_vox": p95, "median_mm": 1000 * h * med, "p95_mm": 1000 * h * p95,
            "voxel_mm": 1000 * h}


def _report():
    recs = [_rec("a", "mesh", [0, 1], [True, True], [True, False]),  # 1 of 2 passes both, the first: top-1 ok
            _rec("b", "mesh", [2], [True], [True]),
            _rec("a", "5 views, noisy", [3, 1], [False, True], [True, True], surface=_surf(0.2, 1.0)),
            _rec("b", "5 views, noisy", error="no table found", valid=0),  # a failed fusion fails its top-1
            ]
    conf = {"mode": "accuracy", "command": "python bench/depth.py --n 4", "protocols": ["lift-shake", "six-dir"],
            "physics": "on", "physics_backend": "cpu", "friction": 0.6, "max_grasps_per_object": 0, "width": 640,
            "height": 480, "res": 32, "sampler": "cvae", "n": 4, "seed": 0, "group_counts": {"builtin": 2},
            "filter_mesh": "true",
            "machine": {"backend": "cpu", "device": "cpu", "device_count": 1, "cpus": 2, "date": "2026-01-01"}}
    return {"config": conf, "records": recs}


def test_figures_of_a_fabricated_report(depth):
    mesh, fused = depth.summarise(_report())
    assert mesh["both"] == (2, 3) and mesh["top1"] == (2, 2) and mesh["success"]["six-dir"] == (2, 3)
    assert fused["failed"] == 1 and fused["both"] == (1, 2) and fused["top1"] == (0, 2)
    assert fused["surface"]["median_vox"] == pytest.approx(0.2) and fused["worst_p95_vox"] == pytest.approx(1.0)
    table = depth.table(_report())
    row = next(ln for ln in table.splitlines() if ln.startswith("| 5 views, noisy |"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[1] == "2 (1)" and cells[8] == "-16.7 pp"  # 50 % against the mesh row's 66.7 %
    assert "Target, 5 noisy views within 5 pp of mesh-planned: -16.7 pp, not met." in table
    assert "failed: no table found" in depth.per_object_table(_report())


def test_results_block_is_replaced_not_duplicated(depth, tmp_path):
    path = tmp_path / "RESULTS.md"
    path.write_text("# Results\n\nkept\n")
    depth.write_results(path, "depth", "first")
    depth.write_results(path, "depth-speed", "speed")
    depth.write_results(path, "depth", "second")
    text = path.read_text()
    assert text.count("<!-- depth:begin -->") == 1 and "second" in text and "first" not in text and "speed" in text


@pytest.mark.parametrize("argv, message", [
    (["--objects", "builtin,nope"], "--objects: unknown group(s) nope"),
    (["--objects", "builtin", "--views", "1,x"], "--views: expected a comma list of integers >= 1"),
    (["--objects", "builtin", "--noise", "loud"], "--noise: expected a comma list of off, on"),
    (["--objects", "builtin", "--scene", "room"], "--scene: expected a comma list of plane, table, clutter"),
    (["--speed", "--object", "no_such_thing"], "--object: neither a built-in"),
    (["--res", "8"], "argument --res: must be >= 16"),
])
def test_bad_input_is_one_line_and_exit_2(depth, capsys, argv, message):
    with pytest.raises(SystemExit) as e:
        depth.parse_args(argv)
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("depth.py: error: ") and message in err[0]


def _run(tmp_path, *argv):
    out = tmp_path / "d.json"
    r = subprocess.run([sys.executable, str(SCRIPT), *argv, "--json", str(out), "--results", str(tmp_path / "R.md")],
                       capture_output=True, text=True, timeout=600, cwd=REPO)
    assert r.returncode == 0, r.stderr[-2000:]
    return r.stdout, json.loads(out.read_text()), (tmp_path / "R.md").read_text()


@pytest.mark.e2e  # the depth benchmark script end to end
def test_speed_on_tiny_frames(tmp_path):
    out, report, md = _run(tmp_path, "--speed", "--width", "80", "--height", "60", "--repeats", "1", "--points", "200")
    steps = [r["step"] for r in report["records"]]
    assert "tsdf.integrate" in steps and any(s.startswith("open3d") for s in steps)
    fuse = next(r for r in report["records"] if r["step"].startswith("tsdf.fuse"))
    assert fuse["median_ms"] > 0 and fuse["surface"]["median_vox"] < 2
    assert "<!-- depth-speed-cpu:begin -->" in md and "| tsdf.integrate |" in out


@pytest.mark.slow  # compiles the synthesis (a minute on a 2-core CPU)
def test_accuracy_on_tiny_frames_without_physics(tmp_path):
    out, report, md = _run(tmp_path, "--objects", "builtin", "--only", "box", "--views", "3", "--noise", "on",
                           "--width", "80", "--height", "60", "--n", "2", "--physics", "off", "--points", "200")
    assert [r["condition"] for r in report["records"]] == ["mesh", "3 views, noisy"]
    assert report["records"][1]["surface"]["median_vox"] < 1
    assert "| 3 views, noisy | 1 (0) |" in out and "no physics" in md
