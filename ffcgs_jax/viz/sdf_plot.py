"""A picture of a Gradient-SDF: three mid-slices of the distance channel (host side, NumPy only)."""

import numpy as np

from ffcgs_jax.geometry.sdf import GradientSDF

_INSIDE = np.array([40, 90, 200], float)  # blue: negative distance
_OUTSIDE = np.array([215, 80, 50], float)  # red: positive distance
_WHITE = np.array([250, 250, 250], float)


def _colour(d: np.ndarray, scale: float, band: float) -> np.ndarray:
    t = np.clip(np.abs(d) / scale, 0, 1)[..., None] ** 0.7
    rgb = np.where(d[..., None] < 0, _WHITE + t * (_INSIDE - _WHITE), _WHITE + t * (_OUTSIDE - _WHITE))
    rgb[np.abs(d) < band] = 0  # the surface (zero level) in black
    return rgb


def slices_image(sdf: GradientSDF, size: int = 256) -> np.ndarray:
    """(size, 3*size, 3) uint8: the x-y slice at mid z, x-z at mid y, y-z at mid x (first axis drawn right)."""
    d = np.asarray(sdf.grid[..., 0], float)
    r = d.shape[0]
    h = float(sdf.voxel_size)
    scale = max(np.abs(d).max(), 1e-9)
    mid = r // 2
    panels = [d[:, :, mid], d[:, mid, :], d[mid, :, :]]
    out = []
    for p in panels:
        img = _colour(p.T[::-1], scale, 0.5 * h)  # rows = second axis, drawn upwards
        idx = np.minimum((np.arange(size) * r) // size, r - 1)
        out.append(img[idx][:, idx])
    sep = np.full((size, 2, 3), 255.0)
    return np.concatenate([out[0], sep, out[1], sep, out[2]], 1).astype(np.uint8)
