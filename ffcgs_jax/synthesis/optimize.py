"""Algorithm 1 of the paper over a whole batch of wrist poses: one jit-compiled descent on q (and the wrist).

Every pose starts from q = 0 clamped into the joint limits (the SVH's open hand) and takes T steps: the paper's
q <- clip(q - beta_t dE/dq) (`method="gd"`, beta_t decaying linearly from `step` to `step_end`) or the same with
Adam's per-channel scaling (`method="adam"`, `lr` to `lr_end`). With `wrist=True` a 6-D twist of the wrist pose
descends with q (`twist_pose`). A pose stops early (masked, the batch keeps its shape) once E_g < eps_g with the
fingertips on the surface (E_c < eps_c). A pose whose LP failed
at an iteration is not moved at that iteration. Fingertip positions are recorded at every iteration: they are the
path the fingers sweep while closing, which the table filter checks.
The weight of E_c grows over the descent (`optim.contact_ramp`): E_c enters E in metres, so with the paper's
constant a_c = 5 a fingertip 5 mm short costs 0.025 while E_g reaches 0 early, and nothing pushes the last
millimetres.
With `optim.project_steps` > 0 a final projection (`synthesis.project`) then backs penetrating links out of the
object by moving q; the final terms are those of the projected grasp.
"""

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from ffcgs_jax.hand.kinematics import Hand
from ffcgs_jax.kernels.quality import margin_start
from ffcgs_jax.synthesis.config import EnergyConfig, OptimConfig
from ffcgs_jax.synthesis.energy import Target, Terms, energy
from ffcgs_jax.synthesis.project import project_batch
from ffcgs_jax.kernels.adam import adam_init, adam_update


class Trace(NamedTuple):
    """Per-iteration history, index 0 = the start, index T = the result."""

    E: Float[Array, "T B"]
    E_g: Float[Array, "T B"]
    E_c: Float[Array, "T B"]
    tips: Float[Array, "T B C 3"]


class OptResult(NamedTuple):
    q: Float[Array, "B Q"]
    wrist_pose: Float[Array, "B 4 4"]  # the input poses, or the refined ones with optim.wrist
    final: Terms  # each field with a leading B
    iters: Int[Array, " B"]  # descent steps taken before the early stop
    converged: Bool[Array, " B"]  # stopped early (E_g < eps_g and E_c < eps_c)
    lp_ok: Bool[Array, " B"]  # every LP of this pose solved
    trace: Trace


def twist_pose(H: Float[Array, "4 4"], xi: Float[Array, " 6"]) -> Float[Array, "4 4"]:
    """H @ [R(xi[:3]) | xi[3:]]: a rotation vector and a translation applied in the hand's root frame."""
    w = xi[:3]
    th2 = jnp.sum(w**2)
    th = jnp.sqrt(th2 + 1e-30)
    K = jnp.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]], dtype=xi.dtype)
    small = th2 < 1e-12  # Taylor terms near 0 keep the derivative exact there
    a = jnp.where(small, 1.0 - th2 / 6, jnp.sin(th) / th)
    b = jnp.where(small, 0.5 - th2 / 24, (1 - jnp.cos(th)) / jnp.where(small, 1.0, th2))
    R = jnp.eye(3, dtype=xi.dtype) + a * K + b * (K @ K)
    D = jnp.eye(4, dtype=xi.dtype).at[:3, :3].set(R).at[:3, 3].set(xi[3:])
    return H @ D


def descend(hand: Hand, target: Target, poses, energy_cfg: EnergyConfig, optim_cfg: OptimConfig,
              q_start=None) -> OptResult:
    """`optimize` unjitted, for callers that trace it inside their own compiled function (`synthesis.grasp`)."""
    B = poses.shape[0]
    T = optim_cfg.iters
    wrist = optim_cfg.wrist

    def total(H, x, lp_basis, dirs, ramp):
        q, xi = x
        E, terms = energy(hand, target, twist_pose(H, xi) if wrist else H, q, energy_cfg, lp_basis, dirs)
        # the contact term's weight grows from a_c to contact_ramp x a_c over the descent: early on the hand shapes
        # the grasp (E_g), late the fingertips must end on the surface with it
        return E + (ramp - 1.0) * energy_cfg.a_c * terms.E_c, terms

    value_and_grad = jax.vmap(jax.value_and_grad(total, argnums=1, has_aux=True), in_axes=(0, 0, 0, 0, None))
    q0 = jnp.zeros_like(hand.lower) if q_start is None else jnp.asarray(q_start, hand.lower.dtype)
    q0 = jnp.clip(jnp.broadcast_to(q0, (B, hand.n_channels)), hand.lower[None], hand.upper[None])
    xi0 = jnp.zeros((B, 6), poses.dtype)
    # per-variable scale of the step: channels in rad, wrist rotation in rad, wrist translation in metres
    scale = (jnp.ones_like(hand.lower),
             jnp.concatenate([jnp.full(3, optim_cfg.wrist_rot_scale), jnp.full(3, optim_cfg.wrist_shift_scale)])
             .astype(poses.dtype))

    adam = optim_cfg.method == "adam"
    first, last = (optim_cfg.lr, optim_cfg.lr_end) if adam else (optim_cfg.step, optim_cfg.step_end)

    def step(carry, t):
        x, active, iters, lp_ok, state, lp_basis, dirs = carry
        ramp = 1.0 + (optim_cfg.contact_ramp - 1.0) * t / max(T - 1, 1)
        (_, terms), g = value_and_grad(poses, x, lp_basis, dirs, ramp)
        done = (terms.E_g + terms.E_m < optim_cfg.eps_g) & (terms.E_c < optim_cfg.eps_c)
        active = active & ~done
        beta = first + (last - first) * t / max(T - 1, 1)
        move = active & terms.lp_ok
        g = jax.tree.map(lambda a: jnp.where(jnp.isfinite(a), a, 0.0), g)
        if adam:
            delta, state = adam_update(g, state, beta)
        else:
            delta = jax.tree.map(lambda a: -beta * a, g)
        delta = jax.tree.map(lambda d, s_: d * s_[None, :], delta, scale)
        q_new = jnp.where(move[:, None], jnp.clip(x[0] + delta[0], hand.lower[None], hand.upper[None]), x[0])
        xi_new = jnp.where(move[:, None] & wrist, x[1] + delta[1], x[1])
        record = (terms.E, terms.E_g, terms.E_c, terms.contacts)
        return ((q_new, xi_new), active, iters + active, lp_ok & (terms.lp_ok | ~active), state,
                terms.lp_basis, terms.margin_dirs), record

    x0 = (q0, xi0)
    # each step's LP starts from the previous step's optimal basis: the wrenches move little per step, so it is
    # often still optimal or a few pivots away (-1s: no warm start for the first step)
    init = (x0, jnp.ones(B, bool), jnp.zeros(B, jnp.int32), jnp.ones(B, bool), adam_init(x0),
            jnp.full((B, 7), -1, jnp.int32),
            jnp.broadcast_to(jnp.asarray(margin_start(energy_cfg.margin_dirs), poses.dtype),
                             (B, energy_cfg.margin_dirs, 6)))
    ((q, xi), active, iters, lp_ok, _, lp_basis, dirs), hist = jax.lax.scan(step, init, jnp.arange(T))
    poses = jax.vmap(twist_pose)(poses, xi) if wrist else poses
    # before the final terms, so the energy, contacts and filters judge the projected grasp
    q = project_batch(hand, target.sdf, poses, q, optim_cfg.project_steps, optim_cfg.project_allow)
    _, final = jax.vmap(lambda H, qq, b, u: energy(hand, target, H, qq, energy_cfg, b, u))(poses, q, lp_basis, dirs)
    trace = Trace(*(jnp.concatenate([h, f[None]], 0) for h, f in
                    zip(hist, (final.E, final.E_g, final.E_c, final.contacts))))
    converged = (final.E_g + final.E_m < optim_cfg.eps_g) & (final.E_c < optim_cfg.eps_c)
    return OptResult(q, poses, final, iters, converged, lp_ok & final.lp_ok, trace)


optimize = jax.jit(descend, static_argnames=("energy_cfg", "optim_cfg"))
optimize.__doc__ = """Optimise the channels of B wrist poses (B, 4, 4) on one target; see the module docstring.

Args:
    hand: from `kinematics.load_hand`.
    target: `energy.make_target(sdf)`.
    poses: (B, 4, 4) wrist poses in the object frame.
    q_start: optional (B, Q) starting channels (clipped to the limits); default the open hand, q = 0.
    energy_cfg, optim_cfg: frozen configs (static: a new config compiles a new function).
Returns:
    OptResult with q (B, Q), the final energy terms, iteration counts, flags and the per-iteration trace.
"""
