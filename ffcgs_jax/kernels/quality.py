"""Grasp quality in JAX: friction cones, primitive wrenches and the Q-distance E_g (eq. 6-9 of the paper).

Which convex set E_g measures. The paper writes the grasp wrench space as C_w = {sum alpha_i w_i : alpha >= 0,
sum alpha <= 1} (eq. 8). That set always contains the origin (alpha = 0), so the distance from the origin to it
would always be 0. What the paper means, and what its derivative (eq. 10, built from differences w_is - w_i1, i.e.
affine combinations) computes, is the distance from the origin to the convex hull of the primitive wrenches:
sum alpha = 1. That distance is 0 exactly when the origin lies in the hull, which for primitive wrenches of
friction-cone edges is the force-closure condition, and it grows as the contacts bunch up on one side. So:

    E_g = min over w in conv{w_ij} of gauge_U(w),   gauge_U(w) = min {1^T rho : U rho = w, rho >= 0}

with U the K basis directions on the 6-D unit sphere (the paper's "linearised unit sphere"). See `lp_host.py`
for how it is solved and differentiated.

Wrenches: w_ij = [f_ij, (c_i - centre) x f_ij / L]: torques about the object's centre divided by a characteristic
length L (the object's radius, from `geometry.sdf.object_extent`), so E_g has no units and does not change with
object size.
Forces are unit edges of an m-sided pyramid around the inward normal -n_i with half-angle atan(mu).
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from ffcgs_jax.kernels import lp_host, lp_jax
from ffcgs_jax.kernels.directions import sphere_basis


@functools.lru_cache(maxsize=8)
def basis(K: int) -> np.ndarray:
    """(6, K) unit directions: +-e_i plus K - 12 spread ones (deterministic, shared with `evaluation.metrics`)."""
    return sphere_basis(K)


def _unit(v: Float[Array, " 3"]) -> Float[Array, " 3"]:
    # sqrt(|v|^2 + tiny) keeps the derivative finite at v = 0 (degenerate normals), where |v| has none
    return v / jnp.sqrt(jnp.sum(v**2) + 1e-24)


def tangent_frame(n: Float[Array, " 3"]) -> tuple[Float[Array, " 3"], Float[Array, " 3"]]:
    """Two unit tangents orthogonal to the unit normal n; the reference axis is the world axis least aligned with n."""
    k = jnp.argmin(jnp.abs(n))
    a = jax.nn.one_hot(k, 3, dtype=n.dtype)
    t1 = _unit(jnp.cross(n, a))
    return t1, jnp.cross(n, t1)


def cone_edges(normal: Float[Array, " 3"], mu: float, m: int) -> Float[Array, "M 3"]:
    """m unit forces on the edges of the linearised friction cone around the inward normal -normal."""
    n = _unit(normal)
    t1, t2 = tangent_frame(n)
    th = 2 * jnp.pi * jnp.arange(m) / m
    f = -n[None, :] + mu * (jnp.cos(th)[:, None] * t1[None, :] + jnp.sin(th)[:, None] * t2[None, :])
    return f / jnp.sqrt(1 + mu**2)


def primitive_wrenches(
    contacts: Float[Array, "C 3"],
    normals: Float[Array, "C 3"],
    centre: Float[Array, " 3"],
    radius: Float[Array, ""] | float,
    mu: float,
    m: int,
) -> Float[Array, "6 N"]:
    """(6, C*m) wrenches [f, (c - centre) x f / radius] of the cone edges at every contact (outward normals)."""
    f = jax.vmap(cone_edges, (0, None, None))(normals, mu, m)  # (C, m, 3)
    r = (contacts - centre[None, :]) / radius
    tau = jnp.cross(jnp.broadcast_to(r[:, None, :], f.shape), f)
    return jnp.concatenate([f, tau], -1).reshape(-1, 6).T


def q_distance(
    contacts: Float[Array, "C 3"],
    normals: Float[Array, "C 3"],
    centre: Float[Array, " 3"],
    radius: Float[Array, ""] | float,
    mu: float = 0.2,
    m: int = 8,
    K: int = 64,
    solver: str = "jax",
    pivots: int = lp_jax.MAX_ITER,
) -> tuple[Float[Array, ""], Bool[Array, ""]]:
    """E_g of one grasp (0 = force closure) and whether it is trustworthy. Differentiable in contacts and normals.

    `solver` picks the LP path ("proxsuite": host callback; "jax": in-graph simplex with `pivots` pivots at most).
    `ok` is False when the LP failed, or when a normal is (near) zero: its cone, and so its wrenches, vanish,
    which would put the origin in the hull and fake force closure.
    """
    value, ok, _ = q_distance_warm(contacts, normals, centre, radius, mu, m, K, solver, pivots)
    return value, ok


def margin_start(M: int) -> np.ndarray:
    """(M, 6) unit wrench directions the margin's search starts from: +-e_i, then spread ones (`basis`)."""
    return basis(max(M, 12))[:, :M].T


def refine_directions(W: Float[Array, "6 N"], dirs: Float[Array, "M 6"], steps: int, eta: float = 0.05,
                      tau: float = 0.002) -> Float[Array, "M 6"]:
    """`steps` projected descent steps of each unit direction u on the support h(u) = max_j u . w_j, smoothed to
    tau logsumexp(u . w / tau): each u slides on the sphere towards a direction where the wrench hull is thin (a
    local minimum of h on the sphere is the normal of a hull facet, h there the facet's distance from the origin).
    Not differentiated: the margin's gradient is that of h at fixed u (the envelope theorem)."""
    W = jax.lax.stop_gradient(W)

    def step(_, u):
        p = jax.nn.softmax((u @ W) / tau, axis=1)
        g = p @ W.T
        g = g - jnp.sum(g * u, axis=1, keepdims=True) * u
        u = u - eta * g
        return u / jnp.linalg.norm(u, axis=1, keepdims=True)

    return jax.lax.fori_loop(0, steps, step, dirs)


def support_margin(W: Float[Array, "6 N"], dirs: Float[Array, "M 6"], delta: float
                   ) -> tuple[Float[Array, ""], Float[Array, ""]]:
    """E_m = mean over the directions u_m of max(0, delta - h(u_m)), h(u) = max_j u . w_j the support function of
    the primitive wrenches (dimensionless, like E_g), and min_m h(u_m).

    Why: E_g is 0 as soon as the origin touches the wrench hull, so the descent stops on the hull's boundary: a grasp
    with zero margin, which slips under the smallest disturbance. Ferrari-Canny's epsilon (the largest ball about
    the origin inside the hull) is the minimum of h over unit directions, so epsilon >= delta gives E_m = 0, and
    min_m h(u_m) >= epsilon always. Fixed directions cannot find the thin side of a hull in 6-D (on returned grasps
    with epsilon about 0.01, h exceeded 0.1 in all of 64 spread directions), so the directions are searched
    (`refine_directions`) and carried from one descent step to the next, where the hull has moved little.
    """
    h = jnp.max(dirs @ W, axis=1)
    return jnp.mean(jnp.maximum(delta - h, 0.0)), jnp.min(h)


def q_distance_warm(contacts, normals, centre, radius, mu: float = 0.2, m: int = 8, K: int = 64,
                    solver: str = "jax", pivots: int = lp_jax.MAX_ITER, basis0: Int[Array, " 7"] | None = None,
                    W: Float[Array, "6 N"] | None = None) -> tuple[Float[Array, ""], Bool[Array, ""], Int[Array, " 7"]]:
    """`q_distance`, plus the LP's final basis, and a warm start from `basis0` (the "jax" solver uses it when it is
    a feasible basis of this LP, e.g. the previous descent step's). The "proxsuite" path returns -1s. `W`: the
    primitive wrenches of these contacts when the caller has built them already (`primitive_wrenches`)."""
    if W is None:
        W = primitive_wrenches(contacts, normals, centre, radius, mu, m)
    if solver == "jax":
        value, ok, final_basis = lp_jax.q_distance(W, basis(K), pivots, basis0)
    else:
        value, ok = lp_host.q_distance(W, basis(K))
        final_basis = jnp.full(7, -1, jnp.int32)
    return value, ok & jnp.all(jnp.sum(normals**2, axis=1) > 1e-12), final_basis
