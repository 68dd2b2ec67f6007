"""Property tests of every loader of the user's files: random bytes as each kind of file, and random array shapes
and dtypes in grasp and pose files, either load (and then validate) or raise `FfcgsError`, never another exception.

No JAX compiles run inside the examples (the loaders are host code), so the file stays fast on one core."""

import json
import string

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from ffcgs_jax.core import config as ffcgs_config
from ffcgs_jax.dataset import stats as dataset_stats
from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.geometry import depth_io, mesh_io
from ffcgs_jax.hand import spec as hand_spec
from ffcgs_jax.learning import weights
from ffcgs_jax.synthesis import grasp_io
from ffcgs_jax.synthesis.config import GraspConfig

FAST = settings(max_examples=50, deadline=None, database=None, suppress_health_check=[HealthCheck.function_scoped_fixture])

# Prefixes that steer random bytes past the loaders' first checks: the formats' magic numbers and openings
PREFIXES = [b"", b"PK\x03\x04", b"\x93NUMPY\x01\x00", b"\x89PNG\r\n\x1a\n", b"\x89MCAP0\r\n", b"ply\nformat ascii 1.0\n",
            b"solid x\n", b"v 0 0 0\nf 1 2 3\n", b"glTF", b"[grasp]\n", b"{", b"\x00" * 80 + b"\x01\x00\x00\x00"]
contents = st.builds(lambda p, b: p + b, st.sampled_from(PREFIXES), st.binary(max_size=600))


def _loads_or_refuses(load, *args) -> None:
    try:
        load(*args)
    except FfcgsError as e:
        assert str(e) and "\n" not in str(e).strip(), str(e)  # one line


def _load_frames_folder(folder, data: bytes, name: str) -> None:
    """A depth folder whose `name` holds `data`, the other files good."""
    good = {"camera.json": json.dumps({"fx": 50.0, "fy": 50.0, "cx": 4.0, "cy": 3.0, "width": 8.0, "height": 6.0,
                                       "depth_scale": 0.001}).encode(),
            "poses.json": json.dumps({"v0.png": np.eye(4).tolist()}).encode()}
    for k, v in good.items():
        (folder / k).write_bytes(v)
    (folder / name).write_bytes(data)
    depth_io.load_frames(folder)


LOADERS = {
    "mesh.obj": mesh_io.load_mesh, "mesh.stl": mesh_io.load_mesh, "mesh.ply": mesh_io.load_mesh,
    "grasps.npz": grasp_io.load_npz, "poses.npy": grasp_io.load_poses, "poses.npz": grasp_io.load_poses,
    "config.toml": lambda p: ffcgs_config.load(GraspConfig, p), "hand.toml": hand_spec.load_spec,
    "depth.npz": depth_io.load_frames, "weights.npz": weights.load_weights, "dataset.mcap": dataset_stats.stats,
}


@pytest.mark.parametrize("name", sorted(LOADERS))
@FAST
@given(data=contents)
def test_random_bytes_load_or_raise_ffcgs_error(tmp_path, name, data):
    path = tmp_path / name
    path.write_bytes(data)
    _loads_or_refuses(LOADERS[name], path)


@pytest.mark.parametrize("name", ["camera.json", "poses.json", "v0.png"])
@FAST
@given(data=contents)
def test_random_bytes_in_a_depth_folder_load_or_raise_ffcgs_error(tmp_path, name, data):
    folder = tmp_path / "frames"
    folder.mkdir(exist_ok=True)
    for p in folder.iterdir():
        p.unlink()
    _loads_or_refuses(_load_frames_folder, folder, data, name)


dtypes = st.one_of(hnp.floating_dtypes(), hnp.integer_dtypes(), hnp.boolean_dtypes(), hnp.complex_number_dtypes(),
                   hnp.unicode_string_dtypes(max_len=3), hnp.datetime64_dtypes())
shapes = st.one_of(st.sampled_from([(), (0, 4, 4), (2, 4, 4), (2, 3, 3), (2, 9), (3, 9), (2,), (2, 16), (1, 4, 4)]),
                   hnp.array_shapes(min_dims=0, max_dims=3, min_side=0, max_side=5))
arrays = st.builds(lambda dt, sh, fill: np.full(sh, fill).astype(dt) if dt.kind != "U" else np.full(sh, "a", dt),
                   dtypes, shapes, st.sampled_from([0.0, 1.0, np.nan]))
rigid = np.tile(np.eye(4), (2, 1, 1))
GRASP_KEYS = ["wrist_pose", "q", "valid", "squeeze_dir", "object_scale", "object_source", "object_sha256",
              "channel_names", "object_name"]


@FAST
@given(fields=st.dictionaries(st.sampled_from(GRASP_KEYS), arrays, max_size=4))
def test_grasp_files_of_any_shapes_and_dtypes_load_validated_or_raise(tmp_path, fields):
    good = {"wrist_pose": rigid, "q": np.zeros((2, 9)), "valid": np.ones(2, bool), "object_scale": np.float64(1),
            "object_source": np.array("ball")}
    path = tmp_path / "g.npz"
    np.savez(path, **{**good, **fields})
    try:
        data = grasp_io.load_npz(path)
    except FfcgsError:
        return
    # what loaded is what the commands may index without further checks
    n = len(data["wrist_pose"])
    assert data["wrist_pose"].shape == (n, 4, 4) and data["q"].ndim == 2 and len(data["q"]) == n
    assert np.isfinite(data["wrist_pose"]).all() and np.isfinite(data["q"]).all() and len(data["valid"]) == n
    assert float(data["object_scale"]) > 0 and isinstance(str(data["object_source"]), str)


@FAST
@given(poses=arrays, npz=st.booleans())
def test_pose_files_of_any_shapes_and_dtypes_load_validated_or_raise(tmp_path, poses, npz):
    path = tmp_path / ("p.npz" if npz else "p.npy")
    (np.savez(path, wrist_pose=poses) if npz else np.save(path, poses))
    try:
        out = grasp_io.load_poses(path)
    except FfcgsError:
        return
    assert out.ndim == 3 and out.shape[1:] == (4, 4) and len(out) >= 1 and np.isfinite(out).all()


@FAST
@given(text=st.text(alphabet=string.printable, max_size=200))
def test_config_toml_text_loads_or_raises(tmp_path, text):
    path = tmp_path / "c.toml"
    path.write_text("[grasp]\n" + text)
    _loads_or_refuses(lambda p: ffcgs_config.load(GraspConfig, p), path)


@FAST
@given(value=st.one_of(st.booleans(), st.integers(), st.floats(), st.text(max_size=5),
                       st.lists(st.integers(), max_size=3)),
       key=st.sampled_from(["n", "seed", "sampler", "sdf.res", "optim.iters", "energy.lp_solver", "devices"]))
def test_config_values_of_any_type_load_or_raise(tmp_path, value, key):
    *section, leaf = ["grasp", *key.split(".")]
    path = tmp_path / "c.toml"
    path.write_text(f"[{'.'.join(section)}]\n{leaf} = {json.dumps(value)}\n".replace("NaN", "nan")
                    .replace("Infinity", "inf"))
    _loads_or_refuses(lambda p: ffcgs_config.load(GraspConfig, p), path)
