"""Algorithm 1 of the paper over a whole batch of wrist poses: one jit-compiled gradient descent on q.

Every pose starts from q = 0 clamped into the joint limits (the SVH's open hand), takes T steps
q <- clip(q - beta_t dE/dq) with beta_t decaying linearly from `step` to `step_end`, and stops early (masked, the
batch keeps its shape) once E_g < eps_g with the fingertips on the surface (E_c < eps_c). A pose whose LP failed
at an iteration is not moved at that iteration. Fingertip positions are recorded at every iteration: they are the
path the fingers sweep while closing, which the table filter checks.
"""

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from ffcgs_jax.config import EnergyConfig, OptimConfig
from ffcgs_jax.energy import Target, Terms, energy
from ffcgs_jax.kinematics import Hand


class Trace(NamedTuple):
    """Per-iteration history, index 0 = the start, index T = the result."""

    E: Float[Array, "T B"]
    E_g: Float[Array, "T B"]
    E_c: Float[Array, "T B"]
    tips: Float[Array, "T B C 3"]


class OptResult(NamedTuple):
    q: Float[Array, "B Q"]
    final: Terms  # each field with a leading B
    iters: Int[Array, " B"]  # descent steps taken before the early stop
    converged: Bool[Array, " B"]  # stopped early (E_g < eps_g and E_c < eps_c)
    lp_ok: Bool[Array, " B"]  # every LP of this pose solved
    trace: Trace


def _optimize(hand: Hand, target: Target, poses, energy_cfg: EnergyConfig, optim_cfg: OptimConfig) -> OptResult:
    B = poses.shape[0]
    T = optim_cfg.iters
    value_and_grad = jax.vmap(
        jax.value_and_grad(lambda H, q: energy(hand, target, H, q, energy_cfg), argnums=1, has_aux=True)
    )
    q0 = jnp.broadcast_to(jnp.clip(jnp.zeros_like(hand.lower), hand.lower, hand.upper), (B, hand.n_channels))

    def step(carry, t):
        q, active, iters, lp_ok = carry
        (_, terms), g = value_and_grad(poses, q)
        done = (terms.E_g < optim_cfg.eps_g) & (terms.E_c < optim_cfg.eps_c)
        active = active & ~done
        beta = optim_cfg.step + (optim_cfg.step_end - optim_cfg.step) * t / max(T - 1, 1)
        move = active & terms.lp_ok
        g = jnp.where(jnp.isfinite(g), g, 0.0)
        q_new = jnp.where(move[:, None], jnp.clip(q - beta * g, hand.lower, hand.upper), q)
        record = (terms.E, terms.E_g, terms.E_c, terms.contacts)
        return (q_new, active, iters + active, lp_ok & (terms.lp_ok | ~active)), record

    init = (q0, jnp.ones(B, bool), jnp.zeros(B, jnp.int32), jnp.ones(B, bool))
    (q, active, iters, lp_ok), hist = jax.lax.scan(step, init, jnp.arange(T))
    _, final = jax.vmap(lambda H, qq: energy(hand, target, H, qq, energy_cfg))(poses, q)
    trace = Trace(*(jnp.concatenate([h, f[None]], 0) for h, f in
                    zip(hist, (final.E, final.E_g, final.E_c, final.contacts))))
    converged = (final.E_g < optim_cfg.eps_g) & (final.E_c < optim_cfg.eps_c)
    return OptResult(q, final, iters, converged, lp_ok & final.lp_ok, trace)


optimize = jax.jit(_optimize, static_argnames=("energy_cfg", "optim_cfg"))
optimize.__doc__ = """Optimise the channels of B wrist poses (B, 4, 4) on one target; see the module docstring.

Args:
    hand: from `kinematics.load_hand`.
    target: `energy.make_target(sdf)`.
    poses: (B, 4, 4) wrist poses in the object frame.
    energy_cfg, optim_cfg: frozen configs (static: a new config compiles a new function).
Returns:
    OptResult with q (B, Q), the final energy terms, iteration counts, flags and the per-iteration trace.
"""
