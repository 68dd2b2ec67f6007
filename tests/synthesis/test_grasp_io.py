"""Grasp files: the .npz round trip and the MCAP log, read back with the `mcap` library and checked against the
JSON Schemas stored in it and against what Foxglove needs (schema names, scene entities, transforms, timeline).
Uses a synthetic GraspSet with the dtypes `grasp.finish` writes (no compilation here; tests/cli/test_cli_grasp.py
checks the files of a real run)."""

import dataclasses
import json

import numpy as np
import pytest

from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.synthesis import grasp_io
from ffcgs_jax.viz import grasp_log
from ffcgs_jax.synthesis.config import EnergyConfig, OptimConfig
from ffcgs_jax.synthesis.grasp import GraspConfig, GraspSet

from mcap_checks import check_run_log, read_timed, schema_errors

G_, T, C, Q = 3, 4, 5, 9
CFG = GraspConfig(n=G_, seed=7, energy=EnergyConfig(d0=0.005, a_c=4.0), optim=OptimConfig(iters=T))
SUMMARY = [("grasps (valid / sampled)", "2 / 3"), ("median E", "0.25")]


def _grasp_set() -> GraspSet:
    rng = np.random.default_rng(0)
    f = lambda *s: rng.uniform(0.0, 1.0, s)  # noqa: E731
    poses = np.tile(np.eye(4), (G_, 1, 1))
    poses[:, :3, 3] = f(G_, 3)
    arrays = {
        "wrist_pose": poses, "q": f(G_, Q), "channel_names": np.array([f"ch{i}" for i in range(Q)]),
        "joint_pos": f(G_, 20), "joint_names": np.array([f"j{i}" for i in range(20)]), "contacts": f(G_, C, 3),
        "E": f(G_), "E_g": f(G_), "E_c": f(G_), "E_q": f(G_), "epsilon": f(G_), "force_closure": f(G_) > 0.5,
        "penetration": f(G_), "valid": np.array([True, False, True]), "iters": np.array([4, 2, 4], np.int32),
        "synthesis_s": np.float64(0.12), "compile_s": np.float64(21.5),
    }
    trace = {k: f(T + 1, G_) for k in ("E", "E_g", "E_c")}
    return GraspSet(arrays, trace, CFG, "box")


@pytest.fixture(scope="module")
def gs():
    return _grasp_set()


# ---------------------------------------------------------------------------------------------------------------
# npz
# ---------------------------------------------------------------------------------------------------------------


def test_npz_round_trip(gs, tmp_path):
    path = tmp_path / "g.npz"
    grasp_io.save_npz(gs, path)
    back = grasp_io.load_npz(path)
    assert set(back) == set(gs.arrays) | {"object_name", "config_json"}
    for k, v in gs.arrays.items():
        assert back[k].dtype == np.asarray(v).dtype, k
        np.testing.assert_array_equal(back[k], v, err_msg=k)
    assert str(back["object_name"]) == "box"
    cfg = json.loads(str(back["config_json"]))
    assert cfg["energy"] == dataclasses.asdict(CFG.energy) and cfg["energy"]["d0"] == 0.005
    assert cfg["optim"]["iters"] == T and cfg["seed"] == 7 and cfg["n"] == G_
    assert all(a.dtype != object for a in back.values())  # no pickles


def test_load_npz_missing_or_garbage(tmp_path):
    with pytest.raises(FfcgsError, match="grasp file not found"):
        grasp_io.load_npz(tmp_path / "nope.npz")
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"this is not a zip archive")
    with pytest.raises(FfcgsError, match="not a readable grasp .npz"):
        grasp_io.load_npz(junk)


def test_save_npz_creates_its_folder_and_refuses_a_path_under_a_file(gs, tmp_path):
    """One rule for every output (issue 23): a missing folder is created; a path that cannot be a file is refused."""
    grasp_io.save_npz(gs, tmp_path / "no" / "such" / "dir.npz")
    assert grasp_io.load_npz(tmp_path / "no" / "such" / "dir.npz")["q"].shape == gs["q"].shape
    (tmp_path / "plain").write_text("a file")
    with pytest.raises(FfcgsError, match="cannot write"):
        grasp_io.save_npz(gs, tmp_path / "plain" / "dir.npz")


# ---------------------------------------------------------------------------------------------------------------
# MCAP
# ---------------------------------------------------------------------------------------------------------------

def check_mcap(path, gs, summary, hand_drawn=True):
    """Everything a log of `gs` must hold: the Foxglove scene and timeline (mcap_checks.check_run_log), then the
    package's own topics' contents."""
    T1, G = gs.trace["E"].shape
    msgs = check_run_log(path, gs.arrays, gs.order(), T1, hand_drawn=hand_drawn)
    tf = 1 + (T1 * min(G, grasp_log.HANDS) if "wrist_pose" in gs.trace else 0)  # + each shown wrist per iteration
    assert {k: len(v) for k, v in msgs.items() if not k.startswith("/hand/")} == {
        "/config": 1, "/scene": 1, "/tf": tf, "/energy": T1, "/grasp": G, "/summary": 1}
    cfg = msgs["/config"][0]
    assert cfg["object"] == gs.object_name and cfg["config"] == json.loads(json.dumps(dataclasses.asdict(gs.config)))
    for t, m in enumerate(msgs["/energy"]):
        assert m["iteration"] == t
        for k in ("E", "E_g", "E_c"):
            assert len(m[k]) == G
            np.testing.assert_allclose(m[k], gs.trace[k][t], rtol=1e-15)
        assert m["E_min"] == min(m["E"]) and m["E_median"] == pytest.approx(np.median(gs.trace["E"][t]))
    a = gs.arrays
    for i, m in enumerate(msgs["/grasp"]):
        assert m["index"] == i and m["valid"] == bool(a["valid"][i])
        for k in ("wrist_pose", "q", "contacts", "E", "E_g", "E_c", "E_q", "epsilon", "penetration"):
            np.testing.assert_allclose(np.asarray(m[k]), a[k][i], rtol=1e-15, err_msg=k)
    assert msgs["/summary"][0] == dict(summary)
    assert grasp_log.read_mcap(path) == msgs  # the package's reader agrees
    return msgs


@pytest.fixture(scope="module")
def box():
    from ffcgs_jax.geometry import mesh_io

    return mesh_io.load_mesh("box")


def test_mcap_topics_schemas_and_contents(gs, svh, box, tmp_path):
    path = tmp_path / "run.mcap"
    grasp_log.write_mcap(gs, path, svh, SUMMARY, mesh=box)
    msgs = check_mcap(path, gs, SUMMARY)
    assert msgs["/config"][0]["hand"] == svh.spec.name and msgs["/config"][0]["version"]
    assert msgs["/config"][0]["config"]["energy"]["d0"] == 0.005
    assert all(len(msgs[f"/hand/{k}"]) == 1 for k in range(G_))  # no per-iteration poses: the result only
    best = gs.order()[0]
    hand = msgs["/hand/0"][0]["entities"][0]
    assert hand["frame_id"] == f"wrist_{best}" and "valid" in hand["texts"][0]["text"]
    # a capsule is a cylinder and two spheres, a box a cube: the SVH's 27 collision geoms
    assert len(hand["cylinders"]) == len(hand["spheres"]) // 2 and len(hand["cubes"]) + len(hand["cylinders"]) == 27


def test_mcap_hand_name_only_draws_contacts(gs, box, tmp_path):
    path = tmp_path / "run.mcap"
    grasp_log.write_mcap(gs, path, "svh", SUMMARY, mesh=box)
    check_mcap(path, gs, SUMMARY, hand_drawn=False)


def test_mcap_replays_a_trace_of_poses(gs, svh, box, tmp_path):
    """A trace with per-iteration channels, wrist poses and fingertips puts the hands, their wrist frames and the
    fingertips on the timeline, one frame per iteration (up to MAX_FRAMES, evenly spaced)."""
    rng = np.random.default_rng(1)
    trace = dict(gs.trace, q=rng.uniform(0, 0.5, (T + 1, G_, Q)), tips=rng.uniform(0, 0.1, (T + 1, G_, C, 3)),
                 wrist_pose=np.tile(gs["wrist_pose"], (T + 1, 1, 1, 1)))
    trace["tips"][-1] = gs["contacts"]  # the last frame is the result
    trace["wrist_pose"][:, :, 2, 3] += np.linspace(0.05, 0, T + 1)[:, None]  # the wrists descend onto the result
    traced = GraspSet(gs.arrays, trace, gs.config, gs.object_name)
    path = tmp_path / "run.mcap"
    grasp_log.write_mcap(traced, path, svh, SUMMARY, mesh=box)
    msgs = check_mcap(path, traced, SUMMARY)
    timed = read_timed(path)
    energy_times = [t for topic, _, t, _ in timed if topic == "/energy"]
    for k in range(G_):
        assert [t for topic, _, t, _ in timed if topic == f"/hand/{k}"] == energy_times
        i = gs.order()[k]
        for t, m in enumerate(msgs[f"/hand/{k}"]):
            spheres = m["entities"][1]["spheres"]
            np.testing.assert_allclose([[s["pose"]["position"][c] for c in "xyz"] for s in spheres],
                                       trace["tips"][t, i], atol=1e-12)
    wrists = [(t, x) for topic, _, t, m in timed if topic == "/tf" for x in m["transforms"]
              if x["child_frame_id"] == f"wrist_{gs.order()[0]}"]
    assert len(wrists) == T + 2  # the result at the start, then one per iteration
    np.testing.assert_allclose([x["translation"]["z"] for _, x in wrists[1:]],
                               trace["wrist_pose"][:, gs.order()[0], 2, 3], atol=1e-12)


def test_mcap_writes_strict_json(gs, tmp_path):
    """JSON has no NaN: a non-finite energy is written as null, so Foxglove can still parse the message."""
    bad = GraspSet(gs.arrays, dict(gs.trace, E=np.where(np.arange(G_) == 1, np.nan, gs.trace["E"])), gs.config,
                   gs.object_name)
    path = tmp_path / "run.mcap"
    grasp_log.write_mcap(bad, path, "svh", SUMMARY)
    raw = [m for topic, _, _, m in read_timed(path) if topic == "/energy"]
    assert raw[0]["E"][1] is None and raw[0]["E"][0] == gs.trace["E"][0, 0]


def test_schema_checker_can_fail():
    s = grasp_log.SCHEMAS
    ok = {"iteration": 0, "E": [1.0], "E_g": [1.0], "E_c": [1.0], "E_min": 1.0, "E_median": 1.0, "E_g_median": 1.0,
          "E_c_median": 1.0}
    assert not schema_errors(ok, s["/energy"])
    assert schema_errors({k: v for k, v in ok.items() if k != "E_c"}, s["/energy"])  # E_c missing
    assert schema_errors({**ok, "iteration": 0.5}, s["/energy"])  # not an integer
    assert schema_errors({"index": 0, "valid": 1, "wrist_pose": [[0.0]], "q": [], "contacts": [], "E": 0.0,
                          "E_g": 0.0, "E_c": 0.0}, s["/grasp"])  # valid is not a boolean
    assert schema_errors({"a": 1}, s["/summary"])  # summary values are strings
    assert not schema_errors({"a": "1"}, s["/summary"])


def test_mcap_unwritable_path(gs, tmp_path):
    (tmp_path / "plain").write_text("a file")
    with pytest.raises(FfcgsError, match="cannot write"):
        grasp_log.write_mcap(gs, tmp_path / "plain" / "run.mcap", "svh", SUMMARY)
    assert list(tmp_path.iterdir()) == [tmp_path / "plain"]
