"""Adam, written out as two pure functions over pytrees (no optax): `adam_init` and `adam_update`.

Used to train the sampler network and, optionally, by the grasp descent (`optim.method = "adam"`), where it
rescales each channel's step by the running size of its own gradient: the Q-distance's gradient is two orders of
magnitude larger than the contact term's (E_c is in metres), so plain gradient descent moves the fingers that
still have to reach the surface by millimetres per step.
"""

from typing import NamedTuple

import jax
import jax.numpy as jnp


class AdamState(NamedTuple):
    count: jax.Array  # () int32: updates taken
    mu: object  # pytree like params: first-moment estimates
    nu: object  # pytree like params: second-moment estimates


def adam_init(params) -> AdamState:
    zeros = jax.tree.map(jnp.zeros_like, params)
    return AdamState(jnp.zeros((), jnp.int32), zeros, jax.tree.map(jnp.zeros_like, params))


def adam_update(grads, state: AdamState, lr, b1: float = 0.9, b2: float = 0.999, eps: float = 1e-8):
    """Return (updates, new_state); apply as params + updates. `lr` may be a traced scalar (schedules)."""
    count = state.count + 1
    mu = jax.tree.map(lambda m, g: b1 * m + (1 - b1) * g, state.mu, grads)
    nu = jax.tree.map(lambda v, g: b2 * v + (1 - b2) * g * g, state.nu, grads)
    t = count.astype(jnp.result_type(float))  # float64 under x64, so bias corrections match the parameters' precision
    c1 = 1 - b1**t
    c2 = 1 - b2**t
    updates = jax.tree.map(lambda m, v: -lr * (m / c1) / (jnp.sqrt(v / c2) + eps), mu, nu)
    return updates, AdamState(count, mu, nu)
