"""The grasp energy E(q) for one wrist pose: E_g + a_c E_c + a_q E_q (eq. 5, 12, 13 of the paper), + a_m E_m (the
force-closure margin, `quality.support_margin`) + a_pen P (the whole-hand penetration penalty)."""

import cachetools
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from ffcgs_jax.geometry import sdf
from ffcgs_jax.hand import kinematics as K
from ffcgs_jax.hand.kinematics import Hand, forward_kinematics
from ffcgs_jax.kernels import quality
from ffcgs_jax.runtime import compiled
from ffcgs_jax.synthesis import filters as F
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
    E_m: Float[Array, ""]
    support_min: Float[Array, ""]  # min of the wrench support over the margin's directions (>= epsilon); NaN if a_m 0
    P: Float[Array, ""]
    lp_ok: Bool[Array, ""]
    contacts: Float[Array, "C 3"]
    lp_basis: Int[Array, " 7"]  # the LP's final basis ("jax" solver; -1s otherwise): the next step's warm start
    margin_dirs: Float[Array, "M 6"]  # the margin's searched directions: the next step's start


_TARGETS_BYTES = 1 << 29
# id(grid) -> (grid, Target); each counts at least 1/8 of the bytes (so at most 8), one alone always fits
_TARGETS = cachetools.LRUCache(_TARGETS_BYTES, getsizeof=lambda v: min(max(v[1].sdf.cells.nbytes, _TARGETS_BYTES // 8),
                                                                       _TARGETS_BYTES))
compiled.register("synthesis.energy targets", _TARGETS)


def make_target(grid: sdf.GradientSDF) -> Target:
    """Target with centre and radius read off the SDF (on the device), and the SDF's cell table for fast queries.

    Targets are kept per grid object (`sdf.build_sdf` returns the cached grid itself for a mesh it has seen), so a
    repeated call on one object builds neither again: the last 8, and at most 512 MB of cell tables (262 MB each at
    128^3), least recently used dropped first."""
    hit = _TARGETS.get(id(grid))
    if hit is not None and hit[0] is grid:  # the grid is held, so its id cannot have been reused
        return hit[1]
    centre, radius = sdf.object_centre_radius(grid)
    target = Target(sdf.with_cells(grid), centre, radius)
    _TARGETS[id(grid)] = (grid, target)
    return target


def contact_energy(d: Float[Array, " C"], d0: float) -> Float[Array, ""]:
    """E_c = sqrt(mean (d_i + d0)^2), the RMS fingertip distance to the surface (eq. 12), in metres."""
    return jnp.sqrt(jnp.mean((d + d0) ** 2) + 1e-12)  # the floor keeps the gradient finite at d = -d0


def joint_energy(hand: Hand, q: Float[Array, " Q"]) -> Float[Array, ""]:
    """E_q = mean ((q - q0) / (q_max - q_min))^2 with q0 the middle of each range (eq. 13)."""
    return jnp.mean(((q - hand.q_mean) / hand.q_range) ** 2)


class Tips(NamedTuple):
    """Where the fingertips touch (`fingertip_contacts`)."""

    points: Float[Array, "C 3"]  # skin points, centre - radius x normal
    gaps: Float[Array, " C"]  # signed skin-to-surface distances (m; < 0 penetrates), derivative as `sdf.distance`
    normals: Float[Array, "C 3"]  # the SDF's outward normals at the chosen spheres' centres
    centres: Float[Array, "C 3"]  # the chosen spheres' centres
    choice: Int[Array, " C"]  # which of the fingertip's candidate spheres (`Hand.tip_pos`) was chosen


def chosen(a: Float[Array, "C T ..."], choice: Int[Array, " C"]) -> Float[Array, "C ..."]:
    """Per fingertip, the row of its candidates `a` at `choice`."""
    return jnp.take_along_axis(a, choice.reshape((-1, 1) + (1,) * (a.ndim - 2)), axis=1)[:, 0]


def fingertip_contacts(hand: Hand, grid: sdf.GradientSDF, frames) -> Tips:
    """Where each fingertip touches: among its candidate spheres (`kinematics.fingertip_spheres`: the fingertip
    link's collision spheres and the contact site), the one whose skin is nearest to the surface.

    Why not the contact site: a site is one point of the fingertip, while the fingertip link's collision geometry
    reaches past it (the SVH's distal capsules extend 8.6 mm beyond their sites, which lie 1 mm under the skin), so
    a descent that puts the site on the surface pushes the rest of the fingertip into the object: 3.4-4.2 mm deep
    on the built-in objects. The skin point is what touches in physics.

    """
    centres, radii = K.fingertip_spheres(hand, frames)
    C, T = radii.shape
    gap = sdf.distance(grid, centres.reshape(C * T, 3)).reshape(C, T) - radii
    k = jnp.argmin(gap, axis=1)
    centre, r = chosen(centres, k), chosen(radii, k)
    _, n = sdf.query(grid, centre)
    return Tips(centre - r[:, None] * n, chosen(gap, k), n, centre, k)


def energy(
    hand: Hand, target: Target, wrist_pose: Float[Array, "4 4"], q: Float[Array, " Q"], cfg: EnergyConfig,
    lp_basis: Int[Array, " 7"] | None = None, margin_dirs: Float[Array, "M 6"] | None = None,
) -> tuple[Float[Array, ""], Terms]:
    """E and its parts for one wrist pose and channel vector (differentiable in q). `lp_basis`, `margin_dirs`: warm
    starts for the Q-distance LP and the margin's direction search (`Terms.lp_basis`, `Terms.margin_dirs` of a
    nearby call)."""
    frames = forward_kinematics(hand, wrist_pose, q)  # one MJX pass (and one backward) for contacts and spheres
    c, d, n, centre, _ = fingertip_contacts(hand, target.sdf, frames)  # d's derivative: the gradient channel (eq. 12)
    if not cfg.normal_grad:  # the normals, and so the skin offsets along them, held where they are
        n = jax.lax.stop_gradient(n)
        c = centre + jax.lax.stop_gradient(c - centre)
    W = quality.primitive_wrenches(c, n, target.centre, target.radius, cfg.lp_friction, cfg.cone_edges)  # for E_g and E_m
    E_g, ok, basis = quality.q_distance_warm(c, n, target.centre, target.radius, cfg.lp_friction, cfg.cone_edges,
                                             cfg.basis_size, cfg.lp_solver, cfg.lp_pivots, lp_basis, W=W)
    E_c = contact_energy(d, cfg.d0)
    E_q = joint_energy(hand, q)
    if margin_dirs is None:
        margin_dirs = jnp.asarray(quality.margin_start(cfg.margin_dirs), c.dtype)
    if cfg.a_m > 0:
        margin_dirs = quality.refine_directions(W, margin_dirs, cfg.margin_steps)
        E_m, h_min = quality.support_margin(W, margin_dirs, cfg.closure_margin)
    else:
        E_m, h_min = jnp.zeros_like(E_c), jnp.full_like(E_c, jnp.nan)
    P = F.penetration_penalty(hand, target.sdf, wrist_pose, q, frames) if cfg.a_pen > 0 else jnp.zeros_like(E_c)
    E = E_g + cfg.a_c * E_c + cfg.a_q * E_q + cfg.a_m * E_m + cfg.a_pen * P
    return E, Terms(E, E_g, E_c, E_q, E_m, h_min, P, ok, c, basis, margin_dirs)
