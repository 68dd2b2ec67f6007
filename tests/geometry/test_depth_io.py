"""Depth frames: folder and npz round trips, one-line errors for every bad input, background removal."""

import json

import numpy as np
import pytest
import trimesh
from PIL import Image

from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.geometry import depth_io, depth_render

SCALE = 0.001  # m per PNG unit
TABLE_TOL = 0.002  # m: RANSAC table height vs the true one, with sensor noise
W, H = 40, 30


@pytest.fixture(scope="module")
def frames():
    box = trimesh.creation.box(extents=(0.06, 0.05, 0.04))
    return depth_render.render_views(box, views=3, width=W, height=H)


@pytest.fixture
def folder(tmp_path, frames):
    return depth_io.write_frames(frames, tmp_path / "views", depth_scale=SCALE)


def _edit_json(path, edit):
    data = json.loads(path.read_text())
    edit(data)
    path.write_text(json.dumps(data))


def test_folder_round_trip(folder, frames):
    names = sorted(p.name for p in folder.iterdir())
    assert names == ["camera.json", "poses.json"] + [f"view_00{i}{s}.png" for i in range(3) for s in ("", "_mask")]
    back = depth_io.load_frames(folder)
    assert back.names == ("view_000.png", "view_001.png", "view_002.png")  # masks are not frames
    assert back.depth.dtype == np.float32 and back.depth.shape == frames.depth.shape
    np.testing.assert_allclose(back.depth, frames.depth, atol=SCALE / 2 + 1e-6, rtol=0)
    np.testing.assert_array_equal(back.K, frames.K)
    np.testing.assert_array_equal(back.poses, frames.poses)  # JSON keeps every float64 digit
    np.testing.assert_array_equal(back.mask, frames.mask)
    assert (Image.open(folder / "view_000.png").mode, Image.open(folder / "view_000_mask.png").mode) == ("I;16", "L")


def test_npy_depth_and_range_limits(folder, frames):
    (folder / "view_001.png").unlink()
    np.save(folder / "view_001.npy", np.where(frames.depth[1] > 0.45, np.nan, frames.depth[1]).astype(np.float32))
    _edit_json(folder / "camera.json", lambda c: c.update(depth_max=0.42))
    _edit_json(folder / "poses.json", lambda p: p.update({"view_001.npy": p.pop("view_001.png")}))
    back = depth_io.load_frames(folder)
    assert back.names[1] == "view_001.npy"
    expect = np.where(frames.depth[1] <= 0.42, frames.depth[1], 0.0)
    np.testing.assert_allclose(back.depth[1], expect, atol=1e-7)
    assert back.depth.max() <= 0.42


def test_npz_input(tmp_path, frames):
    np.savez(tmp_path / "f.npz", depth=frames.depth, K=frames.K, poses=frames.poses)
    back = depth_io.load_frames(tmp_path / "f.npz")
    np.testing.assert_array_equal(back.depth, frames.depth)
    assert back.mask is None and back.names == ("f[0]", "f[1]", "f[2]")
    np.savez(tmp_path / "m.npz", depth=frames.depth.astype(np.float64), K=frames.K, poses=frames.poses,
             mask=frames.mask.astype(np.uint8))
    np.testing.assert_array_equal(depth_io.load_frames(tmp_path / "m.npz").mask, frames.mask)


def _rigid_fail(p):
    p[0][0] = 1.1


@pytest.mark.parametrize("edit, match", [
    (lambda f: (f / "camera.json").unlink(), "has no camera.json"),
    (lambda f: _edit_json(f / "camera.json", lambda c: c.pop("fy")), r"camera.json lacks key\(s\) fy"),
    (lambda f: _edit_json(f / "camera.json", lambda c: c.update(fx=-615.0)), "fx must be > 0, got -615"),
    (lambda f: _edit_json(f / "camera.json", lambda c: c.update(k1=0.1)), r"unknown key\(s\) k1"),
    (lambda f: _edit_json(f / "camera.json", lambda c: c.update(width=41)), "is 40x30 pixels, camera.json says 41x30"),
    (lambda f: _edit_json(f / "poses.json", lambda p: p.pop("view_001.png")), "no pose for depth image view_001.png"),
    (lambda f: _edit_json(f / "poses.json", lambda p: p.update({"ghost.png": p["view_000.png"]})),
     "pose for ghost.png, but .* has no such depth image"),
    (lambda f: _edit_json(f / "poses.json", lambda p: _rigid_fail(p["view_002.png"])), "not orthonormal"),
    (lambda f: _edit_json(f / "poses.json", lambda p: p.update({"view_000.png": [[1, 0, 0, 0]] * 3})),
     "pose of view_000.png must be a 4x4 matrix, got shape"),
    (lambda f: _edit_json(f / "poses.json", lambda p: p["view_000.png"][0].__setitem__(3, float("nan"))),
     "NaN or inf"),
    (lambda f: (f / "poses.json").write_text("{"), "poses.json is not valid JSON"),
    (lambda f: Image.fromarray(np.zeros((H, W), np.uint8)).save(f / "view_001.png"),
     "view_001.png must be a 16-bit grayscale PNG, got 8-bit grayscale"),
    (lambda f: Image.fromarray(np.zeros((H, W, 3), np.uint8)).save(f / "view_001_mask.png"),
     "mask .*view_001_mask.png must be a grayscale PNG, got 8-bit RGB"),
    (lambda f: (f / "view_002_mask.png").unlink(), "masks for 2 of 3 images; view_002_mask.png is missing"),
    (lambda f: (f / "view_002.png").rename(f / "other.png"), "no pose for depth image other.png"),
    (lambda f: (f / "view_001.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"\0" * 40), "is not a PNG image"),
    (lambda f: [p.unlink() for p in f.glob("view_00?.png")], "has no depth images"),
])
def test_bad_folder_raises_one_line(folder, edit, match):
    edit(folder)
    with pytest.raises(FfcgsError, match=match) as err:
        depth_io.load_frames(folder)
    assert "\n" not in str(err.value)


@pytest.mark.parametrize("change, match", [
    ({"poses": np.eye(4)[None].repeat(2, 0)}, r"poses must have shape \(3, 4, 4\) for 3 depth frames, got \(2, 4, 4\)"),
    ({"depth": np.zeros((3, 30))}, r"depth must have shape \(N, H, W\), got \(3, 30\)"),
    ({"depth": np.zeros((0, H, W)), "poses": np.zeros((0, 4, 4))}, "no depth frames"),
    ({"K": np.full((3, 3), np.nan)}, "K contains NaN or inf"),
    ({"K": np.eye(2)}, r"K must have shape \(3, 3\), got \(2, 2\)"),
    ({"mask": np.ones((3, H, W + 1), bool)}, "mask must have the shape of depth"),
    ({"depth": -np.ones((3, H, W))}, "depth values are negative or infinite"),
    ({"depth": np.ones((3, H, W), np.uint16)}, "depth must be floats, got dtype uint16"),
    ({"extra": np.ones(2)}, r"unknown key\(s\) extra"),
])
def test_bad_npz_raises_one_line(tmp_path, frames, change, match):
    arrays = {"depth": frames.depth, "K": frames.K, "poses": frames.poses} | change
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(FfcgsError, match=match):
        depth_io.load_frames(tmp_path / "bad.npz")


def test_missing_inputs(tmp_path, frames):
    with pytest.raises(FfcgsError, match="depth input not found"):
        depth_io.load_frames(tmp_path / "nowhere")
    np.savez(tmp_path / "few.npz", depth=frames.depth, K=frames.K)
    with pytest.raises(FfcgsError, match=r"lacks key\(s\) poses"):
        depth_io.load_frames(tmp_path / "few.npz")
    (tmp_path / "text.npz").write_text("hello")
    with pytest.raises(FfcgsError, match="not a readable depth .npz: it is a text file"):
        depth_io.load_frames(tmp_path / "text.npz")
    with pytest.raises(FfcgsError, match="does not fit a 16-bit PNG"):
        depth_io.write_frames(frames._replace(depth=frames.depth * 200), tmp_path / "far")


def test_table_is_found_and_removed():
    """Noisy views of a box standing on a table at 0.1 m: the RANSAC height is within 2 mm, the table readings
    leave the mask and the object's stay."""
    box = trimesh.creation.box(extents=(0.06, 0.05, 0.08),
                               transform=trimesh.transformations.translation_matrix((0.02, -0.01, 0.14)))
    frames = depth_render.render_views(box, views=4, width=160, height=120, noise=True, seed=1)
    truth = frames.mask
    bare = frames._replace(mask=None)
    cut, table_z = depth_io.remove_table(bare)
    assert abs(table_z - 0.1) < TABLE_TOL
    readings = frames.depth > 0
    table_left = (cut.mask & ~truth)[readings].sum() / (~truth & readings).sum()
    assert table_left < 0.01
    object_kept = (cut.mask & truth).sum() / (truth & readings).sum()
    assert object_kept > 0.9  # all but the bottom 5 mm band and noise
    points = depth_io.world_points(frames)[readings]
    kept, tz = depth_io.remove_table(points, seed=2)
    assert abs(tz - 0.1) < TABLE_TOL and len(kept) < 0.5 * len(points) and (kept[:, 2] > 0.1).all()
    given, tz = depth_io.remove_table(bare, table_z=0.1)
    assert tz == 0.1 and (given.mask <= readings).all()
    with pytest.raises(FfcgsError, match="no table found: no plane within 10 degrees"):
        depth_io.fit_table(np.random.default_rng(0).normal(size=(50, 3)), tol=1e-9)
    wall = np.c_[np.random.default_rng(0).uniform(size=(100, 1)), np.zeros((100, 1)), np.linspace(0, 1, 100)]
    with pytest.raises(FfcgsError, match="no table found"):
        depth_io.fit_table(wall)


def test_crop_and_apply_mask(frames):
    p = depth_io.world_points(frames)
    box = np.array([[-1.0, -1.0, 0.005], [1.0, 1.0, 1.0]])  # above the table
    cut = depth_io.crop(frames._replace(mask=None), box)
    np.testing.assert_array_equal(cut.mask, (frames.depth > 0) & (p[..., 2] >= 0.005))
    hard = depth_io.apply_mask(frames)
    assert hard.mask is None
    np.testing.assert_array_equal(hard.depth > 0, frames.mask)
    with pytest.raises(FfcgsError, match="bounds must be finite"):
        depth_io.crop(frames, np.array([[0.0, 0.0, 0.0], [1.0, -1.0, 1.0]]))


def test_frames_written_in_the_old_argument_order_get_one_line(tmp_path, frames):
    """`save_frames(folder, frames)` (the order before the public API took one order): refused in one line, and
    nothing written."""
    with pytest.raises(FfcgsError, match="the frames come first"):
        depth_io.save_frames(tmp_path / "old", frames)
    assert not (tmp_path / "old").exists()
