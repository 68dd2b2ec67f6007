"""Triangle kernels shared by the SDF builders (`sdf_build`, `sdf_device`) and the device evaluation
(`evaluation.device_metrics`): closest points (Ericson's Voronoi-region test, per triangle and in
structure-of-arrays form), solid angles (Van Oosterom & Strackee), the triangle table they read, and a mesh's
orientation. One copy of each, below their users."""

import jax.numpy as jnp
import numpy as np


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


def closest_offset(p, row):
    """(closest point - p) on one triangle `row` (12,) for one point `p` (3,); Ericson's Voronoi-region test."""
    a, ab, ac = row[0:3], row[3:6], row[6:9]
    d00, d01, d11 = row[9], row[10], row[11]
    ap = p - a
    d1, d2 = ab @ ap, ac @ ap
    d3, d4, d5, d6 = d1 - d00, d2 - d01, d1 - d01, d2 - d11
    vc, vb, va = d1 * d4 - d3 * d2, d5 * d2 - d1 * d6, d3 * d6 - d5 * d4

    def div(n, d):
        ok = d != 0
        return jnp.where(ok, n / jnp.where(ok, d, 1.0), 0.0)

    e43, e56 = d4 - d3, d5 - d6
    at_a = (d1 <= 0) & (d2 <= 0)
    at_b = (d3 >= 0) & (d4 <= d3)
    on_ab = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
    at_c = (d6 >= 0) & (d5 <= d6)
    on_ac = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
    on_bc = (va <= 0) & (e43 >= 0) & (e56 >= 0)
    w_bc = div(e43, e43 + e56)
    den = va + vb + vc
    v_in, w_in = div(vb, den), div(vc, den)
    # Barycentric weights (v on ab, w on ac) of the closest point, region by region.
    v = jnp.where(on_bc, 1 - w_bc, v_in)
    v = jnp.where(at_a | at_c | on_ac, 0.0, jnp.where(at_b, 1.0, jnp.where(on_ab, div(d1, d1 - d3), v)))
    w = jnp.where(on_bc, w_bc, w_in)
    w = jnp.where(at_a | at_b | on_ab, 0.0, jnp.where(at_c, 1.0, jnp.where(on_ac, div(d2, d2 - d6), w)))
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
    d3, d4, d5, d6 = d1 - d00, d2 - d01, d1 - d01, d2 - d11
    vc, vb, va = d1 * d4 - d3 * d2, d5 * d2 - d1 * d6, d3 * d6 - d5 * d4
    e43, e56 = d4 - d3, d5 - d6
    at_a = (d1 <= 0) & (d2 <= 0)
    at_b = (d3 >= 0) & (d4 <= d3)
    on_ab = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
    at_c = (d6 >= 0) & (d5 <= d6)
    on_ac = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
    on_bc = (va <= 0) & (e43 >= 0) & (e56 >= 0)
    den = va + vb + vc
    inv_den = jnp.where(den != 0, 1.0 / jnp.where(den != 0, den, 1.0), 0.0)
    w_bc = e43 * ibc
    v = jnp.where(on_bc, 1 - w_bc, vb * inv_den)
    v = jnp.where(at_a | at_c | on_ac, 0.0, jnp.where(at_b, 1.0, jnp.where(on_ab, d1 * i00, v)))
    w = jnp.where(on_bc, w_bc, vc * inv_den)
    w = jnp.where(at_a | at_b | on_ab, 0.0, jnp.where(at_c, 1.0, jnp.where(on_ac, d2 * i11, w)))
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


