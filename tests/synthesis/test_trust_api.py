"""Issue 47, "Trust on the first run", through the Python API: a dataset merge that takes only its own build's
parts, a masked depth scene of an implausible size that warns as an isolated one does, and bad arguments that
get one line naming the real cause (a q of the wrong width, one object given twice, an absurd scale, a dict where
a GraspSet belongs) instead of a raw AttributeError or KeyError or a line blaming something else.

Nothing here compiles the synthesis.
"""

import contextlib
import hashlib
import io
import re
import warnings
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest
import trimesh

import ffcgs_jax as fj
from ffcgs_jax.cli import main as cli_main
from ffcgs_jax.dataset import mcap_io, schema
from ffcgs_jax.geometry import depth_object, depth_scene, mesh_io
from ffcgs_jax.hand.spec import load_spec
from ffcgs_jax.synthesis import grasp_io
from ffcgs_jax.synthesis.many import expand_objects

R = 8  # the parts' SDF resolution: a record of a few kB


def _sha(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()


def _record(name: str, mesh_sha256: str) -> schema.Record:
    rng = np.random.default_rng(0)
    g = 2
    return schema.Record.create(
        object_name=name, mesh_sha256=mesh_sha256, rotation_index=0, rotation=np.eye(3), split="train",
        grid=rng.normal(size=(R, R, R, 4)).astype(np.float32), origin=np.zeros(3), voxel_size=np.float64(0.004),
        table_z=np.float64(0.0), wrist_pose=np.tile(np.eye(4), (g, 1, 1)), q=np.zeros((g, 9)),
        epsilon=np.ones(g), E=np.ones(g), E_g=np.ones(g), E_c=np.ones(g))


def _build(tmp_path: Path, parts: dict[str, str]) -> Path:
    """A build's parts folder as `dataset build` leaves it (config.json naming obj_a and obj_b with their geometry
    hashes, one rotation each), holding a part per object in `parts` made with the geometry hash given there."""
    out = tmp_path / "d.mcap"
    objects = [{"name": n, "split": "train", "category": "", "mesh_sha256": _sha(n)} for n in ("obj_a", "obj_b")]
    folder = mcap_io.init_parts(mcap_io.parts_dir_for(out), {"rotations": 1}, {"objects": objects})
    for name, sha in parts.items():
        mcap_io.write_part(folder, _record(name, sha))
    return out


def test_merge_takes_the_builds_own_parts(tmp_path):
    out = _build(tmp_path, {"obj_a": _sha("obj_a"), "obj_b": _sha("obj_b")})
    assert fj.merge_dataset(out) == {"out": str(out), "records": 2, "objects": 2}
    assert [r.object_name for r in mcap_io.iter_records(out)] == ["obj_a", "obj_b"]


def test_merge_refuses_a_part_of_another_build(tmp_path):
    """obj_b's part was built from another mesh (another build's, copied into the shared parts folder)."""
    out = _build(tmp_path, {"obj_a": _sha("obj_a"), "obj_b": _sha("another obj_b")})
    with pytest.raises(fj.FfcgsError, match=r"part .*obj_b\.r0000\.mcap holds object 'obj_b' with mesh_sha256 "
                                            r"\w+\.\.\., but this build's 'obj_b' has \w+\.\.\.: it comes from "
                                            r"another build"):
        fj.merge_dataset(out)
    assert not out.exists()
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        code = cli_main.main(["dataset", "merge", str(out)])
    assert code == 2 and err.getvalue().count("\n") == 1 and "obj_b.r0000.mcap holds object 'obj_b'" in err.getvalue()
    assert not out.exists()


def test_merge_refuses_a_part_of_an_object_the_build_does_not_have(tmp_path):
    out = _build(tmp_path, {"obj_a": _sha("obj_a"), "obj_b": _sha("obj_b")})
    parts = mcap_io.parts_dir_for(out)
    mcap_io.write_part(parts, _record("obj_c", _sha("obj_c")))
    with pytest.raises(fj.FfcgsError, match=r"part .*obj_c\.r0000\.mcap holds object 'obj_c', which this build "
                                            r"does not have"):
        mcap_io.merge(parts, out)  # without the expected record list, as a partial build merges


def test_a_masked_scene_of_49_cm_warns_as_an_isolated_one_does():
    slab = trimesh.creation.box((0.49, 0.3, 0.05)).apply_translation((0, 0, 0.025))
    frames = depth_scene.render_scene(slab, "table", 3, 80, 60, distance=0.8)
    assert frames.mask is not None and frames.mask.any()  # the renderer's masks: the user's isolation
    with pytest.warns(UserWarning, match=r"the frames' masks hold an object of 4\d\.\d x .* cm, wider than 40 cm"):
        fused = depth_object.from_depth(frames, res=24)
    assert fused.masks_given and fused.isolation is None
    mug = depth_scene.render_scene(mesh_io.load_mesh("mug"), "clutter", 3, 80, 60, noise=True, seed=1)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a plausible masked object warns of nothing
        depth_object.from_depth(mug, res=24)


def _grasps(tmp_path: Path, q_width: int) -> Path:
    names = load_spec("svh").channel_names
    path = tmp_path / "g.npz"
    grasp_io.save_arrays({"wrist_pose": np.tile(np.eye(4), (2, 1, 1)), "q": np.zeros((2, q_width)),
                          "squeeze_dir": np.ones((2, len(names))), "channel_names": np.array(names),
                          "valid": np.ones(2, bool)}, path)
    return path


def test_a_q_of_the_wrong_width_names_q_not_squeeze_dir(tmp_path):
    with pytest.raises(fj.FfcgsError, match=r"q has 8 columns, but the hand the grasps were made for has 9 "
                                            r"channels \(its channel_names\): q must have shape \(B, 9\)"):
        fj.load_grasps(_grasps(tmp_path, 8))
    assert fj.load_grasps(_grasps(tmp_path, 9))["q"].shape == (2, 9)


def test_one_object_given_twice_is_named_not_renamed(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    trimesh.creation.box().export("a.stl")
    Path("m").mkdir()
    trimesh.creation.box().export("m/a.obj")
    for objects, said in ((["a.stl", "a.stl"], "'a.stl' is given twice"),
                          (["a.stl", str(tmp_path / "a.stl")], f"'a.stl' (also as '{tmp_path / 'a.stl'}') is given"),
                          (["mug", "mug"], "the same object 'mug' is given twice")):
        with pytest.raises(fj.FfcgsError, match="the same object .*given twice: give each object once") as e:
            expand_objects(objects)
        assert said in str(e.value)
    with pytest.raises(fj.FfcgsError, match=r"two objects are named 'a' .* so rename one"):  # two files, one name
        expand_objects(["a.stl", "m"])


@pytest.mark.parametrize("scale", [1e300, 1e-300, 1e10])
def test_a_scale_that_breaks_the_mesh_is_named(scale):
    said = re.escape(f"scale {scale:g} (--scale) makes mesh ")
    with pytest.raises(fj.FfcgsError, match=said + r".*mug.ply .* m across \(0\.117 unscaled\)"):
        fj.load_mesh("mug", scale=scale)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # millimetres of a metre mesh: a warning, not an error
        assert fj.load_mesh("mug", scale=0.01).extents.max() == pytest.approx(0.00117, rel=0.01)


@pytest.fixture(scope="module")
def a_dict():
    return {"wrist_pose": np.eye(4)[None], "q": np.zeros((1, 9)), "valid": np.ones(1, bool)}


def _grid():
    from ffcgs_jax.geometry.sdf import GradientSDF

    return GradientSDF(jnp.zeros((8, 8, 8, 4)), jnp.zeros(3), jnp.asarray(0.004), jnp.asarray(0.0))


@pytest.mark.parametrize("name, call", [
    ("save_grasps", lambda hand, d, tmp: fj.save_grasps(d, tmp / "x.npz")),
    ("validate", lambda hand, d, tmp: fj.validate(hand, fj.load_mesh("box"), d)),
    ("plot_grasps", lambda hand, d, tmp: fj.plot_grasps(hand, fj.load_mesh("box"), d)),
    ("show", lambda hand, d, tmp: fj.show(hand, fj.load_mesh("box"), d)),
    ("check_on_mesh", lambda hand, d, tmp: fj.check_on_mesh(hand, fj.load_mesh("box"), d, _grid())),
])
def test_a_dict_where_a_grasp_set_belongs_is_one_line(tmp_path, svh, a_dict, name, call):
    with pytest.raises(fj.FfcgsError, match=rf"^{name} needs a GraspSet \(from fj.synthesize or fj.load_grasps\), "
                                            r"got dict$"):
        call(svh, a_dict, tmp_path)
    assert not (tmp_path / "x.npz").exists()


def test_the_functions_that_take_a_dict_too_say_what_they_take(a_dict):
    """evaluate_physics takes a dict of arrays as well, summary the physics results as a dict: another type is
    one line there too."""
    with pytest.raises(fj.FfcgsError, match="grasps must be a GraspSet or a dict of arrays"):
        fj.evaluate_physics(load_spec("svh"), fj.load_mesh("box"), [a_dict])
    with pytest.raises(fj.FfcgsError, match="summary takes a GraspSet or fj.evaluate_physics's results, got list"):
        fj.summary([a_dict])
