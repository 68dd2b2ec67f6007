"""Grasp filters of Algorithm 1 (section IV.B) and the whole-hand collision check, as pure JAX masks and depths.

The paper filters twice: before optimising, a wrist pose is dropped when a corner of the hand's collision boxes
(all channels at 0) lies inside the object or the table, or when the palm points upwards (unreachable for the
robot arm); after optimising, a grasp is dropped when a fingertip went below the table on its way from the open hand (q = 0 clamped into the limits) to
the final q (the cached fingertip path approximates the real closing motion). Its penetration term covers the
fingertips only, so palms can end up inside the object (its Fig. 7 b-c); `hand_penetration` measures that with the
hand's collision spheres and `penetration_penalty` is a smooth version to add to the energy.

Every function here handles one pose (or one path) and returns a boolean or a depth, never raising, so it can be
traced inside jit; the `*_batch` versions vmap over a leading B axis. Extra dim letter: T, steps of a cached
optimisation path.
"""


import jax
import jax.numpy as jnp

from ffcgs_jax.geometry import sdf as S
from ffcgs_jax.geometry.sdf import GradientSDF
from ffcgs_jax.hand import kinematics as K
from ffcgs_jax.hand.kinematics import Hand
from ffcgs_jax.synthesis.config import FilterConfig
from ffcgs_jax.core.types import Array, Bool, Float

# ----------------------------------------------------------------------------------------------------------------
# Pose filters (before optimisation)
# ----------------------------------------------------------------------------------------------------------------


def pose_clearance(hand: Hand, sdf: GradientSDF, wrist_pose: Float[Array, "4 4"]) -> Float[Array, ""]:
    """Smallest signed distance (metres) from a box corner of the open hand (q = 0 clamped into the limits) to the object or the table.

    Negative means a corner is inside; the geometric sampler ranks poses that fail the filter by it.
    """
    d, _ = S.query_scene(sdf, K.box_vertices(hand, wrist_pose))
    return jnp.min(d)


def pose_collides(
    hand: Hand, sdf: GradientSDF, wrist_pose: Float[Array, "4 4"], cfg: FilterConfig = FilterConfig()
) -> Bool[Array, ""]:
    """True when a corner of the hand's collision boxes of the open hand is closer than cfg.clearance to object or table.

    The paper's pose filter: corners rather than the whole boxes, so a thin object edge can slip between two
    corners; the whole-hand check at the final grasp (`hand_penetration`) catches what this misses.

    Args:
        hand: from `hand.kinematics.load_hand`.
        sdf: the object grid; its table_z is the table plane.
        wrist_pose: (4, 4) world <- hand root.
        cfg: cfg.clearance in metres.
    Returns:
        () bool.
    """
    return pose_clearance(hand, sdf, wrist_pose) < cfg.clearance


def palm_up(hand: Hand, wrist_pose: Float[Array, "4 4"], cfg: FilterConfig = FilterConfig()) -> Bool[Array, ""]:
    """True when the palm normal's world z component exceeds cfg.palm_up_max (the palm points upwards).

    Args:
        hand: gives the palm normal in the root frame.
        wrist_pose: (4, 4) world <- hand root; z is up.
        cfg: cfg.palm_up_max, in [-1, 1].
    Returns:
        () bool.
    """
    n = wrist_pose[:3, :3] @ hand.palm_normal
    return n[2] > cfg.palm_up_max


def tips_below_table(sdf: GradientSDF, cached_tips: Float[Array, "T C 3"], margin: float = 0.0) -> Bool[Array, ""]:
    """True when any cached fingertip position along the optimisation path lies below table_z + margin.

    The path from the open hand to the final q stands in for the real closing motion (section IV.B), so a tip that dips
    below the table on the way would hit it on the robot even if the final grasp is above it.

    Args:
        sdf: gives table_z.
        cached_tips: (T, C, 3) fingertip positions at each of T optimisation steps, metres.
        margin: metres above the table the tips must stay.
    Returns:
        () bool.
    """
    return jnp.any(cached_tips[..., 2] < sdf.table_z + margin)


# ----------------------------------------------------------------------------------------------------------------
# Whole-hand collision at the final grasp
# ----------------------------------------------------------------------------------------------------------------


def hand_penetration(
    hand: Hand, sdf: GradientSDF, wrist_pose: Float[Array, "4 4"], q: Float[Array, " Q"],
    frames: K.HandFrames | None = None,
) -> tuple[Float[Array, ""], Float[Array, " S"]]:
    """How deep the hand's collision spheres reach into the object (the table is left to `hand_table_penetration`).

    A sphere of radius r centred at c penetrates by max(0, r - d(c)), d the object's signed distance; with spheres
    covering every collision geom this catches the palm inside the object (the paper's Fig. 7 b-c), which the
    fingertip-only energy does not see. Accurate to the grid's interpolation error (a fraction of a voxel) and
    the spheres' cover of the geoms (capsules to 3 % of their radius).

    Args:
        hand: from `hand.kinematics.load_hand`.
        sdf: the object grid.
        wrist_pose: (4, 4) world <- hand root.
        q: (Q,) channels.
        frames: `hand.kinematics.forward_kinematics(hand, wrist_pose, q)`, if the caller has it.
    Returns:
        (largest depth (), depth of each sphere (S,)), metres, >= 0.
    """
    centres, radii = K.collision_spheres(hand, wrist_pose, q, frames)
    d, _ = S.query(sdf, centres)
    depth = jnp.maximum(radii - d, 0.0)
    return jnp.max(depth), depth


def hand_table_penetration(
    hand: Hand, sdf: GradientSDF, wrist_pose: Float[Array, "4 4"], q: Float[Array, " Q"],
    frames: K.HandFrames | None = None,
) -> tuple[Float[Array, ""], Float[Array, " S"]]:
    """As `hand_penetration`, against the table half-space z <= table_z: depth max(0, r - (z_c - table_z))."""
    centres, radii = K.collision_spheres(hand, wrist_pose, q, frames)
    depth = jnp.maximum(radii - (centres[:, 2] - sdf.table_z), 0.0)
    return jnp.max(depth), depth


CONTACT_TOL = 0.002  # m of sphere overlap the penetration penalty tolerates (soft contact at the fingertips)


def _scene_distance(sdf: GradientSDF, points: Float[Array, "P 3"]) -> Float[Array, " P"]:
    """Distance to object union table with Gradient-SDF derivatives (`geometry.sdf.distance` for the object, z for
    the table)."""
    return jnp.minimum(S.distance(sdf, points), points[:, 2] - sdf.table_z)


def penetration_penalty(
    hand: Hand, sdf: GradientSDF, wrist_pose: Float[Array, "4 4"], q: Float[Array, " Q"],
    frames: K.HandFrames | None = None,
) -> Float[Array, ""]:
    """Whole-hand collision penalty (metres^2): sum over collision spheres of max(0, r - d(c) - CONTACT_TOL)^2
    against object and table at q, plus sum over the open hand's box corners of max(0, -d(v))^2 at the same wrist pose.

    The first term keeps the closed hand out of the object and the table (the paper's Fig. 7 failure mode); the
    second is what the approach filter (`pose_collides`) checks, and only matters when the wrist moves. A sum, not
    a mean, so one deep link weighs as much as it does in the filter. Squared, so the derivative is continuous
    where contact starts; the distance is `geometry.sdf.distance`, whose derivative is the Gradient-SDF's gradient
    channel, so descent pushes penetrating links out along the surface normal.

    Args:
        hand, sdf, wrist_pose, q: as in `hand_penetration`.
        frames: `hand.kinematics.forward_kinematics(hand, wrist_pose, q)`, if the caller has it (`collision_spheres`).
    Returns:
        () penalty, differentiable wrt q and the wrist pose.
    """
    centres, radii = K.collision_spheres(hand, wrist_pose, q, frames)
    # Overlaps up to CONTACT_TOL are free: fingertip pads are meant to touch, and their contact points lie just
    # inside their capsules, so a penalty from zero depth would hold every fingertip off the surface E_c pulls it to.
    depth = jax.nn.relu(radii - _scene_distance(sdf, centres) - CONTACT_TOL)
    corners = jax.nn.relu(-_scene_distance(sdf, K.box_vertices(hand, wrist_pose)))
    return jnp.sum(depth**2) + jnp.sum(corners**2)


# ----------------------------------------------------------------------------------------------------------------
# Batches (vmap over a leading B axis; the config stays a Python constant, so it is static under jit)
# ----------------------------------------------------------------------------------------------------------------


def pose_collides_batch(
    hand: Hand, sdf: GradientSDF, wrist_poses: Float[Array, "B 4 4"], cfg: FilterConfig = FilterConfig()
) -> Bool[Array, " B"]:
    return jax.vmap(lambda T: pose_collides(hand, sdf, T, cfg))(wrist_poses)


def pose_clearance_batch(hand: Hand, sdf: GradientSDF, wrist_poses: Float[Array, "B 4 4"]) -> Float[Array, " B"]:
    return jax.vmap(pose_clearance, (None, None, 0))(hand, sdf, wrist_poses)


def palm_up_batch(
    hand: Hand, wrist_poses: Float[Array, "B 4 4"], cfg: FilterConfig = FilterConfig()
) -> Bool[Array, " B"]:
    return jax.vmap(lambda T: palm_up(hand, T, cfg))(wrist_poses)


def tips_below_table_batch(
    sdf: GradientSDF, cached_tips: Float[Array, "B T C 3"], margin: float = 0.0
) -> Bool[Array, " B"]:
    return jax.vmap(lambda t: tips_below_table(sdf, t, margin))(cached_tips)


def hand_penetration_batch(
    hand: Hand, sdf: GradientSDF, wrist_poses: Float[Array, "B 4 4"], q: Float[Array, "B Q"]
) -> tuple[Float[Array, " B"], Float[Array, "B S"]]:
    return jax.vmap(hand_penetration, (None, None, 0, 0))(hand, sdf, wrist_poses, q)


def hand_table_penetration_batch(
    hand: Hand, sdf: GradientSDF, wrist_poses: Float[Array, "B 4 4"], q: Float[Array, "B Q"]
) -> tuple[Float[Array, " B"], Float[Array, "B S"]]:
    return jax.vmap(hand_table_penetration, (None, None, 0, 0))(hand, sdf, wrist_poses, q)


def penetration_penalty_batch(
    hand: Hand, sdf: GradientSDF, wrist_poses: Float[Array, "B 4 4"], q: Float[Array, "B Q"]
) -> Float[Array, " B"]:
    return jax.vmap(penetration_penalty, (None, None, 0, 0))(hand, sdf, wrist_poses, q)
