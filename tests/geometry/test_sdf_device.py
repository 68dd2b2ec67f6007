"""Device SDF builder: the same grid as the host builder (the reference), for meshes of one chunk and of many, compiled
once for every mesh size; `build_sdf`'s cache."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh
from paths import SHARED

from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.geometry import sdf, sdf_build, sdf_device
from ffcgs_jax.geometry.config import SDFConfig
from ffcgs_jax.kernels import triangles

DIST_TOL = 1e-6  # m: device vs host distances (both exact; the float32 search may pick another of near-tied faces)
SURFACE_TOL = 1e-6  # m: closer to the surface, the sign and the normal may differ between builders
GRAD_TOL = 1e-5  # gradient channels, away from voxels with two nearest points
ON_MESH_TOL = 1e-9  # m: the closest point a device gradient implies lies on the mesh
SPHERE_R = 0.04
YCB = SHARED / "objects" / "ycb"


def _frame(mesh: trimesh.Trimesh, res: int):
    flat = np.asarray(mesh.triangles).reshape(-1, 3)
    return sdf.grid_frame(np.stack([flat.min(0), flat.max(0)]), SDFConfig(res=res))


@jax.jit
def _nearest(points, rows):
    return jax.vmap(lambda q: jnp.min(jax.vmap(lambda r: jnp.linalg.norm(triangles.closest_offset(q, r)))(rows)))(
        points)


def _distance_to_mesh(points: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Float64 brute force: distance from each point to the nearest of all triangles."""
    return np.asarray(_nearest(jnp.asarray(points), jnp.asarray(triangles.tri_table(tri, np.float64))))


def _compare_with_host(mesh: trimesh.Trimesh, res: int) -> tuple[np.ndarray, np.ndarray]:
    """Both builders on the same grid: equal distances, equal signs off the surface, equal gradients except where a
    voxel has two nearest points, and there the device's gradient must point from a nearest point. Returns the
    device's distances (R, R, R) and the voxel centres (R, R, R, 3)."""
    verts, faces = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)
    origin, voxel = _frame(mesh, res)
    d_host, g_host = sdf_build.signed_distance_grid(verts, faces, origin, voxel, res)
    d_dev, g_dev = (np.asarray(x) for x in sdf_device.signed_distance_grid_device(verts, faces, origin, voxel, res))
    assert d_dev.dtype == np.float64 and d_dev.shape == (res,) * 3 and g_dev.shape == (res,) * 3 + (3,)
    np.testing.assert_allclose(np.abs(d_dev), np.abs(d_host), rtol=0, atol=DIST_TOL)
    near = np.abs(d_host) <= SURFACE_TOL
    np.testing.assert_array_equal(np.sign(d_dev)[~near], np.sign(d_host)[~near])
    np.testing.assert_allclose(np.linalg.norm(g_dev, axis=-1), 1.0, atol=1e-12)
    tie = (np.abs(g_dev - g_host).max(-1) > GRAD_TOL) & ~near
    assert tie.mean() < 0.01, tie.sum()
    if tie.any():
        p = origin + voxel * np.argwhere(tie)
        implied = p - d_dev[tie][:, None] * g_dev[tie]
        np.testing.assert_allclose(_distance_to_mesh(implied, verts[faces]), 0.0, atol=ON_MESH_TOL)
    return d_dev, origin + voxel * np.stack(np.meshgrid(*[np.arange(res)] * 3, indexing="ij"), -1)


def _hollow(mesh: trimesh.Trimesh, z_cut: float) -> trimesh.Trimesh:
    """The mesh without the faces whose centre lies above z_cut: a hole at the top (as in test_sdf.py)."""
    out = trimesh.Trimesh(mesh.vertices, mesh.faces[mesh.triangles_center[:, 2] <= z_cut], process=False)
    assert not out.is_watertight
    return out


def _inside_out_box() -> trimesh.Trimesh:
    box = trimesh.creation.box(extents=(0.05, 0.08, 0.14))
    box.invert()
    return box


CASES = {
    "box": lambda: trimesh.creation.box(extents=(0.05, 0.08, 0.14)),
    "sphere": lambda: trimesh.creation.icosphere(3, SPHERE_R),
    "small_hole": lambda: _hollow(trimesh.creation.icosphere(3, SPHERE_R), 0.036),
    "bowl": lambda: _hollow(trimesh.creation.icosphere(3, SPHERE_R), 0.0),
    "inside_out": _inside_out_box,
    "plate": lambda: trimesh.creation.box(extents=(0.1, 0.08, 0.002)),  # half a voxel thick at 32^3
}


@pytest.mark.parametrize("name", CASES)
def test_matches_the_host_builder(name):
    d, p = _compare_with_host(CASES[name](), 32)
    assert (d < 0).any() == (name != "plate")  # the plate has no voxel centre inside
    if name == "bowl":  # open: inside below the film that spans the rim, outside above it
        axis = np.linalg.norm(p[..., :2], axis=-1) < 0.005
        assert (d[axis & (p[..., 2] < -0.005) & (p[..., 2] > -0.035)] < 0).all()
        assert (d[axis & (p[..., 2] > 0.005)] > 0).all()


@pytest.mark.parametrize("name", ["025_mug", "011_banana"])
def test_ycb_matches_the_host_builder(name):
    file = YCB / f"{name}.stl"
    if not file.is_file():
        pytest.skip(f"YCB meshes not found at {YCB}")
    _compare_with_host(trimesh.load(file), 32)


def test_matches_trimesh_on_a_watertight_mesh():
    """trimesh's signed distance, except where trimesh's candidate search misses the nearest face (it then reports a
    farther one): there the device equals a float64 brute force over all faces."""
    mesh = trimesh.creation.annulus(0.02, 0.04, 0.05, sections=64)  # a thick ring: inside, outside and the hole
    assert mesh.is_watertight
    origin, voxel = _frame(mesh, 32)
    d, _ = sdf_device.signed_distance_grid_device(np.asarray(mesh.vertices), np.asarray(mesh.faces), origin, voxel, 32)
    idx = np.random.default_rng(0).integers(0, 32, (400, 3))
    d = np.asarray(d)[tuple(idx.T)]
    ref = -trimesh.proximity.signed_distance(mesh, origin + voxel * idx)  # trimesh: positive inside
    np.testing.assert_array_equal(np.sign(d), np.sign(ref))
    off = np.abs(d - ref) > DIST_TOL
    assert off.mean() < 0.01 and (np.abs(d[off]) < np.abs(ref[off])).all()
    np.testing.assert_allclose(np.abs(d), _distance_to_mesh(origin + voxel * idx, mesh.triangles), atol=DIST_TOL)


def test_a_mesh_of_several_chunks_matches_the_host_builder():
    """20,480 faces stream through the device in 5 chunks: the nearest triangle found across chunks is the
    nearest of all, and the signs come out as the host's."""
    mesh = trimesh.creation.icosphere(5, SPHERE_R)
    assert len(mesh.faces) > 4 * sdf_device.FACE_CHUNK
    _compare_with_host(mesh, 16)


def test_meshes_of_any_size_reuse_the_compiled_build():
    """1,280 faces and 81,920 faces (20 chunks): the second mesh compiles nothing."""
    from ffcgs_jax.runtime import compile_clock

    small = trimesh.creation.icosphere(3, SPHERE_R)
    large = trimesh.creation.annulus(0.02, 0.04, 0.05, sections=20480)  # a ring: its hole must stay outside
    assert len(large.faces) > 40 * len(small.faces)
    sdf.build_sdf(small, SDFConfig(res=32), cache=False)
    with compile_clock.compiling() as seconds:
        grid = sdf.build_sdf(large, SDFConfig(res=32), cache=False)
    assert seconds[0] == 0.0
    assert float(grid.grid[16, 16, 16, 0]) > 0.015  # in the ring's hole (radius 0.02), half a voxel off its axis


def test_gpu_step_sizes_give_the_same_grid(monkeypatch):
    """The GPU configuration (larger loop steps, one-shot winding sums), run here on the CPU, builds the same grid."""
    mesh = CASES["small_hole"]()  # open: the cap terms run too
    cpu = sdf.build_sdf(mesh, SDFConfig(res=32), cache=False).grid
    monkeypatch.setattr(sdf_device, "backend_steps", lambda: sdf_device.GPU_STEPS)
    gpu = sdf.build_sdf(mesh, SDFConfig(res=32), cache=False).grid
    np.testing.assert_allclose(np.asarray(gpu), np.asarray(cpu), atol=1e-12)


def test_float32_when_x64_is_off():
    mesh = trimesh.creation.icosphere(2, SPHERE_R)
    origin, voxel = _frame(mesh, 16)
    ref, _ = sdf_build.signed_distance_grid(np.asarray(mesh.vertices), np.asarray(mesh.faces), origin, voxel, 16)
    with jax.enable_x64(False):
        d, g = sdf_device.signed_distance_grid_device(np.asarray(mesh.vertices), np.asarray(mesh.faces), origin,
                                                      voxel, 16)
    assert d.dtype == jnp.float32 and g.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(d), ref, atol=DIST_TOL)


def test_cache_returns_the_same_grid_until_the_mesh_changes():
    sdf.clear_cache()
    box = trimesh.creation.box(extents=(0.05, 0.08, 0.14))
    cfg = SDFConfig(res=16)
    first = sdf.build_sdf(box, cfg)
    assert sdf.build_sdf(trimesh.Trimesh(box.vertices.copy(), box.faces.copy(), process=False), cfg) is first
    moved = np.array(box.vertices)
    moved[0] += 1e-3
    other = sdf.build_sdf(trimesh.Trimesh(moved, box.faces, process=False), cfg)
    assert other is not first and not np.array_equal(np.asarray(other.grid), np.asarray(first.grid))
    assert sdf.build_sdf(box, cfg, table_z=-0.2) is not first
    assert sdf.build_sdf(box, SDFConfig(res=16, margin=0.2)) is not first
    assert sdf.build_sdf(box, cfg, builder="host") is not first
    fresh = sdf.build_sdf(box, cfg, cache=False)
    assert fresh is not first and sdf.build_sdf(box, cfg) is first  # cache=False neither reads nor writes
    np.testing.assert_array_equal(np.asarray(fresh.grid), np.asarray(first.grid))
    sdf.clear_cache()
    assert sdf.build_sdf(box, cfg) is not first


def test_bad_input_raises_one_clear_line():
    box = trimesh.creation.box(extents=(0.05, 0.08, 0.14))
    with pytest.raises(FfcgsError, match="unknown builder 'gpu'; valid: device, host"):
        sdf.build_sdf(box, builder="gpu")
    point = trimesh.Trimesh([[0.0, 0.0, 0.0]] * 3, [[0, 1, 2]], process=False)
    with pytest.raises(FfcgsError, match="zero extent"):
        sdf.build_sdf(point, SDFConfig(res=16, min_margin=0.0))
    with pytest.raises(FfcgsError, match="faces index vertices 0..5, but the mesh has 3 vertices"):
        sdf.build_sdf(trimesh.Trimesh([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 5]], process=False))
    with pytest.raises(FfcgsError, match="table_z must be finite"):
        sdf.build_sdf(box, table_z=float("nan"))
    # A degenerate but valid mesh (a point) builds: the distance to that point, outside everywhere.
    grid = np.asarray(sdf.build_sdf(point, SDFConfig(res=16, min_margin=0.01), cache=False).grid)
    assert (grid[..., 0] > 0).all() and np.isfinite(grid).all()


@pytest.mark.slow
def test_ycb_matches_the_host_builder_at_64():
    file = YCB / "025_mug.stl"
    if not file.is_file():
        pytest.skip(f"YCB meshes not found at {YCB}")
    _compare_with_host(trimesh.load(file), 64)


@pytest.mark.slow
def test_res_128_builds_exactly():
    mesh = trimesh.creation.icosphere(4, SPHERE_R)
    s = sdf.build_sdf(mesh, SDFConfig(res=128), cache=False)
    p = np.asarray(s.origin) + float(s.voxel_size) * np.stack(np.meshgrid(*[np.arange(128)] * 3, indexing="ij"), -1)
    d = np.asarray(s.grid[..., 0])
    r = np.linalg.norm(p, axis=-1)
    facet = SPHERE_R - np.linalg.norm(mesh.triangles_center, axis=1).min()
    assert np.abs(d - (r - SPHERE_R)).max() < facet + 1e-7
    sample = np.random.default_rng(1).integers(0, 128, (300, 3))
    np.testing.assert_allclose(np.abs(d[tuple(sample.T)]), _distance_to_mesh(p[tuple(sample.T)], mesh.triangles),
                               atol=DIST_TOL)
