"""Host build of a Gradient-SDF grid: exact signed distances and their gradients at the voxel centres.

`sdf.build_sdf` picks the grid and wraps the result; the work here runs in three steps:
1. Exact unsigned distance to the triangles at every voxel centre, by candidate pruning on three levels
   (superblocks of 16^3 voxels against all triangles, 4^3 blocks against their superblock's candidates, voxels
   against their block's candidates; see `_exact_distance`). The search runs in float32 jitted kernels; the
   winning triangle's closest point is recomputed in float64.
2. Sign from the generalised winding number (sum of solid angles / 4 pi, inside where > 0.5), never from ray
   parity, so meshes with holes get the right sign. It is evaluated only at a few voxels of each connected region of
   free space (neighbouring voxels u, v are connected when d(u) + d(v) > |u - v|, so the surface cannot cross the
   segment between them), at voxels that no such segment connects (on the surface, inside walls thinner than a
   voxel), and at every voxel near a hole (see `_inside`).
3. Gradient channel: sign * (p - closest) / |p - closest|, or the face normal where p lies on the surface.

Host side, NumPy in and out; the jitted kernels are this module's own (fixed chunk shapes, compiled once).
"""

import jax
import jax.numpy as jnp
import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix, csgraph
from scipy.spatial import cKDTree

from ffcgs_jax.kernels.triangles import closest_offset, orientation, solid_angle_one, tri_table
from ffcgs_jax.runtime.fixed_shapes import pad_rows
from ffcgs_jax.core.types import Float, Int

_BLOCK = 4  # voxels per block edge in the candidate pruning of step 1
_TRI_CHUNK = 1024  # triangles per kernel call (padded with far-away dummies, so kernels compile once)
_PT_CHUNK = 256  # points per kernel call
_ITEM_CHUNK = 8192  # (block, triangle) pairs per kernel call
_SIGN_SAMPLES = 9  # voxels per free-space component whose winding numbers vote on its sign
_RIM_SAMPLES = 256  # extra votes next to the voxels set aside around holes (open meshes only)
_ON_SURFACE = 1e-12  # |p - closest| (m) below which the face normal replaces (p - closest) / |p - closest|


def signed_distance_grid(
    verts: Float[np.ndarray, "verts 3"],
    faces: Int[np.ndarray, "faces 3"],
    origin: Float[np.ndarray, " 3"],
    voxel: float,
    res: int,
) -> tuple[Float[np.ndarray, "R R R"], Float[np.ndarray, "R R R 3"]]:
    """Signed distance and its gradient at the voxel centres of a res^3 grid (exact; steps 1-3 above).

    Args:
        verts: (n, 3) mesh vertices in metres, finite.
        faces: (m, 3) vertex indices of the triangles, m >= 1; the mesh need not be watertight.
        origin: (3,) centre of voxel [0, 0, 0] in metres; voxel [i, j, k] is at origin + voxel * (i, j, k).
        voxel: spacing of the voxel centres in metres, > 0.
        res: voxels along each axis.

    Returns:
        distance (R, R, R) in metres, negative inside, and gradient (R, R, R, 3), outward unit vectors; float64,
        index [i, j, k] along x, y, z.
    """
    tri = verts[faces]
    points = _voxel_centres(origin, voxel, res).reshape(-1, 3)

    dist, closest, face_id = _exact_distance(tri, origin, voxel, res)
    inside = _inside(tri, faces, dist, origin, voxel, res)

    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norm = np.linalg.norm(normals, axis=1, keepdims=True)
    normals = np.where(norm > 0, normals / np.where(norm > 0, norm, 1.0), np.array([0.0, 0.0, 1.0]))
    normals *= orientation(tri)
    sign = np.where(inside, -1.0, 1.0)
    diff = points - closest
    on_surface = dist <= _ON_SURFACE
    grad = np.where(
        on_surface[:, None], normals[face_id], sign[:, None] * diff / np.where(on_surface, 1.0, dist)[:, None]
    )
    return (sign * dist).reshape(res, res, res), grad.reshape(res, res, res, 3)


def _voxel_centres(origin: np.ndarray, voxel: float, res: int) -> np.ndarray:
    axes = [origin[i] + voxel * np.arange(res) for i in range(3)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)


# --- step 1: exact unsigned distance -----------------------------------------------------------------------------


def _dist2_one(p, row):
    r = closest_offset(p, row)
    return r @ r


def _dist2_group(corner, offs, row):
    """Squared distances from the points corner + offs (V, 3) to one triangle."""
    return jax.vmap(lambda o: _dist2_one(corner + o, row))(offs)


def _group_min(corners, offs, rows, tri_id, seg):
    """Per segment of items (sorted ids `seg`), the least squared distance of each of the V points and its triangle."""
    d2 = jax.vmap(_dist2_group, (0, None, 0))(corners, offs, rows)
    n = len(seg)
    low = jax.ops.segment_min(d2, seg, num_segments=n, indices_are_sorted=True)
    arg = jnp.where(d2 <= low[seg], tri_id[:, None], jnp.iinfo(jnp.int32).max)
    return low, jax.ops.segment_min(arg, seg, num_segments=n, indices_are_sorted=True)


# Build kernels: the jit boundary of the host build. Inputs come in fixed chunk shapes, so each compiles once.
_dist2_dense = jax.jit(jax.vmap(jax.vmap(_dist2_one, (None, 0)), (0, None)))  # (P,3), (T,12) -> (P,T)
_dist2_groups = jax.jit(jax.vmap(_dist2_group, (0, None, 0)))  # (M,3), (V,3), (M,12) -> (M,V)
_group_min = jax.jit(_group_min)  # (M,3), (V,3), (M,12), (M,), (M,) -> (M,V), (M,V)
_closest_gather = jax.jit(lambda p, table, face: p + jax.vmap(closest_offset)(p, table[face]))  # float64


def _exact_distance(tri: np.ndarray, origin: np.ndarray, voxel: float, res: int):
    """Exact distance, closest point and nearest face of every voxel centre (flattened, i-major).

    Three levels: superblocks of 16^3 voxels against all triangles, their 4^3 blocks against the superblock's
    candidates, the voxels of each block against the block's candidates. At each level a triangle is kept for a
    cell of radius r (centre to farthest voxel centre) when its distance to the cell centre is at most the
    cell centre's distance + 2 r: any triangle nearest to a voxel of the cell passes.
    """
    n_sub = _BLOCK * _BLOCK  # voxels along a superblock edge
    n_sb = -(-res // n_sub)
    rp = n_sb * n_sub
    centre = origin + voxel * (rp - 1) / 2.0  # work relative to the grid centre: float32 keeps ~1e-8 m
    table = tri_table(tri - centre, multiple=_TRI_CHUNK)
    n_tri = len(tri)
    slack = 1e-6 * voxel * rp  # above float32 rounding
    cube = np.stack(np.meshgrid(*[np.arange(_BLOCK)] * 3, indexing="ij"), -1).reshape(-1, 3)  # (64, 3)

    def cells(n):
        return np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), -1).reshape(-1, 3)

    # Level 0: superblock centres against every triangle.
    sb_ijk = cells(n_sb)
    sb_centre = (origin - centre) + voxel * (n_sub * sb_ijk + (n_sub - 1) / 2.0)
    r_sb = np.sqrt(3.0) * voxel * (n_sub - 1) / 2.0
    sb_items = []
    for s in range(0, len(sb_ijk), _PT_CHUNK):
        pts = pad_rows(sb_centre[s : s + _PT_CHUNK], _PT_CHUNK).astype(np.float32)
        d2 = np.concatenate([np.asarray(_dist2_dense(pts, table[t : t + _TRI_CHUNK]))
                             for t in range(0, len(table), _TRI_CHUNK)], axis=1)
        d = np.sqrt(d2[: min(_PT_CHUNK, len(sb_ijk) - s), :n_tri])
        b, t = np.nonzero(d <= d.min(1, keepdims=True) + 2.0 * r_sb + slack)
        sb_items.append((b + s, t))
    sb_of, tri_of = (np.concatenate(x) for x in zip(*sb_items))

    # Level 1: the 64 block centres of each superblock against its candidates; level 2: voxels of each block.
    nb = n_sb * _BLOCK
    r_b = np.sqrt(3.0) * voxel * (_BLOCK - 1) / 2.0
    block_offs = (voxel * _BLOCK * cube).astype(np.float32)
    voxel_offs = (voxel * cube).astype(np.float32)
    block_corner = (origin - centre) + voxel * _BLOCK * cells(nb)  # first voxel centre of each block
    best_d2 = np.full((nb**3, _BLOCK**3), np.inf, np.float32)
    best_id = np.zeros((nb**3, _BLOCK**3), np.int64)
    sb_start = np.searchsorted(sb_of, np.arange(len(sb_ijk) + 1))
    leaf_b, leaf_t = [], []
    n_leaf = 0
    s0 = 0
    while s0 < len(sb_ijk):  # groups of whole superblocks, about 4 kernel calls each
        s1 = s0 + 1
        while s1 < len(sb_ijk) and sb_start[s1 + 1] - sb_start[s0] <= 4 * _ITEM_CHUNK:
            s1 += 1
        i0, i1 = sb_start[s0], sb_start[s1]
        first_block = np.ravel_multi_index(tuple((_BLOCK * sb_ijk[sb_of[i0:i1]]).T), (nb,) * 3)
        block_centre = block_corner[first_block] + voxel * (_BLOCK - 1) / 2.0
        d2 = _map_items(_dist2_groups, block_centre, block_offs, table[tri_of[i0:i1]])
        starts = sb_start[s0:s1] - i0
        d_min = np.sqrt(np.minimum.reduceat(d2, starts, axis=0))  # (superblocks, 64): block centre distances
        seg = np.repeat(np.arange(s1 - s0), np.diff(sb_start[s0 : s1 + 1]))
        keep = np.sqrt(d2) <= d_min[seg] + 2.0 * r_b + slack
        for k, sb in enumerate(range(s0, s1)):
            blk = _BLOCK * sb_ijk[sb] + cube  # (64, 3) block indices of this superblock
            on_grid = (blk * _BLOCK < res).all(1)  # blocks wholly in the padding are skipped
            c, m = np.nonzero(keep[starts[k] : starts[k] + sb_start[sb + 1] - sb_start[sb]].T & on_grid[:, None])
            leaf_b.append(np.ravel_multi_index(tuple(blk[c].T), (nb,) * 3))
            leaf_t.append(tri_of[i0 + starts[k] + m])
            n_leaf += len(c)
        if n_leaf >= 4 * _ITEM_CHUNK or s1 == len(sb_ijk):
            leaves = np.concatenate(leaf_b), np.concatenate(leaf_t)
            _scan_leaves(*leaves, block_corner, table, voxel_offs, best_d2, best_id)
            leaf_b, leaf_t, n_leaf = [], [], 0
        s0 = s1

    # Back to voxel order, drop the padding beyond res, then the float64 closest point of each winner.
    rb = nb * _BLOCK
    face_id = best_id.reshape(nb, nb, nb, _BLOCK, _BLOCK, _BLOCK).transpose(0, 3, 1, 4, 2, 5).reshape(rb, rb, rb)
    face_id = face_id[:res, :res, :res].reshape(-1)
    points = _voxel_centres(origin, voxel, res).reshape(-1, 3)
    closest = _closest_float64(points, tri, face_id)
    return np.linalg.norm(points - closest, axis=1), closest, face_id


def _map_items(kernel, corners, offs, rows):
    """Run `kernel` over items in _ITEM_CHUNK chunks (the last one padded) and stack the results."""
    out = []
    for s in range(0, len(corners), _ITEM_CHUNK):
        n = len(corners[s : s + _ITEM_CHUNK])
        c = pad_rows(corners[s : s + _ITEM_CHUNK], _ITEM_CHUNK).astype(np.float32)
        out.append(np.asarray(kernel(c, offs, pad_rows(rows[s : s + _ITEM_CHUNK], _ITEM_CHUNK)))[:n])
    return np.concatenate(out)


def _scan_leaves(blocks, tris, block_corner, table, offs, best_d2, best_id):
    """Distances from every voxel of block blocks[m] to triangle tris[m] (items of a block are contiguous); keep
    each voxel's least distance and its triangle in best_d2, best_id."""
    for s in range(0, len(blocks), _ITEM_CHUNK):
        b, t = blocks[s : s + _ITEM_CHUNK], tris[s : s + _ITEM_CHUNK]
        n = len(b)
        new = np.r_[True, b[1:] != b[:-1]]
        seg = np.cumsum(new) - 1
        ub = b[new]
        pad = _ITEM_CHUNK - n
        low, arg = _group_min(
            pad_rows(block_corner[b], _ITEM_CHUNK).astype(np.float32),
            offs,
            pad_rows(table[t], _ITEM_CHUNK),
            np.r_[t, np.zeros(pad, np.int64)].astype(np.int32),
            np.r_[seg, np.full(pad, seg[-1] + 1)].astype(np.int32),
        )
        low, arg = np.asarray(low)[: len(ub)], np.asarray(arg)[: len(ub)]
        better = low < best_d2[ub]
        best_d2[ub] = np.where(better, low, best_d2[ub])
        best_id[ub] = np.where(better, arg, best_id[ub])


def _closest_float64(points: np.ndarray, tri: np.ndarray, face_id: np.ndarray) -> np.ndarray:
    """Closest point on triangle face_id[p] to points[p], in float64."""
    out = np.empty_like(points)
    step = 1 << 16
    with jax.enable_x64(True):
        table = jnp.asarray(tri_table(tri, np.float64))
        for s in range(0, len(points), step):
            n = len(points[s : s + step])
            p = pad_rows(points[s : s + step], step)
            f = pad_rows(face_id[s : s + step], step)
            out[s : s + n] = np.asarray(_closest_gather(p, table, f))[:n]
    return out


# --- step 2: sign from the generalised winding number ------------------------------------------------------------


_solid_angle_sum = jax.jit(jax.vmap(lambda p, ts: jax.vmap(solid_angle_one, (None, 0))(p, ts).sum(), (0, None)))


def _winding(points: np.ndarray, tri_pad: np.ndarray, orient: float) -> np.ndarray:
    """Generalised winding number of each point (0 outside, 1 inside a closed outward mesh)."""
    out = np.zeros(len(points))
    for s in range(0, len(points), _PT_CHUNK):
        n = len(points[s : s + _PT_CHUNK])
        p = pad_rows(points[s : s + _PT_CHUNK], _PT_CHUNK).astype(np.float32)
        for t in range(0, len(tri_pad), _TRI_CHUNK):
            out[s : s + n] += np.asarray(_solid_angle_sum(p, tri_pad[t : t + _TRI_CHUNK]), np.float64)[:n]
    return orient * out / (4.0 * np.pi)


def _inside(tri, faces, dist, origin, voxel, res) -> np.ndarray:
    """Inside flag of every voxel (flattened), from winding numbers at a few voxels of each free-space component.

    Two neighbouring voxels u, v (26-neighbourhood) are joined when d(u) + d(v) > |u - v|: the balls of radius d
    around them hold no surface and cover the segment uv, so the sign cannot change along it (the winding number
    of a closed surface is constant off the surface). Each component takes the majority sign of a few of its
    voxels. An open mesh's winding number also passes 0.5 on a film spanning each hole, off the surface: voxels
    within a reach of the hole borders are set aside (each gets its own winding number) and the reach doubles, up
    to 1.25 x the border loop's radius, until every component's samples agree; components that still disagree
    are evaluated voxel by voxel.
    """
    centre = origin + voxel * (res - 1) / 2.0
    n_pad = -len(tri) % _TRI_CHUNK
    tri_pad = np.concatenate([tri - centre, np.full((n_pad, 3, 3), 1e3)]).astype(np.float32)
    orient = orientation(tri)
    points = _voxel_centres(origin, voxel, res).reshape(-1, 3) - centre
    wind = np.full(len(points), np.nan)

    def inside_at(idx):
        todo = idx[np.isnan(wind[idx])]
        wind[todo] = _winding(points[todo], tri_pad, orient)
        return wind[idx] > 0.5

    tol = 1e-6 * voxel * res  # above the float32 error of the distances
    borders = _hole_borders(tri, faces, voxel)
    reach = 2.0 * voxel
    while True:
        alone = np.zeros(len(points), bool) if borders is None else _near_borders(*borders, points + centre, reach)
        label, n_comp = _free_components(dist, alone, voxel, res, tol)
        free = np.flatnonzero(~alone)
        order = free[np.argsort(label[free], kind="stable")]
        counts = np.bincount(label[free], minlength=n_comp)
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        sample = order[np.unique((starts[:, None] + (np.arange(_SIGN_SAMPLES) * counts[:, None]) // _SIGN_SAMPLES))]
        if alone.any():  # voxels next to the set-aside ones are where a component would cross a film
            grown = ndimage.binary_dilation(alone.reshape((res,) * 3), np.ones((3, 3, 3))).ravel()
            rim = np.flatnonzero(grown & ~alone)
            sample = np.concatenate([sample, rim[:: max(1, len(rim) // _RIM_SAMPLES)]])
        votes = inside_at(sample)
        n_in = np.bincount(label[sample], weights=votes, minlength=n_comp)
        n_all = np.bincount(label[sample], minlength=n_comp)
        mixed = np.flatnonzero((n_in > 0) & (n_in < n_all))
        if len(mixed) == 0 or borders is None or reach >= borders[2].max():
            break
        reach *= 2.0
    inside = np.zeros(len(points), bool)
    inside[free] = (n_in * 2 > n_all)[label[free]]
    exact = alone.copy()
    exact[free[np.isin(label[free], mixed)]] = True
    idx = np.flatnonzero(exact)
    inside[idx] = inside_at(idx)
    return inside


def _free_components(dist, alone, voxel, res, tol) -> tuple[np.ndarray, int]:
    """Component label of every voxel not `alone` (see `_inside`); face-adjacent far voxels (d > voxel / 2) are
    joined by scipy's `label`, the few near voxels through an explicit graph."""
    far = (dist > 0.5 * voxel + tol) & ~alone
    far_label, n_far = ndimage.label(far.reshape(res, res, res))
    node = far_label.reshape(-1) - 1  # far voxels: their component; near voxels: their own node; -1: alone
    near = np.flatnonzero(~far & ~alone)
    node[near] = n_far + np.arange(len(near))
    node[alone] = -1
    ijk = np.stack(np.unravel_index(near, (res,) * 3), axis=1)
    src, dst = [], []
    for step in np.stack(np.meshgrid(*[(-1, 0, 1)] * 3, indexing="ij"), -1).reshape(-1, 3):
        if not step.any():
            continue
        nb = ijk + step
        ok = ((nb >= 0) & (nb < res)).all(1)
        u, v = near[ok], np.ravel_multi_index(tuple(nb[ok].T), (res,) * 3)
        ok = (node[v] >= 0) & (dist[u] + dist[v] > voxel * np.linalg.norm(step) + tol)
        src.append(node[u[ok]])
        dst.append(node[v[ok]])
    src, dst = np.concatenate(src), np.concatenate(dst)
    n_node = n_far + len(near)
    graph = coo_matrix((np.ones(len(src), np.int8), (src, dst)), shape=(n_node, n_node))
    n_comp, comp_of_node = csgraph.connected_components(graph, directed=False)
    return np.where(node >= 0, comp_of_node[node], -1), n_comp


def _hole_borders(tri, faces, voxel):
    """Points every half voxel along the border edges (used by one face) of an open mesh, the border loop of each
    point, and each loop's largest reach (1.25 x its radius + one voxel); None for a closed mesh."""
    edges = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    uniq, count = np.unique(edges, axis=0, return_counts=True)
    border = uniq[count == 1]
    if len(border) == 0:
        return None
    n_v = int(faces.max()) + 1
    graph = coo_matrix((np.ones(len(border)), (border[:, 0], border[:, 1])), shape=(n_v, n_v))
    n_loops, loop_of = csgraph.connected_components(graph, directed=False)
    verts = np.zeros((n_v, 3))
    verts[faces.ravel()] = tri.reshape(-1, 3)
    used = np.unique(border)
    lo = loop_of[used]
    ctr = np.zeros((n_loops, 3))
    np.add.at(ctr, lo, verts[used])
    ctr /= np.maximum(np.bincount(lo, minlength=n_loops), 1)[:, None]
    rad = np.zeros(n_loops)
    np.maximum.at(rad, lo, np.linalg.norm(verts[used] - ctr[lo], axis=1))
    p0, p1 = verts[border[:, 0]], verts[border[:, 1]]
    n_s = np.maximum(np.ceil(np.linalg.norm(p1 - p0, axis=1) / (0.5 * voxel)).astype(int), 1) + 1
    e = np.repeat(np.arange(len(border)), n_s)
    s = np.concatenate([np.linspace(0.0, 1.0, k) for k in n_s])
    return cKDTree(p0[e] + s[:, None] * (p1 - p0)[e]), loop_of[border[e, 0]], 1.25 * rad + voxel


def _near_borders(tree, loop, max_reach, points, reach) -> np.ndarray:
    """Points within min(reach, their loop's max_reach) of a hole border."""
    d, j = tree.query(points, distance_upper_bound=reach, workers=-1)
    hit = np.isfinite(d)
    hit[hit] = d[hit] <= max_reach[loop[j[hit]]]
    return hit
