"""A picture of depth frames: one panel per frame, side by side (host side, NumPy only)."""

import numpy as np

from ffcgs_jax.geometry.depth_io import Frames, object_mask

_NEAR = np.array([250, 200, 60], float)  # yellow: near the camera
_FAR = np.array([60, 30, 120], float)  # violet: far
_NONE = np.array([20, 20, 20], float)  # no reading


def frames_image(frames: Frames, height: int = 180) -> np.ndarray:
    """(height, N * width + gaps, 3) uint8: each frame's depth from near (yellow) to far (violet) over the range
    of all readings, no reading in near-black, readings outside the object mask (background) at half brightness."""
    depth = np.asarray(frames.depth, np.float64)
    obj = object_mask(frames)
    seen = depth > 0
    lo, hi = (np.percentile(depth[seen], [1, 99]) if seen.any() else (0.0, 1.0))
    t = np.clip((depth - lo) / max(hi - lo, 1e-9), 0, 1)[..., None]
    rgb = _NEAR + t * (_FAR - _NEAR)
    rgb = np.where(seen[..., None], rgb * np.where(obj, 1.0, 0.5)[..., None], _NONE)
    n, h, w = depth.shape
    width = max(1, round(w * height / h))
    rows = np.minimum(np.arange(height) * h // height, h - 1)
    cols = np.minimum(np.arange(width) * w // width, w - 1)
    gap = np.full((height, 4, 3), 255.0)
    panels = []
    for i in range(n):
        panels += [rgb[i][rows][:, cols], gap]
    return np.concatenate(panels[:-1], 1).astype(np.uint8)
