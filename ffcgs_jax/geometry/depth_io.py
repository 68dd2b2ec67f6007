"""Depth frames in and out: the input of TSDF fusion (`tsdf.fuse`), checked with one-line errors, and the helpers
that tell the object's readings from the background.

Two input forms, both read by `load_frames`:

- a folder holding `camera.json` (fx fy cx cy in pixels, width height, depth_scale in metres per PNG unit; optional
  depth_min, depth_max in metres: readings outside are dropped), depth images `*.png` (16-bit grayscale; depth =
  value * depth_scale; 0 = no reading) or `*.npy` (float32 metres; 0 or NaN = no reading), `poses.json` mapping each
  image's file name to its 4x4 camera-to-world pose, and optional object masks `<stem>_mask.png` (nonzero = object;
  one per image or none);
- one `.npz` holding depth (N, H, W) float metres, K (3, 3), poses (N, 4, 4) and optionally mask (N, H, W).

Conventions: OpenCV camera (x right, y down, z forward; pixel (u, v) = (column, row), centres at integers), depth
is the camera z of the surface point (not the ray length), world z up with the table horizontal.

The mask is the object/background split that fusion uses: readings outside it are background, whose rays carve
free space but put no surface into the object (see `tsdf`). `remove_table` and `crop` therefore narrow the mask and
keep the depth; `apply_mask` is the hard cut (background readings set to 0) for consumers that want object points
only.
"""

import json
import pathlib
import warnings
from typing import NamedTuple

import numpy as np
from PIL import Image

from ffcgs_jax.core import files
from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.core.files import read_text
from ffcgs_jax.core.types import Bool, Float

CAMERA_KEYS = ("fx", "fy", "cx", "cy", "width", "height", "depth_scale")
CAMERA_OPTIONAL = ("depth_min", "depth_max")
NPZ_KEYS = ("depth", "K", "poses")
ROTATION_TOL = 1e-3  # |R^T R - I| of a pose: looser than float32 round-off of a saved pose, tighter than a typo
_PNG = b"\x89PNG\r\n\x1a\n"
_COLOUR = {0: "grayscale", 2: "RGB", 3: "palette", 4: "grayscale+alpha", 6: "RGBA"}
_MASK = "_mask"
TABLE_BAND = 0.005  # m: readings this close above the table count as table (noise, the object's contact rim)
_TABLE_SHARE = 0.05  # a table seen by the cameras holds at least this share of the readings
_FIT_POINTS, _SCORE_POINTS = 100_000, 20_000  # random readings for the table's refit and hypothesis scores


class Frames(NamedTuple):
    """Depth frames of one object (host NumPy).

    Attributes:
        depth: (N, H, W) float32 depth in metres along the camera z axis; 0 = no reading.
        K: (3, 3) float64 pinhole intrinsics in pixels, shared by all frames.
        poses: (N, 4, 4) float64 camera-to-world transforms (OpenCV camera axes, world z up).
        mask: (N, H, W) bool, True on the object, or None (every reading is the object's).
        names: N frame names (image file names for the folder form).
    """

    depth: Float[np.ndarray, "N H W"]
    K: Float[np.ndarray, "3 3"]
    poses: Float[np.ndarray, "N 4 4"]
    mask: Bool[np.ndarray, "N H W"] | None
    names: tuple[str, ...]


# ----------------------------------------------------------------------------------------------------------------
# Checks shared by both forms
# ----------------------------------------------------------------------------------------------------------------


def _check_pose(pose: np.ndarray, what: str) -> None:
    if pose.shape != (4, 4):
        raise FfcgsError(f"{what} must be a 4x4 matrix, got shape {pose.shape}")
    if not np.isfinite(pose).all():
        raise FfcgsError(f"{what} contains NaN or inf")
    if np.abs(pose[3] - (0, 0, 0, 1)).max() > ROTATION_TOL:
        raise FfcgsError(f"{what} must have last row 0 0 0 1, got {pose[3].tolist()}")
    r = pose[:3, :3]
    err = float(np.abs(r.T @ r - np.eye(3)).max())
    if err > ROTATION_TOL:
        raise FfcgsError(f"{what} has a rotation that is not orthonormal (|R^T R - I| = {err:.3g} > {ROTATION_TOL})")
    if np.linalg.det(r) < 0:
        raise FfcgsError(f"{what} has a reflection (det R = -1), not a rotation")


def _check_K(K: np.ndarray, what: str) -> None:
    if K.shape != (3, 3):
        raise FfcgsError(f"{what}: K must have shape (3, 3), got {K.shape}")
    if not np.isfinite(K).all():
        raise FfcgsError(f"{what}: K contains NaN or inf")
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise FfcgsError(f"{what}: K's focal lengths fx = {K[0, 0]:g}, fy = {K[1, 1]:g} must be > 0")
    if np.abs(K[1, 0]) + np.abs(K[2] - (0, 0, 1)).max() > 0:
        raise FfcgsError(f"{what}: K must be upper triangular with last row 0 0 1, got {K.tolist()}")


def check_frames(frames: Frames, what: str = "frames") -> Frames:
    """`frames` with checked shapes and values, in the dtypes of `Frames` (NaN depth becomes 0).

    Raises:
        FfcgsError naming `what` and the field: zero frames, wrong shapes, non-float depth, negative or infinite
        depth, bad K (NaN, fx or fy <= 0), poses that are not finite rigid transforms, a mask of another shape.
    """
    depth, mask = np.asarray(frames.depth), frames.mask
    if depth.ndim != 3:
        raise FfcgsError(f"{what}: depth must have shape (N, H, W), got {depth.shape}")
    n = depth.shape[0]
    if n == 0 or depth.shape[1] == 0 or depth.shape[2] == 0:
        raise FfcgsError(f"{what}: no depth frames (depth has shape {depth.shape})")
    if not np.issubdtype(depth.dtype, np.floating):
        raise FfcgsError(f"{what}: depth must be float metres, got dtype {depth.dtype}")
    depth = depth.astype(np.float32, copy=False)
    if np.isnan(depth).any():  # checked first: five 640 x 480 frames cost 1 ms here, 5 ms through nan_to_num
        depth = np.where(np.isnan(depth), np.float32(0), depth)
    if not (np.isfinite(depth).all() and depth.min() >= 0):
        bad = int((~np.isfinite(depth) | (depth < 0)).sum())
        raise FfcgsError(f"{what}: {bad} depth values are negative or infinite (use 0 or NaN for no reading)")
    K = np.asarray(frames.K, np.float64)
    _check_K(K, what)
    poses = np.asarray(frames.poses, np.float64)
    if poses.shape != (n, 4, 4):
        raise FfcgsError(f"{what}: poses must have shape ({n}, 4, 4) for {n} depth frames, got {poses.shape}")
    names = tuple(frames.names) if frames.names is not None else tuple(f"frame_{i:03d}" for i in range(n))
    if len(names) != n:
        raise FfcgsError(f"{what}: {len(names)} names for {n} depth frames")
    for name, pose in zip(names, poses):
        _check_pose(pose, f"{what}: pose of {name}")
    if mask is not None:
        mask = np.asarray(mask)
        if mask.shape != depth.shape:
            raise FfcgsError(f"{what}: mask must have the shape of depth {depth.shape}, got {mask.shape}")
        if mask.dtype.kind not in "biuf":
            raise FfcgsError(f"{what}: mask must be bool or numbers (nonzero = object), got dtype {mask.dtype}")
        mask = mask != 0
    return Frames(depth, K, poses, mask, names)


# ----------------------------------------------------------------------------------------------------------------
# Reading
# ----------------------------------------------------------------------------------------------------------------


def _png_format(path: pathlib.Path) -> tuple[int, int]:
    """(bit depth, colour type) from the PNG header, without decoding."""
    with open(path, "rb") as f:
        head = f.read(26)
    if len(head) < 26 or not head.startswith(_PNG) or head[12:16] != b"IHDR":
        raise FfcgsError(f"{path} is not a PNG image")
    return head[24], head[25]


def _read_png(path: pathlib.Path, kind: str, sixteen: bool) -> np.ndarray:
    bits, colour = _png_format(path)
    if colour != 0 or (sixteen and bits != 16):
        got = f"{bits}-bit {_COLOUR.get(colour, f'colour type {colour}')}"
        need = "16-bit grayscale" if sixteen else "grayscale"
        raise FfcgsError(f"{kind} {path} must be a {need} PNG, got {got}")
    try:
        with Image.open(path) as im:
            im.load()
            return np.asarray(im)
    except Exception as e:  # noqa: BLE001 - a truncated or corrupt file: any decode failure is the file's
        raise FfcgsError(f"cannot read {kind} {path}: {type(e).__name__}: {e}") from None


def _read_json(path: pathlib.Path) -> dict:
    if not path.exists():
        raise FfcgsError(f"depth folder {path.parent} has no {path.name}")
    text = read_text(path, "file")
    try:
        data = json.loads(text)
    except ValueError as e:
        raise FfcgsError(f"{path} is not valid JSON: {e}") from None
    if not isinstance(data, dict):
        raise FfcgsError(f"{path} must hold a JSON object, got {type(data).__name__}")
    return data


def _read_camera(path: pathlib.Path) -> dict[str, float]:
    cam = _read_json(path)
    missing = [k for k in CAMERA_KEYS if k not in cam]
    if missing:
        raise FfcgsError(f"{path} lacks key(s) {', '.join(missing)} (needs {' '.join(CAMERA_KEYS)})")
    unknown = sorted(set(cam) - set(CAMERA_KEYS) - set(CAMERA_OPTIONAL))
    if unknown:
        raise FfcgsError(f"{path} has unknown key(s) {', '.join(unknown)}; valid: "
                         f"{' '.join(CAMERA_KEYS + CAMERA_OPTIONAL)}")
    for k, v in cam.items():
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
            raise FfcgsError(f"{path}: {k} must be a finite number, got {v!r}")
    for k in ("fx", "fy", "depth_scale"):
        if not cam[k] > 0:
            raise FfcgsError(f"{path}: {k} must be > 0, got {cam[k]}")
    for k in ("width", "height"):
        if cam[k] != int(cam[k]) or cam[k] < 1:
            raise FfcgsError(f"{path}: {k} must be a positive whole number of pixels, got {cam[k]}")
    lo, hi = cam.get("depth_min", 0.0), cam.get("depth_max", np.inf)
    if not 0 <= lo < hi:
        raise FfcgsError(f"{path}: need 0 <= depth_min < depth_max, got depth_min {lo}, depth_max {hi}")
    return cam


def _listed(folder: pathlib.Path) -> list[pathlib.Path]:
    """The folder's files; only those its manifest names when a run of ours wrote it (`files.manifest_files`),
    so a file left there by anything else is never read as a frame or a mask."""
    named = files.manifest_files(folder)
    return [p for p in folder.iterdir() if p.is_file() and (named is None or p.name in named)]


def _say_unlisted(folder: pathlib.Path) -> None:
    """One warning line when the folder's manifest leaves files out (masks added by hand to a rendered folder):
    they are not read, and the user is told which manifest decides and how to have them read."""
    ignored = files.unlisted(folder)
    if ignored:
        warnings.warn(f"depth folder {folder} holds {len(ignored)} file(s) that its manifest "
                      f"{folder / files.MANIFEST} does not name (e.g. {ignored[0]}); they are ignored (delete the "
                      "manifest to read every file there)", stacklevel=3)


def _hidden(folder: pathlib.Path, name: str) -> str:
    """The words for a file `name` that exists in `folder` but that its manifest leaves out, for an error that would
    otherwise say it is missing; "" when it does not exist or there is no manifest."""
    named = files.manifest_files(folder)
    if named is None or name in named or not (folder / name).is_file():
        return ""
    return (f" ({folder / name} exists, but the folder's manifest {folder / files.MANIFEST} does not name it, so it "
            "is not read; delete the manifest to read every file there)")


def _depth_files(folder: pathlib.Path) -> list[pathlib.Path]:
    found = sorted(p for p in _listed(folder) if p.suffix.lower() in (".png", ".npy")
                   and not (p.suffix.lower() == ".png" and p.stem.endswith(_MASK)))
    if not found:
        named = files.manifest_files(folder)
        why = "" if named is None else f" that its manifest {folder / files.MANIFEST} names"
        raise FfcgsError(f"depth folder {folder} has no depth images{why} (*.png or *.npy besides *{_MASK}.png)")
    twins = files.duplicate_stems(found)
    if twins:
        raise FfcgsError(f"depth folder {folder} has two depth images named {twins[0]} (.png and .npy); keep one")
    return found


def _read_depth(path: pathlib.Path, cam: dict[str, float]) -> np.ndarray:
    if path.suffix.lower() == ".png":
        depth = _read_png(path, "depth image", sixteen=True).astype(np.float64) * cam["depth_scale"]
    else:
        depth = files.read_npz(path, "depth image", ".npy", npy=True)[""]
        if depth.ndim != 2 or not np.issubdtype(depth.dtype, np.floating):
            raise FfcgsError(f"depth image {path} must be an (H, W) float array in metres, got {depth.dtype} "
                             f"{depth.shape}")
    size = (int(cam["height"]), int(cam["width"]))
    if depth.shape != size:
        raise FfcgsError(f"depth image {path} is {depth.shape[1]}x{depth.shape[0]} pixels, camera.json says "
                         f"{size[1]}x{size[0]} (width x height)")
    depth = np.where(np.isnan(depth), 0.0, depth)
    if (depth < 0).any() or np.isinf(depth).any():
        raise FfcgsError(f"depth image {path} has negative or infinite values (use 0 or NaN for no reading)")
    out_of_range = (depth < cam.get("depth_min", 0.0)) | (depth > cam.get("depth_max", np.inf))
    return np.where(out_of_range, 0.0, depth).astype(np.float32)


def _read_folder(folder: pathlib.Path) -> Frames:
    if not any(folder.iterdir()):
        raise FfcgsError(f"depth folder {folder} is empty: it holds no depth frames (camera.json, poses.json and "
                         "depth images)")
    cam = _read_camera(folder / "camera.json")
    _say_unlisted(folder)
    images = _depth_files(folder)
    poses_path = folder / "poses.json"
    poses = _read_json(poses_path)
    names = [p.name for p in images]
    for name in names:
        if name not in poses:
            raise FfcgsError(f"{poses_path} has no pose for depth image {name}")
    extra = sorted(set(poses) - set(names))
    if extra:
        raise FfcgsError(f"{poses_path} has a pose for {extra[0]}, but {folder} has no such depth image"
                         f"{_hidden(folder, extra[0])}")
    mats = []
    for name in names:
        try:
            mat = np.asarray(poses[name], np.float64)
        except (ValueError, TypeError):
            raise FfcgsError(f"{poses_path}: pose of {name} must be a 4x4 list of numbers") from None
        _check_pose(mat, f"{poses_path}: pose of {name}")
        mats.append(mat)
    mask_files = {p.stem[:-len(_MASK)]: p for p in _listed(folder) if p.name.endswith(f"{_MASK}.png")}
    stems = [p.stem for p in images]
    orphan = sorted(set(mask_files) - set(stems))
    if orphan:
        raise FfcgsError(f"mask {mask_files[orphan[0]]} has no depth image {orphan[0]}.png or {orphan[0]}.npy"
                         f"{_hidden(folder, orphan[0] + '.png') or _hidden(folder, orphan[0] + '.npy')}")
    if mask_files and len(mask_files) != len(stems):
        lacking = next(s for s in stems if s not in mask_files)
        raise FfcgsError(f"depth folder {folder} has masks for {len(mask_files)} of {len(stems)} images; "
                         f"{lacking}{_MASK}.png is missing (give a mask for every image or none)"
                         f"{_hidden(folder, f'{lacking}{_MASK}.png')}")
    depth = np.stack([_read_depth(p, cam) for p in images])
    mask = None
    if mask_files:
        mask = np.stack([_read_png(mask_files[s], "mask", sixteen=False) != 0 for s in stems])
        if mask.shape != depth.shape:
            raise FfcgsError(f"depth folder {folder}: masks must be {depth.shape[2]}x{depth.shape[1]} pixels like "
                             f"the depth images, got {mask.shape[2]}x{mask.shape[1]}")
    K = np.array([[cam["fx"], 0.0, cam["cx"]], [0.0, cam["fy"], cam["cy"]], [0.0, 0.0, 1.0]])
    return check_frames(Frames(depth, K, np.stack(mats), mask, tuple(names)), f"depth folder {folder}")


def _read_npz(path: pathlib.Path) -> Frames:
    data = files.read_npz(path, "depth file", "depth .npz")
    missing = [k for k in NPZ_KEYS if k not in data]
    if missing:
        raise FfcgsError(f"depth file {path} lacks key(s) {', '.join(missing)} (has {', '.join(sorted(data))})")
    unknown = sorted(set(data) - set(NPZ_KEYS) - {"mask"})
    if unknown:
        raise FfcgsError(f"depth file {path} has unknown key(s) {', '.join(unknown)}; valid: depth K poses mask")
    for k in ("depth", "K", "poses"):
        if not np.issubdtype(data[k].dtype, np.floating):
            raise FfcgsError(f"depth file {path}: {k} must be floats, got dtype {data[k].dtype}")
    n = len(data["depth"]) if data["depth"].ndim else 0
    names = tuple(f"{path.stem}[{i}]" for i in range(n))
    return check_frames(Frames(data["depth"], data["K"], data["poses"], data.get("mask"), names),
                        f"depth file {path}")


def load_frames(path: str | pathlib.Path) -> Frames:
    """Read depth frames from a folder (camera.json, poses.json, *.png / *.npy, *_mask.png) or an .npz file.

    Args:
        path: the folder or the .npz file (module docstring: the formats).

    Returns:
        The frames, checked (`check_frames`).

    Raises:
        FfcgsError with one line naming the file and the problem.
    """
    path = pathlib.Path(path).expanduser()
    if path.is_dir():
        return _read_folder(path)
    if path.is_file():
        return _read_npz(path)
    raise FfcgsError(f"depth input not found: {path} (a folder with camera.json and poses.json, or an .npz file)")


# ----------------------------------------------------------------------------------------------------------------
# Writing
# ----------------------------------------------------------------------------------------------------------------


def save_frames(frames, folder, depth_scale: float = 0.001) -> pathlib.Path:
    """`fj.save_frames`: `write_frames`, with one line for the order the public API had before (folder first)."""
    if isinstance(frames, (str, pathlib.Path)) and isinstance(folder, Frames):
        raise FfcgsError("save_frames(frames, folder): the frames come first, then the folder (the order changed "
                         "to match save_grasps(gs, path))")
    return write_frames(frames, folder, depth_scale)


def write_frames(frames: Frames, folder: str | pathlib.Path, depth_scale: float = 0.001) -> pathlib.Path:
    """Write `frames` as a depth folder: <stem>.png (16-bit, value = round(depth / depth_scale)), <stem>_mask.png
    (8-bit, 255 = object) when there are masks, camera.json and poses.json; each file atomically.

    Args:
        frames: the frames; K must have no skew (camera.json has none). What is written comes first, where it goes
            second, as in `save_grasps(gs, path)`.
        folder: the output folder (created if missing).
        depth_scale: metres per PNG unit (0.001: millimetres, up to 65.5 m).

    Returns:
        The folder.
    """
    frames = check_frames(frames)
    if not (np.isfinite(depth_scale) and depth_scale > 0):
        raise FfcgsError(f"depth_scale must be > 0, got {depth_scale}")
    K = frames.K
    if K[0, 1] != 0:
        raise FfcgsError(f"K has skew {K[0, 1]:g}, which camera.json cannot hold; write an .npz instead")
    units = np.round(frames.depth.astype(np.float64) / depth_scale)
    if units.max() > np.iinfo(np.uint16).max:
        raise FfcgsError(f"depth up to {frames.depth.max():.4g} m does not fit a 16-bit PNG with depth_scale "
                         f"{depth_scale:g} (at most {65535 * depth_scale:.4g} m); use a larger depth_scale")
    stems = [pathlib.Path(n).stem for n in frames.names]
    bad = [s for s in stems if not s or s.endswith(_MASK) or stems.count(s) > 1]
    if bad:
        raise FfcgsError(f"frame name {bad[0]!r} cannot be a file stem (empty, repeated, or ends with {_MASK})")
    folder = files.check_folder(folder, "depth folder")
    for i, stem in enumerate(stems):
        img = Image.fromarray(units[i].astype(np.uint16))
        files.atomic_write(folder / f"{stem}.png", lambda f, img=img: img.save(f, format="PNG"))
        if frames.mask is not None:
            m = Image.fromarray(frames.mask[i].astype(np.uint8) * 255)
            files.atomic_write(folder / f"{stem}{_MASK}.png", lambda f, m=m: m.save(f, format="PNG"))
    h, w = frames.depth.shape[1:]
    cam = {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2], "width": w, "height": h,
           "depth_scale": depth_scale}
    poses = {f"{s}.png": p.tolist() for s, p in zip(stems, frames.poses)}
    files.write_text(folder / "poses.json", json.dumps(poses, indent=1) + "\n")
    files.write_text(folder / "camera.json", json.dumps({k: float(v) if k not in ("width", "height") else int(v)
                                                         for k, v in cam.items()}, indent=1) + "\n")
    return folder


# ----------------------------------------------------------------------------------------------------------------
# Object vs background
# ----------------------------------------------------------------------------------------------------------------


def pixel_rays(K: Float[np.ndarray, "3 3"], height: int, width: int) -> Float[np.ndarray, "H W 3"]:
    """Camera-frame direction of the ray through each pixel centre, scaled to z = 1 (so depth times it is the
    point)."""
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    return transform(np.linalg.inv(K), np.stack([u, v, np.ones_like(u)], -1))


def transform(M: Float[np.ndarray, "*batch 3 3"], v: Float[np.ndarray, "*shape 3"]) -> Float[np.ndarray, "*shape 3"]:
    """M v for each vector of `v` (M broadcast against v's leading axes), as three broadcast products: numpy's
    matmul on (P, 3) x (3, 3) blocks goes through OpenBLAS threads that cost 10-50x more on a busy 2-core machine."""
    return v[..., :1] * M[..., 0] + v[..., 1:2] * M[..., 1] + v[..., 2:] * M[..., 2]


def world_points(frames: Frames) -> Float[np.ndarray, "N H W 3"]:
    """World position of every pixel's reading, metres; NaN where there is no reading."""
    h, w = frames.depth.shape[1:]
    cam = pixel_rays(frames.K, h, w)[None] * frames.depth.astype(np.float64)[..., None]
    world = transform(frames.poses[:, None, None, :3, :3], cam) + frames.poses[:, None, None, :3, 3]
    world[frames.depth <= 0] = np.nan
    return world


def pixel_points(frames: Frames, n: np.ndarray, r: np.ndarray, c: np.ndarray) -> Float[np.ndarray, "P 3"]:
    """World points of the readings at frame `n`, row `r`, column `c` (integer arrays of one shape P), metres;
    NaN where there is no reading."""
    cam = transform(np.linalg.inv(frames.K), np.stack([c, r, np.ones_like(c)], -1).astype(np.float64))
    d = frames.depth[n, r, c].astype(np.float64)
    world = transform(frames.poses[n, :3, :3], cam * d[:, None]) + frames.poses[n, :3, 3]
    world[d <= 0] = np.nan
    return world


def sample_points(frames: Frames, count: int, seed: int = 0,
                  bounds: Float[np.ndarray, "2 3"] | None = None) -> Float[np.ndarray, "P 3"]:
    """World points of `count` readings drawn at random (with replacement; the masks do not matter: the table is
    background), those outside the x-y extent of `bounds` dropped (any height: the table under the box stays):
    what a table fit needs, without the world points of every pixel (150 ms for five 640 x 480 frames)."""
    valid = np.flatnonzero(frames.depth > 0)
    if not len(valid):
        return np.zeros((0, 3))
    pick = valid[np.random.default_rng(seed).integers(0, len(valid), count)] if len(valid) > count else valid
    world = pixel_points(frames, *np.unravel_index(pick, frames.depth.shape))
    if bounds is not None:
        world = world[((world[:, :2] >= bounds[0, :2]) & (world[:, :2] <= bounds[1, :2])).all(1)]
    return world


def object_mask(frames: Frames) -> Bool[np.ndarray, "N H W"]:
    """The object's pixels: the mask, or every reading when there is none (a pixel without reading tells
    nothing)."""
    return frames.depth > 0 if frames.mask is None else frames.mask


def apply_mask(frames: Frames) -> Frames:
    """The frames with every reading outside the mask set to 0 and no mask (the hard cut; `tsdf.fuse` prefers the
    mask kept, so that background rays still carve free space)."""
    if frames.mask is None:
        return frames
    return frames._replace(depth=np.where(frames.mask, frames.depth, 0.0).astype(np.float32), mask=None)


def check_bounds(bounds) -> Float[np.ndarray, "2 3"]:
    """`bounds` as a float64 (2, 3) box [min corner, max corner], or FfcgsError."""
    b = np.asarray(bounds, np.float64)
    if b.shape != (2, 3) or not np.isfinite(b).all() or not (b[0] < b[1]).all():
        raise FfcgsError(f"bounds must be finite (2, 3) [[xmin, ymin, zmin], [xmax, ymax, zmax]] with min < max, "
                         f"got {np.asarray(bounds).tolist()}")
    return b


def crop(frames: Frames, bounds: Float[np.ndarray, "2 3"], points: np.ndarray | None = None) -> Frames:
    """The frames with readings outside the world box `bounds` (min, max corners, metres) moved to the background.
    `points`: `world_points(frames)` when the caller has it already (they take 80 ms for five 640 x 480 frames)."""
    b = check_bounds(bounds)
    p = world_points(frames) if points is None else points
    inside = ((p >= b[0]) & (p <= b[1])).all(-1)
    return frames._replace(mask=object_mask(frames) & inside)


def fit_table(points: Float[np.ndarray, "P 3"], tol: float = 0.003, max_tilt_deg: float = 10.0,
              low_fraction: float = 0.5, tries: int = 256, seed: int = 0) -> tuple[Float[np.ndarray, " 4"], float]:
    """The table plane by RANSAC: the roughly horizontal plane with the most points within `tol`.

    Hypotheses are planes through 3 points drawn among the lowest `low_fraction` of the points (the table lies
    under the object, so drawing there keeps an object's flat top from winning), kept when their normal is within
    `max_tilt_deg` of +z; the best is refit to its inliers by least squares.

    Args:
        points: (P, 3) world points in metres (z up); NaN rows are ignored.
        tol: inlier distance in metres (sensor noise on the table).
        max_tilt_deg: largest angle between the plane's normal and +z.
        low_fraction: share of the points, lowest first, that hypotheses are drawn from.
        tries: number of hypotheses.
        seed: seed of the draws.

    Returns:
        plane (4,): unit normal n (n_z > 0) and offset c with n . p + c = 0 on the plane; the table height (median
        z of the inliers), metres.
    """
    p = np.asarray(points, np.float64)
    p = p[np.isfinite(p).all(1)]
    if len(p) < 3:
        raise FfcgsError(f"table fit needs at least 3 depth readings, got {len(p)}")
    rng = np.random.default_rng(seed)
    p = p if len(p) <= _FIT_POINTS else p[rng.choice(len(p), _FIT_POINTS, replace=False)]
    score = p[:_SCORE_POINTS]  # already in random order when subsampled
    low = score[score[:, 2] <= np.quantile(score[:, 2], low_fraction)]
    a, b, c = (low[rng.integers(0, len(low), tries)] for _ in range(3))
    n = np.cross(b - a, c - a)
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    n = n / np.where(norm > 0, norm, 1.0) * np.where(n[:, 2:] < 0, -1.0, 1.0)
    ok = (norm[:, 0] > 1e-12) & (n[:, 2] >= np.cos(np.radians(max_tilt_deg)))
    counts = np.where(ok, (np.abs(score @ n.T - (a * n).sum(1)) < tol).sum(0), -1)
    best = int(np.argmax(counts))
    if counts[best] < max(10, _TABLE_SHARE * len(score)):
        raise FfcgsError(f"no table found: no plane within {max_tilt_deg:g} degrees of horizontal holds "
                         f"{_TABLE_SHARE:.0%} of the readings within {tol * 1000:g} mm; give table_z")
    plane = np.append(n[best], -n[best] @ a[best])
    for _ in range(2):  # refit: z = gx x + gy y + z0 through the inliers, then inliers again
        inl = p[np.abs(p @ plane[:3] + plane[3]) < tol]
        (gx, gy, z0), *_ = np.linalg.lstsq(np.c_[inl[:, :2], np.ones(len(inl))], inl[:, 2], rcond=None)
        normal = np.array([-gx, -gy, 1.0]) / np.sqrt(gx * gx + gy * gy + 1.0)
        plane = np.append(normal, -normal[2] * z0)
    inl = p[np.abs(p @ plane[:3] + plane[3]) < tol]
    return plane, float(np.median(inl[:, 2]))


def remove_table(data: Frames | Float[np.ndarray, "P 3"], table_z: float | None = None, band: float = TABLE_BAND,
                 tol: float = 0.003, seed: int = 0,
                 points: np.ndarray | None = None) -> tuple[Frames | Float[np.ndarray, "kept 3"], float]:
    """Readings on or under the table removed: those less than `band` above the table plane.

    Args:
        data: frames (the table's readings leave the mask; the depth is kept) or (P, 3) world points (dropped).
        table_z: the table height in metres (plane z = table_z); None: found by `fit_table` (tilted planes within
            10 degrees are followed as fitted).
        band: metres above the plane that still count as table (noise, the object's contact rim).
        tol: inlier distance of the fit.
        seed: seed of the fit.
        points: for frames, `world_points(data)` when the caller has it already.

    Returns:
        The data without the table, and the table height (metres) for `tsdf.fuse(..., table_z=...)`.
    """
    frames = data if isinstance(data, Frames) else None
    if frames is None:
        p = np.asarray(data, np.float64)
    else:
        p = world_points(frames) if points is None else points
    if table_z is None:
        flat = p.reshape(-1, 3)
        plane, table_z = fit_table(flat[~np.isnan(flat[:, 0])], tol=tol, seed=seed)
        height = (p * plane[:3]).sum(-1) + plane[3]
    else:
        if not np.isfinite(table_z):
            raise FfcgsError(f"table_z must be finite, got {table_z}")
        height = p[..., 2] - table_z
    table = height < band  # NaN (no reading) compares False
    if frames is None:
        return p[~table], float(table_z)
    return frames._replace(mask=object_mask(frames) & ~table), float(table_z)
