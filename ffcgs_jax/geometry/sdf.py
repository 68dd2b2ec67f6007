"""Gradient-SDF of a triangle mesh: built exactly, queried in pure JAX.

A `GradientSDF` is a cubic voxel grid whose four channels hold, at each voxel centre, the signed distance to the
mesh (metres, negative inside) and its gradient (the outward unit vector from the closest surface point).
`query` blends, with trilinear weights, each corner's first-order estimate d_i + g_i . (p - v_i) of the distance
(exact on both sides of a kink of the field, e.g. inside thin walls, where plain trilinear interpolation is off by
up to half a voxel) and the gradient channels themselves; `distance` is the same value with the interpolated
gradient channel as its derivative (the Gradient-SDF idea).

Building (`build_sdf`): this module checks the mesh, picks the grid and keeps recent grids; `sdf_device` computes
the exact distances, their winding-number sign and the gradient channels in one jitted function on the default
JAX device. `sdf_build` does the same on the host: the reference of the tests and benchmarks (its docstring defines
the three steps).
"""

import cachetools
import pathlib
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import trimesh
from jax.custom_derivatives import SymbolicZero

from ffcgs_jax.core import files
from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.geometry import mesh_io, sdf_build, sdf_device
from ffcgs_jax.runtime import compiled
from ffcgs_jax.geometry.config import SDFConfig
from ffcgs_jax.core.types import Array, Float

_FORMAT_VERSION = 1


class GradientSDF(NamedTuple):
    """Signed distance grid with gradient channels (a pytree; all leaves are arrays).

    Attributes:
        grid: (R, R, R, 4). Channel 0: signed distance in metres, negative inside. Channels 1-3: its gradient, an
            outward unit vector. Index [i, j, k] runs along x, y, z.
        origin: (3,) position of the centre of voxel [0, 0, 0] in metres; voxel [i, j, k] is at
            origin + voxel_size * (i, j, k).
        voxel_size: () spacing of voxel centres in metres.
        table_z: () height of the table plane z = table_z (z up).
        cells: None, or the grid regrouped by cell for fast queries (`with_cells`), derived from `grid` and
            `voxel_size`; never stored in files. Build it again (`with_cells`) after changing the grid.
    """

    grid: Float[Array, "R R R 4"]
    origin: Float[Array, " 3"]
    voxel_size: Float[Array, ""]
    table_z: Float[Array, ""]
    cells: Float[Array, "n 2 2 2 4"] | None = None


# ----------------------------------------------------------------------------------------------------------------
# Build
# ----------------------------------------------------------------------------------------------------------------


def grid_frame(bounds: np.ndarray, cfg: SDFConfig) -> tuple[np.ndarray, float]:
    """Origin and voxel size of the cube grid around an axis-aligned box `bounds` (2, 3).

    The cube is centred on the box centre. Its side is the box's largest extent L plus a margin
    max(cfg.margin * L, cfg.min_margin) on each side; voxel centres span the cube from face to face, so the
    voxel size is side / (res - 1).
    """
    lo, hi = np.asarray(bounds, np.float64)
    size = float((hi - lo).max())
    side = size + 2.0 * max(cfg.margin * size, cfg.min_margin)
    if not side > 0:
        raise FfcgsError("build_sdf: the mesh has zero extent and sdf.min_margin is 0, so the grid would be empty")
    voxel = side / (cfg.res - 1)
    return (lo + hi) / 2.0 - side / 2.0, voxel


_CACHE_SIZE = 16  # grids kept by `build_sdf`
_CACHE_BYTES = 1 << 29  # and at most 512 MB of them (a 32^3 grid is 1 MB in float64, a 128^3 one 67 MB)
# key -> GradientSDF; each grid counts at least 1/16 of the bytes, so at most 16 are kept
_cache = cachetools.LRUCache(_CACHE_BYTES, getsizeof=lambda g: min(max(g.grid.nbytes, _CACHE_BYTES // _CACHE_SIZE),
                                                                  _CACHE_BYTES))
compiled.register("geometry.sdf grids", _cache)
_BUILDERS = ("device", "host")


def build_sdf(
    mesh: trimesh.Trimesh,
    cfg: SDFConfig = SDFConfig(),
    table_z: float | None = None,
    *,
    builder: str = "device",
    cache: bool = True,
) -> GradientSDF:
    """Build the Gradient-SDF of `mesh` on a cfg.res^3 cube grid (exact distances).

    The cube is centred on the mesh's bounding-box centre; its side is the largest extent L plus, on each side, a
    margin of max(cfg.margin * L, cfg.min_margin) metres, so fingertips approaching from outside stay on the grid.
    Outside the cube `query` extends the field (see there).

    Grids are kept per process (the last 16 and at most 512 MB, least recently used dropped first), keyed by a
    SHA-256 of the vertices (float64) and faces (int64), cfg.res, cfg.margin, cfg.min_margin, table_z, the builder
    and JAX's default float dtype: a repeated call returns the same GradientSDF at once. Its leaves are immutable
    JAX arrays, so sharing it is safe. `cache=False` builds anew (and keeps nothing); `clear_cache()` empties the
    cache.

    Args:
        mesh: triangle mesh in metres (see `mesh_io.load_mesh`); need not be watertight.
        cfg: grid resolution and margins (cfg.scale is applied when loading, by `mesh_io.load_mesh`).
        table_z: height of the table plane; default the mesh's lowest z (the object rests on the table).
        builder: "device" (`sdf_device`: one jitted function on the default JAX device, GPU or CPU) or "host"
            (`sdf_build`: the host reference, for tests and benchmarks). Both give the same grid up to float32
            rounding of the nearest-triangle search (~1e-8 m).
        cache: look the grid up in, and add it to, the per-process cache.

    Returns:
        The GradientSDF, arrays in JAX's default float dtype.
    """
    cfg.check()
    if builder not in _BUILDERS:
        raise FfcgsError(f"build_sdf: unknown builder {builder!r}; valid: {', '.join(_BUILDERS)}")
    verts = np.asarray(mesh.vertices, np.float64)
    faces = np.asarray(mesh.faces, np.int64)
    if faces.ndim != 2 or faces.shape[0] == 0 or faces.shape[1] != 3:
        raise FfcgsError(f"build_sdf needs a triangle mesh with faces, got faces of shape {faces.shape}")
    if faces.min() < 0 or faces.max() >= len(verts):
        raise FfcgsError(f"build_sdf: faces index vertices 0..{faces.max()}, but the mesh has {len(verts)} vertices")
    if not np.isfinite(verts).all():
        raise FfcgsError("build_sdf: mesh vertices contain NaN or inf")
    if table_z is not None and not np.isfinite(table_z):
        raise FfcgsError(f"table_z must be finite, got {table_z}")
    key = (mesh_io.mesh_sha256(mesh), cfg.res, cfg.margin, cfg.min_margin,
           None if table_z is None else float(table_z), builder, jnp.result_type(float).name)
    if cache and (hit := _cache.get(key)) is not None:
        return hit
    flat = verts[faces].reshape(-1, 3)
    origin, voxel = grid_frame(np.stack([flat.min(0), flat.max(0)]), cfg)
    if builder == "device":
        grid = sdf_device.gradient_grid(verts, faces, origin, voxel, cfg.res)
    else:
        dist, grad = sdf_build.signed_distance_grid(verts, faces, origin, voxel, cfg.res)
        grid = jnp.asarray(np.concatenate([dist[..., None], grad], axis=-1))
    tz = float(flat[:, 2].min()) if table_z is None else float(table_z)
    out = GradientSDF(grid=grid, origin=jnp.asarray(origin), voxel_size=jnp.asarray(voxel), table_z=jnp.asarray(tz))
    if cache:
        _cache[key] = out
    return out


def clear_cache() -> None:
    """Forget the grids `build_sdf` keeps (after this, each mesh is built again)."""
    _cache.clear()


# ----------------------------------------------------------------------------------------------------------------
# JAX queries
# ----------------------------------------------------------------------------------------------------------------


class ObjectExtent(NamedTuple):
    """What the grasp code needs to know of an object, read off its SDF (host-side NumPy).

    Attributes:
        centre: (3,) centroid of the inside voxels: the torque reference point of the grasp wrenches.
        lo, hi: (3,) axis-aligned bounds of the inside voxels, widened by half a voxel.
        radius: largest distance from `centre` to the object (inside voxels, plus half a voxel diagonal): the
            characteristic length that makes torques comparable to forces.
    """

    centre: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    radius: float


def object_extent(sdf: GradientSDF) -> ObjectExtent:
    """Centre, bounds and radius of the object from the SDF alone (so it also works for SDFs fused from depth).

    Objects thinner than a voxel have no voxel centre inside; then the voxels within half a voxel of the surface
    stand in for the inside.
    """
    grid = np.asarray(sdf.grid[..., 0])
    h = float(sdf.voxel_size)
    inside = grid <= 0
    if not inside.any():
        inside = grid <= 0.5 * h
    if not inside.any():
        raise FfcgsError(f"the SDF has no voxel inside or on the object (voxels of {h * 1000:.3g} mm): is the object "
                         "empty, or smaller than a voxel because of a wrong --scale?")
    p = np.asarray(sdf.origin) + h * np.argwhere(inside)
    centre = p.mean(0)
    radius = float(np.linalg.norm(p - centre, axis=1).max() + 0.5 * np.sqrt(3) * h)
    return ObjectExtent(centre, p.min(0) - 0.5 * h, p.max(0) + 0.5 * h, radius)


@jax.jit
def _extent_on_device(grid, origin, h):
    d = grid[..., 0]
    inside = jnp.where((d <= 0).any(), d <= 0, d <= 0.5 * h)
    w = inside.astype(d.dtype)
    # offsets from the origin, summed: the origin's magnitude would cost float32 digits in the mean
    off = h * jnp.stack(jnp.meshgrid(*(jnp.arange(n, dtype=d.dtype) for n in d.shape), indexing="ij"), -1)
    count = w.sum()
    mean = (off * w[..., None]).sum((0, 1, 2)) / jnp.maximum(count, 1.0)
    far = jnp.max(jnp.where(inside, jnp.linalg.norm(off - mean[None, None, None], axis=-1), 0.0))
    return origin + mean, far + 0.5 * jnp.sqrt(3.0).astype(d.dtype) * h, count > 0


def object_centre_radius(sdf: GradientSDF) -> tuple[jax.Array, jax.Array]:
    """`object_extent`'s centre and radius, computed on the device in one call (no copy of the grid to the host:
    that copy and NumPy's pass over it cost more than the rest of a cached `synthesize` call's host work). Agrees
    with `object_extent` to float rounding."""
    centre, radius, ok = _extent_on_device(sdf.grid, sdf.origin, jnp.asarray(sdf.voxel_size, sdf.grid.dtype))
    if not bool(ok):
        h = float(sdf.voxel_size)
        raise FfcgsError(f"the SDF has no voxel inside or on the object (voxels of {h * 1000:.3g} mm): is the object "
                         "empty, or smaller than a voxel because of a wrong --scale?")
    return centre, radius


def _check_points(points) -> None:
    if points.ndim != 2 or points.shape[-1] != 3:
        raise FfcgsError(f"points must have shape (P, 3), got {points.shape}")
    if not isinstance(points, jax.core.Tracer) and not bool(jnp.isfinite(points).all()):
        raise FfcgsError("points contain NaN or inf")


def _norm(v, eps):
    """|v| with a finite gradient at v = 0 (where it returns 0)."""
    n2 = v @ v
    ok = n2 > eps * eps
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, n2, 1.0)), 0.0)


_CORNERS = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], np.int32)  # (8, 3)


def with_cells(sdf: GradientSDF) -> GradientSDF:
    """`sdf` with its cell table: for each of the (R-1)^3 cells, its 8 corners' [d_i - h g_i . c_i, g_i] (c_i the
    corner's 0/1 offset in the cell), so a query reads one contiguous block per point instead of 8 scattered voxels.

    Why: on CPUs XLA's gather of 8 small rows per point cost 4x the whole lookup through the table (penetration
    penalty of 368 points per hand, 2-core CPU). The table holds 8x the grid's numbers (4 MB at 32^3, 262 MB at
    128^3); `synthesis.energy.make_target` builds it once per object. Queries give the same values with or
    without it.
    """
    return sdf._replace(cells=_cell_table(sdf.grid, jnp.asarray(sdf.voxel_size, sdf.grid.dtype)))


@jax.jit
def _cell_table(G, h):  # one compiled call: eagerly, its ~40 small ops cost milliseconds of dispatch on a GPU
    R = G.shape[0]
    blocks = []
    for c in _CORNERS:
        v = G[c[0]:c[0] + R - 1, c[1]:c[1] + R - 1, c[2]:c[2] + R - 1]
        blocks.append(jnp.concatenate([v[..., :1] - h * (v[..., 1:] @ jnp.asarray(c, G.dtype))[..., None],
                                       v[..., 1:]], -1))
    return jnp.stack(blocks, 3).reshape(-1, 2, 2, 2, 4)


def _query_one(sdf: GradientSDF, p):
    """Signed distance (scalar) and unit gradient (3,) at one point p (3,)."""
    res = sdf.grid.shape[0]
    h = sdf.voxel_size
    hi = sdf.origin + h * (res - 1)
    pc = jnp.clip(p, sdf.origin, hi)  # clamped into the grid box
    u = (pc - sdf.origin) / h
    i0 = jnp.clip(jnp.floor(u), 0, res - 2)
    t = u - i0
    i0 = i0.astype(jnp.int32)
    # Each corner's first-order estimate d_i + g_i . (p - v_i), blended trilinearly: exact on both sides of a
    # kink of the distance field (medial axes inside thin walls), where plain trilinear interpolation of d_i is
    # off by up to half a voxel. With e_i = d_i - h g_i . c_i that blend is lerp(e) + h lerp(g) . t, so the four
    # channels [e, g] are blended as one vector by seven lerps, and the blended g is the gradient channel's too.
    if sdf.cells is None:
        corner = jnp.asarray(_CORNERS)
        vals = sdf.grid[i0[0] + corner[:, 0], i0[1] + corner[:, 1], i0[2] + corner[:, 2]]  # (8, 4)
        e = vals[:, 0] - h * jnp.sum(vals[:, 1:] * corner.astype(vals.dtype), axis=1)
        v = jnp.concatenate([e[:, None], vals[:, 1:]], 1).reshape(2, 2, 2, 4)
    else:
        v = sdf.cells[(i0[0] * (res - 1) + i0[1]) * (res - 1) + i0[2]]
    for k in range(3):
        v = v[0] + t[k] * (v[1] - v[0])
    out = p - pc
    dist = v[0] + h * (v[1:] @ t) + _norm(out, 1e-30)
    g = v[1:] + out / h
    n = _norm(g, 1e-12)
    g = jnp.where(n > 0, g / jnp.where(n > 0, n, 1.0), g)
    return dist, g


def query(sdf: GradientSDF, points: Float[Array, "P 3"]) -> tuple[Float[Array, " P"], Float[Array, "P 3"]]:
    """Signed distance and outward unit gradient at points, from the 8 voxels around each point.

    The distance is the trilinear blend of the corners' first-order estimates d_i + g_i . (p - v_i); the gradient
    is the trilinear blend of the gradient channels, normalised.

    Outside the grid box a point p is clamped to the box (p_c) and the field extended as
    d(p) = d(p_c) + |p - p_c| (it grows with the distance to the box) and g(p) = normalise(g(p_c) + (p - p_c) / h),
    which is continuous at the box and whose negative points back toward the object. Pure JAX: jit, vmap and grad
    work; gradients stay finite everywhere.

    Args:
        sdf: the grid.
        points: (P, 3) query points in metres.

    Returns:
        distance (P,) in metres (negative inside) and gradient (P, 3), unit vectors.
    """
    _check_points(points)
    return jax.vmap(_query_one, (None, 0))(sdf, points)


def resample(sdf: GradientSDF, res: int) -> GradientSDF:
    """The same cube sampled at `res`^3 voxel centres (distance and gradient from `query`); for a consumer that needs
    one resolution, such as the cvae sampler. `res` is static. Resampling at the grid's own resolution returns the
    stored values (up to renormalised gradients)."""
    r0 = sdf.grid.shape[0]
    h = sdf.voxel_size * r0 / res
    origin = sdf.origin - sdf.voxel_size / 2 + h / 2
    ijk = jnp.stack(jnp.meshgrid(*(jnp.arange(res),) * 3, indexing="ij"), -1).reshape(-1, 3)
    d, g = query(sdf, origin[None, :] + h * ijk.astype(origin.dtype))
    grid = jnp.concatenate([d[:, None], g], axis=1).reshape(res, res, res, 4).astype(sdf.grid.dtype)
    return GradientSDF(grid, origin, h, sdf.table_z)


@jax.custom_jvp
def _distance_one(sdf: GradientSDF, p):
    return _query_one(sdf, p)[0]


def _distance_one_jvp(primals, tangents):
    sdf, p = primals
    sdf_dot, p_dot = tangents
    d, g = _query_one(sdf, p)
    zero = lambda x: isinstance(x, SymbolicZero)  # noqa: E731
    out = jnp.zeros_like(d) if zero(p_dot) else g @ p_dot
    # Symbolic zeros: the grid is a constant in the descent, and a zero tangent of the cell table would otherwise
    # be built and read at every query (it doubled the penalty's gradient on CPUs).
    leaves = jax.tree.leaves(sdf_dot, is_leaf=zero)
    if not all(map(zero, leaves)):  # through the grid values, if varied
        sdf_dot = jax.tree.map(lambda t, x: jnp.zeros_like(x) if zero(t) else t, sdf_dot, sdf, is_leaf=zero)
        out = out + jax.jvp(lambda s: _query_one(s, p)[0], (sdf,), (sdf_dot,))[1]
    return d, out


_distance_one.defjvp(_distance_one_jvp, symbolic_zeros=True)


def distance(sdf: GradientSDF, points: Float[Array, "P 3"]) -> Float[Array, " P"]:
    """Signed distance at points (as `query`), whose derivative wrt the points is the interpolated gradient channel.

    This is the Gradient-SDF convention: the derivative is the stored (smooth, unit) surface normal field rather
    than the derivative of the trilinear interpolant, which is piecewise and jumps between voxels.

    Args:
        sdf: the grid.
        points: (P, 3) query points in metres.

    Returns:
        (P,) signed distance in metres.
    """
    _check_points(points)
    return jax.vmap(_distance_one, (None, 0))(sdf, points)


def query_scene(sdf: GradientSDF, points: Float[Array, "P 3"]) -> tuple[Float[Array, " P"], Float[Array, "P 3"]]:
    """Distance and gradient to the union of the object and the table half-space z <= table_z.

    Args:
        sdf: the grid (its table_z is used).
        points: (P, 3) query points in metres.

    Returns:
        distance (P,): the smaller of the object distance and z - table_z; gradient (P, 3) of the one that wins,
        (0, 0, 1) for the table.
    """
    d_obj, g_obj = query(sdf, points)
    d_tab = points[:, 2] - sdf.table_z
    table = d_tab < d_obj
    up = jnp.zeros_like(g_obj).at[:, 2].set(1.0)
    return jnp.where(table, d_tab, d_obj), jnp.where(table[:, None], up, g_obj)


# ----------------------------------------------------------------------------------------------------------------
# Files
# ----------------------------------------------------------------------------------------------------------------


def save(sdf: GradientSDF, path: str | pathlib.Path) -> None:
    """Write the grid to an .npz file (no pickles)."""
    arrays = {k: np.asarray(v) for k, v in sdf._asdict().items() if k != "cells"}  # derived, rebuilt on demand
    # a file handle, so numpy does not append .npz to the name; atomic, so a failed write keeps the old file
    files.atomic_write(files.check_output(path, "SDF file"),
                       lambda f: np.savez_compressed(f, version=np.int64(_FORMAT_VERSION), **arrays))


def load(path: str | pathlib.Path) -> GradientSDF:
    """Read a grid written by `save`, checking keys, shapes and finite values."""
    path = pathlib.Path(path)
    data = files.read_npz(path, "SDF file", ".npz")
    need = ("version", "grid", "origin", "voxel_size", "table_z")
    missing = [k for k in need if k not in data]
    if missing:
        raise FfcgsError(f"SDF file {path} lacks key(s) {', '.join(missing)} (has {', '.join(sorted(data))})")
    version = data["version"]
    if version.shape != () or version.dtype.kind not in "iu" or int(version) != _FORMAT_VERSION:
        raise FfcgsError(f"SDF file {path} has format version {data['version']}, expected {_FORMAT_VERSION}")
    grid = data["grid"]
    shapes = {"origin": (3,), "voxel_size": (), "table_z": ()}
    if grid.ndim != 4 or grid.shape[-1] != 4 or not grid.shape[0] == grid.shape[1] == grid.shape[2] >= 2:
        raise FfcgsError(f"SDF file {path}: grid must have shape (R, R, R, 4) with R >= 2, got {grid.shape}")
    for k, shape in shapes.items():
        if data[k].shape != shape:
            raise FfcgsError(f"SDF file {path}: {k} must have shape {shape}, got {data[k].shape}")
    for k in ("grid", *shapes):
        if not np.issubdtype(data[k].dtype, np.floating) or not np.isfinite(data[k]).all():
            raise FfcgsError(f"SDF file {path}: {k} must be finite floats (dtype {data[k].dtype})")
    if not data["voxel_size"] > 0:
        raise FfcgsError(f"SDF file {path}: voxel_size must be > 0, got {data['voxel_size']}")
    return GradientSDF(*(jnp.asarray(data[k]) for k in ("grid", "origin", "voxel_size", "table_z")))
