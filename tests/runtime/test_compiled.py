"""`runtime.compiled`: one bounded cache of executables for every stage, and one call that empties every cache the
package keeps in the process."""

import functools
import importlib

import cachetools
import numpy as np
import pytest

from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.runtime import COMPILED_MAX, compiled

# every module that keeps an in-process cache: importing them registers their caches
MODULES = ("ffcgs_jax.evaluation.device_metrics", "ffcgs_jax.geometry.sdf", "ffcgs_jax.synthesis.energy",
           "ffcgs_jax.synthesis.grasp", "ffcgs_jax.synthesis.prediction", "ffcgs_jax.learning.weights",
           "ffcgs_jax.hand.sites", "ffcgs_jax.runtime.traced_store", "ffcgs_jax.dataset.build",
           "ffcgs_jax.viz.render", "ffcgs_jax.physics.worlds")


def test_the_executables_cache_is_bounded_and_keeps_the_stages_apart():
    compiled.clear_compiled()
    for i in range(COMPILED_MAX + 5):
        compiled.put("a", i, f"exe{i}")
    compiled.put("b", 0, "other")
    assert compiled.sizes()["executables"] == COMPILED_MAX
    assert not compiled.has("a", 0) and compiled.get("a", COMPILED_MAX + 4) == f"exe{COMPILED_MAX + 4}"
    assert compiled.held("b") == ["other"] and compiled.get("a", 0, "gone") == "gone"
    compiled.clear_compiled()
    assert compiled.held("a") == [] and compiled.sizes()["executables"] == 0


def test_register_takes_lru_functions_and_mappings_and_refuses_others():
    @functools.lru_cache(maxsize=2)
    def square(x):
        return x * x

    store = cachetools.LRUCache(4)
    compiled.register("test square", square)
    compiled.register("test store", store)
    square(3)
    store["k"] = 1
    assert compiled.sizes()["test square"] == 1 and compiled.sizes()["test store"] == 1
    compiled.clear_compiled()
    assert compiled.sizes()["test square"] == 0 and compiled.sizes()["test store"] == 0
    with pytest.raises(FfcgsError, match="must be an lru_cache'd function or a mapping"):
        compiled.register("test bad", 3)


def test_one_call_empties_every_cache_the_package_keeps(svh):
    """Fill the package's caches with real work (a grid, its target, a triangle table, the LP basis, a standoff,
    the source hash), then `clear_compiled`: every registered cache is empty, those filled and the others."""
    for m in MODULES:
        importlib.import_module(m)
    import trimesh

    from ffcgs_jax.evaluation import device_metrics
    from ffcgs_jax.geometry import sdf
    from ffcgs_jax.geometry.config import SDFConfig
    from ffcgs_jax.hand import sites
    from ffcgs_jax.kernels import quality
    from ffcgs_jax.runtime import traced_store
    from ffcgs_jax.synthesis import energy

    mesh = trimesh.creation.box((0.05, 0.05, 0.05))
    energy.make_target(sdf.build_sdf(mesh, SDFConfig(res=16)))
    device_metrics.mesh_table(mesh)
    quality.basis(16)
    sites.default_standoff(svh)
    traced_store.key("x", None, [np.zeros(1)], None)
    filled = {k: v for k, v in compiled.sizes().items() if v}
    assert {"geometry.sdf grids", "synthesis.energy targets", "evaluation.device_metrics triangle tables",
            "kernels.quality basis", "hand.sites standoffs", "runtime.traced_store source hash"} <= set(filled), filled
    compiled.clear_compiled()
    assert not any(compiled.sizes().values()), compiled.sizes()
