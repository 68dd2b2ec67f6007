"""The zero level of a Gradient-SDF as a triangle mesh (naive surface nets, host NumPy).

Used where a mesh is needed but only an SDF exists (an object fused from depth frames): the fallback evaluation
(closest points and normals on the SDF's own surface), pictures, and `ffcgs fuse --mesh`. Surface nets rather than
marching cubes because it needs no case table and no extra dependency: one vertex per grid cell that the surface
crosses (the mean of the zero crossings on the cell's edges, linear interpolation of the distance), one quad per
grid edge with a sign change (the four cells around it), split into two triangles. A field whose zero level stays
inside the grid gives a closed mesh.
"""

import numpy as np
import trimesh

from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.core.types import Float

# (b, c) axes with b x c = a: the quad's cells, in this order around edge axis a, wind counter-clockwise seen from +a
_PLANE = {0: (1, 2), 1: (2, 0), 2: (0, 1)}


def zero_level_mesh(values: Float[np.ndarray, "R R R"], origin: Float[np.ndarray, " 3"],
                    voxel_size: float) -> trimesh.Trimesh:
    """The triangle mesh of {values = 0}, faces wound so their normals point to positive values (outside).

    Args:
        values: (R, R, R) signed distance on the voxel centres (index [i, j, k] along x, y, z), negative inside.
        origin: (3,) centre of voxel [0, 0, 0], metres.
        voxel_size: metres.

    Returns:
        The mesh in metres.
    """
    V = np.asarray(values, np.float64)
    if V.ndim != 3 or min(V.shape) < 2 or not np.isfinite(V).all():
        raise FfcgsError(f"zero_level_mesh needs a finite (R, R, R) field with R >= 2, got shape {V.shape}"
                         + ("" if np.isfinite(V).all() else " with NaN or inf"))
    inside = V < 0
    cells = np.array(V.shape) - 1
    total = np.zeros((*cells, 3))
    count = np.zeros(tuple(cells))
    quads = []
    for a in range(3):
        lo, hi = [slice(None)] * 3, [slice(None)] * 3
        lo[a], hi[a] = slice(0, -1), slice(1, None)
        va, vb = V[tuple(lo)], V[tuple(hi)]
        cross = inside[tuple(lo)] != inside[tuple(hi)]
        ijk = np.argwhere(cross)
        t = va[cross] / (va[cross] - vb[cross])
        point = ijk.astype(np.float64)
        point[:, a] += t
        b, c = _PLANE[a]
        # the (up to) four cells around the edge: its own index minus 0 or 1 along b and c
        for db, dc in ((0, 0), (1, 0), (0, 1), (1, 1)):
            cell = ijk.copy()
            cell[:, b] -= db
            cell[:, c] -= dc
            ok = (cell >= 0).all(1) & (cell < cells).all(1)
            np.add.at(total, tuple(cell[ok].T), point[ok])
            np.add.at(count, tuple(cell[ok].T), 1.0)
        inner = (ijk[:, b] >= 1) & (ijk[:, b] < cells[b]) & (ijk[:, c] >= 1) & (ijk[:, c] < cells[c])
        e, out = ijk[inner], inside[tuple(lo)][cross][inner]  # inside at the low end: the outward normal is +a
        ring = []
        for db, dc in ((1, 1), (0, 1), (0, 0), (1, 0)):  # (-,-), (+,-), (+,+), (-,+) in (b, c)
            cell = e.copy()
            cell[:, b] -= db
            cell[:, c] -= dc
            ring.append(cell)
        ring = np.stack(ring, 1)  # (E, 4, 3)
        quads.append(np.where(out[:, None, None], ring, ring[:, ::-1]))
    quads = np.concatenate(quads)
    if not len(quads):
        raise FfcgsError("the SDF has no zero level inside its grid (no voxel inside, or every voxel inside)")
    active = count > 0
    index = np.full(tuple(cells), -1, np.int64)
    index[active] = np.arange(int(active.sum()))
    verts = np.asarray(origin, np.float64) + voxel_size * (total[active] / count[active][:, None])
    q = index[quads[..., 0], quads[..., 1], quads[..., 2]]  # (Q, 4)
    faces = np.concatenate([q[:, [0, 1, 2]], q[:, [0, 2, 3]]])
    mesh = trimesh.Trimesh(verts, faces, process=False)
    mesh.remove_unreferenced_vertices()
    return mesh
