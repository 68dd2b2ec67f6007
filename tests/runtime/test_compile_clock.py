"""`runtime.compile_clock`: the compile seconds of a block, from JAX's compile events."""

import jax
import jax.numpy as jnp

from ffcgs_jax.runtime import compile_clock


def test_a_new_function_counts_and_a_cached_one_does_not():
    f = jax.jit(lambda x: jnp.sin(x) * 3.0 + jnp.cumsum(x))  # a new function object: never compiled before
    x = jnp.arange(17.0)
    with compile_clock.compiling() as first:
        f(x).block_until_ready()
    with compile_clock.compiling() as again:
        f(x).block_until_ready()
    assert first[0] > 0 and again[0] == 0


def test_nested_blocks_each_count():
    g = jax.jit(lambda x: jnp.cos(x) - 1.0)
    with compile_clock.compiling() as outer:
        with compile_clock.compiling() as inner:
            g(jnp.ones(5)).block_until_ready()
    assert inner[0] > 0 and outer[0] >= inner[0]
