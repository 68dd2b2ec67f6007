"""Triangle kernels shared by the SDF builders (`sdf_build`, `sdf_device`) and the device evaluation
(`evaluation.device_metrics`): closest points (Ericson's Voronoi-region test, per triangle and in
structure-of-arrays form), solid angles (Van Oosterom & Strackee), the triangle table they read, and a mesh's
orientation; and the host scan conversion of screen-space triangles with its z-test, shared by the depth-frame
ray caster (`geometry.depth_render`) and the software picture renderer (`viz.render_software`). One copy of each,
below their users."""

from collections.abc import Callable, Iterator
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from ffcgs_jax.core.types import Array


def orientation(tri: np.ndarray) -> float:
    """+1 if the faces wind outward (positive signed volume), -1 if the mesh is inside out."""
    c = tri.reshape(-1, 3).mean(0)
    t = tri - c
    vol = np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2])).sum()
    return 1.0 if vol >= 0 else -1.0


def tri_table(tri: np.ndarray, dtype=np.float32, multiple: int = 1) -> np.ndarray:
    """(F_pad, 12) rows a, b - a, c - a, |ab|^2, ab.ac, |ac|^2, padded to a multiple of `multiple` with degenerate
    triangles 1 km away (never nearest, zero solid angle)."""
    n_pad = -len(tri) % multiple
    t = np.concatenate([tri, np.full((n_pad, 3, 3), 1e3)]) if n_pad else tri
    a, ab, ac = t[:, 0], t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
    dots = np.stack([(ab * ab).sum(1), (ab * ac).sum(1), (ac * ac).sum(1)], axis=1)
    return np.concatenate([a, ab, ac, dots], axis=1).astype(dtype)


class _Regions(NamedTuple):
    """Ericson's Voronoi-region tests of a point against a triangle, from d1 = ab.ap, d2 = ac.ap and the edge dots:
    shared by the one-point (`closest_offset`) and the structure-of-arrays (`dist2`) forms, which differ only in
    how they divide."""

    d3: Array
    d6: Array
    va: Array
    vb: Array
    vc: Array
    e43: Array
    e56: Array
    at_a: Array
    at_b: Array
    on_ab: Array
    at_c: Array
    on_ac: Array
    on_bc: Array

    @classmethod
    def of(cls, d1, d2, d00, d01, d11) -> "_Regions":
        d3, d4, d5, d6 = d1 - d00, d2 - d01, d1 - d01, d2 - d11
        vc, vb, va = d1 * d4 - d3 * d2, d5 * d2 - d1 * d6, d3 * d6 - d5 * d4
        e43, e56 = d4 - d3, d5 - d6
        return cls(d3, d6, va, vb, vc, e43, e56,
                   at_a=(d1 <= 0) & (d2 <= 0), at_b=(d3 >= 0) & (d4 <= d3), on_ab=(vc <= 0) & (d1 >= 0) & (d3 <= 0),
                   at_c=(d6 >= 0) & (d5 <= d6), on_ac=(vb <= 0) & (d2 >= 0) & (d6 <= 0),
                   on_bc=(va <= 0) & (e43 >= 0) & (e56 >= 0))

    def weights(self, w_bc, v_in, w_in, v_ab, w_ac):
        """Barycentric weights (v on ab, w on ac) of the closest point, region by region, from each region's own:
        on edge bc, inside, on edge ab (v), on edge ac (w)."""
        v = jnp.where(self.on_bc, 1 - w_bc, v_in)
        v = jnp.where(self.at_a | self.at_c | self.on_ac, 0.0,
                      jnp.where(self.at_b, 1.0, jnp.where(self.on_ab, v_ab, v)))
        w = jnp.where(self.on_bc, w_bc, w_in)
        w = jnp.where(self.at_a | self.at_b | self.on_ab, 0.0,
                      jnp.where(self.at_c, 1.0, jnp.where(self.on_ac, w_ac, w)))
        return v, w


def closest_offset(p, row):
    """(closest point - p) on one triangle `row` (12,) for one point `p` (3,); Ericson's Voronoi-region test."""
    a, ab, ac = row[0:3], row[3:6], row[6:9]
    d00, d01, d11 = row[9], row[10], row[11]
    ap = p - a
    d1, d2 = ab @ ap, ac @ ap
    r = _Regions.of(d1, d2, d00, d01, d11)

    def div(n, d):
        ok = d != 0
        return jnp.where(ok, n / jnp.where(ok, d, 1.0), 0.0)

    den = r.va + r.vb + r.vc
    v, w = r.weights(div(r.e43, r.e43 + r.e56), div(r.vb, den), div(r.vc, den), div(d1, d1 - r.d3),
                     div(d2, d2 - r.d6))
    return v * ab + w * ac - ap


def solid_angle_one(p, t):
    """Signed solid angle of triangle t (3, 3) seen from p (3,) (Van Oosterom & Strackee)."""
    a, b, c = t[0] - p, t[1] - p, t[2] - p
    la, lb, lc = jnp.linalg.norm(a), jnp.linalg.norm(b), jnp.linalg.norm(c)
    num = a @ jnp.cross(b, c)
    den = la * lb * lc + (a @ b) * lc + (a @ c) * lb + (b @ c) * la
    return 2.0 * jnp.arctan2(num, den)


def search_table(t):
    """(F, 15) float32 rows a, b - a, c - a, |ab|^2, ab.ac, |ac|^2 and the reciprocals of |ab|^2, |ac|^2, |bc|^2:
    `tri_table` plus the edge divisions of Ericson's test, done once per triangle."""
    a, ab, ac = t[:, 0], t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
    d00, d01, d11 = (ab * ab).sum(1), (ab * ac).sum(1), (ac * ac).sum(1)
    bc = ((ac - ab) ** 2).sum(1)

    def inv(x):
        return jnp.where(x != 0, 1.0 / jnp.where(x != 0, x, 1.0), 0.0)

    return jnp.concatenate([a, ab, ac, jnp.stack([d00, d01, d11, inv(d00), inv(d11), inv(bc)], 1)], 1)


def dist2(px, py, pz, c):
    """Squared distance from points (px, py, pz) to triangles given as the 15 broadcastable columns c of
    `search_table`: `closest_offset` in structure-of-arrays form (the same Voronoi-region tests and
    precedence), which XLA vectorises over whole arrays."""
    ax, ay, az, bx, by, bz, cx, cy, cz, d00, d01, d11, i00, i11, ibc = c
    apx, apy, apz = px - ax, py - ay, pz - az
    d1 = bx * apx + by * apy + bz * apz
    d2 = cx * apx + cy * apy + cz * apz
    r = _Regions.of(d1, d2, d00, d01, d11)
    den = r.va + r.vb + r.vc
    inv_den = jnp.where(den != 0, 1.0 / jnp.where(den != 0, den, 1.0), 0.0)
    v, w = r.weights(r.e43 * ibc, r.vb * inv_den, r.vc * inv_den, d1 * i00, d2 * i11)
    rx, ry, rz = v * bx + w * cx - apx, v * by + w * cy - apy, v * bz + w * cz - apz
    return rx * rx + ry * ry + rz * rz


def solid_angles(px, py, pz, t):
    """Signed solid angle of triangles (9 broadcastable columns a, b, c) seen from points: `sdf_build.
    solid_angle_one` (Van Oosterom & Strackee) in structure-of-arrays form."""
    ax, ay, az, bx, by, bz, cx, cy, cz = t
    ax, ay, az, bx, by, bz, cx, cy, cz = ax - px, ay - py, az - pz, bx - px, by - py, bz - pz, cx - px, cy - py, cz - pz
    la, lb, lc = (jnp.sqrt(x * x + y * y + z * z) for x, y, z in ((ax, ay, az), (bx, by, bz), (cx, cy, cz)))
    num = ax * (by * cz - bz * cy) + ay * (bz * cx - bx * cz) + az * (bx * cy - by * cx)
    ab, ac, bc = ax * bx + ay * by + az * bz, ax * cx + ay * cy + az * cz, bx * cx + by * cy + bz * cz
    return 2.0 * jnp.arctan2(num, la * lb * lc + ab * lc + ac * lb + bc * la)




# --- scan conversion (host NumPy) --------------------------------------------------------------------------------

_FLAT = 1e-12  # px^2: twice the screen area below which an exact scan drops a triangle (it covers no centre)


class Spans(NamedTuple):
    """Runs of covered pixel centres, one per (triangle, pixel row): triangle `tri` covers columns
    `start` .. `start + count - 1` of row `row` (all (R,) int64)."""

    tri: np.ndarray
    row: np.ndarray
    start: np.ndarray
    count: np.ndarray


def signed_area(sx: np.ndarray, sy: np.ndarray) -> np.ndarray:
    """Twice the signed screen area of each triangle (T,) from corner coordinates sx, sy (T, 3); positive when the
    corners run counter-clockwise in (x right, y down) coordinates."""
    return (sx[:, 1] - sx[:, 0]) * (sy[:, 2] - sy[:, 0]) - (sx[:, 2] - sx[:, 0]) * (sy[:, 1] - sy[:, 0])


def scan_spans(sx: np.ndarray, sy: np.ndarray, width: int, height: int, centre: float = 0.5,
               margin: float = 0.0) -> Spans:
    """The pixel centres of a width x height image inside each screen-space triangle, row by row (edge functions).

    Args:
        sx, sy: (T, 3) corner coordinates in pixels (x right, y down).
        width, height: image size.
        centre: where pixel (col, row)'s centre lies: (col + centre, row + centre); 0.5 for corner-origin
            coordinates, 0 for OpenCV's (centres on the integers).
        margin: 0 for the exact cover. Above 0 a conservative cover for callers that decide coverage themselves
            (a ray cast): each edge moved out by `margin` px, and triangles thinner than `margin` given their whole
            bounding box, since their 2-D orientation may be rounding noise.

    Returns:
        `Spans`, rows of each triangle contiguous, in triangle order.
    """
    sx, sy = sx.copy(), sy.copy()  # reordered in place below
    T = len(sx)
    area = signed_area(sx, sy)
    # Orient counter-clockwise so "inside" is the same sign for every edge.
    flip = area < 0
    for a in (sx, sy):
        a[flip, 1], a[flip, 2] = a[flip, 2].copy(), a[flip, 1].copy()
    area = np.abs(area)
    y0 = np.maximum(np.ceil(sy.min(1) - (centre + margin)), 0)
    y1 = np.minimum(np.floor(sy.max(1) - (centre - margin)), height - 1)
    x0 = np.maximum(np.ceil(sx.min(1) - (centre + margin)), 0)
    x1 = np.minimum(np.floor(sx.max(1) - (centre - margin)), width - 1)
    if margin:
        longest = np.sqrt(np.max((sx - np.roll(sx, 1, 1)) ** 2 + (sy - np.roll(sy, 1, 1)) ** 2, 1))
        thin = area <= margin * longest  # height over the longest edge below the margin
        live = np.flatnonzero((y1 >= y0) & (x1 >= x0))
    else:
        thin = np.zeros(T, dtype=bool)
        live = np.flatnonzero((area > _FLAT) & (y1 >= y0) & (x1 >= x0))
    rows = (y1[live] - y0[live] + 1).astype(np.int64)
    t = np.repeat(live, rows)
    y = y0[t] + (np.arange(len(t)) - np.repeat(np.cumsum(rows) - rows, rows))
    yc = y + centre
    # Edge k from corner k to corner k+1; a pixel centre is inside when cross(edge, p - start) >= 0 for all k,
    # i.e. A x + B >= 0 with A = -(ey) and B = ex (yc - sy_k) + ey sx_k.
    lo = x0[t] + (centre - 1.0)
    hi = x1[t] + centre
    empty = np.zeros(len(t), dtype=bool)
    edged = ~thin[t]
    for k in range(3):
        ax, ay = sx[t, k], sy[t, k]
        ex, ey = sx[t, (k + 1) % 3] - ax, sy[t, (k + 1) % 3] - ay
        A = -ey
        B = ex * (yc - ay) + ey * ax
        if margin:
            B = B + margin * np.hypot(ex, ey)  # A x + B is the distance to the edge times its length
        with np.errstate(divide="ignore", invalid="ignore"):
            bound = -B / A
        lo = np.where((A > 0) & edged, np.maximum(lo, bound - 1e-9), lo)
        hi = np.where((A < 0) & edged, np.minimum(hi, bound + 1e-9), hi)
        empty |= (A == 0) & (B < 0) & edged
    xs = np.maximum(np.ceil(lo - centre), x0[t]).astype(np.int64)
    xe = np.minimum(np.floor(hi - centre), x1[t]).astype(np.int64)
    count = np.where(empty, 0, np.maximum(xe - xs + 1, 0))
    return Spans(t.astype(np.int64), y.astype(np.int64), xs, count)


def span_pixels(spans: Spans, batch: int) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """The covered pixels of `spans` as (triangle, row, column) arrays, about `batch` at a time (at least one
    span's worth), so callers' per-pixel temporaries stay bounded on big images."""
    count = spans.count
    ends = np.cumsum(count)
    start = 0
    while start < len(count):
        stop = int(np.searchsorted(ends, (ends[start - 1] if start else 0) + batch, side="right"))
        stop = max(stop, start + 1)
        s = count[start:stop]
        n = int(s.sum())
        if n:
            r = np.repeat(np.arange(start, stop), s)
            col = spans.start[r] + (np.arange(n) - np.repeat(np.cumsum(s) - s, s))
            yield spans.tri[r], spans.row[r], col
        start = stop


def rasterise(sx: np.ndarray, sy: np.ndarray, width: int, height: int,
              fragment: Callable[[np.ndarray, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray | None]],
              zbuffer: np.ndarray, nearer: np.ufunc = np.minimum, centre: float = 0.5, margin: float = 0.0,
              batch: int = 1 << 22) -> np.ndarray:
    """Scan-convert triangles into `zbuffer` (height * width,), keeping per pixel the nearest fragment.

    Args:
        sx, sy: (T, 3) screen coordinates of the corners; `centre` and `margin` as in `scan_spans`.
        width, height: image size.
        fragment: (triangle, row, column) arrays of covered pixels -> (value, hit): each pixel's value for the
            z-test and a mask of those that count (None: all), e.g. a depth, or an inverse depth packed with the
            triangle's index so that the z-test also says which triangle won.
        zbuffer: (height * width,) values so far, updated in place: the empty value is one `nearer` never keeps.
        nearer: np.minimum when smaller values are nearer (depth), np.maximum when larger are (inverse depth).
        batch: pixels per batch (`span_pixels`).

    Returns:
        `zbuffer`.
    """
    for tri, row, col in span_pixels(scan_spans(sx, sy, width, height, centre, margin), batch):
        value, hit = fragment(tri, row, col)
        pixel = row * width + col
        if hit is not None:
            pixel, value = pixel[hit], value[hit]
        nearer.at(zbuffer, pixel, value)
    return zbuffer
