"""Synthetic depth views: exact depth and masks against closed forms and trimesh, camera conventions, seeded noise."""

import numpy as np
import pytest
import trimesh

from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.geometry import depth_render, mesh_io

DEPTH_TOL = 1e-6  # m: ray cast vs closed form (float64 on both sides)
BOX_EXTENTS = np.array([0.1, 0.08, 0.06])
BOX_CENTRE = np.array([0.0, 0.0, 0.03])  # resting on z = 0
W, H = 80, 60


@pytest.fixture(scope="module")
def box():
    return trimesh.creation.box(extents=BOX_EXTENTS, transform=trimesh.transformations.translation_matrix(BOX_CENTRE))


def _rays(K, pose, width, height):
    """World direction (H, W, 3) of each pixel-centre ray, scaled to camera z = 1."""
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    return np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T @ pose[:3, :3].T


def _box_hits(eye, d):
    """Slab test: entry parameter (camera depth) of each ray against the box, inf where it misses."""
    lo, hi = BOX_CENTRE - BOX_EXTENTS / 2, BOX_CENTRE + BOX_EXTENTS / 2
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (lo - eye) / d, (hi - eye) / d
    near, far = np.minimum(t1, t2).max(-1), np.maximum(t1, t2).min(-1)
    return np.where((near <= far) & (near > 0), near, np.inf)


def test_camera_convention():
    """OpenCV axes: z toward the target, y down (world z up appears up in the image), right-handed."""
    pose = depth_render.look_at(np.array([0.0, -0.5, 0.2]), np.zeros(3))
    R = pose[:3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) > 0
    np.testing.assert_allclose(R[:, 2], np.array([0.0, 0.5, -0.2]) / np.hypot(0.5, 0.2), atol=1e-12)
    assert R[2, 1] < 0 and R[0, 0] > 0.99  # image down is world down; image right is world +x seen from -y
    K = depth_render.camera_K()
    assert K[0, 0] == K[1, 1] == 615.0 and (K[0, 2], K[1, 2]) == (320.0, 240.0)
    poses = depth_render.view_poses(np.zeros(3), views=4, elevation_deg=30.0, distance=0.5)
    np.testing.assert_allclose(np.linalg.norm(poses[:, :3, 3], axis=1), 0.5, atol=1e-12)
    np.testing.assert_allclose(poses[:, 2, 3], 0.25, atol=1e-12)  # sin 30 * 0.5
    with pytest.raises(FfcgsError, match="straight up or down"):
        depth_render.look_at(np.array([0.0, 0.0, 1.0]), np.zeros(3))


@pytest.mark.parametrize("eye", [(0.25, -0.18, 0.3), (-0.2, 0.22, 0.15), (0.01, 0.02, 0.4)])
def test_box_depth_and_mask_match_closed_form(box, eye):
    eye = np.asarray(eye)
    pose = depth_render.look_at(eye, np.array([0.01, 0.005, 0.02]))
    K = depth_render.camera_K(W, H)
    depth, mask = depth_render.render_depth(box, K, pose, W, H, table_z=None)
    t = _box_hits(eye, _rays(K, pose, W, H))
    np.testing.assert_array_equal(mask, np.isfinite(t))  # exactly the pixels whose ray hits the box
    assert 0.05 < mask.mean() < 0.95
    np.testing.assert_allclose(depth[mask], t[mask], atol=DEPTH_TOL, rtol=0)
    assert (depth[~mask] == 0).all()
    # with the table z = 0: the other pixels read the plane, the mask is unchanged
    depth_t, mask_t = depth_render.render_depth(box, K, pose, W, H, table_z=0.0)
    np.testing.assert_array_equal(mask_t, mask)
    d = _rays(K, pose, W, H)
    plane = np.where(d[..., 2] < 0, -eye[2] / np.where(d[..., 2] < 0, d[..., 2], -1.0), 0.0)
    np.testing.assert_allclose(depth_t[~mask], plane[~mask], atol=DEPTH_TOL, rtol=0)
    np.testing.assert_allclose(depth_t[mask], t[mask], atol=DEPTH_TOL, rtol=0)


def test_mug_matches_trimesh_ray_caster():
    """Same hits as trimesh's intersector (an independent ray-triangle code) on a concave mesh."""
    mug = mesh_io.load_mesh("mug")
    K = depth_render.camera_K(W, H)
    for pose in depth_render.view_poses(mug.bounds.mean(0), views=2, distance=0.3):
        depth, mask = depth_render.render_depth(mug, K, pose, W, H)
        d = _rays(K, pose, W, H).reshape(-1, 3)
        loc, ray, _ = mug.ray.intersects_location(np.broadcast_to(pose[:3, 3], d.shape), d, multiple_hits=False)
        ref = np.zeros(W * H)
        ref[ray] = (loc - pose[:3, 3]) @ pose[:3, 2]
        both = mask.ravel() & (ref > 0)
        assert (mask.ravel() != (ref > 0)).sum() <= 2  # rays through a shared edge may count on either side
        np.testing.assert_allclose(depth.ravel()[both], ref[both], atol=1e-9, rtol=0)


def test_render_views_masks_are_the_object(box):
    frames = depth_render.render_views(box, views=3, width=W, height=H)
    assert frames.depth.shape == (3, H, W) and frames.depth.dtype == np.float32 and frames.mask.shape == (3, H, W)
    for i in range(3):
        alone, mask = depth_render.render_depth(box, frames.K, frames.poses[i], W, H, table_z=None)
        np.testing.assert_array_equal(frames.mask[i], mask)
        np.testing.assert_allclose(frames.depth[i][mask], alone[mask], rtol=1e-6)  # float32 storage
        assert (frames.depth[i][~mask] > 0).all()  # the table fills the rest from these elevations
    bare = depth_render.render_views(box, views=3, width=W, height=H, table=False)
    np.testing.assert_array_equal(bare.depth > 0, bare.mask)


def test_noise_is_seeded_and_grows_with_depth(box):
    a = depth_render.render_views(box, views=2, width=W, height=H, noise=True, seed=3)
    b = depth_render.render_views(box, views=2, width=W, height=H, noise=True, seed=3)
    c = depth_render.render_views(box, views=2, width=W, height=H, noise=True, seed=np.random.default_rng(4))
    clean = depth_render.render_views(box, views=2, width=W, height=H)
    np.testing.assert_array_equal(a.depth, b.depth)
    assert np.abs(a.depth - c.depth).max() > 1e-4
    lost = (a.depth == 0) & (clean.depth > 0)
    assert 0.005 < lost.mean() < 0.05  # the 2 % dropout
    rng = np.random.default_rng(0)
    stds = []
    for z in (0.5, 1.0):
        flat = np.full((200, 200), z)
        noisy = depth_render.add_noise(flat, rng, a=0.002, dropout=0.0)
        stds.append(np.std(noisy - flat))
        np.testing.assert_allclose(stds[-1], 0.002 * z**2, rtol=0.03)
    assert stds[1] > 3.5 * stds[0]  # sigma ~ z^2: x4 from 0.5 m to 1 m
    assert (depth_render.add_noise(np.zeros((4, 4)), rng) == 0).all()  # no reading stays no reading
