"""Device build of a Gradient-SDF grid: exact signed distances and their gradients, streamed over the triangles.

The contract and the definitions are the host builder's (`sdf_build.signed_distance_grid`: exact distance, sign
from the generalised winding number, gradient channel); here the build is XLA code over fixed shapes, the same on a
GPU and on the CPU. The triangles pass through the device in chunks of `FACE_CHUNK`, every chunk through the same
compiled steps (`_near_chunk`, `_wind_chunk`; caps through `_cap_chunk`), so one set of executables per grid
resolution serves meshes of any size, 100 faces or 200,000, and the work grows linearly with the face count.

Host side (`_pack`, NumPy, O(faces)): the triangles in Morton order relative to the grid centre (so float32 keeps
~1e-8 m; each chunk is then a compact region), cut into groups of _GROUP and padded to whole chunks; for an open
mesh, caps over its holes (below).

On the device:
1. Distance, exact, by candidate pruning over (tile, group) pairs. A tile is 4^3 voxels (64: the vector lanes on a
   CPU), a group 16 consecutive triangles with their bounding box. Each voxel first gets an upper bound u(v), its
   distance to the 4 groups nearest its tile's box; a pair (tile, group) is kept when the group's box lies within
   u(v) of some voxel v of the tile. The group of a voxel's nearest triangle is no farther than that triangle, so
   it is kept: the kept pairs, compacted into a list of fixed capacity and scanned in chunks, give every voxel its
   exact nearest triangle (float32 search). Its closest point is recomputed in the default float dtype with
   `closest_offset`.
2. Sign: inside where the generalised winding number w > 0.5. Neighbouring voxels u, v (26-neighbourhood) are
   joined when d(u) + d(v) > |u - v|: no surface crosses the segment uv. Components come from min-label propagation
   with hooking and pointer jumping in a `lax.while_loop` (about 5 rounds); w is evaluated at one voxel of each
   (its farthest from the surface), which covers every voxel that nothing joins (on the surface, in walls thinner
   than a voxel). On a closed mesh w is an integer off the surface, so one value holds for the whole component.
   An open mesh's w passes 0.5 on a film spanning each hole, off the surface. Caps close the holes: over each loop
   of border edges (directed edges whose uses do not cancel), a fan from the loop's centroid, oriented to cancel
   them. The capped mesh's winding number N is an integer, constant on the components of the free space of mesh and
   caps (d there is the distance to both), and w = N - w_caps, with w_caps, the caps' own winding number (a few
   triangles), evaluated at every voxel: exact voxel by voxel, where the host builder sets voxels near holes aside.
3. Gradient channel: sign * (p - closest) / |p - closest|, or the face normal where p lies on the surface.

Capacities: a chunk's pair list has room for all of its (tile, group) pairs and the component list for one component
per voxel, so neither can overflow and no size depends on the mesh. Only the steps of a list that hold entries run,
so the room costs memory, not time.

Cost on the 2-core CPU, 32^3, a 3,000-face YCB mesh: ~12-18 k pairs (~12-18 M point-triangle distances, 1 ns
each), a few hundred winding numbers over all faces, 4-5 propagation rounds: ~35 ms the whole call. Open meshes
add one pass of all voxels over the caps. The XLA CPU backend drove several layout choices (noted where made).
"""

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from scipy.sparse import coo_matrix, csgraph

from ffcgs_jax.kernels.triangles import closest_offset, dist2, orientation, search_table, solid_angles, tri_table
from ffcgs_jax.core.types import Array, Float, Int

_TILE = 4  # voxels per tile edge: a tile's 64 voxels share one candidate list
_GROUP = 16  # consecutive triangles (Morton order) per group: the unit of pruning
_SEEDS = 4  # groups nearest each tile whose triangles give the first upper bounds
FACE_CHUNK = 2048  # triangles per streamed chunk (256 groups): every mesh runs through the same executables
CAP_CHUNK = 256  # cap triangles per chunk (an open mesh's caps are a few hundred at most, a closed one has none)
_FAR = 1e3  # m: where padding triangles sit (degenerate: never nearest, zero solid angle)
_SLACK = 1e-6  # x grid side: margin of the pruning tests over float32 rounding (as the host builder)
_ON_SURFACE = 1e-12  # m, as the host builder: closer than this the face normal is the gradient


class Steps(NamedTuple):
    """Loop step sizes of `_build` (static). On a CPU, working sets its caches hold; on a GPU, enough work per step
    to fill it, since each step of a loop costs a round trip there."""

    pair: int  # (tile, group) pairs per step
    rep: int  # winding numbers per step
    vox: int  # voxels per step of the per-voxel passes (closest points, cap terms)
    tri: int  # triangles per step of a winding-number sum; 0: all at once
    unroll: int  # neighbours per step of the loops over the 26 neighbours (26: one fused kernel on a GPU)


CPU_STEPS = Steps(pair=1024, rep=64, vox=4096, tri=64, unroll=1)
GPU_STEPS = Steps(pair=8192, rep=512, vox=1 << 18, tri=0, unroll=26)



def signed_distance_grid_device(
    verts: Float[np.ndarray, "verts 3"],
    faces: Int[np.ndarray, "faces 3"],
    origin: Float[np.ndarray, " 3"],
    voxel: float,
    res: int,
) -> tuple[Float[Array, "R R R"], Float[Array, "R R R 3"]]:
    """Signed distance and its gradient at the voxel centres of a res^3 grid, built on the default JAX device.

    Same arguments and definitions as `sdf_build.signed_distance_grid`; returns jnp arrays in the default float
    dtype (float32 unless x64 is on; the distances are exact up to float32 rounding, ~1e-8 m, either way).

    Returns:
        distance (R, R, R) in metres, negative inside, and gradient (R, R, R, 3), outward unit vectors.
    """
    grid = gradient_grid(verts, faces, origin, voxel, res)
    return grid[..., 0], grid[..., 1:]


def gradient_grid(
    verts: Float[np.ndarray, "verts 3"],
    faces: Int[np.ndarray, "faces 3"],
    origin: Float[np.ndarray, " 3"],
    voxel: float,
    res: int,
) -> Float[Array, "R R R 4"]:
    """`signed_distance_grid_device` as one (R, R, R, 4) array: [distance, gradient] (`GradientSDF.grid`).

    The triangles stream through the device in chunks of `FACE_CHUNK`, each through the same compiled steps, so a
    mesh of any size reuses the executables of the first (one set per grid resolution, dtype and backend)."""
    dtype = jnp.result_type(float)
    steps = backend_steps()
    verts, faces = np.asarray(verts, np.float64), np.asarray(faces, np.int64)
    pk = _pack(verts, faces, np.asarray(origin, np.float64), float(voxel), res, dtype)
    voxel_a, orient = jnp.asarray(voxel, dtype), jnp.asarray(pk.orient, dtype)
    tri = [jnp.asarray(pk.tri[i:i + FACE_CHUNK]) for i in range(0, len(pk.tri), FACE_CHUNK)]
    rows = [jnp.asarray(pk.rows[i:i + FACE_CHUNK]) for i in range(0, len(pk.rows), FACE_CHUNK)]
    state = _start(voxel_a, res=res, dtype=np.dtype(dtype).name)
    for k, (t, r) in enumerate(zip(tri, rows)):
        state = _near_chunk(state, t, r, jnp.int32(k * FACE_CHUNK), voxel_a, res=res, steps=steps)
    n = res**3
    d_cap, w_caps = jnp.full(n, jnp.inf, jnp.float32), jnp.zeros(n, jnp.float32)
    for i in range(0, len(pk.caps), CAP_CHUNK):
        d_cap, w_caps = _cap_chunk(d_cap, w_caps, jnp.asarray(pk.caps[i:i + CAP_CHUNK]), voxel_a, res=res)
    comp = _sign_components(state, d_cap, voxel_a, res=res, steps=steps)
    wind = jnp.zeros(n, jnp.float32)
    for t in tri:
        wind = _wind_chunk(wind, comp, t, steps=steps)
    return _grid(state, comp, wind, w_caps, voxel_a, orient, res=res)


def backend_steps() -> Steps:
    """The loop step sizes for JAX's default backend: CPU_STEPS on the CPU, else GPU_STEPS."""
    return CPU_STEPS if jax.default_backend() == "cpu" else GPU_STEPS


# --- host packing -------------------------------------------------------------------------------------------------


class _Packed(NamedTuple):
    tri: np.ndarray  # (F_pad, 3, 3) Morton-ordered triangles relative to the grid centre, default dtype
    rows: np.ndarray  # (F_pad, 12) `tri_table` rows of tri, default dtype
    caps: np.ndarray  # (C_pad, 3, 3) cap triangles relative to the grid centre, float32; none for a closed mesh
    orient: float  # +1, or -1 for an inside-out mesh (`orientation`)


def _pack(verts, faces, origin, voxel, res, dtype) -> _Packed:
    tri = verts[faces]
    centre = origin + voxel * (res - 1) / 2.0
    t = tri[_morton_order(tri.mean(1))] - centre
    n_grouped = -(-len(t) // _GROUP) * _GROUP
    # The last group is filled with points (degenerate triangles) at a vertex of its last triangle: they never beat
    # that triangle, add no solid angle, and keep the group's bounding box tight.
    point = np.repeat(t[-1:, :1], 3, axis=1)
    far = np.full((-n_grouped % FACE_CHUNK, 3, 3), _FAR)
    t = np.concatenate([t, np.repeat(point, n_grouped - len(t), axis=0), far])
    caps = _hole_caps(verts, faces) - centre
    caps = np.concatenate([caps, np.full((-len(caps) % CAP_CHUNK, 3, 3), _FAR)])
    return _Packed(t.astype(dtype), tri_table(t, dtype), caps.astype(np.float32), orientation(tri))


def _morton_order(c: np.ndarray) -> np.ndarray:
    """Order of points (n, 3) along a Morton (Z-order) curve of 10 bits per axis: neighbours stay close."""
    lo, hi = c.min(0), c.max(0)
    q = ((c - lo) / np.maximum(hi - lo, 1e-30) * 1023).astype(np.uint32)
    for shift, mask in ((16, 0x030000FF), (8, 0x0300F00F), (4, 0x030C30C3), (2, 0x09249249)):  # bit k -> bit 3k
        q = (q | (q << np.uint32(shift))) & np.uint32(mask)
    return np.argsort(q[:, 0] | q[:, 1] << np.uint32(1) | q[:, 2] << np.uint32(2), kind="stable")


def _hole_caps(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Triangles (n, 3, 3) closing the holes of a mesh: for each border edge a -> b (a directed edge that its
    opposite does not cancel), the triangle (b, a, centroid of its border loop); none for a closed mesh. Vertices
    at the same position count as one, so an unmerged triangle soup is closed where its faces meet."""
    a, b = _border_edges(faces, len(verts))
    if len(a) == 0:
        return np.zeros((0, 3, 3))
    pos, vid = np.unique(verts, axis=0, return_inverse=True)  # only open meshes pay for merging
    a, b = _border_edges(vid.reshape(-1)[faces], len(pos))
    if len(a) == 0:
        return np.zeros((0, 3, 3))
    n = len(pos)
    _, loop = csgraph.connected_components(coo_matrix((np.ones(len(a)), (a, b)), shape=(n, n)), directed=False)
    used = np.unique(np.concatenate([a, b]))
    n_loop = loop.max() + 1
    centre = np.zeros((n_loop, 3))
    np.add.at(centre, loop[used], pos[used])
    centre /= np.maximum(np.bincount(loop[used], minlength=n_loop), 1)[:, None]
    return np.stack([pos[b], pos[a], centre[loop[a]]], axis=1)


def _border_edges(faces: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Start and end vertices of the directed edges of the faces that their opposites do not cancel (repeated as
    often as they are left over)."""
    e = np.stack([faces, np.roll(faces, -1, axis=1)], -1).reshape(-1, 2)
    e = e[e[:, 0] != e[:, 1]]
    lo, hi = e.min(1), e.max(1)
    key, inv = np.unique(lo * n + hi, return_inverse=True)
    net = np.bincount(inv.reshape(-1), weights=np.where(e[:, 0] < e[:, 1], 1.0, -1.0), minlength=len(key))
    net = np.rint(net).astype(np.int64)
    lo, hi, net = key[net != 0] // n, key[net != 0] % n, net[net != 0]
    a, b = np.where(net > 0, lo, hi), np.where(net > 0, hi, lo)  # the leftover edge runs a -> b
    return np.repeat(a, np.abs(net)), np.repeat(b, np.abs(net))


# --- device kernels (float32 search, structure-of-arrays: the voxels run along the vector lanes) -------------------


def _tree_min(x, axis):
    """Least value along `axis` (a power of two long) by halving: elementwise minima, which XLA's CPU backend fuses
    and vectorises where a reduction over a fused expression runs scalar."""
    while x.shape[axis] > 1:
        h = x.shape[axis] // 2
        x = jnp.minimum(lax.slice_in_dim(x, 0, h, axis=axis), lax.slice_in_dim(x, h, 2 * h, axis=axis))
    return jnp.squeeze(x, axis)


def _pair_min(tile_pts, gtab, tile, grp, shift):
    """Least squared distance from each of the 64 voxels of tile[k] to the triangles of group grp[k], and that
    triangle's index in the mesh (the chunk's groups start at group `shift`): (K, 64) each."""
    pts = tile_pts[tile]  # (K, 3, 64): gathered from a table, so the distance loop reads plain arrays
    rows = gtab[grp]  # (K, 15, G)
    d2 = dist2(pts[:, 0:1], pts[:, 1:2], pts[:, 2:3], [rows[:, i, :, None] for i in range(15)])  # (K, G, 64)
    low = _tree_min(d2, 1)
    arg = jnp.min(jnp.where(d2 <= low[:, None], jnp.arange(_GROUP, dtype=jnp.int32)[None, :, None], _GROUP), axis=1)
    return low, (grp[:, None] + shift) * _GROUP + arg


def _scan_pairs(best, tile_pts, gtab, tile, grp, count, chunk, shift):
    """Fold the pairs (tile[k], grp[k]), k < count, into the per-voxel best (squared distance, triangle), (T, 64)
    each; only the chunks holding pairs run. Ties go to the lower triangle index.

    Software-pipelined: step i merges the chunk that step i - 1 computed, so the chunk's minima reach the scatter
    as a loop-carried (stored) array; fused into the scatter, XLA's CPU backend recomputed them element by element
    (6x slower)."""

    def run(i):
        t = lax.dynamic_slice_in_dim(tile, i * chunk, chunk)
        low, arg = _pair_min(tile_pts, gtab, t, lax.dynamic_slice_in_dim(grp, i * chunk, chunk), shift)
        return t, jnp.where((i * chunk + jnp.arange(chunk) < count)[:, None], low, jnp.inf), arg

    def step(i, carry):
        best, done = carry
        return _merge(best, *done), run(i)

    n_steps = (jnp.minimum(count, len(tile)) + chunk - 1) // chunk
    none = (jnp.zeros(chunk, jnp.int32), jnp.full((chunk, 64), jnp.inf, jnp.float32), jnp.zeros((chunk, 64), jnp.int32))
    best, done = lax.fori_loop(0, n_steps, step, (best, none))
    return _merge(best, *done)


def _merge(best, tile, low, arg):
    """best with the candidates (low, arg) (K, 64) of tiles `tile` (K,): least distance, then least index."""
    d2, ids = best
    big = jnp.iinfo(jnp.int32).max
    new = d2.at[tile].min(low)
    ids = jnp.where(new < d2, big, ids).at[tile].min(jnp.where(low <= new[tile], arg, big))
    return new, ids


def _needed(ax4, gmin, gmax, bound):
    """(nt, nt, nt, NG): does some voxel v of the tile have group g's box within bound(v) (squared)?"""

    def gap2(k):  # (nt, 4, NG) squared gap along axis k between the voxel coordinates and the boxes
        x, lo, hi = ax4[:, :, None], gmin[None, None, :, k], gmax[None, None, :, k]
        g = jnp.maximum(0.0, jnp.maximum(lo - x, x - hi))
        return g * g

    gx, gy, gz = gap2(0), gap2(1), gap2(2)

    def slab(args):  # tiles with one x index: (nt, nt, 4, 4, 4, NG) squared box distances, then any over voxels
        gxi, b = args
        ex = gxi[None, None, :, None, None, :] + gy[:, None, None, :, None, :] + gz[None, :, None, None, :, :]
        ex = ex - b[..., None]
        return _tree_min(_tree_min(_tree_min(ex, 4), 3), 2) <= 0

    return lax.map(slab, (gx, bound))


def _components(dfree, voxel, res, tol, unroll):
    """Component label (the least flat index in it) of each voxel; u, v are joined when neighbours with
    dfree(u) + dfree(v) > |u - v| + tol. Min-label propagation with hooking and pointer jumping (as in
    Shiloach-Vishkin) until nothing changes; every label ever assigned is a voxel of the same component."""
    n = res**3
    step = np.array([s for s in np.ndindex(3, 3, 3) if s != (1, 1, 1)], np.int32)  # 26 neighbours, + 1
    corner, length = jnp.asarray(step), jnp.asarray(np.linalg.norm(step - 1, axis=1), dfree.dtype)

    def shifted(xp, k):  # x[u + step k] from x padded by one voxel
        return lax.dynamic_slice(xp, (corner[k, 0], corner[k, 1], corner[k, 2]), (res, res, res))

    # Loops over the 26 neighbours rather than unrolled code on CPUs: 4x quicker to compile, 2x quicker to run at
    # 128^3.
    dp = jnp.pad(dfree, 1, constant_values=-jnp.inf)
    links = lax.fori_loop(  # bit k: u is joined to its neighbour k
        0, 26, lambda k, acc: acc | (dfree + shifted(dp, k) > voxel * length[k] + tol).astype(jnp.int32) << k,
        jnp.zeros((res,) * 3, jnp.int32), unroll=unroll)

    def body(carry):
        lab, _ = carry
        lp = jnp.pad(lab, 1, constant_values=n)
        m = lax.fori_loop(0, 26, lambda k, m: jnp.minimum(m, jnp.where((links >> k) & 1 != 0, shifted(lp, k), n)), lab,
                          unroll=unroll)
        # Hook the parent of each voxel to its least neighbouring label too (whole trees merge per round: 6 rounds
        # instead of 78 at 128^3), then jump pointers, in a loop of their own: fused into the gathers, XLA's CPU
        # backend recomputed the 26-neighbour minimum at every gathered index (6x slower).
        m, f = m.reshape(-1), lab.reshape(-1)
        f = jnp.minimum(f.at[f].min(m), m)
        f = lax.fori_loop(0, 2, lambda _, f: f[f], f).reshape(res, res, res)
        return f, jnp.any(f != lab)

    lab0 = jnp.arange(n, dtype=jnp.int32).reshape(res, res, res)
    return lax.while_loop(lambda c: c[1], body, (lab0, jnp.array(True)))[0].reshape(-1)


def _winding_sum(pts, tri_cols, chunk):
    """Sum of the solid angles of all triangles (9 columns (F, 1)) at points (K, 3): (K,). With chunk > 0
    (F a multiple of it), accumulated elementwise over chunks of triangles: on CPUs a fused sum over all F ran 2x
    slower."""
    if not chunk:
        return solid_angles(pts[None, :, 0], pts[None, :, 1], pts[None, :, 2], tri_cols).sum(0)
    cols = jnp.concatenate(tri_cols, 1).reshape(-1, chunk, 9)

    def add(acc, c):
        q = pts[None, :, 0], pts[None, :, 1], pts[None, :, 2]
        return acc + solid_angles(*q, [c[:, i:i + 1] for i in range(9)]), None

    return lax.scan(add, jnp.zeros((chunk, pts.shape[0]), jnp.float32), cols)[0].sum(0)


def _cap_terms(pts, caps):
    """Distance to the caps and their raw winding number (solid angles / 4 pi) at points x, y, z (N,): (N,) each. One
    pass over the caps, 8 a step, each against all points as flat vectors: what XLA's CPU backend vectorises best
    (a loop over chunks of points, all caps at once, ran 8x slower)."""
    rows = jnp.concatenate([search_table(caps), caps.reshape(-1, 9)], 1).reshape(-1, 8, 24)

    def step(acc, r):
        d2, w = acc
        for j in range(8):
            d2 = jnp.minimum(d2, dist2(*pts, [r[j, i] for i in range(15)]))
            w = w + solid_angles(*pts, [r[j, i] for i in range(15, 24)])
        return (d2, w), None

    n = pts[0].shape[0]
    (d2, w), _ = lax.scan(step, (jnp.full(n, jnp.inf, jnp.float32), jnp.zeros(n, jnp.float32)), rows)
    return jnp.sqrt(d2), w / (4 * jnp.pi)


class _Near(NamedTuple):
    """The nearest triangle found so far per voxel: squared float32 distance and global triangle index in tile
    layout (T, 64), and that triangle's `tri_table` row per voxel in grid order (N, 12)."""

    d2: Array
    ids: Array
    row: Array


def _tile_axes(voxel, res):
    nt = -(-res // _TILE)
    return ((jnp.arange(nt * _TILE) - (res - 1) / 2.0) * voxel).astype(jnp.float32).reshape(nt, _TILE)


def _voxel_points(voxel, res, dtype):
    ijk = jnp.stack(jnp.meshgrid(*[jnp.arange(res)] * 3, indexing="ij"), -1).reshape(-1, 3)
    return ((ijk - (res - 1) / 2.0).astype(voxel.dtype) * voxel).astype(dtype)


def _tiles_to_grid(x, res):
    """(T, 64) tile layout -> (res^3,) grid order."""
    nt = -(-res // _TILE)
    x = x.reshape((nt,) * 3 + (_TILE,) * 3).transpose(0, 3, 1, 4, 2, 5)
    return x.reshape((nt * _TILE,) * 3)[:res, :res, :res].reshape(-1)


@functools.partial(jax.jit, static_argnames=("res", "dtype"))
def _start(voxel, *, res, dtype):
    nt = -(-res // _TILE)
    return _Near(jnp.full((nt**3, 64), jnp.inf, jnp.float32), jnp.zeros((nt**3, 64), jnp.int32),
                 jnp.zeros((res**3, 12), dtype))


@functools.partial(jax.jit, static_argnames=("res", "steps"))
def _near_chunk(state: _Near, tri, rows, base, voxel, *, res, steps) -> _Near:
    """Step 1 for one chunk of triangles (FACE_CHUNK, 3, 3), the first of them triangle `base` of the mesh.

    Each tile's bound is its voxels' best so far, lowered by the `_SEEDS` groups of this chunk nearest the tile; a
    (tile, group) pair of the chunk is scanned when the group's box lies within the bound of a voxel of the tile. The
    pair list has room for every pair of the chunk, so it never overflows; only its chunks holding pairs run."""
    f32 = jnp.float32
    n_grp = FACE_CHUNK // _GROUP
    nt = -(-res // _TILE)
    slack = _SLACK * voxel.astype(f32) * res
    t32 = tri.astype(f32)
    gtab = search_table(t32).reshape(n_grp, _GROUP, 15).transpose(0, 2, 1)  # (NG, 15, G)
    gv = t32.reshape(n_grp, _GROUP * 3, 3)
    gmin, gmax = gv.min(1), gv.max(1)
    ax4 = _tile_axes(voxel, res)
    grids = [ax4[:, None, None, :, None, None], ax4[None, :, None, None, :, None], ax4[None, None, :, None, None, :]]
    tile_pts = jnp.stack([jnp.broadcast_to(x, (nt,) * 3 + (_TILE,) * 3).reshape(nt**3, 64) for x in grids], 1)

    lo, hi = ax4[:, 0], ax4[:, -1]
    gap = [jnp.maximum(0.0, jnp.maximum(gmin[None, :, k] - hi[:, None], lo[:, None] - gmax[None, :, k])) ** 2
           for k in range(3)]
    box2 = gap[0][:, None, None] + gap[1][None, :, None] + gap[2][None, None, :]  # (nt, nt, nt, NG)
    seeds = lax.top_k(-box2.reshape(nt**3, n_grp), _SEEDS)[1].reshape(-1)
    seed_tile = jnp.repeat(jnp.arange(nt**3, dtype=jnp.int32), _SEEDS)
    n_seed = -(-len(seeds) // steps.pair) * steps.pair
    # local group indices shifted to the mesh's: ties between chunks then go to the lower triangle, as in one pass
    shift = base // _GROUP
    best = (state.d2, state.ids)
    best = _scan_pairs(best, tile_pts, gtab, jnp.pad(seed_tile, (0, n_seed - len(seeds))),
                       jnp.pad(seeds, (0, n_seed - len(seeds))), len(seeds), steps.pair, shift)
    bound = ((jnp.sqrt(best[0]) + slack) ** 2).reshape((nt,) * 3 + (_TILE,) * 3)
    need = _needed(ax4, gmin, gmax, bound).reshape(-1)
    cap = -(-need.shape[0] // steps.pair) * steps.pair
    pair = jnp.nonzero(need, size=cap, fill_value=0)[0].astype(jnp.int32)
    best = _scan_pairs(best, tile_pts, gtab, pair // n_grp, pair % n_grp, need.sum(dtype=jnp.int32), steps.pair,
                       shift)
    face = _tiles_to_grid(best[1], res)
    mine = (face >= base) & (face < base + FACE_CHUNK)
    row = jnp.where(mine[:, None], rows[jnp.clip(face - base, 0, FACE_CHUNK - 1)], state.row)
    return _Near(best[0], best[1], row)


@functools.partial(jax.jit, static_argnames=("res",))
def _cap_chunk(d_cap, w_caps, caps, voxel, *, res):
    """Distance to the caps so far and their winding number so far at every voxel, with one chunk of caps."""
    p32 = _voxel_points(voxel, res, jnp.float32)
    d, w = _cap_terms(list(p32.T), caps)
    return jnp.minimum(d_cap, d), w_caps + w


class _Components(NamedTuple):
    label: Array  # (N,) component of each voxel (`_components`)
    roots: Array  # (N,) the components' labels first, then N
    n_comp: Array  # () how many components
    rep: Array  # (N,) a voxel of each component (its farthest from the surface), in `roots` order
    rep_pts: Array  # (N, 3) float32, those voxels' centres
    size: Array  # (N,) voxels per component, in `roots` order
    dist: Array  # (N,) unsigned distance to the mesh


@functools.partial(jax.jit, static_argnames=("res", "steps"))
def _sign_components(state: _Near, d_cap, voxel, *, res, steps) -> _Components:
    """Step 2's components of the free space of mesh and caps, each with the voxel its winding number is read at.
    The lists have room for one component per voxel: they cannot overflow, and only the components found are
    summed (`_wind_chunk`)."""
    dtype = state.row.dtype
    n = res**3
    p = _voxel_points(voxel, res, dtype)
    off = jax.vmap(closest_offset)(p, state.row)
    dist = jnp.sqrt(jnp.sum(off * off, axis=1))
    dfree = jnp.minimum(dist, d_cap.astype(dtype))
    label = _components(dfree.reshape(res, res, res), voxel, res, _SLACK * voxel * res, steps.unroll)
    idx = jnp.arange(n, dtype=jnp.int32)
    far = jax.ops.segment_max(dfree, label, num_segments=n)
    rep = jax.ops.segment_min(jnp.where(dfree >= far[label], idx, n), label, num_segments=n)
    size = jax.ops.segment_sum(jnp.ones(n, jnp.int32), label, num_segments=n)
    is_root = label == idx
    roots = jnp.nonzero(is_root, size=n, fill_value=n)[0]
    at = jnp.minimum(roots, n - 1)
    rep = jnp.minimum(rep[at], n - 1)
    return _Components(label, roots, is_root.sum(dtype=jnp.int32), rep, p.astype(jnp.float32)[rep], size[at], dist)


@functools.partial(jax.jit, static_argnames=("steps",))
def _wind_chunk(acc, comp: _Components, tri, *, steps):
    """The solid angles of one chunk of triangles added at the components' voxels (only the `n_comp` first)."""
    tri_cols = [tri.astype(jnp.float32)[:, i // 3, i % 3][:, None] for i in range(9)]

    def wind_step(i, acc):
        q = lax.dynamic_slice_in_dim(comp.rep_pts, i * steps.rep, steps.rep)
        w = lax.dynamic_slice_in_dim(acc, i * steps.rep, steps.rep) + _winding_sum(q, tri_cols, steps.tri)
        return lax.dynamic_update_slice_in_dim(acc, w, i * steps.rep, 0)

    n_steps = (comp.n_comp + steps.rep - 1) // steps.rep
    # the accumulator is padded to whole steps so that the last slice stays in bounds
    pad = -acc.shape[0] % steps.rep
    return lax.fori_loop(0, n_steps, wind_step, jnp.pad(acc, (0, pad)))[:acc.shape[0]]


@functools.partial(jax.jit, static_argnames=("res",))
def _grid(state: _Near, comp: _Components, wind, w_caps, voxel, orient, *, res):
    """Steps 2 and 3 finished: the sign from each component's winding number, then the gradient channel."""
    f32 = jnp.float32
    dtype = state.row.dtype
    n = res**3
    # the capped mesh's winding number at each component's voxel: the mesh's solid angles and the caps' own
    total = wind / (4 * jnp.pi) + w_caps[comp.rep]
    # A component of several voxels has an integer winding number (of the capped mesh); a lone voxel keeps its own.
    total = jnp.where(comp.size > 1, jnp.round(total), total)
    w = orient.astype(f32) * (jnp.zeros(n, f32).at[comp.roots].set(total, mode="drop")[comp.label] - w_caps)
    sign = jnp.where(w > 0.5, -1.0, 1.0).astype(dtype)

    p = _voxel_points(voxel, res, dtype)
    off = jax.vmap(closest_offset)(p, state.row)
    dist = comp.dist
    r = state.row
    normal = jnp.cross(r[:, 3:6], r[:, 6:9])
    norm = jnp.sqrt(jnp.sum(normal * normal, axis=1, keepdims=True))
    normal = jnp.where(norm > 0, normal / jnp.where(norm > 0, norm, 1.0), jnp.array([[0.0, 0.0, 1.0]], dtype))
    # The host's threshold in float64; in float32, p - closest below the rounding of the coordinates has no direction.
    on_surface = dist <= jnp.maximum(_ON_SURFACE, 4 * jnp.finfo(dtype).eps * voxel * res)
    grad = jnp.where(on_surface[:, None], orient * normal,
                     -sign[:, None] * off / jnp.where(on_surface, 1.0, dist)[:, None])
    return jnp.concatenate([(sign * dist)[:, None], grad], axis=1).reshape(res, res, res, 4)
