"""The physics test's collision geometry (`physics.collision`, `physics.voxel_parts`) against its mesh."""

import time
import warnings

import numpy as np
import pytest
import trimesh

from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.geometry import mesh_io, procedural
from ffcgs_jax.physics import collision, convex, voxel_parts
from ffcgs_jax.physics.config import PhysicsConfig
from physics_trials import ONE_TRIAL

XOR_MM = 2.5  # |union of parts xor mesh| / mesh area: the mean thickness where they differ (thin walls make a
# ratio to the volume meaningless), within a 3 mm voxel
SURFACE_MM = 4.0  # 95th percentile of the distance from mesh points to the parts, and from parts to the mesh
FAST = PhysicsConfig(robust=ONE_TRIAL, voxel_cells=40)  # a coarser grid keeps each test to seconds on a loaded CPU


def _union_inside(parts, points):
    return np.logical_or.reduce([voxel_parts.inside(p, points) for p in parts])


def _torus():
    return trimesh.creation.torus(major_radius=0.04, minor_radius=0.012, major_sections=48, minor_sections=16)


@pytest.mark.parametrize("which", ["mug", "torus", "cup"])
def test_voxel_hulls_cover_the_mesh_and_stay_near_it(which):
    mesh = {"mug": lambda: mesh_io.load_mesh("mug"), "torus": _torus,
            "cup": lambda: procedural.complex_shape(0, 3)[1]}[which]()
    parts = collision.parts(mesh, FAST)
    assert 1 < len(parts) <= FAST.max_hulls and all(len(v) <= FAST.hull_vertices for v, _ in parts)
    rng = np.random.default_rng(0)
    points = rng.uniform(*mesh.bounds, (4000, 3))
    inside = mesh.contains(points)
    covered = _union_inside(parts, points)
    box = np.prod(mesh.extents)
    assert (covered != inside).mean() * box / mesh.area * 1e3 < XOR_MM
    surface = trimesh.sample.sample_surface(mesh, 2000, seed=0)[0]
    # mesh points within the parts (the parts reach the surface) ...
    near = np.logical_or.reduce([voxel_parts.inside(p, surface, SURFACE_MM / 1e3) for p in parts])
    assert near.mean() > 0.95
    # ... and part vertices near the mesh (no part bulges out)
    verts = np.concatenate([v for v, _ in parts])
    _, dist, _ = trimesh.proximity.closest_point(mesh, verts[:: max(1, len(verts) // 1000)])
    assert np.percentile(dist, 95) * 1e3 < SURFACE_MM


def test_holes_stay_open():
    mug = mesh_io.load_mesh("mug")
    # the handle's opening: of the points inside the mug's hull, outside the mug and beyond its cup wall, the three
    # farthest from its surface (the middle of the opening between handle and cup)
    rng = np.random.default_rng(1)
    centre = mug.bounds.mean(0)[:2]
    body = np.percentile(np.linalg.norm(mug.vertices[:, :2] - centre, axis=1), 50)
    pts = rng.uniform(*mug.bounds, (6000, 3))
    pts = pts[np.linalg.norm(pts[:, :2] - centre, axis=1) > body + 0.003]
    pts = pts[mug.convex_hull.contains(pts)]
    pts = pts[~mug.contains(pts)]
    _, dist, _ = trimesh.proximity.closest_point(mug, pts)
    hole = pts[np.argsort(-dist)[:3]]
    assert dist.max() > 0.005
    assert not _union_inside(collision.parts(mug, FAST), hole).any()
    torus = _torus()
    centre = np.array([[0.0, 0.0, 0.0], [0.02, 0.0, 0.0], [0.0, -0.02, 0.005]])
    assert not _union_inside(collision.parts(torus, FAST), centre).any()


def test_time_bound_falls_back_with_one_warning():
    blob = trimesh.util.concatenate([trimesh.creation.icosphere(4, 0.012).apply_translation(c)
                                     for c in np.random.default_rng(2).uniform(-0.05, 0.05, (12, 3))])
    cfg = PhysicsConfig(voxel_cells=128, max_hulls=256, collision_budget=0.5)
    t0 = time.monotonic()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        parts = collision.parts(blob, cfg)
    assert time.monotonic() - t0 < cfg.collision_budget + 10.0  # the grid's fixed passes, on a loaded CPU
    lines = [str(w.message) for w in caught if issubclass(w.category, collision.BudgetWarning)]
    assert len(lines) == 1 and "budget" in lines[0] and "\n" not in lines[0]
    assert len(parts) >= 1


def test_worker_method_past_its_budget_gets_the_fallback():
    mug = mesh_io.load_mesh("mug")
    cfg = PhysicsConfig(collision="coacd", collision_budget=0.05)
    t0 = time.monotonic()
    with pytest.warns(collision.BudgetWarning, match="coacd passed its 0.05 s budget"):
        parts = collision.parts(mug, cfg)
    assert time.monotonic() - t0 < 10.0
    assert len(parts) > 1


def test_budget_fallback_is_not_cached(tmp_path, monkeypatch):
    monkeypatch.setenv("FFCGS_CACHE_DIR", str(tmp_path))
    with pytest.warns(collision.BudgetWarning):
        convex.decompose(mesh_io.load_mesh("mug"), PhysicsConfig(collision="coacd", collision_budget=0.05))
    assert not list(tmp_path.rglob("*.npz"))


@pytest.mark.parametrize("mesh,match", [
    (trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), int)), "empty or degenerate"),
    (trimesh.creation.box([0.1, 0.1, 0.1]).apply_scale([1, 1, 0]), "flat"),
])
def test_bad_meshes_get_one_line(mesh, match):
    with pytest.raises(FfcgsError, match=match):
        collision.parts(mesh, FAST)


def test_unknown_method_is_refused():
    with pytest.raises(FfcgsError, match="unknown physics.collision 'sdf'; choices: voxel-hulls"):
        collision.parts(mesh_io.load_mesh("mug"), PhysicsConfig(collision="sdf"))


def test_complex_shapes_are_deterministic_watertight_and_sized():
    for i in range(len(procedural.COMPLEX_KINDS)):
        name, mesh = procedural.complex_shape(3, i)
        again = procedural.complex_shape(3, i)[1]
        assert name.endswith(procedural.COMPLEX_KINDS[i])
        np.testing.assert_array_equal(mesh.vertices, again.vertices)
        np.testing.assert_array_equal(mesh.faces, again.faces)
        assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0
        assert 0.05 <= mesh.extents.max() <= 0.15
        assert 300 <= len(mesh.faces) <= 1.2 * procedural.COMPLEX_FACES
        assert abs(mesh.bounds[0, 2]) < 1e-9 and np.allclose(mesh.bounds[:, :2].mean(0), 0, atol=1e-9)
    assert not np.array_equal(procedural.complex_shape(3, 0)[1].vertices, procedural.complex_shape(4, 0)[1].vertices)
