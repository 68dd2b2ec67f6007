"""The object isolated from its scene in depth frames without masks: `isolate` (host NumPy and SciPy).

Cameras aimed at an object on a table also see the table's edges and sides, the floor, walls, other things on
the table, and a few stray readings (noise, flying pixels). Removing the table plane leaves all of these but the
table top, and fusion would fit its grid around them (a 2 cm voxel over a 1 m table instead of 2 mm over the
object). The object is taken to be what the cameras look at:

1. the views' focus: the point nearest to every camera's optical axis (least squares), pulled weakly toward
   each camera's median reading along its axis so that one view, or parallel views, still have one;
2. a subsample of the readings (every s-th pixel of each frame, about `_SAMPLE` points in all), those more than
   `depth_io.TABLE_BAND` above the table plane and within `REACH` of the focus, binned into `CELL` cells;
3. the connected parts of the occupied cells (26-neighbours: parts less than a cell apart join);
4. the part with the reading nearest the focus is the object. Its pixels (each sample standing for its s x s
   block, grown by one block so that no reading of the object's silhouette is lost, and of those the readings
   in or next to the part's cells) become the mask, and a box around its points with `SLACK` becomes the crop box
   fusion fits its grid in (`tsdf.fuse(crop=...)`).

Everything else (the other parts, the stray readings) becomes background, whose rays still carve free space.
Deterministic (no random draws) and cheap: 5 frames of 640 x 480 take 15 ms for the parts and 85 ms in all
(the mask's readings included) on a busy 2-core CPU (tests/geometry/test_depth_scene.py bounds it at 200 ms).

Precedence: object masks given with the frames are the user's own isolation, so `isolate` is not run on them (only
the size check: `check_masked`);
an explicit workspace box (`bounds`) keeps its meaning (readings outside are background, the grid is the cube
around it) and the isolation runs inside it, removing the parts within the box that are not the object.
"""

import math
import warnings
from typing import NamedTuple

import numpy as np
from scipy.ndimage import binary_dilation
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from ffcgs_jax.geometry import depth_io
from ffcgs_jax.core.types import Float

CELL = 0.01  # m: the connectivity cell: parts closer than this always join, parts 2 cells apart never do
REACH = 0.5  # m: readings farther from the focus are never the object (larger than any graspable object)
SLACK = 0.02  # m: the crop box's margin around the kept samples (the readings between samples, noise)
MAX_SIZE = 0.40  # m: a kept part wider than this is no object a hand grasps (warning)
MIN_SIZE = 0.01  # m: nor one smaller than this
NEAR_FOCUS = 0.20  # m: a kept part farther than this from the focus is not what the cameras look at (warning)
PART_POINTS = 10  # samples: smaller removed parts are counted as stray readings
_SAMPLE = 40_000  # readings sampled (the stride's target)
_PULL = 0.01  # weight of each camera's median-depth point in the focus (against 1 for its axis)
# the 13 forward neighbours of a cell (the other 13 are their opposites)
_OFFSETS = np.array([o for o in np.ndindex(3, 3, 3) if o > (1, 1, 1)]) - 1


class Isolation(NamedTuple):
    """What `isolate` kept and removed.

    Attributes:
        points: sampled readings in the kept part.
        extents: (3,) its size in metres: x and y of its readings, z from the table to its top.
        focus: (3,) the views' focus, world metres.
        focus_distance: metres from the focus to the kept part's nearest reading.
        parts: other parts removed (at least `PART_POINTS` samples each).
        stray: sampled readings removed in smaller parts.
        below: sampled readings below the table plane (its sides, the floor), removed with the table.
        far: sampled readings above the table farther than `REACH` from the focus, removed.
        stride: the sampling stride in pixels.
        box: (2, 3) the crop box (min, max corners, metres).
    """

    points: int
    extents: Float[np.ndarray, " 3"]
    focus: Float[np.ndarray, " 3"]
    focus_distance: float
    parts: int
    stray: int
    below: int
    far: int
    stride: int
    box: Float[np.ndarray, "2 3"]

    def summary(self) -> str:
        """One line: what was kept, its size, and what was removed."""
        size = " x ".join(f"{100 * e:.1f}" for e in self.extents)
        removed = ["the table"] + [f"{self.below} readings below it"] * (self.below > 0)
        removed += [f"{self.parts} other part{'s' * (self.parts != 1)}"] * (self.parts > 0)
        removed += [f"{self.stray} stray readings"] * (self.stray > 0)
        removed += [f"{self.far} readings beyond {100 * REACH:g} cm"] * (self.far > 0)
        return (f"part of {self.points} sampled readings, {size} cm, {100 * self.focus_distance:.1f} cm from the "
                f"cameras' focus; removed: {', '.join(removed)} (sampled every {self.stride} px)")


def focus(frames: depth_io.Frames) -> Float[np.ndarray, " 3"]:
    """The point nearest to all the cameras' optical axes (least squares), with a weak pull (`_PULL`) toward each
    camera's median central reading along its axis, which decides it for one view or parallel views."""
    eyes, axes = frames.poses[:, :3, 3], frames.poses[:, :3, 2]
    h, w = frames.depth.shape[1:]
    A, b = np.zeros((3, 3)), np.zeros(3)
    for eye, d, depth in zip(eyes, axes, frames.depth):
        centre = depth[h // 4:h - h // 4, w // 4:w - w // 4]
        seen = centre[centre > 0] if (centre > 0).any() else depth[depth > 0]
        reach = float(np.median(seen)) if len(seen) else 1.0
        P = np.eye(3) - np.outer(d, d)  # distance to the axis through `eye` along `d`
        A += P + _PULL * np.eye(3)
        b += P @ eye + _PULL * (eye + reach * d)
    return np.linalg.solve(A, b)


def components(cells: np.ndarray) -> np.ndarray:
    """Connected parts of occupied grid cells (26-neighbours): a label per row of `cells` (P, 3) ints."""
    if not len(cells):
        return np.zeros(0, np.int64)
    c = cells - cells.min(0) + 1  # a zero border, so that neighbour keys never wrap into another row
    dims = c.max(0) + 2
    keys = (c[:, 0] * dims[1] + c[:, 1]) * dims[2] + c[:, 2]
    uniq, inv = np.unique(keys, return_inverse=True)
    rows, cols = [], []
    for o in _OFFSETS:
        nk = uniq + (o[0] * dims[1] + o[1]) * dims[2] + o[2]
        j = np.minimum(np.searchsorted(uniq, nk), len(uniq) - 1)
        hit = uniq[j] == nk
        rows.append(np.flatnonzero(hit))
        cols.append(j[hit])
    r, k = np.concatenate(rows), np.concatenate(cols)
    graph = coo_matrix((np.ones(len(r), np.int8), (r, k)), shape=(len(uniq), len(uniq)))
    return connected_components(graph, directed=False)[1][inv.ravel()]


def isolate(frames: depth_io.Frames, plane: Float[np.ndarray, " 4"],
            bounds: Float[np.ndarray, "2 3"] | None = None) -> tuple[depth_io.Frames, Isolation | None]:
    """The frames with the object's readings alone in the mask (module docstring), and what was kept.

    Args:
        frames: the frames (their mask, if any, narrows what can be kept: the table removed on the host).
        plane: (4,) the table plane, n . p + c = 0, unit n up (`depth_io.fit_table`; level: (0, 0, 1, -table_z)).
        bounds: (2, 3) workspace box or None: samples outside it are not the object.

    Returns:
        The frames with the narrowed mask, and the `Isolation`; the frames unchanged and None when no reading
        above the table lies within `REACH` of the focus (with a warning: then every reading above the table is
        fused).

    Warns:
        when the kept part is implausible for a graspable object: wider than `MAX_SIZE`, smaller than
        `MIN_SIZE`, or farther than `NEAR_FOCUS` from the focus.
    """
    n, h, w = frames.depth.shape
    s = max(1, math.ceil(math.sqrt(n * h * w / _SAMPLE)))
    rows, cols = np.arange(s // 2, h, s), np.arange(s // 2, w, s)
    N, R, C = (a.ravel() for a in np.meshgrid(np.arange(n), rows, cols, indexing="ij"))
    p = depth_io.pixel_points(frames, N, R, C)
    height = np.where(np.isfinite(p[:, 0]), p @ plane[:3] + plane[3], np.nan)
    f = focus(frames)
    dist = np.linalg.norm(p - f, axis=1)
    above = depth_io.object_mask(frames)[N, R, C] & (height >= depth_io.TABLE_BAND)  # NaN compares False
    if bounds is not None:
        above &= ((p >= bounds[0]) & (p <= bounds[1])).all(1)
    near = above & (dist <= REACH)
    if not near.any():
        if not above.any():  # nothing above the table at all: fusion says so in its error, a warning would not help
            return frames, None
        warnings.warn(f"object isolation: no reading above the table within {100 * REACH:g} cm of the cameras' "
                      f"focus ({', '.join(f'{x:.3f}' for x in f)} m); fusing every reading above the table",
                      stacklevel=2)
        return frames, None
    idx = np.flatnonzero(near)
    labels = components(np.floor(p[idx] / CELL).astype(np.int64))
    part_dist = np.full(labels.max() + 1, np.inf)
    np.minimum.at(part_dist, labels, dist[idx])
    best = int(np.argmin(part_dist))
    sizes = np.bincount(labels)
    others = np.delete(sizes, best)
    keep = np.zeros(len(p), bool)
    keep[idx[labels == best]] = True
    kept = p[keep]
    lo, hi = kept.min(0), kept.max(0)
    extents = np.append(hi[:2] - lo[:2], np.max(height[keep]))
    table_lo = -(plane[3] + plane[0] * kept[:, 0] + plane[1] * kept[:, 1]) / plane[2]  # the table under the part
    box = np.stack([np.append(lo[:2], min(lo[2], table_lo.min())) - SLACK, hi + SLACK])
    iso = Isolation(int(keep.sum()), extents, f, float(part_dist[best]), int((others >= PART_POINTS).sum()),
                    int(others[others < PART_POINTS].sum()), int((height < -depth_io.TABLE_BAND).sum()),
                    int((above & ~near).sum()), s, box)
    _warn_implausible(iso)
    cells = np.floor(kept / CELL).astype(np.int64)
    return frames._replace(mask=_pixel_mask(keep.reshape(n, len(rows), len(cols)), s, frames, cells)), iso


def check_masked(frames: depth_io.Frames, plane: Float[np.ndarray, " 4"],
                 bounds: Float[np.ndarray, "2 3"] | None = None) -> Float[np.ndarray, " 3"] | None:
    """The size of the object that the frames' own masks hold (x and y of its readings, z from the table to its
    top, metres, from a subsample as `isolate` takes; the outermost 0.5 % each way left out as flying pixels), with
    the warning `isolate` gives for an implausible part: masks are the user's isolation, and a mask that holds a
    49 cm slab deserves the same word as a part isolated at that size. None (and no warning) when fewer than
    `PART_POINTS` sampled readings lie above the table (fusion then says what is wrong)."""
    n, h, w = frames.depth.shape
    s = max(1, math.ceil(math.sqrt(n * h * w / _SAMPLE)))
    N, R, C = (a.ravel() for a in np.meshgrid(np.arange(n), np.arange(s // 2, h, s), np.arange(s // 2, w, s),
                                              indexing="ij"))
    p = depth_io.pixel_points(frames, N, R, C)
    height = np.where(np.isfinite(p[:, 0]), p @ plane[:3] + plane[3], np.nan)
    keep = depth_io.object_mask(frames)[N, R, C] & (height >= depth_io.TABLE_BAND)  # NaN compares False
    if bounds is not None:
        keep &= ((p >= bounds[0]) & (p <= bounds[1])).all(1)
    if keep.sum() < PART_POINTS:
        return None
    lo, hi = np.quantile(p[keep, :2], [0.005, 0.995], axis=0)
    extents = np.append(hi - lo, np.quantile(height[keep], 0.995))
    size = " x ".join(f"{100 * e:.1f}" for e in extents)
    why = f"wider than {100 * MAX_SIZE:g} cm" if extents.max() > MAX_SIZE else \
        f"smaller than {100 * MIN_SIZE:g} cm" if extents.max() < MIN_SIZE else ""
    if why:
        warnings.warn(f"the frames' masks hold an object of {size} cm, {why}: not a graspable object? (check the "
                      "masks)", stacklevel=3)
    return extents


def _pixel_mask(samples: np.ndarray, s: int, frames: depth_io.Frames, cells: np.ndarray) -> np.ndarray:
    """The readings of each kept sample's s x s block, grown by one block (the silhouette between samples), that
    lie in the kept part's cells or next to them (so that what the grown blocks catch of other things is left
    out), on pixels with a reading in the frames' mask."""
    n, h, w = frames.depth.shape
    grown = binary_dilation(samples, np.ones((1, 3, 3), bool))
    full = np.repeat(np.repeat(grown, s, 1), s, 2)[:, :h, :w]
    full = np.pad(full, ((0, 0), (0, h - full.shape[1]), (0, w - full.shape[2])), mode="edge")
    full &= depth_io.object_mask(frames) & (frames.depth > 0)
    N, R, C = np.nonzero(full)
    near = np.floor(depth_io.pixel_points(frames, N, R, C) / CELL).astype(np.int64)
    base, dims = cells.min(0) - 1, cells.max(0) - cells.min(0) + 3  # the part's cells with a border of one
    ok = ((near >= base) & (near < base + dims)).all(1)
    occupied = np.zeros(dims, bool)
    occupied[tuple((cells - base).T)] = True
    occupied = binary_dilation(occupied, np.ones((3, 3, 3), bool))
    keep = np.zeros(len(N), bool)
    keep[ok] = occupied[tuple((near[ok] - base).T)]
    full[N[~keep], R[~keep], C[~keep]] = False
    return full


def _warn_implausible(iso: Isolation) -> None:
    size = " x ".join(f"{100 * e:.1f}" for e in iso.extents)
    why = []
    if iso.extents.max() > MAX_SIZE:
        why.append(f"wider than {100 * MAX_SIZE:g} cm")
    if iso.extents.max() < MIN_SIZE:
        why.append(f"smaller than {100 * MIN_SIZE:g} cm")
    if iso.focus_distance > NEAR_FOCUS:
        why.append(f"{100 * iso.focus_distance:.0f} cm from the cameras' focus (more than {100 * NEAR_FOCUS:g})")
    if why:
        warnings.warn(f"object isolation kept a part of {size} cm, {' and '.join(why)}: not a graspable object "
                      f"the cameras look at? (give masks or --bounds)", stacklevel=3)
