# Copyright 2025 The ffcgs-jax Authors.
# SPDX-License-Identifier: Apache-2.0
"""Grasp evaluation in float64 NumPy/SciPy, independent of the JAX optimiser.

The optimiser scores grasps through its own SDF, contact model and LP path; this module re-scores them from the
object MESH (trimesh closest points and face normals) so the two can be compared:

- `epsilon_q1`: Ferrari–Canny ε (Q1), the radius of the largest origin-centred ball inside the convex hull of the
  primitive wrenches (Qhull). ε > 0 iff the grasp is force closure for the linearised cones.
- `q_distance_reference`: the Q-distance E_g of paper eq. (9), solved as an LP with HiGHS. It is the float64
  reference for the JAX/ProxSuite path, and `sphere_basis` is the directions u_k both paths share.
- `energies`: E_c (eq. 12), E_q (eq. 13) and E = E_g + a_c E_c + a_q E_q (eq. 5).
- `evaluate` / `summary` / `wilcoxon`: per-grasp metrics, medians over valid grasps, paired tests as in the paper.

Dims (see `types.py`): B grasps, C contacts per grasp, Q actuated channels; W = C*m primitive wrenches, K basis
directions. Units: metres, radians; torques are divided by the radius L so wrenches are unit-free.
Host only: no jax import, and nothing here is traced.
"""

import dataclasses
import math
from typing import ClassVar

import numpy as np
import scipy.optimize
import scipy.spatial
import scipy.stats
import trimesh
from jaxtyping import Float

from ffcgs_jax.core.config import keeps_old_names
from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.kernels.directions import N_FIXED, sphere_basis

EPS_TOL = 1e-12  # Qhull facet offsets carry ~1e-15 rounding: an ε at or below this counts as 0 (not force closure)
RANK_TOL = 1e-9  # relative singular value under which a wrench set is flat (rank < 6) in `epsilon_q1`
EDGE_TOL = 1e-9  # barycentric coordinate under which a closest point lies on a triangle edge or vertex
SCALARS = ("epsilon", "E_g", "E", "E_c", "E_c_cm", "E_q", "joint_limit_use", "penetration")  # (B,) keys of evaluate


@keeps_old_names
@dataclasses.dataclass(frozen=True)
class MetricsConfig:
    """Settings of the evaluation metrics. The pipeline derives them from the synthesis's settings
    (`from_energy`), which it checks before compiling anything; `check` guards a config built here by hand.

    Attributes:
        lp_friction: friction coefficient of the linearised cone (paper's mu: 0.2); >= 0. Formerly `mu`.
        cone_edges: m, edges of the polyhedral friction cone (eq. 7); >= 3.
        d0: E_c offset of eq. (12) in metres: 0 in simulation, 0.005 for the real-robot setting; >= 0 (a negative
            d0 would score fingertips hovering off the surface as in contact; `synthesis.config.D0_RANGE`).
        a_c, a_q: weights of E_c and E_q in E (eq. 5; paper: 5 and 0.5); >= 0.
        basis_size: K, directions u_k on the 6-D unit sphere for the Q-distance LP; >= 12.
        contact_tol: a fingertip counts as a contact only when its distance to the mesh is at most this (metres):
            ε, force closure and E_g use only those. 2 mm, about the SDF grid's own error at 32^3.
    """

    RENAMED: ClassVar[dict[str, str]] = {"mu": "lp_friction"}

    lp_friction: float = 0.2
    cone_edges: int = 8
    d0: float = 0.0
    a_c: float = 5.0
    a_q: float = 0.5
    basis_size: int = 64
    contact_tol: float = 0.002

    @classmethod
    def from_energy(cls, energy, contact_tol: float) -> "MetricsConfig":
        """The evaluation's settings from the synthesis's `EnergyConfig` and `GraspConfig.contact_tol`: every other
        field is the energy field of its name (friction, cone, offset, weights, basis), so an energy setting is never
        evaluated under another value, and its range is checked once, where the user sets it."""
        names = {f.name for f in dataclasses.fields(cls)} - {"contact_tol"}
        return cls(**{name: getattr(energy, name) for name in names}, contact_tol=contact_tol)

    def check(self) -> None:
        """Raise `FfcgsError` naming the first out-of-range field."""
        for name in ("lp_friction", "d0", "a_c", "a_q", "contact_tol"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise FfcgsError(f"metrics.{name} must be a finite number >= 0, got {v!r}")
        for name, lo in (("cone_edges", 3), ("basis_size", N_FIXED)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
                raise FfcgsError(f"metrics.{name} must be an integer >= {lo}, got {v!r}")


# ----------------------------------------------------------------------------------------------- input checks


def _array(x, name: str, shape: tuple) -> np.ndarray:
    """`x` as finite float64 with the given shape; None in `shape` matches any size."""
    try:
        a = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise FfcgsError(f"{name} must be a numeric array, got {type(x).__name__}: {e}") from None
    want = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ("," if len(shape) == 1 else "") + ")"
    if a.ndim != len(shape) or any(s is not None and s != n for s, n in zip(shape, a.shape)):
        raise FfcgsError(f"{name} must have shape {want}, got {a.shape}")
    if not np.isfinite(a).all():
        raise FfcgsError(f"{name} contains NaN or inf ({int((~np.isfinite(a)).sum())} entries)")
    return a


def _mesh(mesh) -> trimesh.Trimesh:
    if not isinstance(mesh, trimesh.Trimesh):
        raise FfcgsError(f"mesh must be a trimesh.Trimesh, got {type(mesh).__name__}")
    if len(mesh.faces) == 0:
        raise FfcgsError("mesh has no triangles")
    return mesh


def _limits(q_lower, q_upper, n: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    lo = _array(q_lower, "q_lower", (n,))
    hi = _array(q_upper, "q_upper", (lo.shape[0],))
    if not (hi > lo).all():
        bad = np.flatnonzero(~(hi > lo)).tolist()
        raise FfcgsError(f"q_upper must exceed q_lower on every channel; it does not on channel(s) {bad}")
    return lo, hi


# --------------------------------------------------------------------------------------- contacts and wrenches


def mesh_contacts(
    mesh: trimesh.Trimesh, points
) -> tuple[Float[np.ndarray, "B C 3"], Float[np.ndarray, "B C 3"], Float[np.ndarray, "B C"]]:
    """Closest surface points, outward normals and signed distances of fingertip points, from the mesh itself.

    The normal is the closest triangle's face normal, except where the closest point lies on a triangle edge or
    vertex (a barycentric coordinate < `EDGE_TOL`): for a point outside it is the direction p - closest (the
    exact distance gradient, which a face normal is not at convex edges); for a point on the surface (distance
    <= `EDGE_TOL` * mesh.scale) it is the normalised sum of the normals of the faces sharing that edge or vertex,
    so it does not depend on which neighbouring face trimesh returned; inside, the face normal is kept. The sign
    comes from `mesh.contains` (ray tests), as in `trimesh.proximity.signed_distance` but negated: negative
    inside. Meshes must wind outward.

    Args:
        mesh: the object, metres.
        points: (B, C, 3) fingertip contact points in the mesh frame, metres.

    Returns:
        closest (B, C, 3) metres, normals (B, C, 3) unit outward, signed_dist (B, C) metres (< 0 inside).
    """
    mesh = _mesh(mesh)
    p = _array(points, "points", (None, None, 3))
    flat = p.reshape(-1, 3)
    if len(flat) == 0:
        return p.copy(), p.copy(), np.zeros(p.shape[:2])
    closest, dist, tri = trimesh.proximity.closest_point(mesh, flat)
    closest = np.asarray(closest, np.float64)
    tri = np.asarray(tri, np.int64)
    dist = np.linalg.norm(flat - closest, axis=1)
    inside = np.zeros(len(flat), bool)
    off = dist > 0
    if off.any():
        inside[off] = mesh.contains(flat[off])
    signed = np.where(inside, -dist, dist)

    normals = np.asarray(mesh.face_normals, np.float64)[tri].copy()
    bary = trimesh.triangles.points_to_barycentric(mesh.triangles[tri], closest)
    on_edge = (bary < EDGE_TOL).any(axis=1)
    scale = max(float(mesh.scale), 1e-12)
    on_surface = dist <= EDGE_TOL * scale
    use_dir = on_edge & ~inside & ~on_surface
    normals[use_dir] = (flat[use_dir] - closest[use_dir]) / dist[use_dir, None]
    for i in np.flatnonzero(on_edge & on_surface):  # few points lie exactly on an edge or vertex
        normals[i] = _shared_normal(mesh, mesh.faces[tri[i]][bary[i] >= EDGE_TOL])
    return closest.reshape(p.shape), normals.reshape(p.shape), signed.reshape(p.shape[:2])


def sdf_contacts(grid, points) -> tuple[Float[np.ndarray, "B C 3"], Float[np.ndarray, "B C 3"], Float[np.ndarray, "B C"]]:
    """`mesh_contacts` for an object known only by its Gradient-SDF (fused from depth frames): the signed distance
    and unit gradient the planner itself reads (`sdf.query`), and the closest point p - d n to first order."""
    import jax.numpy as jnp

    from ffcgs_jax.geometry import sdf as sdf_mod

    p = _array(points, "points", (None, None, 3))
    flat = p.reshape(-1, 3)
    if len(flat) == 0:
        return p.copy(), p.copy(), np.zeros(p.shape[:2])
    d, n = sdf_mod.query(grid, jnp.asarray(flat, grid.grid.dtype))
    d, n = np.asarray(d, np.float64), np.asarray(n, np.float64)
    n = n / np.linalg.norm(n, axis=1, keepdims=True)
    return (flat - d[:, None] * n).reshape(p.shape), n.reshape(p.shape), d.reshape(p.shape[:2])


def _shared_normal(mesh: trimesh.Trimesh, verts: np.ndarray) -> np.ndarray:
    """Normalised sum of the face normals of all faces holding every vertex in `verts` (an edge or a vertex)."""
    faces = set(mesh.vertex_faces[verts[0]].tolist()) - {-1}
    for v in verts[1:]:
        faces &= set(mesh.vertex_faces[v].tolist())
    n = np.asarray(mesh.face_normals, np.float64)[sorted(faces)].sum(axis=0)
    return n / np.linalg.norm(n)


def _tangents(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit tangents (C, 3) orthogonal to unit normals n (C, 3) and to each other."""
    helper = np.eye(3)[np.argmin(np.abs(n), axis=1)]  # the axis least aligned with n
    t1 = np.cross(n, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    return t1, np.cross(n, t1)


def primitive_wrenches(contacts, normals, centre, radius: float, mu: float, m: int) -> Float[np.ndarray, "W 6"]:
    """Primitive wrenches of the linearised friction cones (eq. 6-8), contact-major.

    Edge j of contact i is the unit force f = normalize(-n_i + mu (cos th_j t1 + sin th_j t2)), th_j = 2 pi j / m,
    pushing into the object; its wrench is [f, (c_i - centre) x f / L].

    Args:
        contacts: (C, 3) contact points, metres.
        normals: (C, 3) outward surface normals (normalised here; must be non-zero).
        centre: (3,) torque origin, metres (object centre of mass).
        radius: L > 0, metres: torque scale making wrenches unit-free (max distance centre-surface).
        mu: friction coefficient >= 0.
        m: cone edges >= 3.

    Returns:
        (C*m, 6) wrenches; rows i*m .. i*m+m-1 belong to contact i.
    """
    c = _array(contacts, "contacts", (None, 3))
    n = _array(normals, "normals", (c.shape[0], 3))
    o = _array(centre, "centre", (3,))
    if not (isinstance(radius, (int, float, np.floating)) and math.isfinite(radius) and radius > 0):
        raise FfcgsError(f"radius must be a finite number > 0, got {radius!r}")
    if not (isinstance(mu, (int, float, np.floating)) and math.isfinite(mu) and mu >= 0):
        raise FfcgsError(f"mu must be a finite number >= 0, got {mu!r}")
    if isinstance(m, bool) or not isinstance(m, (int, np.integer)) or m < 3:
        raise FfcgsError(f"m (cone edges) must be an integer >= 3, got {m!r}")
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    if (norm < 1e-12).any():
        raise FfcgsError(f"normals must be non-zero; rows {np.flatnonzero(norm[:, 0] < 1e-12).tolist()} are zero")
    n = n / norm
    t1, t2 = _tangents(n)
    th = 2.0 * np.pi * np.arange(m) / m
    tangent = np.cos(th)[None, :, None] * t1[:, None, :] + np.sin(th)[None, :, None] * t2[:, None, :]  # (C, m, 3)
    f = -n[:, None, :] + mu * tangent
    f /= np.linalg.norm(f, axis=2, keepdims=True)
    tau = np.cross((c - o)[:, None, :], f) / float(radius)
    return np.concatenate([f, tau], axis=2).reshape(-1, 6)


# --------------------------------------------------------------------------------------------- quality metrics


def epsilon_q1(wrenches) -> float:
    """Ferrari–Canny ε (Q1): radius of the largest origin-centred ball inside conv{w_i}.

    Qhull returns each facet as n.x + b <= 0 with |n| = 1, so -b is the origin's distance to the facet plane;
    ε = max(0, min over facets of -b), and values <= `EPS_TOL` are returned as 0.0. Force closure iff ε > 0.
    A flat wrench set (rank < 6 after centring: coincident or collinear contacts, fewer than 7 wrenches) cannot
    hold the origin in its interior and returns 0.0 without calling Qhull. If Qhull still fails on a full-rank set
    (a precision error), it is retried once with "QJ" (joggled input, perturbations ~1e-11 relative), which
    always succeeds and changes ε by about that much.

    Args:
        wrenches: (W, 6) primitive wrenches.

    Returns:
        ε >= 0 (unit-free, like the wrenches).
    """
    w = _array(wrenches, "wrenches", (None, 6))
    if len(w) < 7:
        return 0.0
    centred = w - w.mean(axis=0)
    sv = np.linalg.svd(centred, compute_uv=False)
    if sv[0] == 0 or sv[-1] <= RANK_TOL * sv[0]:
        return 0.0
    try:
        hull = scipy.spatial.ConvexHull(w)
    except scipy.spatial.QhullError:
        try:
            hull = scipy.spatial.ConvexHull(w, qhull_options="QJ")
        except scipy.spatial.QhullError:
            return 0.0
    eps = float(np.min(-hull.equations[:, -1]))
    return eps if eps > EPS_TOL else 0.0


def q_distance_reference(wrenches, basis) -> float:
    """Q-distance E_g (eq. 9): the gauge of conv{u_k} of the point of conv{w_i} closest to the origin.

    Solves, with `scipy.optimize.linprog(method="highs")`,
        min 1^T rho  s.t.  U rho = W^T alpha,  1^T alpha = 1,  rho >= 0,  alpha >= 0,
    over rho (K,) and alpha (W,). The value is 0 iff the origin lies in conv{w_i}. When U has unit columns
    (as `sphere_basis` does) it is >= the Euclidean distance from the origin to the hull.

    Args:
        wrenches: (W, 6) primitive wrenches, W >= 1.
        basis: (6, K) directions u_k that positively span R^6.

    Returns:
        E_g >= 0.

    Raises:
        FfcgsError: bad shapes or values, or an LP that HiGHS cannot solve (a basis that does not positively span).
    """
    w = _array(wrenches, "wrenches", (None, 6))
    u = _array(basis, "basis", (6, None))
    if len(w) == 0 or u.shape[1] == 0:
        raise FfcgsError(f"q_distance_reference needs >= 1 wrench and >= 1 basis column, got {len(w)}, {u.shape[1]}")
    k, n = u.shape[1], len(w)
    cost = np.concatenate([np.ones(k), np.zeros(n)])
    a_eq = np.zeros((7, k + n))
    a_eq[:6, :k] = u
    a_eq[:6, k:] = -w.T
    a_eq[6, k:] = 1.0
    b_eq = np.zeros(7)
    b_eq[6] = 1.0
    # HiGHS's default feasibility tolerances (1e-7) are coarser than the in-graph LP it checks (`simplex.pivot_tol`,
    # 1e-9): at small wrench scales its answer was the one off (a rank-deficient set, |W| <= 0.014: 4.6e-9 away from
    # a basis certified optimal to 1e-9 in NumPy). The reference is held to 1e-10.
    res = scipy.optimize.linprog(cost, A_eq=a_eq, b_eq=b_eq, bounds=(0, None), method="highs",
                                 options={"primal_feasibility_tolerance": 1e-10, "dual_feasibility_tolerance": 1e-10})
    if res.status != 0:
        raise FfcgsError(f"Q-distance LP failed ({res.message}); does the basis positively span R^6?")
    return max(0.0, float(res.fun))


# ------------------------------------------------------------------------------------------------- energies


def energies(dist, q, q_lower, q_upper, e_g, cfg: MetricsConfig) -> dict[str, Float[np.ndarray, " B"]]:
    """The paper's energies per grasp: E_c (eq. 12), E_q (eq. 13), E = E_g + a_c E_c + a_q E_q (eq. 5).

    E_c = sqrt(mean_i (d_i + d0)^2) in metres; E_q = mean_j ((q_j - q0_j) / (qmax_j - qmin_j))^2 with
    q0 = (qmin + qmax) / 2.

    Args:
        dist: (B, C) signed fingertip distances, metres (negative inside).
        q: (B, Q) channel positions, radians.
        q_lower, q_upper: (Q,) channel limits, q_upper > q_lower.
        e_g: (B,) Q-distance per grasp.
        cfg: weights and d0.

    Returns:
        dict of (B,) arrays: E, E_g, E_c (metres), E_c_cm, E_q.
    """
    cfg.check()
    d = _array(dist, "dist", (None, None))
    qq = _array(q, "q", (d.shape[0], None))
    lo, hi = _limits(q_lower, q_upper, qq.shape[1])
    eg = _array(e_g, "e_g", (d.shape[0],))
    if d.shape[1] == 0 or qq.shape[1] == 0:
        raise FfcgsError(f"energies needs >= 1 contact and >= 1 channel, got dist {d.shape}, q {qq.shape}")
    e_c = np.sqrt(np.mean((d + cfg.d0) ** 2, axis=1))
    e_q = np.mean(((qq - 0.5 * (lo + hi)) / (hi - lo)) ** 2, axis=1)
    return {"E": eg + cfg.a_c * e_c + cfg.a_q * e_q, "E_g": eg, "E_c": e_c, "E_c_cm": 100.0 * e_c, "E_q": e_q}


def joint_limit_use(q, q_lower, q_upper) -> Float[np.ndarray, " B"]:
    """Per grasp, max over channels of |q - q0| / (range / 2): 0 at mid-range, 1 at a limit, > 1 beyond.

    Args:
        q: (B, Q) channel positions, radians.
        q_lower, q_upper: (Q,) limits, q_upper > q_lower.
    """
    qq = _array(q, "q", (None, None))
    lo, hi = _limits(q_lower, q_upper, qq.shape[1])
    if qq.shape[1] == 0:
        raise FfcgsError("joint_limit_use needs >= 1 channel")
    return np.max(np.abs(qq - 0.5 * (lo + hi)) / (0.5 * (hi - lo)), axis=1)


# ---------------------------------------------------------------------------------------------- evaluation


def default_centre_radius(mesh) -> tuple[Float[np.ndarray, " 3"], float]:
    """Torque origin and scale: centre of mass if watertight, else bounding-box centre; max vertex distance (for a
    Gradient-SDF: `sdf.object_extent`'s centre and radius)."""
    if _is_sdf(mesh):
        from ffcgs_jax.geometry import sdf as sdf_mod

        ext = sdf_mod.object_extent(mesh)
        return np.asarray(ext.centre, np.float64), float(ext.radius)
    mesh = _mesh(mesh)
    centre = np.asarray(mesh.center_mass if mesh.is_watertight else mesh.bounds.mean(axis=0), np.float64)
    radius = float(np.linalg.norm(np.asarray(mesh.vertices) - centre, axis=1).max())
    return centre, radius


def _is_sdf(obj) -> bool:
    from ffcgs_jax.geometry.sdf import GradientSDF

    return isinstance(obj, GradientSDF)


def evaluate(
    mesh,
    contacts_world,
    q,
    q_lower,
    q_upper,
    cfg: MetricsConfig = MetricsConfig(),
    centre=None,
    radius: float | None = None,
    penetration=None,
) -> dict[str, np.ndarray]:
    """Score grasps from the mesh: ε (Q1), force closure, reference Q-distance and the paper's energies.

    Wrenches are built at the mesh's closest points to the touching fingertips (|distance| <= cfg.contact_tol)
    with the mesh's outward normals, so they are independent of the SDF the optimiser used; both ε and E_g use the
    same wrenches. A fingertip farther away exerts no force: it contributes no wrench (with none touching, ε = 0
    and E_g = NaN).

    Args:
        mesh: the object in the frame of `contacts_world`, metres: a trimesh, or a `GradientSDF` for an object known
            only by its SDF (fused from depth frames; `sdf_contacts`: the SDF's own zero level).
        contacts_world: (B, C, 3) fingertip contact points, metres.
        q: (B, Q) channel positions, radians.
        q_lower, q_upper: (Q,) channel limits.
        cfg: friction, cone, basis and energy settings.
        centre: (3,) torque origin; default `default_centre_radius(mesh)[0]`.
        radius: torque scale L > 0; default max distance from the centre to a vertex.
        penetration: optional (B,) hand-object penetration depth from elsewhere, passed through.

    Returns:
        dict of (B,) arrays: epsilon, force_closure (bool), E_g, E, E_c, E_c_cm, E_q, joint_limit_use,
        penetration (NaN when not given), n_contacts (int: touching fingertips); contact_dist (B, C) signed
        distances, metres, and normals (B, C, 3), the mesh's outward normals at the closest points.
    """
    cfg.check()
    on_sdf = _is_sdf(mesh)
    mesh = mesh if on_sdf else _mesh(mesh)
    pts = _array(contacts_world, "contacts_world", (None, None, 3))
    b = pts.shape[0]
    if pts.shape[1] == 0:
        raise FfcgsError("contacts_world needs >= 1 contact per grasp")
    qq = _array(q, "q", (b, None))
    lo, hi = _limits(q_lower, q_upper, qq.shape[1])
    c0, r0 = default_centre_radius(mesh) if centre is None or radius is None else (None, None)
    o = c0 if centre is None else _array(centre, "centre", (3,))
    r = r0 if radius is None else radius
    if not (isinstance(r, (int, float, np.floating)) and math.isfinite(r) and r > 0):
        raise FfcgsError(f"radius must be a finite number > 0, got {r!r}")
    pen = np.full(b, np.nan) if penetration is None else _array(penetration, "penetration", (b,))

    closest, normals, signed = sdf_contacts(mesh, pts) if on_sdf else mesh_contacts(mesh, pts)
    basis = sphere_basis(cfg.basis_size)
    eps = np.zeros(b)
    e_g = np.zeros(b)
    touching = np.abs(signed) <= cfg.contact_tol
    for g in range(b):  # host loop over grasps: Qhull and HiGHS are not batched
        if not touching[g].any():
            eps[g], e_g[g] = 0.0, np.nan
            continue
        w = primitive_wrenches(closest[g][touching[g]], normals[g][touching[g]], o, float(r), cfg.lp_friction,
                               cfg.cone_edges)
        eps[g] = epsilon_q1(w)
        e_g[g] = q_distance_reference(w, basis)
    out = energies(signed, qq, lo, hi, np.nan_to_num(e_g), cfg)
    out["E"][np.isnan(e_g)], out["E_g"][np.isnan(e_g)] = np.nan, np.nan
    out.update(
        epsilon=eps,
        force_closure=eps > 0,
        joint_limit_use=joint_limit_use(qq, lo, hi),
        contact_dist=signed,
        normals=normals,
        penetration=pen,
        n_contacts=touching.sum(axis=1),
    )
    return out


def squeeze_direction(jac, normals, near) -> np.ndarray:
    """The channel direction that presses the `near` fingertips into the surface: sum_i J_i^T (-n_i), scaled so its
    largest channel moves by 1 (0 where no fingertip is near). The physics test closes the servos to q + squeeze x
    this direction; a grasp file carries it (`squeeze_dir`) so a robot presses the same way.

    Args:
        jac: (B, C, 3, Q) fingertip contact-point Jacobians with respect to the channels, metres per radian.
        normals: (B, C, 3) outward unit surface normals at the fingertips' closest mesh points.
        near: (B, C) bool, the fingertips that press.

    Returns:
        (B, Q) directions, max |entry| 1 or all zero.
    """
    direction = np.einsum("bkiq,bki->bq", np.asarray(jac, np.float64),
                          -np.asarray(normals, np.float64) * np.asarray(near, bool)[..., None])
    scale = np.abs(direction).max(axis=1, keepdims=True)
    return np.where(scale > 1e-12, direction / np.maximum(scale, 1e-12), 0.0)


def summary(results: dict, valid=None) -> dict[str, float | int]:
    """Medians of the (B,) metrics over valid grasps, the share with ε > 0, and counts.

    Args:
        results: output of `evaluate` (any subset of its (B,) keys, plus `epsilon`).
        valid: (B,) mask of grasps to include (e.g. collision-free); None = all.

    Returns:
        {"median_<key>": float for each (B,) key present (NaN-ignoring; NaN if no valid grasp),
         "force_closure_share": share of valid grasps with ε > 0, and int counts "n" (= B), "n_valid",
         "n_force_closure"}.
    """
    if not isinstance(results, dict) or "epsilon" not in results:
        raise FfcgsError("results must be the dict returned by evaluate (it needs an 'epsilon' entry)")
    eps = _array(results["epsilon"], "results['epsilon']", (None,))
    b = len(eps)
    if valid is None:
        mask = np.ones(b, bool)
    else:
        mask = np.asarray(valid)
        if mask.dtype != bool or mask.shape != (b,):
            raise FfcgsError(f"valid must be a boolean array of shape ({b},), got {mask.dtype} {mask.shape}")
    out: dict[str, float | int] = {}
    for key in SCALARS:
        if key not in results:
            continue
        v = np.asarray(results[key], np.float64)
        if v.shape != (b,):
            raise FfcgsError(f"results[{key!r}] must have shape ({b},), got {v.shape}")
        sel = v[mask]
        out[f"median_{key}"] = float(np.nanmedian(sel)) if np.isfinite(sel).any() else float("nan")
    n_valid = int(mask.sum())
    n_fc = int((eps[mask] > 0).sum())
    out.update(
        force_closure_share=n_fc / n_valid if n_valid else float("nan"),
        n=b,
        n_valid=n_valid,
        n_force_closure=n_fc,
    )
    return out


def wilcoxon(a, b) -> tuple[float, float]:
    """Two-sided Wilcoxon signed-rank test on paired samples (e.g. E_g of two samplers on the same objects).

    Args:
        a, b: (n,) paired samples, n >= 1.

    Returns:
        (statistic, p-value) of `scipy.stats.wilcoxon(a, b)`; (0.0, 1.0) when all differences are zero.
    """
    x = _array(a, "a", (None,))
    y = _array(b, "b", (len(x),))
    if len(x) == 0:
        raise FfcgsError("wilcoxon needs at least one pair")
    if np.all(x == y):
        return 0.0, 1.0
    res = scipy.stats.wilcoxon(x, y)
    return float(res.statistic), float(res.pvalue)
