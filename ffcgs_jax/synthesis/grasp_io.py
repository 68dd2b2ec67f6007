"""Grasp files: `grasps.npz` (arrays, no pickles). The MCAP log of a run that Foxglove plays back is
`viz.grasp_log`."""

import dataclasses
import json
from pathlib import Path

import numpy as np

from ffcgs_jax.core import files
from ffcgs_jax.core.errors import FfcgsError, check_grasp_set


def save_npz(gs, path: str | Path) -> None:
    """Write a GraspSet's arrays (and its config as JSON text) to an .npz file."""
    check_grasp_set(gs, "save_grasps")
    save_arrays({"object_name": np.array(gs.object_name),
                 "config_json": np.array(json.dumps(dataclasses.asdict(gs.config))), **gs.arrays}, path)


def save_arrays(arrays: dict[str, np.ndarray], path: str | Path) -> None:
    """Write named arrays to a compressed .npz file (no pickles), atomically: a failed write leaves an existing
    file as it was. FfcgsError naming the path."""
    files.atomic_write(files.check_output(path, "grasp file"), lambda f: np.savez_compressed(f, **arrays))


def load_npz(path: str | Path) -> dict[str, np.ndarray]:
    """The arrays of a grasp file, checked (`check_arrays`): FfcgsError naming the file and the problem."""
    return check_arrays(files.read_npz(path, "grasp file", "grasp .npz"), path)


_ROWS = {"wrist_pose": (None, 4, 4), "q": (None, None), "valid": (None,), "squeeze_dir": (None, None),
         "pred_success": (None,), "search_round": (None,)}
"""Per-grasp arrays the commands read, one row per grasp, and their shapes (None: any length)."""
_TEXT = ("object_source", "object_name", "object_sha256", "config_json", "rank_by", "search_why", "search_stop")
"""Fields that hold one string."""


def check_arrays(data: dict[str, np.ndarray], path: str | Path) -> dict[str, np.ndarray]:
    """`data` (a grasp file's arrays) once the fields the commands read are known to be sound: the per-grasp arrays
    `_ROWS` of real numbers, finite, of their shapes and one row per grasp; `object_scale` one number > 0; the
    `_TEXT` fields one string each; `channel_names` a list of strings. Fields that are absent are not required."""
    def bad(what: str) -> FfcgsError:
        return FfcgsError(f"grasp file {path}: {what}")

    rows = {}
    for key, shape in _ROWS.items():
        if key not in data:
            continue
        a = data[key]
        if a.dtype.kind not in ("biuf" if key == "valid" else "iuf"):
            raise bad(f"{key} must hold {'booleans' if key == 'valid' else 'real numbers'}, got dtype {a.dtype}")
        if a.ndim != len(shape) or any(n is not None and n != m for n, m in zip(shape, a.shape)):
            want = ", ".join("B" if i == 0 else "Q" if n is None else str(n) for i, n in enumerate(shape))
            raise bad(f"{key} must have shape ({want}{',' if len(shape) == 1 else ''}), got {a.shape}")
        finite = np.isfinite(a).all(axis=tuple(range(1, a.ndim)))
        if not finite.all():
            raise bad(f"{key} contains NaN or inf (grasp {int(np.flatnonzero(~finite)[0])})")
        rows[key] = len(a)
    if "wrist_pose" in data and len(data["wrist_pose"]):
        from ffcgs_jax.hand.kinematics import check_wrist_poses

        check_wrist_poses(data["wrist_pose"], f"grasp file {path}: wrist_pose")
    if len(set(rows.values())) > 1:
        raise bad("its arrays must have one row per grasp, got " + ", ".join(f"{n} in {k}" for k, n in rows.items()))
    if "channel_names" in data and (data["channel_names"].ndim != 1 or data["channel_names"].dtype.kind != "U"):
        raise bad(f"channel_names must be a list of strings, got {_show(data['channel_names'])}")
    # q first: squeeze_dir is measured against q, and a q of the wrong width must not be blamed on squeeze_dir
    width = len(data["channel_names"]) if "channel_names" in data else None
    for key in ("q", "squeeze_dir"):
        if width is not None and key in data and data[key].shape[1] != width:
            raise bad(f"{key} has {data[key].shape[1]} columns, but the hand the grasps were made for has {width} "
                      f"channels (its channel_names): {key} must have shape (B, {width})")
    if "squeeze_dir" in data and "q" in data and data["squeeze_dir"].shape != data["q"].shape:
        raise bad(f"q has {data['q'].shape[1]} columns and squeeze_dir {data['squeeze_dir'].shape[1]}: both have "
                  "one column per channel of the hand the grasps were made for")
    if "object_scale" in data:
        a = data["object_scale"]
        if a.shape != () or a.dtype.kind not in "iuf" or not (np.isfinite(a) and a > 0):
            raise bad(f"object_scale must be one number > 0, got {_show(a)}")
    for key in _TEXT:
        if key in data and (data[key].shape != () or data[key].dtype.kind != "U"):
            raise bad(f"{key} must be one string, got {_show(data[key])}")
    return data


def _show(a: np.ndarray) -> str:
    """An array in a message: its value when small, else its dtype and shape."""
    return repr(a.tolist()) if a.size <= 4 and a.dtype.kind in "biufU" else f"dtype {a.dtype}, shape {a.shape}"


def check_hand(data: dict[str, np.ndarray], path: str | Path, spec) -> None:
    """FfcgsError when the grasp file's q (or squeeze_dir) does not have the channels of hand spec `spec`."""
    n = len(spec.channel_names)
    for key in ("q", "squeeze_dir"):
        if key in data and data[key].shape[1] != n:
            raise FfcgsError(f"grasp file {path}: {key} has {data[key].shape[1]} channels, hand {spec.name} has {n}: "
                             "pass --hand with the hand the grasps were made for")


def load_poses(path: str | Path) -> np.ndarray:
    """Wrist poses (B, 4, 4) from an .npy of shape (B, 4, 4) or (4, 4), or an .npz with `wrist_pose` (a grasp file
    is checked as one); FfcgsError naming the file and the problem."""
    from ffcgs_jax.hand.kinematics import check_wrist_poses

    arrays = files.read_npz(path, "pose file", ".npy/.npz pose file", npy=True)
    if "" not in arrays and "wrist_pose" not in arrays:
        raise FfcgsError(f"pose file {path} has no 'wrist_pose' array (has {', '.join(arrays) or 'none'})")
    if "" not in arrays:
        check_arrays(arrays, path)
    return check_wrist_poses(arrays.get("", arrays.get("wrist_pose")), f"wrist poses in {path}").reshape(-1, 4, 4)
