"""`ffcgs grasp` as a user runs it: table printed, npz / MCAP / PNG written; bad input refused with one line, exit 2.

The successful run uses the same settings as tests/synthesis/test_grasp.py's box run, so in one session it reuses that
compiled executable.
"""

import contextlib
import io
import re

import numpy as np
import pytest
from PIL import Image

from ffcgs_jax.cli import main as cli_main
from ffcgs_jax.evaluation.ranking import ranked
from ffcgs_jax.synthesis import grasp_io

from mcap_checks import check_run_log

N, ITERS = 4, 5
SMALL = ["--n", str(N), "--iters", str(ITERS), "--res", "16"]


def run(capsys, *argv):
    code = cli_main.main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture(scope="module")
def outputs(tmp_path_factory):
    d = tmp_path_factory.mktemp("grasp")
    paths = {k: d / f"g.{k}" for k in ("npz", "mcap", "png")}
    out, err = io.StringIO(), io.StringIO()  # module scope has no capsys: capture by hand
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = cli_main.main(["grasp", "box", *SMALL, "--out", str(paths["npz"]), "--mcap", str(paths["mcap"]),
                         "--png", str(paths["png"])])
    return code, out.getvalue(), err.getvalue(), paths


@pytest.mark.e2e  # the module's `ffcgs grasp` run: 70 s of compile on the 2-core CPU
def test_grasp_succeeds_and_prints_the_summary(outputs):
    code, out, err, paths = outputs
    assert code == 0, err
    line = next(l for l in out.splitlines() if l.startswith("grasps (valid / sampled)"))
    assert re.search(rf"\b\d+ / {N}$", line), line
    for p in paths.values():
        assert p.is_file() and f"wrote {p}" in out


@pytest.mark.e2e  # the module's `ffcgs grasp` run: 70 s of compile on the 2-core CPU
def test_grasp_npz(outputs):
    a = grasp_io.load_npz(outputs[3]["npz"])
    assert a["wrist_pose"].shape == (N, 4, 4) and a["q"].shape == (N, 9) and a["contacts"].shape == (N, 5, 3)
    assert str(a["object_name"]) == "box"
    line = next(l for l in outputs[1].splitlines() if l.startswith("grasps (valid / sampled)"))
    assert line.split()[-3] == str(int(a["valid"].sum()))
    # the whole call's parts: an SDF was built, and the total holds the device and the evaluation
    assert float(a["sdf_s"]) > 0 and float(a["evaluation_s"]) > 0
    assert float(a["total_s"]) >= float(a["sdf_s"]) + float(a["synthesis_s"]) + float(a["evaluation_s"])
    assert re.search(r"whole call \(s\)\s+\d+\.\d+ \(SDF \d", outputs[1])


@pytest.mark.e2e  # the module's `ffcgs grasp` run: 70 s of compile on the 2-core CPU
def test_grasp_mcap(outputs):
    """The log of a real run plays in Foxglove: scene, transforms, hands and /energy on a real timeline
    (mcap_checks.check_run_log), and its numbers are the run's."""
    a = grasp_io.load_npz(outputs[3]["npz"])
    order = ranked(a)  # GraspSet.order: by predicted success, as the run ranked them
    msgs = check_run_log(outputs[3]["mcap"], a, order, ITERS + 1)
    assert {k: len(v) for k, v in msgs.items()} == {"/config": 1, "/scene": 1, "/tf": 1, "/energy": ITERS + 1,
                                                     "/grasp": N, "/summary": 1, **{f"/hand/{k}": 1 for k in range(4)}}
    assert all(len(m["E"]) == N for m in msgs["/energy"])
    np.testing.assert_allclose(msgs["/energy"][-1]["E"], a["E"], rtol=1e-15)
    for i, m in enumerate(msgs["/grasp"]):
        np.testing.assert_allclose(np.asarray(m["wrist_pose"]), a["wrist_pose"][i], rtol=1e-15)
        assert m["valid"] == bool(a["valid"][i])
    assert "svh" in msgs["/config"][0]["hand"] and msgs["/config"][0]["config"]["optim"]["iters"] == ITERS
    assert msgs["/summary"][0]["grasps (valid / sampled)"].endswith(f"/ {N}")


@pytest.mark.e2e  # the module's `ffcgs grasp` run: 70 s of compile on the 2-core CPU
def test_grasp_png(outputs):
    img = np.asarray(Image.open(outputs[3]["png"]).convert("RGB"))
    assert img.shape[0] >= 64 and img.shape[1] >= 64
    assert img.std() > 10  # a picture, not a blank canvas


def _poses_file(tmp_path, array):
    p = tmp_path / "poses.npy"
    np.save(p, array)
    return str(p)


def _nan_poses():
    a = np.tile(np.eye(4), (2, 1, 1))
    a[1, 2, 3] = np.nan
    return a


@pytest.mark.parametrize("make_argv, message", [
    (lambda t: ["grasp", "/no/such/mesh.stl"], "mesh.stl"),
    (lambda t: ["grasp", "nonexistent_thing"], "nonexistent_thing"),
    (lambda t: ["grasp", "box", "--n", "0"], r"n must be an integer in \[1, 1000000\]"),
    (lambda t: ["grasp", "box", "--sampler", "learned"], "invalid choice 'learned' for argument '--sampler'"),
    (lambda t: ["grasp", "box", "--poses", _poses_file(t, _nan_poses())], "NaN"),
    (lambda t: ["grasp", "box", "--poses", _poses_file(t, np.zeros((2, 3, 4)))], r"shape \(4, 4\) or \(B, 4, 4\)"),
    (lambda t: ["grasp", "box", "--poses", str(t / "missing.npy")], "pose file not found"),
], ids=["missing-mesh", "unknown-object", "n-0", "unknown-sampler", "nan-poses", "wrong-shape", "missing-poses"])
def test_bad_input_is_one_line_exit_2(capsys, tmp_path, make_argv, message):
    code, out, err = run(capsys, *make_argv(tmp_path))
    assert code == 2
    assert err.startswith("ffcgs: error:") and err.count("\n") == 1, err
    assert re.search(message, err), err


def test_unknown_optim_key_in_config_file(capsys, tmp_path):
    cfg = tmp_path / "c.toml"
    cfg.write_text("[grasp.optim]\niters = 5\nlearning_rate = 0.1\n")
    code, _, err = run(capsys, "grasp", "box", "--config", str(cfg))
    assert code == 2 and err.count("\n") == 1
    assert "unknown config key(s) grasp.optim.learning_rate" in err and "lr" in err
