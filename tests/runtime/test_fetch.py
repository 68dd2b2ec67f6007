"""`fetch.device_get` against `jax.device_get`, leaf by leaf."""

import jax
import jax.numpy as jnp
import numpy as np

from ffcgs_jax.runtime import fetch


def test_packed_copy_equals_leafwise_copy():
    key = jax.random.key(0)
    tree = {"a": jax.random.normal(key, (3, 4)), "b": (jnp.arange(5, dtype=jnp.int32), jnp.asarray(2.5)),
            "c": jnp.array([True, False, True]), "d": None, "e": np.ones((2, 2)), "f": 3,
            "g": jax.random.normal(key, (2, 0, 3)), "h": jnp.asarray(7, jnp.int64).astype(jnp.float32)}
    got, want = fetch.device_get(tree), jax.device_get(tree)
    assert jax.tree.structure(got) == jax.tree.structure(want)
    for x, y in zip(jax.tree.leaves(got), jax.tree.leaves(want)):
        assert np.asarray(x).dtype == np.asarray(y).dtype and np.shape(x) == np.shape(y)
        np.testing.assert_array_equal(x, y)
