"""The grasp energy E(q) for one wrist pose: E_g + a_c E_c + a_q E_q (+ a_pen P), eq. 5, 12, 13 of the paper."""

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from ffcgs_jax.geometry import sdf
from ffcgs_jax.hand.kinematics import Hand, forward_kinematics
from ffcgs_jax.synthesis import filters as F
from ffcgs_jax.synthesis import quality
from ffcgs_jax.synthesis.config import EnergyConfig


class Target(NamedTuple):
    """The object the hand grasps, as the optimiser sees it (a pytree).

    Attributes:
        sdf: its Gradient-SDF (object frame).
        centre: (3,) torque reference point (`geometry.sdf.object_extent`).
        radius: () characteristic length L dividing torques.
    """

    sdf: sdf.GradientSDF
    centre: Float[Array, " 3"]
    radius: Float[Array, ""]


class Terms(NamedTuple):
    """The parts of E for one grasp."""

    E: Float[Array, ""]
    E_g: Float[Array, ""]
    E_c: Float[Array, ""]
    E_q: Float[Array, ""]
    P: Float[Array, ""]
    lp_ok: Bool[Array, ""]
    contacts: Float[Array, "C 3"]
    lp_basis: Int[Array, " 7"]  # the LP's final basis ("jax" solver; -1s otherwise): the next step's warm start


def make_target(grid: sdf.GradientSDF) -> Target:
    """Target with centre and radius read off the SDF (host side), and the SDF's cell table for fast queries."""
    ext = sdf.object_extent(grid)
    dtype = grid.grid.dtype
    return Target(sdf.with_cells(grid), jnp.asarray(ext.centre, dtype), jnp.asarray(ext.radius, dtype))


def contact_energy(d: Float[Array, " C"], d0: float) -> Float[Array, ""]:
    """E_c = sqrt(mean (d_i + d0)^2), the RMS fingertip distance to the surface (eq. 12), in metres."""
    return jnp.sqrt(jnp.mean((d + d0) ** 2) + 1e-12)  # the floor keeps the gradient finite at d = -d0


def joint_energy(hand: Hand, q: Float[Array, " Q"]) -> Float[Array, ""]:
    """E_q = mean ((q - q0) / (q_max - q_min))^2 with q0 the middle of each range (eq. 13)."""
    return jnp.mean(((q - hand.q_mean) / hand.q_range) ** 2)


def energy(
    hand: Hand, target: Target, wrist_pose: Float[Array, "4 4"], q: Float[Array, " Q"], cfg: EnergyConfig,
    lp_basis: Int[Array, " 7"] | None = None,
) -> tuple[Float[Array, ""], Terms]:
    """E and its parts for one wrist pose and channel vector (differentiable in q). `lp_basis`: a warm start for
    the Q-distance LP (`Terms.lp_basis` of a nearby call)."""
    frames = forward_kinematics(hand, wrist_pose, q)  # one MJX pass (and one backward) for contacts and spheres
    c = frames.contacts
    _, n = sdf.query(target.sdf, c)
    if not cfg.normal_grad:
        n = jax.lax.stop_gradient(n)
    d = sdf.distance(target.sdf, c)  # derivative = the Gradient-SDF's gradient channel, as in eq. 12
    E_g, ok, basis = quality.q_distance_warm(c, n, target.centre, target.radius, cfg.mu, cfg.cone_edges,
                                             cfg.basis_size, cfg.lp_solver, cfg.lp_pivots, lp_basis)
    E_c = contact_energy(d, cfg.d0)
    E_q = joint_energy(hand, q)
    P = F.penetration_penalty(hand, target.sdf, wrist_pose, q, frames) if cfg.a_pen > 0 else jnp.zeros_like(E_c)
    E = E_g + cfg.a_c * E_c + cfg.a_q * E_q + cfg.a_pen * P
    return E, Terms(E, E_g, E_c, E_q, P, ok, c, basis)
