"""Test-wide JAX settings: float64 references and no silent rank promotion (set at import, before any test)."""

import jax

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")
