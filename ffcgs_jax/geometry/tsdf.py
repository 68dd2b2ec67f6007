"""TSDF fusion of depth frames into the `GradientSDF` the grasp planner takes.

Fusion (`integrate`, JAX, jit-compiled, one code path on CPU and GPU) follows KinectFusion: every voxel centre is
projected into every frame (nearest pixel); where that pixel has a reading d, the projective signed distance
sdf = d - z_cam is truncated to [-trunc, trunc] and averaged over the frames with unit weights,
D <- (W D + w d) / (W + w), W <- W + w (a `lax.scan` over the frames, so memory does not grow with their number).
Readings outside the object mask (`depth_io.Frames.mask`: the table, things outside the workspace) are background:
they say the space in front of them (and up to half a voxel behind, the error of the nearest-pixel lookup on a
grazing table) is empty (+trunc), and nothing about the object.

Unobserved voxels. A voxel that no frame observed (weight 0) gets a value by this rule:

- in the object's shadow, i.e. behind an object reading by more than trunc in some frame, or on the ray of an
  object pixel that has no reading: unknown, taken as inside (-trunc);
- anywhere else (outside every view, behind only the background, on rays without reading and without mask): free
  (+trunc);
- below the table (z < table_z, when it is known) never object: the table is modelled apart (`sdf.query_scene`),
  and counting the space under it as object would wreck the object's centre and size (`sdf.object_extent`).

Why: a grasp planner must not put fingers into space behind the object that no camera has seen, so the shadow is
solid until some camera sees through it (a voxel observed empty in any frame has weight > 0 and a positive
average). The rest of the never-seen space is not next to what the cameras saw of the object, and treating it as
solid would add walls at the edges of the views or a slab under the table. Averaging the background's "empty"
votes with the object's readings (rather than carving with any one of them) keeps one mislabelled silhouette pixel
from cutting through the object.

Conversion (`to_gradient_sdf`, jit-compiled, part of the same compiled function as the fusion in `fuse`). The fused
value is a truncated, projective (along the camera axis) distance, not the Euclidean distance the planner's queries
assume away from the surface. So the zero level is taken from it with sub-voxel accuracy (the zero crossings along
the grid's edges, by linear interpolation of the fused values), every voxel gets its Euclidean distance to those
crossing points (jump flooding on the device; `to_gradient_sdf_reference` finds the exact nearest with a KD-tree on
the host), refined next to the surface to the first-order distance |D| / |grad D| (exact for a plane, whatever the
viewing angle), signed by the fused sign; the gradient channels are central differences of that distance,
normalised.
"""

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from scipy.ndimage import binary_dilation
from scipy.spatial import cKDTree

from ffcgs_jax.core.config import check_integer, check_range
from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.geometry import depth_io
from ffcgs_jax.geometry.config import SDFConfig
from ffcgs_jax.geometry.sdf import GradientSDF
from ffcgs_jax.geometry.sdf import grid_frame as sdf_grid_frame
from ffcgs_jax.core.types import Array, Bool, Float

_MIN_Z = 1e-6  # m: voxels this close to a camera's plane (or behind it) do not project
# voxels: background readings also vote "empty" this far behind them, so that voxels on the table, which the
# nearest-pixel lookup puts a little behind a grazing table's reading as often as in front, do not stay unknown
_BG_SLACK = 0.5
_FIRST_ORDER_REACH = 2.0  # voxels: up to where |V| / |grad V| is trusted over the distance to the crossing points


class Volume(NamedTuple):
    """Fused frames on the voxel centres (index [i, j, k] along x, y, z, as `GradientSDF.grid`).

    Attributes:
        tsdf: (R, R, R) weighted average of the truncated projective distances, metres in [-trunc, trunc]; 0 where
            the weight is 0.
        weight: (R, R, R) number of frames that observed the voxel (a reading within trunc of it, or in front).
        seen_free: (R, R, R) some frame saw the voxel empty (more than trunc in front of an object reading, or in
            front of a background reading, up to half a voxel behind it).
        shadow: (R, R, R) some frame saw the voxel behind an object reading by more than trunc, or it lies on the
            ray of an object pixel without reading.
    """

    tsdf: Float[Array, "R R R"]
    weight: Float[Array, "R R R"]
    seen_free: Bool[Array, "R R R"]
    shadow: Bool[Array, "R R R"]


def grid_frame(bounds: Float[np.ndarray, "2 3"], res: int, margin: float = 0.0,
               min_margin: float = 0.0) -> tuple[Float[np.ndarray, " 3"], float]:
    """Origin (centre of voxel [0, 0, 0]) and voxel size of the res^3 cube around the box `bounds` (min and max
    corners, metres): centred on the box, side = its largest extent plus max(margin * extent, min_margin) on each
    side (as `sdf.build_sdf`)."""
    return sdf_grid_frame(np.asarray(bounds, np.float64), SDFConfig(res=res, margin=margin, min_margin=min_margin))


# ----------------------------------------------------------------------------------------------------------------
# Fusion (JAX)
# ----------------------------------------------------------------------------------------------------------------


def _observe(centres, depth, mask, K, pose, trunc, slack):
    """One frame's vote on each voxel (P,): truncated value, weight (0 or 1), seen free, in the shadow."""
    rot, t = pose[:3, :3], pose[:3, 3]
    cam = (centres - t[None, :]) @ rot  # R^T (p - t), row by row
    z = cam[:, 2]
    front = z > _MIN_Z
    uvw = cam @ K.T
    zs = jnp.where(front, z, 1.0)
    col, row = jnp.floor(uvw[:, 0] / zs + 0.5), jnp.floor(uvw[:, 1] / zs + 0.5)  # nearest pixel centre
    h, w = depth.shape
    seen = front & (col >= 0) & (col <= w - 1) & (row >= 0) & (row <= h - 1)
    r, c = jnp.clip(row, 0, h - 1).astype(jnp.int32), jnp.clip(col, 0, w - 1).astype(jnp.int32)
    d, obj = depth[r, c], mask[r, c]
    has = seen & (d > 0)
    sdf = d - z
    fg, bg = has & obj, has & ~obj
    fg_vote = fg & (sdf >= -trunc)
    bg_vote = bg & (sdf > -slack)
    value = jnp.where(fg_vote, jnp.clip(sdf, -trunc, trunc), trunc)
    weight = (fg_vote | bg_vote).astype(value.dtype)
    free = (fg & (sdf > trunc)) | bg_vote
    shadow = (fg & (sdf < -trunc)) | (seen & ~(d > 0) & obj)
    return value, weight, free, shadow


def _integrate(depth, mask, K, poses, origin, voxel_size, trunc, res):
    ijk = jnp.stack(jnp.meshgrid(*(jnp.arange(res),) * 3, indexing="ij"), -1).reshape(-1, 3)
    centres = origin[None, :] + voxel_size * ijk.astype(origin.dtype)

    def step(carry, frame):
        D, W, free, shadow = carry
        value, w, f, s = _observe(centres, frame[0], frame[1], K, frame[2], trunc, _BG_SLACK * voxel_size)
        W_new = W + w
        D = jnp.where(w > 0, (W * D + w * value) / jnp.where(W_new > 0, W_new, 1.0), D)
        return (D, W_new, free | f, shadow | s), None

    zeros = jnp.zeros(len(centres), origin.dtype)
    init = (zeros, zeros, jnp.zeros(len(centres), bool), jnp.zeros(len(centres), bool))
    out, _ = jax.lax.scan(step, init, (depth, mask, poses))
    return Volume(*(x.reshape(res, res, res) for x in out))


_integrate_jit = jax.jit(_integrate, static_argnames="res")


def integrate(depth: Float[Array | np.ndarray, "N H W"], K: Float[Array | np.ndarray, "3 3"],
              poses: Float[Array | np.ndarray, "N 4 4"], origin: Float[Array | np.ndarray, " 3"],
              voxel_size: float | Float[Array, ""], res: int, trunc: float | Float[Array, ""],
              mask: Bool[Array | np.ndarray, "N H W"] | None = None) -> Volume:
    """KinectFusion integration of depth frames on a res^3 grid of voxel centres (jit-compiled once per res and
    frame shape; the values of the other arguments do not recompile).

    Args:
        depth: (N, H, W) depth in metres along each camera's z; 0 = no reading.
        K: (3, 3) intrinsics in pixels.
        poses: (N, 4, 4) camera-to-world transforms (OpenCV axes).
        origin: (3,) centre of voxel [0, 0, 0], metres.
        voxel_size: spacing of voxel centres, metres.
        res: voxels along each axis (static).
        trunc: truncation distance, metres.
        mask: (N, H, W) True on the object; readings outside are background (module docstring). None: every
            reading is the object's.

    Returns:
        The fused `Volume`, in JAX's default float dtype.
    """
    check_integer("res", res, 2, 512)
    voxel_size, trunc = float(voxel_size), float(trunc)
    if not (np.isfinite(voxel_size) and voxel_size > 0 and np.isfinite(trunc) and trunc > 0):
        raise FfcgsError(f"voxel_size and trunc must be > 0, got voxel_size {voxel_size}, trunc {trunc}")
    n = np.shape(depth)[0] if np.ndim(depth) == 3 else -1
    shapes = {"depth": (np.shape(depth), (n,) + tuple(np.shape(depth)[1:]) if n > 0 else "(N, H, W), N > 0"),
              "K": (np.shape(K), (3, 3)), "poses": (np.shape(poses), (n, 4, 4)), "origin": (np.shape(origin), (3,))}
    if mask is not None:
        shapes["mask"] = (np.shape(mask), np.shape(depth))
    for name, (got, want) in shapes.items():
        if got != want:
            raise FfcgsError(f"integrate: {name} must have shape {want}, got {got}")
    fdt = jnp.result_type(float)
    depth = jnp.asarray(depth, fdt)
    mask = depth > 0 if mask is None else jnp.asarray(mask, bool)
    return _integrate_jit(depth, mask, jnp.asarray(K, fdt), jnp.asarray(poses, fdt), jnp.asarray(origin, fdt),
                          jnp.asarray(voxel_size, fdt), jnp.asarray(trunc, fdt), int(res))


# ----------------------------------------------------------------------------------------------------------------
# From the fused volume to a GradientSDF: host reference (NumPy, SciPy's KD-tree), kept for the tests
# ----------------------------------------------------------------------------------------------------------------


def _centres(origin: np.ndarray, h: float, res: int) -> np.ndarray:
    axes = [origin[i] + h * np.arange(res) for i in range(3)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1)


def resolve(volume: Volume, trunc: float, origin: Float[np.ndarray, " 3"], voxel_size: float,
            table_z: float | None = None) -> Float[np.ndarray, "R R R"]:
    """The fused values with the unobserved voxels decided (module docstring): the average where observed, -trunc
    in the shadow, +trunc elsewhere; with `table_z`, the result intersected with the half-space above the table
    (max(value, table_z - z), so the object's underside lies exactly on the table)."""
    W, D = np.asarray(volume.weight), np.asarray(volume.tsdf, np.float64)
    values = np.where(W > 0, D, np.where(np.asarray(volume.shadow), -trunc, trunc))
    if table_z is not None:
        z = _centres(np.asarray(origin, np.float64), voxel_size, values.shape[0])[..., 2]
        values = np.maximum(values, table_z - z)
    return values


def _zero_crossings(V: np.ndarray, origin: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray]:
    """Points (M, 3) where the field crosses zero along the grid's edges (linear interpolation), and the voxels
    (R, R, R) at either end of such an edge."""
    points, band = [], np.zeros(V.shape, bool)
    for axis in range(3):
        lo = [slice(None)] * 3
        hi = [slice(None)] * 3
        lo[axis], hi[axis] = slice(0, -1), slice(1, None)
        a, b = V[tuple(lo)], V[tuple(hi)]
        cross = (a < 0) != (b < 0)  # a - b is nonzero there
        band[tuple(lo)] |= cross
        band[tuple(hi)] |= cross
        ijk = np.argwhere(cross).astype(np.float64)
        ijk[:, axis] += a[cross] / (a[cross] - b[cross])
        points.append(origin + h * ijk)
    return np.concatenate(points), band


def to_gradient_sdf_reference(values: Float[np.ndarray, "R R R"], origin: Float[np.ndarray, " 3"],
                              voxel_size: float, table_z: float) -> GradientSDF:
    """`to_gradient_sdf` on the host with exact nearest crossing points (a KD-tree): the reference the device
    conversion is tested against (about 0.4 s at 64^3 on two cores).

    Args:
        values: (R, R, R) fused field on the voxel centres, metres.
        origin: (3,) centre of voxel [0, 0, 0].
        voxel_size: metres.
        table_z: table height stored in the result.

    Returns:
        The GradientSDF, arrays in JAX's default float dtype.
    """
    V = np.asarray(values, np.float64)
    origin = np.asarray(origin, np.float64)
    h = float(voxel_size)
    inside = V < 0
    _check_sides(bool(inside.any()), bool(inside.all()))
    points, band = _zero_crossings(V, origin, h)
    dist = cKDTree(points).query(_centres(origin, h, V.shape[0]).reshape(-1, 3), workers=-1)[0].reshape(V.shape)
    # Next to the surface the crossing points are too sparse (one per grid edge: a voxel 0.7 h inside a diagonal
    # surface is 1 h from the nearest), so there the first-order distance |V| / |grad V| takes over, where its
    # central differences read no clipped (truncated or unknown) value.
    slope = np.linalg.norm(np.stack(np.gradient(V, h), -1), axis=-1)
    first = np.abs(V) / np.where(slope > 0, slope, 1.0)
    clipped = binary_dilation(np.abs(V) >= np.abs(V).max() * (1 - 1e-9))  # a clipped value in the stencil
    near = (band | ~clipped) & (slope > 0) & (first < _FIRST_ORDER_REACH * h)
    dist = np.where(near, np.minimum(dist, first), dist)
    sd = np.where(inside, -dist, dist)
    grad = np.stack(np.gradient(sd, h), -1)
    norm = np.linalg.norm(grad, axis=-1, keepdims=True)
    up = np.zeros_like(grad)
    up[..., 2] = 1.0
    grad = np.where(norm > 1e-12, grad / np.where(norm > 1e-12, norm, 1.0), up)  # flat spots: any unit vector
    grid = np.concatenate([sd[..., None], grad], -1)
    return GradientSDF(grid=jnp.asarray(grid), origin=jnp.asarray(origin), voxel_size=jnp.asarray(h),
                       table_z=jnp.asarray(float(table_z)))


# ----------------------------------------------------------------------------------------------------------------
# From the fused volume to a GradientSDF (JAX: the path `fuse` takes)
# ----------------------------------------------------------------------------------------------------------------

_JFA_CLEANUP = (2, 1)  # extra jump-flooding passes after the halving ones (JFA+2: mends most of JFA's rare misses)
UNROLL_JFA_ON = frozenset({"gpu"})  # backends where the jump-flooding offsets are unrolled (bench/depth.py --speed)


def _shift(x, offset, fill):
    """x[i + offset] along each of the first three axes (static offsets), `fill` where that falls off the grid."""
    r = x.shape[0]
    for axis, o in enumerate(offset):
        if o == 0:
            continue
        pad = [(0, 0)] * x.ndim
        pad[axis] = (0, o) if o > 0 else (-o, 0)
        x = jnp.pad(x, pad, constant_values=fill)
        x = jax.lax.slice_in_dim(x, o if o > 0 else 0, (o if o > 0 else 0) + r, axis=axis)
    return x


def flood_seeds(V):
    """Each voxel's nearest zero crossing on the grid edges it touches ((R, R, R, 3) voxel coordinates; inf where
    no edge of the voxel crosses), and the band mask."""
    r = V.shape[0]
    ijk = jnp.stack(jnp.meshgrid(*(jnp.arange(r, dtype=V.dtype),) * 3, indexing="ij"), -1)
    best = jnp.full(V.shape + (3,), jnp.inf, V.dtype)
    best_d = jnp.full(V.shape, jnp.inf, V.dtype)
    for axis in range(3):
        for o in (1, -1):
            e = [0, 0, 0]
            e[axis] = o
            other = _shift(V, e, jnp.nan)
            cross = (V < 0) != (other < 0)  # NaN (off the grid) compares False: no crossing
            t = V / jnp.where(cross, V - other, 1.0)  # share of the way to the neighbour, in [0, 1]
            d = jnp.where(cross, t, jnp.inf)
            point = ijk.at[..., axis].add(o * t)
            take = d < best_d
            best = jnp.where(take[..., None], point, best)
            best_d = jnp.where(take, d, best_d)
    return best, jnp.isfinite(best_d)


def jump_flood(seeds, unroll: bool = False):
    """Distance (voxels) from every voxel to its nearest seed by jump flooding (Rong and Tan 2006): passes of step
    R/2, R/4, ..., 1, then `_JFA_CLEANUP`, each voxel taking the nearest of its own seed and those held by the 26
    voxels a step away. Scans over passes and offsets keep the compile under a second; `unroll` unrolls the offsets
    (faster on a GPU: bench/depth.py --speed)."""
    r = seeds.shape[0]
    pad = r // 2
    ijk = jnp.stack(jnp.meshgrid(*(jnp.arange(r, dtype=seeds.dtype),) * 3, indexing="ij"), -1)
    steps, k = [], r // 2
    while k >= 1:
        steps.append(k)
        k //= 2
    offsets = np.stack(np.meshgrid(*([-1, 0, 1],) * 3, indexing="ij"), -1).reshape(-1, 3)
    offsets = jnp.asarray(offsets[np.abs(offsets).sum(1) > 0], jnp.int32)

    def one_pass(best, k):
        padded = jnp.pad(best, ((pad, pad),) * 3 + ((0, 0),), constant_values=jnp.inf)

        def candidate(carry, o):
            b, bd = carry
            start = jnp.append(pad + o * k, 0)  # one index dtype for all four (int32, also under x64)
            c = jax.lax.dynamic_slice(padded, tuple(start), (r, r, r, 3))
            d = jnp.sum((c - ijk) ** 2, -1)
            take = d < bd
            return (jnp.where(take[..., None], c, b), jnp.where(take, d, bd)), None

        carry = (best, jnp.sum((best - ijk) ** 2, -1))
        if unroll:  # one fused kernel per pass on a GPU instead of 26 small ones
            for o in offsets:
                carry, _ = candidate(carry, o)
        else:
            carry, _ = jax.lax.scan(candidate, carry, offsets)
        return carry[0], None

    best, _ = jax.lax.scan(one_pass, seeds, jnp.asarray(steps + list(_JFA_CLEANUP), jnp.int32))
    return jnp.sqrt(jnp.sum((best - ijk) ** 2, -1))


def _dilate(mask):
    """Binary dilation by the 6-neighbour cross (scipy.ndimage.binary_dilation's default)."""
    out = mask
    for axis in range(3):
        for o in (1, -1):
            e = [0, 0, 0]
            e[axis] = o
            out = out | _shift(mask, e, False)
    return out


def _to_grid(V, h):
    """(R, R, R, 4) distance and unit gradient from the resolved field V (module docstring: the conversion)."""
    seeds, band = flood_seeds(V)
    dist = h * jump_flood(seeds, jax.default_backend() in UNROLL_JFA_ON)
    slope = jnp.linalg.norm(jnp.stack(jnp.gradient(V, h), -1), axis=-1)
    first = jnp.abs(V) / jnp.where(slope > 0, slope, 1.0)
    clipped = _dilate(jnp.abs(V) >= jnp.abs(V).max() * (1 - 1e-9))
    near = (band | ~clipped) & (slope > 0) & (first < _FIRST_ORDER_REACH * h)
    dist = jnp.where(near, jnp.minimum(dist, first), dist)
    sd = jnp.where(V < 0, -dist, dist)
    grad = jnp.stack(jnp.gradient(sd, h), -1)
    norm = jnp.linalg.norm(grad, axis=-1, keepdims=True)
    up = jnp.zeros_like(grad).at[..., 2].set(1.0)
    grad = jnp.where(norm > 1e-12, grad / jnp.where(norm > 1e-12, norm, 1.0), up)  # flat spots: any unit vector
    return jnp.concatenate([sd[..., None], grad], -1)


def _check_sides(any_inside: bool, all_inside: bool) -> None:
    if not any_inside:
        raise FfcgsError("the fused volume has no voxel inside the object: no depth reading on the object lies in "
                         "the grid (check the masks, the poses and the bounds)")
    if all_inside:
        raise FfcgsError("the fused volume is inside the object everywhere: no camera saw free space in the grid "
                         "(check the poses: camera-to-world, OpenCV axes)")


@jax.jit
def _convert(V, h):
    return _to_grid(V, h), (V < 0).any(), (V < 0).all()


def to_gradient_sdf(values: Float[Array | np.ndarray, "R R R"], origin: Float[np.ndarray, " 3"],
                    voxel_size: float, table_z: float) -> GradientSDF:
    """The GradientSDF whose zero level is that of `values` (a truncated or projective field, negative inside),
    with Euclidean distances away from it (module docstring: the conversion), jit-compiled: the distance to the
    zero crossings comes from jump flooding instead of a KD-tree (it agrees with `to_gradient_sdf_reference`
    except for rare voxels far from the surface, a fraction of a voxel off: tests/geometry/test_tsdf.py).

    Args:
        values: (R, R, R) fused field on the voxel centres, metres.
        origin: (3,) centre of voxel [0, 0, 0].
        voxel_size: metres.
        table_z: table height stored in the result.

    Returns:
        The GradientSDF, arrays in JAX's default float dtype.
    """
    fdt = jnp.result_type(float)
    grid, any_inside, all_inside = _convert(jnp.asarray(values, fdt), jnp.asarray(voxel_size, fdt))
    _check_sides(bool(any_inside), bool(all_inside))
    return GradientSDF(grid=grid, origin=jnp.asarray(origin, fdt), voxel_size=jnp.asarray(voxel_size, fdt),
                       table_z=jnp.asarray(float(table_z), fdt))


def _world_points(depth, K, poses):
    h, w = depth.shape[1:]
    v, u = jnp.meshgrid(jnp.arange(h, dtype=depth.dtype), jnp.arange(w, dtype=depth.dtype), indexing="ij")
    rays = jnp.stack([u, v, jnp.ones_like(u)], -1) @ jnp.linalg.inv(K).T  # (H, W, 3), z = 1
    cam = rays[None] * depth[..., None]
    return jnp.einsum("nij,nhwj->nhwi", poses[:, :3, :3], cam) + poses[:, None, None, :3, 3]


def _fuse_device(depth, mask, K, poses, table_z, box, margin, min_margin, trunc_voxels, res, cut_table, crop,
                 fit_box):
    """`fuse` from the frames to the grid in one compiled function: the object's readings (mask, above the table
    band, in the box if `crop`), the grid frame around them or around the box (as `grid_frame`), the fusion and
    the conversion."""
    p = _world_points(depth, K, poses)
    obj = mask & (depth > 0)
    if cut_table:
        obj = obj & (p[..., 2] - table_z >= depth_io.TABLE_BAND)
    if crop:
        obj = obj & jnp.all((p >= box[0][None, None, None]) & (p <= box[1][None, None, None]), -1)
    if fit_box:  # the cube around the object's readings
        lo = jnp.min(jnp.where(obj[..., None], p, jnp.inf), axis=(0, 1, 2))
        hi = jnp.max(jnp.where(obj[..., None], p, -jnp.inf), axis=(0, 1, 2))
        if cut_table:
            lo = lo.at[2].min(table_z)  # the object's hidden underside reaches the table
    else:
        lo, hi, margin, min_margin = box[0], box[1], 0.0, 0.0
    size = jnp.max(hi - lo)
    side = size + 2.0 * jnp.maximum(margin * size, min_margin)
    h = side / (res - 1)
    origin = (lo + hi) / 2.0 - side / 2.0
    trunc = trunc_voxels * h
    volume = _integrate(depth, obj, K, poses, origin, h, trunc, res)
    V = jnp.where(volume.weight > 0, volume.tsdf, jnp.where(volume.shadow, -trunc, trunc))
    if cut_table:
        z = origin[2] + h * jnp.arange(res, dtype=V.dtype)
        V = jnp.maximum(V, table_z - z[None, None, :])
    return _to_grid(V, h), origin, h, jnp.sum(obj), (V < 0).any(), (V < 0).all()


_fuse_jit = jax.jit(_fuse_device, static_argnames=("res", "cut_table", "crop", "fit_box"))


def fuse(frames: depth_io.Frames, res: int = 64, trunc_voxels: float = 4.0,
         bounds: Float[np.ndarray, "2 3"] | None = None, table_z: float | None = None, margin: float = 0.15,
         min_margin: float = 0.01, on_device: bool = True, points: np.ndarray | None = None,
         crop: Float[np.ndarray, "2 3"] | None = None) -> GradientSDF:
    """Depth frames of one object fused into its GradientSDF.

    Typical use: `frames, tz = depth_io.remove_table(depth_io.load_frames(path))`, then `fuse(frames, table_z=tz)`.

    Args:
        frames: the frames (`depth_io`); the mask tells the object's readings from the background's.
        res: voxels along each axis of the cube (16-128).
        trunc_voxels: truncation distance in voxels (3-4: wider smooths noise, narrower keeps thin parts).
        bounds: (2, 3) workspace box (min, max corners, metres): readings outside it become background and the
            grid is the cube around it. None: the cube around the object's readings (in the mask, above the table)
            plus `margin` (share of the largest extent, at least `min_margin` metres) on each side, as
            `sdf.build_sdf`.
        table_z: table height in metres (from `depth_io.remove_table`): readings less than 5 mm above it become
            background (as `remove_table` with this height), nothing below it is object, and the result keeps it.
            None: no table; the result's table_z is the bottom of the grid.
        margin, min_margin: see `bounds`.
        on_device: everything from the frames to the GradientSDF in one compiled function (the conversion by
            jump flooding), on whatever JAX runs on; False: the host's steps (NumPy, the conversion by a KD-tree),
            kept as the tests' reference. The compiled path is also the faster on a CPU (bench/depth.py --speed:
            281 against 568 ms on two cores).
        points: for the host steps, `depth_io.world_points(frames)` when the caller has it already.
        crop: (2, 3) box (min, max corners, metres) or None: readings outside it become background, as with
            `bounds`, but the grid is still fitted to the readings left (`depth_isolate`'s box around the object).
            Ignored when `bounds` is given.

    Returns:
        The GradientSDF, arrays in JAX's default float dtype.
    """
    frames = depth_io.check_frames(frames)
    check_integer("res", res, 16, 128)
    check_range("trunc_voxels", trunc_voxels, 1, 16)
    check_range("margin", margin, 0.0, 2.0)
    check_range("min_margin", min_margin, 0.0, 1.0)
    crop = None if crop is None or bounds is not None else depth_io.check_bounds(crop)
    if on_device:
        return _fuse_on_device(frames, res, trunc_voxels, bounds, table_z, margin, min_margin, crop)
    p = depth_io.world_points(frames) if points is None else points
    if table_z is not None:
        frames, table_z = depth_io.remove_table(frames, table_z, points=p)  # idempotent after the caller's own
    if crop is not None:
        frames = depth_io.crop(frames, crop, points=p)
    if bounds is not None:
        box = depth_io.check_bounds(bounds)
        frames = depth_io.crop(frames, box, points=p)
        origin, h = grid_frame(box, res)
    else:
        p = p[depth_io.object_mask(frames) & (frames.depth > 0)]
        if not len(p):
            raise FfcgsError(_NO_READING)
        lo, hi = p.min(0), p.max(0)
        if table_z is not None:
            lo[2] = min(lo[2], table_z)  # the object's hidden underside reaches the table
        origin, h = grid_frame(np.stack([lo, hi]), res, margin, min_margin)
    trunc = trunc_voxels * h
    volume = integrate(frames.depth, frames.K, frames.poses, origin, h, res, trunc, mask=depth_io.object_mask(frames))
    values = resolve(volume, trunc, origin, h, table_z)
    return to_gradient_sdf_reference(values, origin, h, origin[2] if table_z is None else table_z)


_NO_READING = ("no depth reading on the object in any frame (all readings are zero, outside the masks or under the "
               "table)")


def _fuse_on_device(frames, res, trunc_voxels, bounds, table_z, margin, min_margin, crop) -> GradientSDF:
    fdt = jnp.result_type(float)
    box = depth_io.check_bounds(bounds) if bounds is not None else np.zeros((2, 3)) if crop is None else crop
    if table_z is not None and not np.isfinite(table_z):
        raise FfcgsError(f"table_z must be finite, got {table_z}")
    f = lambda x: jnp.asarray(x, fdt)  # noqa: E731
    grid, origin, h, n_obj, any_inside, all_inside = _fuse_jit(
        f(frames.depth), jnp.asarray(depth_io.object_mask(frames)), f(frames.K), f(frames.poses),
        f(0.0 if table_z is None else table_z), f(box), f(margin), f(min_margin), f(trunc_voxels), res=int(res),
        cut_table=table_z is not None, crop=bounds is not None or crop is not None, fit_box=bounds is None)
    if int(n_obj) == 0:
        raise FfcgsError(_NO_READING)
    _check_sides(bool(any_inside), bool(all_inside))
    return GradientSDF(grid=grid, origin=origin, voxel_size=h,
                       table_z=origin[2] if table_z is None else jnp.asarray(table_z, fdt))
