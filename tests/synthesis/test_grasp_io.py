"""Grasp files: the .npz round trip and the MCAP log, read back with the `mcap` library and checked against the
JSON Schemas stored in it. Uses a synthetic GraspSet with the dtypes `grasp._finish` writes (no compilation here;
tests/cli/test_cli_grasp.py checks the files of a real run)."""

import dataclasses
import json

import numpy as np
import pytest

from ffcgs_jax.errors import FfcgsError
from ffcgs_jax.synthesis import grasp_io
from ffcgs_jax.synthesis.config import EnergyConfig, OptimConfig
from ffcgs_jax.synthesis.grasp import GraspConfig, GraspSet

from mcap_checks import read_raw, schema_errors

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

def check_mcap(path, gs, summary):
    """Everything a log of `gs` must hold; shared with tests/cli/test_cli_grasp.py."""
    msgs, meta = read_raw(path)
    T1, G = gs.trace["E"].shape
    assert {k: len(v) for k, v in msgs.items()} == {"/config": 1, "/iteration": T1, "/grasp": G, "/summary": 1}
    for topic, (encoding, schema, message_encoding) in meta.items():
        assert encoding == "jsonschema" and message_encoding == "json"
        assert schema == grasp_io.SCHEMAS[topic]
        for m in msgs[topic]:
            assert schema_errors(m, schema) == [], (topic, m)
    try:  # not a dependency; a second opinion where it is installed
        import jsonschema
    except ImportError:
        pass
    else:
        for topic, (_, schema, _) in meta.items():
            for m in msgs[topic]:
                jsonschema.validate(m, schema)
    cfg = msgs["/config"][0]
    assert cfg["object"] == gs.object_name and cfg["config"] == json.loads(json.dumps(dataclasses.asdict(gs.config)))
    for t, m in enumerate(msgs["/iteration"]):
        assert m["iteration"] == t
        for k in ("E", "E_g", "E_c"):
            assert len(m[k]) == G
            np.testing.assert_allclose(m[k], gs.trace[k][t], rtol=1e-15)
    a = gs.arrays
    for i, m in enumerate(msgs["/grasp"]):
        assert m["index"] == i and m["valid"] == bool(a["valid"][i])
        for k in ("wrist_pose", "q", "contacts", "E", "E_g", "E_c", "E_q", "epsilon", "penetration"):
            np.testing.assert_allclose(np.asarray(m[k]), a[k][i], rtol=1e-15, err_msg=k)
    assert msgs["/summary"][0] == dict(summary)
    assert grasp_io.read_mcap(path) == msgs  # the package's reader agrees
    return msgs


def test_mcap_topics_schemas_and_contents(gs, tmp_path):
    path = tmp_path / "run.mcap"
    grasp_io.write_mcap(gs, path, "svh", SUMMARY)
    msgs = check_mcap(path, gs, SUMMARY)
    assert msgs["/config"][0]["hand"] == "svh" and msgs["/config"][0]["version"]
    assert msgs["/config"][0]["config"]["energy"]["d0"] == 0.005


def test_schema_checker_can_fail():
    s = grasp_io.SCHEMAS
    assert schema_errors({"iteration": 0, "E": [1.0], "E_g": [1.0]}, s["/iteration"])  # E_c missing
    assert schema_errors({"iteration": 0.5, "E": [], "E_g": [], "E_c": []}, s["/iteration"])  # not an integer
    assert schema_errors({"index": 0, "valid": 1, "wrist_pose": [[0.0]], "q": [], "contacts": [], "E": 0.0,
                          "E_g": 0.0, "E_c": 0.0}, s["/grasp"])  # valid is not a boolean
    assert schema_errors({"a": 1}, s["/summary"])  # summary values are strings
    assert not schema_errors({"a": "1"}, s["/summary"])


def test_mcap_unwritable_path(gs, tmp_path):
    (tmp_path / "plain").write_text("a file")
    with pytest.raises(FfcgsError, match="cannot write"):
        grasp_io.write_mcap(gs, tmp_path / "plain" / "run.mcap", "svh", SUMMARY)
    assert list(tmp_path.iterdir()) == [tmp_path / "plain"]
