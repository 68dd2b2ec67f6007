"""bench/quality.py without synthesis: its bad-input errors, its figures from a fabricated report, and its block
in a RESULTS file."""

import subprocess
import sys

import pytest

from paths import REPO, bench_script

SCRIPT = REPO / "bench" / "quality.py"


@pytest.fixture(scope="module")
def quality():
    return bench_script("quality")


def _record(obj, valid, E, order, tested, physics, force_closure, contact_dist=None, warm=True):
    n = len(valid)
    return {"object": obj, "group": "builtin", "row": "cvae", "sampler": "cvae", "warm": warm, "n": n,
            "valid": valid, "order": order, "tested": tested, "E": E, "E_g": [e / 10 for e in E],
            "E_c": [0.001] * n, "penetration": [0.002] * n, "epsilon": [0.0] * n, "force_closure": force_closure,
            "n_contacts": None, "contact_dist": contact_dist, "score": None, "physics": physics,
            "wall_s": 2.0 if warm else 50.0, "synthesis_s": 0.5, "compile_s": 0.0 if warm else 45.0,
            "physics_s": 1.0 if tested else 0.0}


def fabricated_report(contact_dist=None):
    # object a: valid 0, 2, 3; order by E puts 2 (E 0.3) first; its two best are tested, the first passes both
    a = _record("a", [True, False, True, True], [0.5, 0.1, 0.3, 0.9], [2, 0, 3, 1], [2, 0],
                {"lift_shake_success": [True, True], "six_dir_success": [True, False]},
                [True, True, False, False], contact_dist, warm=False)
    # object b: nothing valid, so nothing tested and its top-1 fails
    b = _record("b", [False] * 4, [1.0, 2.0, 3.0, 4.0], [0, 1, 2, 3], [], {}, [False] * 4,
                None if contact_dist is None else [[0.0] * 5] * 4)
    conf = {"command": "python bench/quality.py --n 4", "n": 4, "seed": 0, "friction": 0.6,
            "protocols": ["lift-shake", "six-dir"], "physics_backend": "cpu", "max_grasps_per_object": 2,
            "contact_tol": 0.002, "group_counts": {"builtin": 2},
            "machine": {"backend": "cpu", "device": "cpu", "device_count": 1, "cpus": 2, "date": "2026-01-01"}}
    return {"config": conf, "records": [a, b]}


def test_figures_of_a_fabricated_report(quality):
    (s,) = quality.summarise(fabricated_report())
    assert s["valid"] == (3, 8)
    assert s["fc"] == (1, 3)  # returned grasps of a are 2, 0, 3: only 0 is in force closure
    assert s["all_touch"] is None  # no contact_dist: the figure is absent, not zero
    assert s["E"] == pytest.approx(0.5)  # pooled median of the returned E 0.3, 0.5, 0.9
    assert s["t2_E"] == pytest.approx((0.45 + 2.5) / 2)  # fewer than 20 poses: mean of all, median over objects
    assert s["success"] == {"lift-shake": (2, 2), "six-dir": (1, 2)}
    assert s["both"] == (1, 2) and s["top1"] == (1, 2) and s["top1_none"] == 1
    assert s["yield"] == (1, 2)  # n / 4 = 1 returned grasp: a has 3, b none
    assert s["wall_s"] == pytest.approx(2.0)  # the compiling first call is left out
    table = quality.table(fabricated_report())
    row = next(ln for ln in table.splitlines() if ln.startswith("| cvae |"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[2] == "37.5 % (3/8)"
    assert cells[3] == "1 / 3 = 33.3 % (6-79 %)"
    assert cells[8] == "1 / 2 = 50.0 % (9-91 %)"
    assert "(cvae: 1)" in table  # the object without a valid grasp is named in the footnote
    per = quality.per_object_table(fabricated_report())
    assert "| a | cvae | 3/4 | 2 of 3 | 1/2 | yes |" in per
    assert "| b | cvae | 0/4 | 0 of 0 | 0/0 | no valid grasp |" in per


def test_the_validated_first_grasp_is_the_first_that_passes_both(quality):
    """Object c: the analytic first (grasp 1, lowest E) fails six-dir, grasp 3 passes both and dexgraspbench: the
    validated ranking offers 3. Object a's first passes both already; b has no valid grasp: a failure either way."""
    rep = fabricated_report()
    rep["config"]["protocols"] = ["lift-shake", "six-dir", "dexgraspbench"]
    rep["config"]["max_grasps_per_object"] = 0
    a, b = rep["records"]
    a["physics"]["dexgraspbench_success"] = [False, True]
    c = _record("c", [False, True, True, True], [0.1, 0.2, 0.3, 0.4], [1, 2, 3, 0], [1, 2, 3],
                {"lift_shake_success": [True, False, True], "six_dir_success": [False, True, True],
                 "dexgraspbench_success": [True, False, True]}, [True] * 4)
    rep["records"].append(c)
    assert quality.validated_first(c) == (3, {"lift_shake": True, "six_dir": True, "dexgraspbench": True})
    assert quality.validated_first(a)[0] == 2 and quality.validated_first(b) == (None, {})
    row = next(ln for ln in quality.validated_table(rep).splitlines() if ln.startswith("| cvae |"))
    cells = [x.strip() for x in row.strip("|").split("|")]
    assert cells[1] == "3"
    assert cells[2].startswith("1 / 3") and cells[3].startswith("2 / 3")  # both: analytic a; validated a and c
    assert cells[4].startswith("1 / 3") and cells[5].startswith("1 / 3")  # dexgraspbench: analytic c; validated c
    rep["config"]["protocols"] = ["six-dir"]
    assert quality.validated_table(rep) == ""  # without both protocols there is no validated ranking to show


def test_all_tips_touching_uses_the_tolerance(quality):
    dist = [[0.001, -0.0015, 0.0, 0.0, 0.0], [0.01] * 5, [0.0] * 5, [0.0, 0.0, 0.0, 0.0, -0.003]]
    (s,) = quality.summarise(fabricated_report(dist))
    assert s["all_touch"] == (2, 3)  # returned 2 and 0 touch within 2 mm; 3 has a tip 3 mm inside


def test_results_block_is_replaced_not_duplicated(quality, tmp_path):
    path = tmp_path / "RESULTS.md"
    path.write_text("# Results\n\nkept\n")
    quality.write_results(path, "first")
    path.write_text(path.read_text() + "after\n")
    quality.write_results(path, "second")
    text = path.read_text()
    assert text.count(quality.BEGIN) == 1 and text.count(quality.END) == 1
    assert "second" in text and "first" not in text
    assert text.startswith("# Results\n\nkept\n") and text.endswith("after\n")
    quality.write_results(path, "allegro first", "allegro")  # another hand: a block of its own
    quality.write_results(path, "allegro second", "allegro")
    text = path.read_text()
    assert "second" in text and "allegro second" in text and "allegro first" not in text
    assert text.count(quality.markers("allegro")[0]) == 1
    assert list(tmp_path.iterdir()) == [path]  # no temp file left behind


@pytest.mark.parametrize("argv, message", [
    (["--objects", "builtin,nope"], "--objects: unknown group(s) nope"),
    (["--objects", "ycb-test", "--ycb", "/no/such/folder"], "--ycb: no such folder"),
    (["--n", "0"], "argument --n: must be >= 1"),
    (["--friction", "abc"], "argument --friction: expected a number"),
    (["--samplers", "cvae,magic"], "unknown sampler(s) magic"),
])
def test_bad_input_is_one_line_and_exit_2(quality, capsys, argv, message):
    with pytest.raises(SystemExit) as e:
        quality.parse_args(["--objects", "builtin", *argv])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("quality.py: error: ") and message in err[0]


def test_bad_input_from_the_shell_has_no_traceback():
    r = subprocess.run([sys.executable, str(SCRIPT), "--objects", "spheres"], capture_output=True, text=True,
                       timeout=60, cwd=REPO)
    assert r.returncode == 2 and r.stdout == ""
    assert r.stderr.startswith("quality.py: error: --objects: unknown group(s) spheres") and "Traceback" not in r.stderr
