"""Test-wide JAX settings: float64 references and no silent rank promotion (set at import, before any test).

The CLI's persistent compilation cache is off for the suite (tests must not write to the user's home);
tests/cli/test_jax_cache.py turns it on in a folder of its own."""

import os

import jax

os.environ.setdefault("FFCGS_JAX_CACHE", "off")
jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")
