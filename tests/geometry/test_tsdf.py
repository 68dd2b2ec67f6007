"""TSDF fusion: the sequential KinectFusion update, the unobserved-voxel rule, the fused sphere against its closed
form, the conversion to a Euclidean GradientSDF, and no recompilation."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.geometry import depth_io, depth_render, sdf, tsdf
from ffcgs_jax.runtime import compile_clock

R = 0.04  # m: sphere radius; it rests on the table z = 0
CENTRE = np.array([0.0, 0.0, R])
RES = 32
SEQ_TOL = 1e-9  # float64: scan over frames vs a Python loop of the same update
W, H = 160, 120


def _sphere_mesh():
    return trimesh.creation.icosphere(subdivisions=4, radius=R).apply_translation(CENTRE)


def _true(p):
    return np.linalg.norm(p - CENTRE, axis=-1) - R


def _centres(origin, h, res):
    axes = [origin[i] + h * np.arange(res) for i in range(3)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1)


def _hidden(p, eyes, clearance):
    """Points whose segment to every camera passes at least `clearance` inside the sphere's outline."""
    hidden = np.ones(len(p), bool)
    for eye in eyes:
        d = eye - p
        s = np.clip(((CENTRE - p) * d).sum(-1) / (d * d).sum(-1), 0, 1)
        miss = np.linalg.norm(p + s[:, None] * d - CENTRE, axis=-1)
        hidden &= (miss < R - clearance) & (s > 0) & (s < 1)
    return hidden


@pytest.fixture(scope="module")
def views():
    frames = depth_render.render_views(_sphere_mesh(), views=5, width=W, height=H)
    return depth_io.remove_table(frames)


@pytest.fixture(scope="module")
def fused(views):
    frames, table_z = views
    return tsdf.fuse(frames, res=RES, table_z=table_z)


def _reference(depth, mask, K, poses, origin, h, res, trunc):
    """KinectFusion one frame at a time, in NumPy: D <- (W D + w d) / (W + w), W <- W + w. Background readings
    vote +trunc for the voxels in front of them (up to half a voxel behind)."""
    p = _centres(origin, h, res).reshape(-1, 3)
    D, Wt = np.zeros(len(p)), np.zeros(len(p))
    free, shadow = np.zeros(len(p), bool), np.zeros(len(p), bool)
    for n in range(len(depth)):
        cam = (p - poses[n, :3, 3]) @ poses[n, :3, :3]
        z = cam[:, 2]
        pix = cam @ K.T
        with np.errstate(divide="ignore", invalid="ignore"):
            u, v = np.floor(pix[:, 0] / z + 0.5), np.floor(pix[:, 1] / z + 0.5)
        ok = (z > 1e-6) & (u >= 0) & (u < depth.shape[2]) & (v >= 0) & (v < depth.shape[1])
        for i in np.flatnonzero(ok):
            d, obj = depth[n, int(v[i]), int(u[i])], mask[n, int(v[i]), int(u[i])]
            s = d - z[i]
            if d == 0:
                shadow[i] |= obj
                continue
            if obj and s >= -trunc or not obj and s > -h / 2:
                val = min(s, trunc) if obj else trunc
                D[i] = (Wt[i] * D[i] + val) / (Wt[i] + 1)
                Wt[i] += 1
            free[i] |= s > trunc if obj else s > -h / 2
            shadow[i] |= obj and s < -trunc
    return [x.reshape(res, res, res) for x in (D, Wt, free, shadow)]


def test_scan_equals_sequential_update():
    frames = depth_render.render_views(_sphere_mesh(), views=3, width=40, height=30, noise=True, seed=0)
    frames, _ = depth_io.remove_table(frames)
    mask = frames.mask.copy()
    mask[0, 10:14, 15:20] = True  # object pixels without reading: rays of unknown space
    depth = frames.depth.astype(np.float64)
    depth[0, 10:14, 15:20] = 0.0
    origin, h = tsdf.grid_frame(np.array([CENTRE - 1.5 * R, CENTRE + 1.5 * R]), 12)
    trunc = 3 * h
    vol = tsdf.integrate(depth, frames.K, frames.poses, origin, h, 12, trunc, mask=mask)
    assert vol.tsdf.dtype == jnp.float64
    ref = _reference(depth, mask, frames.K, frames.poses, origin, h, 12, trunc)
    np.testing.assert_allclose(vol.tsdf, ref[0], atol=SEQ_TOL, rtol=0)
    np.testing.assert_array_equal(vol.weight, ref[1])
    np.testing.assert_array_equal(vol.seen_free, ref[2])
    np.testing.assert_array_equal(vol.shadow, ref[3])
    assert ref[1].max() == 3 and ref[2].any() and ref[3].any() and (ref[1] == 0).any()


def test_fused_sphere_matches_closed_form_where_observed(views, fused):
    frames, table_z = views
    h = float(fused.voxel_size)
    assert abs(float(fused.table_z) - table_z) < 1e-12 and abs(table_z) < 1e-6
    rng = np.random.default_rng(0)
    n = rng.normal(size=(4000, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    p = CENTRE + R * n
    eyes = frames.poses[:, :3, 3]
    observed = (np.einsum("pi,epi->pe", n, eyes[:, None] - p[None]) > 0).any(1)
    assert observed.mean() > 0.6
    d, g = sdf.query(fused, jnp.asarray(p[observed]))
    assert np.abs(np.asarray(d)).max() < h  # the zero level within a voxel of the true sphere
    assert np.abs(np.asarray(d)).mean() < 0.25 * h
    cos = (np.asarray(g) * n[observed]).sum(1)
    assert np.median(cos) > 0.99 and cos.min() > 0.8
    c = _centres(np.asarray(fused.origin), h, RES)
    stored = np.asarray(fused.grid)
    np.testing.assert_allclose(np.linalg.norm(stored[..., 1:], axis=-1), 1.0, atol=1e-12)
    # away from the surface, outside in the open (seen by the cameras): Euclidean distance, not the truncated one
    far = (_true(c) > 4 * h) & (c[..., 2] > 2 * R)
    assert far.any()
    np.testing.assert_allclose(stored[..., 0][far], _true(c[far]), atol=0.75 * h)
    assert stored[..., 0][far].max() > 3 * 4 * h  # well past trunc


def test_noisy_views_without_masks():
    """Sensor noise and dropout, no masks: the table comes off by RANSAC and the sphere is still within a voxel."""
    frames = depth_render.render_views(_sphere_mesh(), views=5, width=W, height=H, noise=True, seed=2)
    frames, table_z = depth_io.remove_table(frames._replace(mask=None))
    got = tsdf.fuse(frames, res=RES, table_z=table_z)
    h = float(got.voxel_size)
    n = np.random.default_rng(1).normal(size=(2000, 3))
    n = n[n[:, 2] > 0] / np.linalg.norm(n[n[:, 2] > 0], axis=1, keepdims=True)  # the upper half: seen by all
    d, _ = sdf.query(got, jnp.asarray(CENTRE + R * n))
    assert np.abs(np.asarray(d)).max() < h
    ext = sdf.object_extent(got)
    np.testing.assert_allclose(ext.lo, CENTRE - R, atol=1.5 * h)
    np.testing.assert_allclose(ext.hi, CENTRE + R, atol=1.5 * h)


def test_unseen_voxels_behind_the_object_are_not_free():
    """One camera: the shadow behind the sphere is solid, the air it saw between it and the sphere is free, and
    the space under the table is not object."""
    frames = depth_render.render_views(_sphere_mesh(), views=1, width=W, height=H)
    frames, table_z = depth_io.remove_table(frames)
    box = np.array([CENTRE - 2.5 * R, CENTRE + 2.5 * R])
    box[0, 2] = -0.02
    got = tsdf.fuse(frames, res=RES, bounds=box, table_z=table_z)
    h = float(got.voxel_size)
    c = _centres(np.asarray(got.origin), h, RES).reshape(-1, 3)
    values = np.asarray(got.grid[..., 0]).ravel()
    outside = (_true(c) > 2 * h) & (c[:, 2] > table_z + h)
    hidden = outside & _hidden(c, frames.poses[:, :3, 3], 2 * h)
    assert hidden.sum() > 50
    assert (values[hidden] < 0).all()
    eye = frames.poses[0, :3, 3]
    air = CENTRE + np.array([0.0, 0.0, 1.5 * R]) + 0.2 * (eye - CENTRE)  # above, toward the camera
    i = np.argmin(np.linalg.norm(c - air, axis=1))
    vol = tsdf.integrate(frames.depth, frames.K, frames.poses, got.origin, h, RES, 4 * h, mask=frames.mask)
    assert bool(np.asarray(vol.seen_free).ravel()[i]) and values[i] > 0
    under = c[:, 2] < table_z - h
    assert (values[under] > 0).all()  # the table is modelled apart, not as object
    ext = sdf.object_extent(got)
    assert ext.lo[2] > table_z - h  # the solid shadow does not leak under the table


def test_without_table_the_grid_bottom_is_the_table(views):
    frames, _ = views
    got = tsdf.fuse(frames, res=16)
    assert float(got.table_z) == float(got.origin[2])


def test_fused_sdf_works_with_the_planner_queries(fused):
    p = jnp.asarray(CENTRE + np.array([[0.0, 0.0, 1.2 * R], [1.3 * R, 0.0, 0.2 * R], [0.0, 0.0, 0.0]]))
    d, g = sdf.query(sdf.with_cells(fused), p)
    d0, _ = sdf.query(fused, p)
    np.testing.assert_allclose(d, d0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(np.asarray(g), axis=1), 1.0, atol=1e-12)
    assert float(d[0]) > 0 and float(d[1]) > 0 and float(d[2]) < 0
    grads = jax.grad(lambda x: sdf.distance(fused, x).sum())(p)
    assert np.isfinite(np.asarray(grads)).all()


def test_to_gradient_sdf_turns_a_projective_field_into_distances():
    """A truncated field of twice the sphere distance (the slope a slanted view gives) becomes the Euclidean
    distance: exact to first order at the surface, close away from it."""
    origin, h = tsdf.grid_frame(np.array([CENTRE - R, CENTRE + R]), RES, margin=0.3)
    c = _centres(origin, h, RES)
    values = np.clip(2.0 * _true(c), -4 * h, 4 * h)
    got = tsdf.to_gradient_sdf(values, origin, h, 0.0)
    err = np.abs(np.asarray(got.grid[..., 0]) - _true(c))
    near = np.abs(_true(c)) < h
    assert err[near].max() < 0.05 * h
    assert err.max() < 0.2 * h
    with pytest.raises(FfcgsError, match="no voxel inside the object"):
        tsdf.to_gradient_sdf(np.ones((8, 8, 8)), origin, h, 0.0)


def test_second_fuse_of_the_same_shapes_does_not_recompile(views):
    frames, table_z = views
    noisy = depth_render.render_views(_sphere_mesh(), views=5, width=W, height=H, noise=True, seed=7)
    noisy, tz = depth_io.remove_table(noisy)
    tsdf.fuse(noisy, res=16, table_z=tz)
    with compile_clock.compiling() as seconds:
        other = tsdf.fuse(frames, res=16, table_z=table_z, trunc_voxels=3.0)  # other values, same shapes
    assert seconds[0] == 0.0
    assert float(other.voxel_size) > 0


def test_bad_arguments_raise_one_line(views):
    frames, _ = views
    with pytest.raises(FfcgsError, match=r"res must be an integer in \[16, 128\], got 8"):
        tsdf.fuse(frames, res=8)
    with pytest.raises(FfcgsError, match=r"trunc_voxels must be in \[1, 16\], got 0.5"):
        tsdf.fuse(frames, trunc_voxels=0.5)
    with pytest.raises(FfcgsError, match="no depth reading on the object"):
        tsdf.fuse(frames._replace(mask=np.zeros_like(frames.mask)), res=16)
    with pytest.raises(FfcgsError, match=r"poses must have shape \(5, 4, 4\)"):
        tsdf.fuse(frames._replace(poses=frames.poses[:4]), res=16)


def test_jump_flooding_finds_the_nearest_seed():
    """Jump flooding against a KD-tree's exact nearest seed, for scattered sub-voxel seeds on a 32^3 grid."""
    rng = np.random.default_rng(3)
    seeds = np.full((RES, RES, RES, 3), np.inf)
    at = rng.integers(0, RES, size=(60, 3))
    seeds[tuple(at.T)] = at + rng.uniform(-0.5, 0.5, size=(60, 3))
    got = np.asarray(tsdf.jump_flood(jnp.asarray(seeds)))
    ijk = _centres(np.zeros(3), 1.0, RES).reshape(-1, 3)
    exact = cKDTree(seeds[tuple(at.T)]).query(ijk)[0].reshape((RES,) * 3)
    err = got - exact
    assert err.min() > -1e-9  # never nearer than the nearest seed
    assert np.percentile(err, 99.9) < 1e-6 and err.max() < 0.5


@pytest.mark.parametrize("res, box", [(RES, False), (17, False), (RES, True)])  # 17: the jump steps do not halve
def test_device_conversion_matches_the_kdtree_reference(views, res, box):
    """`fuse` compiled from the frames (grid frame, table band, box, fusion, conversion by jump flooding) against
    the host's steps (NumPy, the exact nearest crossing by a KD-tree)."""
    frames, table_z = views
    bounds = np.array([CENTRE - 1.6 * R, CENTRE + 1.6 * R]) if box else None
    dev = tsdf.fuse(frames, res=res, table_z=table_z, bounds=bounds, on_device=True)
    ref = tsdf.fuse(frames, res=res, table_z=table_z, bounds=bounds, on_device=False)
    h = float(ref.voxel_size)
    for k in ("origin", "voxel_size", "table_z"):
        np.testing.assert_allclose(np.asarray(getattr(dev, k)), np.asarray(getattr(ref, k)), atol=1e-12)
    d = np.abs(np.asarray(dev.grid[..., 0]) - np.asarray(ref.grid[..., 0])) / h
    # the device keeps one crossing per voxel (the nearest of its edges'), so it may miss one by < 1/2 voxel
    assert np.median(d) < 1e-6 and np.percentile(d, 99) < 0.2 and d.max() < 0.5
    assert (np.sign(np.asarray(dev.grid[..., 0])) == np.sign(np.asarray(ref.grid[..., 0]))).all()
    dots = (np.asarray(dev.grid[..., 1:]) * np.asarray(ref.grid[..., 1:])).sum(-1)
    assert np.percentile(dots, 1) > 0.95


def test_fused_box_matches_closed_form_on_its_seen_faces():
    """A box on the table: its top and side faces (seen by cameras 35 degrees up) against the closed form."""
    half = np.array([0.03, 0.04, 0.025])
    centre = np.array([0.0, 0.0, half[2]])
    box = trimesh.creation.box(2 * half).apply_translation(centre)
    frames, table_z = depth_io.remove_table(depth_render.render_views(box, views=5, width=W, height=H))
    fused = tsdf.fuse(frames, res=RES, table_z=table_z)
    h = float(fused.voxel_size)
    rng = np.random.default_rng(1)
    p, face = trimesh.sample.sample_surface(box, 4000, seed=1)
    normals = box.face_normals[face]
    seen = (normals[:, 2] > -0.5) & (p[:, 2] > 0.004)  # not the bottom (on the table), not the rim at the table
    # away from edges by a voxel: there the trilinear field rounds the corner by design
    inner = (np.abs(np.abs(p - centre) - half) > h).sum(1) >= 2
    d, g = sdf.query(fused, jnp.asarray(p[seen & inner]))
    err = np.abs(np.asarray(d)) / h  # at 160 x 120 a pixel covers about a voxel (2.9 mm at 0.45 m)
    assert np.median(err) < 0.15 and np.percentile(err, 95) < 0.8 and err.max() < 1.5
    assert np.median((np.asarray(g) * normals[seen & inner]).sum(1)) > 0.99
    q = centre + rng.uniform(-1, 1, size=(2000, 3)) * (half + 3 * h)  # around the box, above the table
    q = q[q[:, 2] > 0]
    closed = np.linalg.norm(np.maximum(np.abs(q - centre) - half, 0), axis=1) \
        + np.minimum(np.max(np.abs(q - centre) - half, axis=1), 0)
    near = np.abs(closed) < 2 * h
    got = np.asarray(sdf.distance(fused, jnp.asarray(q[near])))
    assert np.median(np.abs(got - closed[near])) < 0.2 * h


def test_frames_in_any_order_give_the_same_grid(views):
    frames, table_z = views
    order = np.array([3, 0, 4, 2, 1])
    shuffled = frames._replace(depth=frames.depth[order], poses=frames.poses[order], mask=frames.mask[order],
                               names=tuple(frames.names[i] for i in order))
    a = tsdf.fuse(frames, res=RES, table_z=table_z)
    b = tsdf.fuse(shuffled, res=RES, table_z=table_z)
    np.testing.assert_allclose(np.asarray(a.grid), np.asarray(b.grid), atol=1e-12)  # the mean's rounding only
