"""Convex parts of a mesh from its own voxel grid, in time bounded by the grid (no search, no remeshing).

`voxel_hulls` (the physics test's default, `PhysicsConfig.collision`): the solid is voxelised at
`max extent / cells` (surface samples mark their voxels; the enclosed voxels are filled). Every connected piece
starts as one cluster. The cluster whose hull reaches farthest out of the solid is cut in two across its longest
side (then split into its connected pieces), until every hull stays within `tol` of the solid or there are
`max_parts` clusters. A part is the hull of the cluster's own surface samples and the corners of its interior
voxels, so its faces lie on the mesh's surface, not on voxel steps. "Reaches out" is measured on the grid: the
distance from each empty voxel inside the hull to the nearest solid voxel (one Euclidean distance transform for the
whole grid), so a hull bridging a handle's opening or a cup's mouth is cut, and a hull over a gentle curve is not.
Cost: a fixed number of grid passes and at most 2 x `max_parts` hulls, whatever the mesh's shape.

`voxel_boxes`: the solid voxels greedily merged into axis-aligned boxes (exact to the voxel, staircase surface).
`patch_hulls`: MuJoCo meshes of surface patches, each the hull of the samples in one coarse cell and the same
samples `depth` inward: a shell with no interior.
"""

import heapq
import time

import numpy as np
import trimesh
from scipy import ndimage
from scipy.spatial import ConvexHull, QhullError

from ffcgs_jax.core.errors import FfcgsError

Part = tuple[np.ndarray, np.ndarray]  # (V, 3) float64 vertices, (F, 3) int32 faces
SAMPLES_PER_VOXEL_FACE = 6  # surface samples per voxel-face area, so every voxel the surface crosses gets one
_CHUNK = 4096  # voxels tested against a hull at once
_CORNERS = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], np.float64)


class Grid:
    """The voxelised solid: `solid` (X, Y, Z) bool, voxel [i, j, k] spans origin + pitch [i, i+1] x ...;
    `surface` marks voxels holding surface samples `points` (P, 3) whose voxels are `point_voxel` (P,) flat ids;
    `reach` (X, Y, Z): metres from each voxel centre to the nearest solid voxel's centre (0 inside)."""

    def __init__(self, mesh: trimesh.Trimesh, cells: int):
        lo, hi = np.asarray(mesh.bounds, np.float64)
        self.pitch = float(np.max(hi - lo)) / cells
        self.origin = lo - self.pitch  # one empty layer around, so the fill sees the outside everywhere
        self.shape = tuple(int(n) for n in np.ceil((hi - lo) / self.pitch).astype(int) + 3)
        n = int(np.clip(SAMPLES_PER_VOXEL_FACE * mesh.area / self.pitch ** 2, 20_000, 400_000))
        samples, _ = trimesh.sample.sample_surface(mesh, n, seed=0)
        self.points = np.concatenate([np.asarray(mesh.vertices, np.float64), samples])
        ijk = np.clip(((self.points - self.origin) / self.pitch).astype(np.int64), 0, np.array(self.shape) - 1)
        self.point_voxel = np.ravel_multi_index(ijk.T, self.shape)
        self.surface = np.zeros(self.shape, bool)
        self.surface.flat[self.point_voxel] = True
        # random samples can miss a voxel the surface only clips, and one such pinhole lets the fill leak into the
        # whole interior: close pinholes by filling the shell thickened by a voxel, then peel that voxel off again
        six = ndimage.generate_binary_structure(3, 1)
        thick = ndimage.binary_fill_holes(ndimage.binary_dilation(self.surface, six))
        self.solid = ndimage.binary_erosion(thick, six) | self.surface
        self.reach = ndimage.distance_transform_edt(~self.solid) * self.pitch

    def corners(self, voxels: np.ndarray) -> np.ndarray:
        """(8 n, 3) corners of voxels (n, 3) ijk."""
        return (self.origin + self.pitch * (voxels[:, None, :] + _CORNERS)).reshape(-1, 3)

    def centres(self, voxels: np.ndarray) -> np.ndarray:
        return self.origin + self.pitch * (voxels + 0.5)


def simplified_hull(points: np.ndarray, k: int) -> Part | None:
    """The hull of at most k of the points' hull vertices, chosen by farthest-point sampling (keeps the extremes,
    and stays inside the full hull); None when the points span no volume."""
    try:
        hull = ConvexHull(points)
    except (QhullError, ValueError):
        return None
    v = points[hull.vertices]
    if len(v) > k:
        chosen = [int(np.argmax(np.linalg.norm(v - v.mean(0), axis=1)))]
        d = np.linalg.norm(v - v[chosen[0]], axis=1)
        while len(chosen) < k:
            i = int(np.argmax(d))
            chosen.append(i)
            d = np.minimum(d, np.linalg.norm(v - v[i], axis=1))
        v = v[chosen]
    try:
        mesh = trimesh.convex.convex_hull(v)  # wound outward, unlike qhull's raw simplices
    except (QhullError, ValueError):
        return None
    if len(mesh.faces) < 4:
        return None
    return np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int32)


def planes(part: Part) -> np.ndarray:
    """(K, 4) outward unit normals and offsets (n . x + d <= 0 inside) of the part's faces, coplanar ones merged."""
    v, f = part
    tri = v[f]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True) + 1e-300
    planes = np.concatenate([normal, -np.einsum("fi,fi->f", normal, tri[:, 0])[:, None]], axis=1)
    return np.unique(np.round(planes, 9), axis=0)


def inside(part: Part, points: np.ndarray, margin: float = 0.0) -> np.ndarray:
    """Which points lie inside the convex part (or within `margin` metres outside its faces)."""
    pl = planes(part)
    return (points @ pl[:, :3].T + pl[:, 3] <= margin).all(axis=1)


class _Clusters:
    """Clusters of solid voxels with their hulls and how far each hull reaches out of the solid."""

    def __init__(self, grid: Grid, max_vertices: int):
        self.grid, self.k = grid, max_vertices
        self.owner = np.full(grid.shape, -1, np.int64)
        self.voxels: list[np.ndarray] = []
        self.parts: list[Part | None] = []

    def add(self, voxels: np.ndarray) -> tuple[float, int]:
        """Register a cluster (n, 3) ijk; returns (reach of its hull in metres, its id)."""
        cid = len(self.voxels)
        self.owner[tuple(voxels.T)] = cid
        self.voxels.append(voxels)
        part = self._hull(cid)
        self.parts.append(part)
        return self._reach(voxels, part), cid

    def _hull(self, cid: int) -> Part | None:
        g, vox = self.grid, self.voxels[cid]
        own = self.owner.flat[g.point_voxel] == cid
        inner = vox[~g.surface[tuple(vox.T)]]
        points = np.concatenate([g.points[own], g.corners(inner)])
        part = simplified_hull(points, self.k) if len(points) >= 4 else None
        return part if part is not None else simplified_hull(g.corners(vox), self.k)  # flat: its voxels' box

    def _reach(self, voxels: np.ndarray, part: Part | None) -> float:
        g = self.grid
        if part is None or len(voxels) < 2:
            return 0.0
        lo = np.maximum(np.floor((part[0].min(0) - g.origin) / g.pitch).astype(int), 0)
        hi = np.minimum(np.ceil((part[0].max(0) - g.origin) / g.pitch).astype(int) + 1, g.shape)
        box = np.stack(np.meshgrid(*[np.arange(a, b) for a, b in zip(lo, hi)], indexing="ij"), -1).reshape(-1, 3)
        reach = g.reach[tuple(box.T)]
        far = np.flatnonzero(reach > g.pitch * 1.01)  # the first empty layer is within any tolerance
        far = far[np.argsort(-reach[far], kind="stable")]
        pl = planes(part)
        for start in range(0, len(far), _CHUNK):  # deepest first: the first voxel found inside is the answer
            rows = far[start:start + _CHUNK]
            inside = (g.centres(box[rows]) @ pl[:, :3].T + pl[:, 3] <= 0).all(axis=1)
            if inside.any():
                return float(reach[rows][np.argmax(inside)])
        return 0.0

    def split(self, cid: int) -> list[np.ndarray]:
        """The cluster's voxels cut across the middle of its longest side, as connected pieces."""
        vox = self.voxels[cid]
        lo = vox.min(0)
        span = vox.max(0) - lo + 1
        axis = int(np.argmax(span))
        if span[axis] < 2:
            return [vox]
        local = np.zeros(tuple(span), np.int8)
        local[tuple((vox - lo).T)] = 1
        cut = span[axis] // 2
        pieces = []
        for half in (slice(0, cut), slice(cut, None)):
            sub = [slice(None)] * 3
            sub[axis] = half
            labels, n = ndimage.label(local[tuple(sub)], structure=np.ones((3, 3, 3)))
            shift = lo.copy()
            shift[axis] += 0 if half.start == 0 else cut
            for i in range(1, n + 1):
                pieces.append(np.argwhere(labels == i) + shift)
        return pieces


def voxel_hulls(mesh: trimesh.Trimesh, cells: int = 64, tol: float = 0.002, max_parts: int = 32,
                max_vertices: int = 64, deadline: float | None = None) -> tuple[list[Part], bool]:
    """Convex parts of the mesh's solid (module docstring) and whether they are complete: False when `deadline`
    (a `time.monotonic()` value) passed first, leaving the coarser parts of the clusters so far (still covering the
    solid). `tol`: metres a hull may reach out of the solid (beyond the voxel layer next to it)."""
    grid = Grid(mesh, cells)
    clusters = _Clusters(grid, max_vertices)
    labels, n = ndimage.label(grid.solid, structure=np.ones((3, 3, 3)))
    heap = []
    for i in range(1, n + 1):
        reach, cid = clusters.add(np.argwhere(labels == i))
        heapq.heappush(heap, (-reach, cid))
    live = set(range(n))
    complete = True
    while heap and -heap[0][0] > tol + grid.pitch:
        if deadline is not None and time.monotonic() > deadline:
            complete = False
            break
        _, cid = heapq.heappop(heap)
        pieces = clusters.split(cid)
        if len(pieces) == 1 or len(live) - 1 + len(pieces) > max_parts:
            continue  # cannot be cut finer (or not within the part budget): keep it as it is
        live.discard(cid)
        for piece in pieces:
            reach, new = clusters.add(piece)
            live.add(new)
            heapq.heappush(heap, (-reach, new))
    return [clusters.parts[c] for c in sorted(live) if clusters.parts[c] is not None], complete


def voxel_boxes(mesh: trimesh.Trimesh, cells: int = 32) -> list[Part]:
    """The solid voxels merged greedily into boxes: grow along x, then y, then z while every voxel is solid."""
    grid = Grid(mesh, cells)
    free = grid.solid.copy()
    parts = []
    for i, j, k in np.argwhere(grid.solid):
        if not free[i, j, k]:
            continue
        a = i + 1
        while a < free.shape[0] and free[a, j, k]:
            a += 1
        b = j + 1
        while b < free.shape[1] and free[i:a, b, k].all():
            b += 1
        c = k + 1
        while c < free.shape[2] and free[i:a, j:b, c].all():
            c += 1
        free[i:a, j:b, k:c] = False
        lo, hi = grid.origin + grid.pitch * np.array([i, j, k]), grid.origin + grid.pitch * np.array([a, b, c])
        box = trimesh.creation.box(bounds=[lo, hi])
        parts.append((np.asarray(box.vertices, np.float64), np.asarray(box.faces, np.int32)))
    return parts


def patch_hulls(mesh: trimesh.Trimesh, cells: int = 10, depth: float = 0.004, max_vertices: int = 64
                ) -> list[Part]:
    """Hulls of the surface samples in each cell of a coarse grid together with the same samples `depth` metres
    inward along the face normals (the `MuJoCo meshes of surface patches` option)."""
    pitch = float(np.max(mesh.extents)) / cells
    n = int(np.clip(SAMPLES_PER_VOXEL_FACE * mesh.area / (pitch / 8) ** 2, 20_000, 200_000))
    points, face = trimesh.sample.sample_surface(mesh, n, seed=0)
    inward = points - depth * np.asarray(mesh.face_normals)[face]
    key = np.floor((points - mesh.bounds[0]) / pitch).astype(np.int64)
    _, group = np.unique(key, axis=0, return_inverse=True)
    parts = []
    for g in range(int(group.max()) + 1):
        sel = group.ravel() == g
        part = simplified_hull(np.concatenate([points[sel], inward[sel]]), max_vertices)
        if part is not None:
            parts.append(part)
    if not parts:
        raise FfcgsError("the mesh's surface patches span no volume (is the mesh degenerate?)")
    return parts
