"""Network layers as pure functions over nested dicts of arrays (no flax): 3-D convolutions, residual blocks,
pooling, upsampling and dense layers, each an `init_*(key, ...) -> params` and an apply function.

Volumes are channels-last, (D, H, W, C) for one item and (B, D, H, W, C) for a batch; convolutions go through
`lax.conv_general_dilated` with "SAME" padding (zeros outside the grid).
"""

import math

import jax
import jax.numpy as jnp
from jax import lax

from ffcgs_jax.core.types import Array, Float

_DIMS = ("NDHWC", "DHWIO", "NDHWC")


def init_conv(key: jax.Array, c_in: int, c_out: int, k: int = 3, zero: bool = False) -> dict:
    """A k^3 convolution, He-normal weights (for ReLU-family activations), zero bias.

    `zero=True` starts the weights at 0: the last convolution of a residual branch, so that every block starts as
    the identity and a deep stack trains without normalisation layers (the Fixup/SkipInit idea).
    """
    std = 0.0 if zero else math.sqrt(2.0 / (c_in * k**3))
    return {"w": std * jax.random.normal(key, (k, k, k, c_in, c_out)), "b": jnp.zeros((c_out,))}


def conv(p: dict, x: Float[Array, "B D H W Ci"], stride: int = 1) -> Float[Array, "B d h w Co"]:
    """3-D convolution with zero padding ("SAME"); stride 2 halves each spatial size."""
    y = lax.conv_general_dilated(x, p["w"].astype(x.dtype), (stride,) * 3, "SAME", dimension_numbers=_DIMS)
    return y + p["b"].astype(x.dtype).reshape(1, 1, 1, 1, -1)


def init_resblock(key: jax.Array, c: int) -> dict:
    k1, k2 = jax.random.split(key)
    return {"c1": init_conv(k1, c, c), "c2": init_conv(k2, c, c, zero=True)}


def resblock(p: dict, x: Float[Array, "B D H W C"]) -> Float[Array, "B D H W C"]:
    """x + conv(act(conv(act(x)))), pre-activation (He et al. 2016), identity at initialisation."""
    return x + conv(p["c2"], jax.nn.silu(conv(p["c1"], jax.nn.silu(x))))


def max_pool(x: Float[Array, "B D H W C"]) -> Float[Array, "B d h w C"]:
    """2x2x2 max pooling with stride 2; odd sizes round up ("SAME"), so a 1^3 volume stays 1^3."""
    return lax.reduce_window(x, -jnp.inf, lax.max, (1, 2, 2, 2, 1), (1, 2, 2, 2, 1), "SAME")


def upsample(x: Float[Array, "B D H W C"]) -> Float[Array, "B d h w C"]:
    """Nearest-neighbour 2x upsampling of each spatial axis."""
    for axis in (1, 2, 3):
        x = jnp.repeat(x, 2, axis=axis)
    return x


def init_dense(key: jax.Array, c_in: int, c_out: int, scale: float = 1.0) -> dict:
    """A dense layer, He-normal weights times `scale` (small for output heads), zero bias."""
    return {"w": scale * math.sqrt(2.0 / c_in) * jax.random.normal(key, (c_in, c_out)), "b": jnp.zeros((c_out,))}


def dense(p: dict, x: Float[Array, "*B Ci"]) -> Float[Array, "*B Co"]:
    b = p["b"].astype(x.dtype)
    return x @ p["w"].astype(x.dtype) + b.reshape((1,) * (x.ndim - 1) + b.shape)


def num_params(params) -> int:
    return sum(int(x.size) for x in jax.tree.leaves(params))
