"""`GraspSet`: typed fields, read-only arrays, `with_arrays`, the deterministic order, files of the version before
the typed fields, and the provenance `synthesize` records so that `ffcgs eval` needs no `--object`."""

import contextlib
import io
import pickle
import shutil
from pathlib import Path

import numpy as np
import pytest
import trimesh

import ffcgs_jax as fj
from ffcgs_jax.cli import main as cli_main
from ffcgs_jax.geometry import mesh_io, objects
from ffcgs_jax.geometry.config import SDFConfig
from ffcgs_jax.synthesis.config import GraspConfig, OptimConfig
from ffcgs_jax.synthesis.grasp import load_grasps, save_grasps
from ffcgs_jax.synthesis.grasp_set import FIELDS, GraspSet

DATA = Path(__file__).parents[1] / "data"
TOY = DATA / "toy_hand" / "toy.toml"
# written by `fj.save_grasps` at commit ae66fbd (before the typed fields; it holds `score`): toy hand, box, n=4, seed 3
BEFORE = DATA / "grasps_ae66fbd_toy_box.npz"


def _arrays(n=3) -> dict:
    return {"wrist_pose": np.tile(np.eye(4), (n, 1, 1)), "q": np.zeros((n, 2)), "E": np.arange(n, dtype=float),
            "valid": np.array([True, False, True][:n]), "pred_success": np.linspace(0, 1, n)}


def test_typed_fields_hold_the_arrays_and_the_optional_ones_are_extra():
    gs = GraspSet(_arrays(), {"E": np.zeros((2, 3))}, GraspConfig(), "thing")
    assert gs.E is gs["E"] is gs.arrays["E"] and gs.q.shape == (3, 2)
    assert gs.epsilon is None and "epsilon" not in gs  # absent: None, and gs["epsilon"] a KeyError as before
    with pytest.raises(KeyError):
        gs["epsilon"]
    assert dict(gs.extra).keys() == {"pred_success"} and set(gs.arrays) == set(_arrays())
    assert {"wrist_pose", "q", "contacts", "E", "E_g", "E_c", "E_q", "epsilon", "valid", "force_closure",
            "penetration", "squeeze_dir"} <= set(FIELDS)
    assert "score" not in FIELDS


def test_a_grasp_set_is_never_changed_in_place():
    given = _arrays()
    gs = GraspSet(given, {}, GraspConfig(), "thing")
    given["E"] = np.zeros(3)  # the caller's dict changing later does not change the set
    assert gs.E.tolist() == [0.0, 1.0, 2.0]
    with pytest.raises(TypeError):
        gs.arrays["E"] = np.zeros(3)
    with pytest.raises(TypeError):
        gs.trace["E"] = np.zeros((2, 3))
    with pytest.raises(AttributeError, match="read-only"):
        gs.E = np.zeros(3)
    more = gs.with_arrays(sdf_s=np.asarray(0.5), E=np.ones(3))
    assert float(more.sdf_s) == 0.5 and more.E.tolist() == [1, 1, 1] and gs.sdf_s is None and gs.E[0] == 0
    only = gs.with_arrays({"q": gs.q, "valid": gs.valid})  # a mapping replaces the arrays whole
    assert set(only.arrays) == {"q", "valid"} and only.object_name == "thing"
    back = pickle.loads(pickle.dumps(more))
    assert back.E.tolist() == [1, 1, 1] and set(back.arrays) == set(more.arrays)


def test_order_is_deterministic_valid_first_then_E_then_index():
    n = 12
    rng = np.random.default_rng(2)
    E = rng.choice([0.1, 0.2, 0.3], n)  # ties on purpose
    valid = rng.uniform(size=n) < 0.6
    gs = GraspSet({"valid": valid, "E": E}, {}, GraspConfig(), "x")
    expected = sorted(range(n), key=lambda i: (not valid[i], E[i], i))
    assert gs.order().tolist() == expected and gs.order().tolist() == expected  # and again
    assert gs.select(gs.order()[:2]).E.tolist() == [E[i] for i in expected[:2]]


def test_a_file_written_before_the_typed_fields_loads_and_saves_again(tmp_path):
    gs = load_grasps(BEFORE)
    assert gs.object_name == "box" and gs.q.shape == (4, 2) and gs.valid.dtype == bool
    assert "score" in gs.extra and len(gs["score"]) == 4  # kept as it was, no longer computed
    save_grasps(gs, tmp_path / "again.npz")
    again = np.load(tmp_path / "again.npz")
    old = np.load(BEFORE)
    assert set(again.files) == set(old.files)
    for k in set(old.files) - {"config_json"}:  # the config is written in this version's names
        np.testing.assert_array_equal(again[k], old[k], err_msg=k)
    assert load_grasps(tmp_path / "again.npz").config == gs.config


def test_load_mesh_records_its_source_until_the_mesh_changes(tmp_path):
    trimesh.creation.box((0.05, 0.06, 0.07)).export(tmp_path / "cube.stl")
    mesh = fj.load_mesh(tmp_path / "cube.stl", scale=2.0)
    src = mesh_io.source_of(mesh)
    assert str(src["object_source"]) == str((tmp_path / "cube.stl").resolve()) and float(src["object_scale"]) == 2.0
    assert str(src["object_sha256"]) == mesh_io.mesh_sha256(mesh)
    assert str(mesh_io.source_of(fj.load_mesh("mug"))["object_source"]) == "mug"
    moved = mesh.copy()
    moved.apply_translation([0.0, 0.0, 0.01])  # no longer what the file holds
    assert mesh_io.source_of(moved) == {} and mesh_io.source_of(trimesh.creation.box()) == {}
    assert mesh_io.source_of(mesh.copy())["object_sha256"] == src["object_sha256"]


@pytest.mark.e2e  # one toy-hand synthesis compiled: about 30 s on a loaded 2-core CPU
def test_a_file_saved_from_python_is_evaluated_without_naming_its_object(tmp_path):
    """`ffcgs eval` of a file saved from Python finds and checks its object from the file alone. The toy hand has
    no actuators to simulate, so the run stops at the physics, after the object was found; the same file without
    its provenance stops before, asking for --object."""
    mine = tmp_path / f"my_box{objects.path('box').suffix}"  # the built-in box's file under another name
    shutil.copy(objects.path("box"), mine)
    hand, mesh = fj.load_hand(TOY), fj.load_mesh(mine)
    cfg = GraspConfig(n=4, seed=3, sdf=SDFConfig(res=16), optim=OptimConfig(iters=5))
    gs = fj.synthesize(hand, mesh, cfg)  # object_name "object": not a built-in, so only the provenance can say
    assert str(gs["object_source"]) == str(mine.resolve()) and float(gs["object_scale"]) == 1.0
    assert str(gs["object_sha256"]) == mesh_io.mesh_sha256(mesh)
    fj.save_grasps(gs, tmp_path / "g.npz")
    fj.save_grasps(gs.with_arrays({k: v for k, v in gs.arrays.items() if not k.startswith("object_")}),
                   tmp_path / "bare.npz")

    def evaluate(name: str) -> str:
        out, err = io.StringIO(), io.StringIO()
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            cli_main.main(["eval", str(tmp_path / name), "--hand", str(TOY), "--all", "--backend", "cpu"])
        return err.getvalue()

    found = evaluate("g.npz")
    assert "needs one actuator per channel of hand 'toy'" in found and "--object" not in found, found
    assert "does not name a built-in object ('object'): pass --object" in evaluate("bare.npz")
