"""A final projection that backs a grasp's penetrating links out of the object, moving the finger channels only.

The descent (`optimize.descend`) tolerates overlaps: its penetration penalty is free up to `filters.CONTACT_TOL`
(2 mm) for every collision sphere, and E_c pulls each fingertip's nearest skin point onto the surface while the
rest of the finger may sink into a curved or concave surface. The SDF is not what sinks them: the collision spheres
measured against the mesh itself overlap as deeply as against the 32^3 grid (bench/penetration.py). So after the
descent a few damped Gauss-Newton steps on q solve, per grasp,

    min_q  sum_s max(0, r_s - d(c_s) - allow)^2  +  w_tip^2 sum_i (g_i - max(-allow, g_i(q_start)))^2

over the collision spheres s (centre c_s, radius r_s, d the distance to the object or the table) and the
fingertips i (g_i the skin gap that E_c drives to 0, `energy.fingertip_contacts`): penetrating links come out along
the SDF's gradient, a fingertip that sank deeper than `allow` is lifted to that depth, one within it or hovering
stays where it is (a fingertip that touched keeps touching). A grasp whose spheres are all within `allow` has a zero
residual and zero step: it is not moved. The wrist stays where the descent left it: moving it would move every fingertip.

Pure JAX: `project` handles one grasp and traces inside jit; `project_batch` vmaps it.
"""

import jax
import jax.numpy as jnp

from ffcgs_jax.core.types import Array, Float
from ffcgs_jax.geometry import sdf as S
from ffcgs_jax.geometry.sdf import GradientSDF
from ffcgs_jax.hand import kinematics as K
from ffcgs_jax.hand.kinematics import Hand
from ffcgs_jax.synthesis.energy import fingertip_contacts

TIP_WEIGHT = 1.0  # a fingertip's gap counts as much as a link's overlap: both are metres of the same geometry
DAMPING = 1e-6  # m^2 per rad^2 on the normal equations' diagonal: lever arms of cm give J^T J of about 1e-3
MAX_STEP = 0.05  # rad per channel and step: the residual is piecewise (relu, argmin of the tip spheres)


def _residuals(hand: Hand, sdf: GradientSDF, wrist_pose, q, tip_target, allow):
    frames = K.forward_kinematics(hand, wrist_pose, q)
    centres, radii = K.collision_spheres(hand, wrist_pose, q, frames)
    # object or table: backing a link out of the object into the table would trade one overlap for another
    d = jnp.minimum(S.distance(sdf, centres), centres[:, 2] - sdf.table_z)
    depth = jax.nn.relu(radii - d - allow)
    gaps = fingertip_contacts(hand, sdf, frames).gaps
    return jnp.concatenate([depth, TIP_WEIGHT * (gaps - tip_target)])


def project(hand: Hand, sdf: GradientSDF, wrist_pose: Float[Array, "4 4"], q: Float[Array, " Q"], steps: int,
            allow: float | Float[Array, ""] = 0.0) -> Float[Array, " Q"]:
    """q after `steps` damped Gauss-Newton steps that back the hand's collision spheres out to at most `allow`
    metres of overlap with the object and the table, keeping the fingertips' contact (module docstring).

    Args:
        hand: from `hand.kinematics.load_hand`.
        sdf: the object grid (with its table plane).
        wrist_pose: (4, 4) world <- hand root, held fixed.
        q: (Q,) channels the descent returned.
        steps: Gauss-Newton steps (static); 0 returns q.
        allow: metres of overlap left free, >= 0 (a traced scalar too).
    Returns:
        (Q,) channels within the joint limits.
    """
    if steps == 0:
        return q
    start_gaps = fingertip_contacts(hand, sdf, K.forward_kinematics(hand, wrist_pose, q)).gaps
    tip_target = jnp.maximum(start_gaps, -allow)
    eye = jnp.eye(q.shape[0], dtype=q.dtype)

    def step(x, _):
        res = lambda y: _residuals(hand, sdf, wrist_pose, y, tip_target, allow)  # noqa: E731
        r = res(x)
        J = jax.jacfwd(res)(x)  # (R, Q): Q forward passes of a small kinematic tree
        dx = -jnp.linalg.solve(J.T @ J + DAMPING * eye, J.T @ r)
        dx = jnp.where(jnp.isfinite(dx), jnp.clip(dx, -MAX_STEP, MAX_STEP), 0.0)
        # a step that does not lower the residual is not taken: the relu's kinks can make Gauss-Newton overshoot
        x_new = jnp.clip(x + dx, hand.lower, hand.upper)
        better = jnp.sum(res(x_new) ** 2) < jnp.sum(r**2)
        return jnp.where(better, x_new, x), None

    out, _ = jax.lax.scan(step, q, None, length=steps)
    return out


def project_batch(hand: Hand, sdf: GradientSDF, wrist_poses: Float[Array, "B 4 4"], q: Float[Array, "B Q"],
                  steps: int, allow: float | Float[Array, ""] = 0.0) -> Float[Array, "B Q"]:
    """`project` over a leading B axis."""
    return jax.vmap(lambda H, x: project(hand, sdf, H, x, steps, allow))(wrist_poses, q)
