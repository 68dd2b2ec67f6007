"""Mesh loading: every kind of bad file gives a clear FfcgsError; built-in objects are closed and sized in metres."""

import numpy as np
import pytest
import trimesh

from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.geometry import mesh_io, objects

BUILTINS = ("ball", "banana", "bottle", "box", "can", "mug")


def _write(tmp_path, name, text):
    file = tmp_path / name
    file.write_text(text) if isinstance(text, str) else file.write_bytes(text)
    return file


def test_missing_file(tmp_path):
    with pytest.raises(FfcgsError, match="not found.*nope.stl"):
        mesh_io.load_mesh(tmp_path / "nope.stl")
    with pytest.raises(FfcgsError, match="not found.*built-in objects: ball"):
        mesh_io.load_mesh("no_such_object")


def test_unsupported_and_unreadable(tmp_path):
    with pytest.raises(FfcgsError, match="unsupported format '.xyz'"):
        mesh_io.load_mesh(_write(tmp_path, "p.xyz", "0 0 0\n"))
    with pytest.raises(FfcgsError, match="bad.ply is not a PLY mesh: it is a file of another format"):
        mesh_io.load_mesh(_write(tmp_path, "bad.ply", b"\x00garbage" * 10))


def test_not_a_mesh(tmp_path):
    cloud = tmp_path / "cloud.ply"
    trimesh.PointCloud(np.random.default_rng(0).random((20, 3))).export(cloud)
    with pytest.raises(FfcgsError, match="cloud.ply is not a triangle mesh but a PointCloud"):
        mesh_io.load_mesh(cloud)
    lines = _write(tmp_path, "lines.obj", "v 0 0 0\nv 1 0 0\nv 1 1 0\nl 1 2 3\n")
    with pytest.raises(FfcgsError, match="not a triangle mesh"):
        mesh_io.load_mesh(lines)


def test_empty(tmp_path):
    with pytest.raises(FfcgsError, match="mesh file .*empty.stl is empty"):
        mesh_io.load_mesh(_write(tmp_path, "empty.stl", ""))


def test_nan_vertices(tmp_path):
    obj = "v 0 0 0\nv 1 0 0\nv nan 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n"
    with pytest.raises(FfcgsError, match="1 vertices with NaN or inf"):
        mesh_io.load_mesh(_write(tmp_path, "nan.obj", obj))


def test_flat_and_degenerate(tmp_path):
    tilted = "v 0 0 0\nv 1 0 1\nv 1 1 1\nv 0 1 0\nf 1 2 3\nf 1 3 4\n"  # a square on a slanted plane
    with pytest.raises(FfcgsError, match="flat.*no volume"):
        mesh_io.load_mesh(_write(tmp_path, "flat.obj", tilted))
    collinear = "v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n"
    with pytest.raises(FfcgsError, match="degenerate: all its faces have zero area"):
        mesh_io.load_mesh(_write(tmp_path, "line.obj", collinear))


def test_scale(tmp_path):
    box = tmp_path / "box_mm.stl"
    trimesh.creation.box(extents=(50, 80, 140)).export(box)
    with pytest.warns(UserWarning, match="looks like millimetres; pass --scale 0.001"):
        mesh_io.load_mesh(box)
    mesh = mesh_io.load_mesh(box, scale=0.001)
    np.testing.assert_allclose(mesh.extents, [0.05, 0.08, 0.14])
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(FfcgsError, match="scale must be a finite number > 0"):
            mesh_io.load_mesh(box, scale=bad)


def test_glb_scene_is_concatenated(tmp_path):
    cube = trimesh.creation.box(extents=(0.05, 0.05, 0.05))
    ball = trimesh.creation.icosphere(2, radius=0.02).apply_translation([0.1, 0.0, 0.0])
    file = tmp_path / "scene.glb"
    trimesh.Scene([cube, ball]).export(file)
    mesh = mesh_io.load_mesh(file)
    assert len(mesh.faces) == len(cube.faces) + len(ball.faces)
    np.testing.assert_allclose(mesh.bounds, [[-0.025, -0.025, -0.025], [0.12, 0.025, 0.025]], atol=1e-6)
    assert mesh.is_watertight


def test_open_mesh_warns_and_inverted_mesh_is_flipped(tmp_path):
    box = trimesh.creation.box(extents=(0.05, 0.08, 0.14))
    trimesh.Trimesh(box.vertices, box.faces[1:]).export(tmp_path / "open.stl")
    with pytest.warns(UserWarning, match="not watertight"):
        mesh = mesh_io.load_mesh(tmp_path / "open.stl")
    assert len(mesh.faces) == 11
    box.invert()
    box.export(tmp_path / "inside_out.stl")
    assert trimesh.load(tmp_path / "inside_out.stl").volume < 0
    assert mesh_io.load_mesh(tmp_path / "inside_out.stl").volume == pytest.approx(0.05 * 0.08 * 0.14)


def test_builtin_objects():
    assert set(BUILTINS) <= set(objects.names())
    assert objects.names() == sorted(objects.names())
    rows = {row["name"]: row for row in objects.describe()}
    for name in BUILTINS:
        assert objects.path(name).stat().st_size < 20_000
        mesh = mesh_io.load_mesh(name)
        assert mesh.is_watertight and mesh.is_winding_consistent
        assert mesh.volume > 0
        lo, hi = mesh.bounds
        assert lo[2] == pytest.approx(0.0, abs=1e-6)  # resting on the table
        np.testing.assert_allclose((lo + hi)[:2] / 2, 0.0, atol=1e-6)  # centred in x/y
        assert 0.03 < mesh.extents.max() < 0.25  # metres, hand-sized
        assert rows[name]["watertight"] and rows[name]["faces"] == len(mesh.faces)
        assert rows[name]["volume"] == pytest.approx(mesh.volume, rel=1e-6)
    with pytest.raises(FfcgsError, match="unknown built-in object 'teapot'; valid names: ball, banana"):
        objects.path("teapot")
