"""The process's compiled executables, in one bounded cache for every stage, and the registry of every in-process
cache, so that one call (`clear_compiled`, `fj.clear_compiled`) gives all of their memory back.

Each stage keeps its executables here under its own name (`synthesis.grasp` "device_part",
`evaluation.device_metrics` "evaluate_mesh"): ahead-of-time compiles bypass jit's own cache, and an executable holds
its code and, on a CPU, hundreds of the process's 65,530 memory mappings, so the stages share one bound
(`runtime.COMPILED_MAX`, the least recently used dropped first) instead of each keeping its own.

Every other cache a module keeps (grids, triangle tables, weights, hand data) registers here with `register`, and
`clear_compiled` empties them all and JAX's own caches: a test that fills them and clears sees every one empty
(`sizes`).
"""

from collections.abc import Callable, Hashable
from typing import Any

import cachetools

from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.runtime import COMPILED_MAX

_EXECUTABLES = cachetools.LRUCache(COMPILED_MAX)  # (stage, key) -> what the stage keeps for it
_REGISTRY: dict[str, tuple[Callable[[], None], Callable[[], int]]] = {}


def get(stage: str, key: Hashable, default: Any = None) -> Any:
    """What `stage` put under `key` (marking it recently used), or `default`."""
    return _EXECUTABLES.get((stage, key), default)


def has(stage: str, key: Hashable) -> bool:
    return (stage, key) in _EXECUTABLES


def put(stage: str, key: Hashable, value: Any) -> None:
    """Keep `value` (an executable, with whatever its stage needs to call it) for `stage`'s `key`."""
    _EXECUTABLES[stage, key] = value


def held(stage: str) -> list:
    """What `stage` holds, in the order it was put (`clear_compiled` empties it)."""
    return [v for (s, _), v in _EXECUTABLES.items() if s == stage]


def register(name: str, cache) -> None:
    """Have `clear_compiled` empty `cache`: a `functools.lru_cache`-wrapped function, or a mapping or set (a
    `cachetools` cache, a dict) that the module keeps bounded itself. Registering a name again replaces it (a
    reloaded module's new cache)."""
    if hasattr(cache, "cache_clear") and hasattr(cache, "cache_info"):
        _REGISTRY[name] = cache.cache_clear, lambda: cache.cache_info().currsize
    elif hasattr(cache, "clear") and hasattr(cache, "__len__"):
        _REGISTRY[name] = cache.clear, lambda: len(cache)
    else:
        raise FfcgsError(f"cache {name!r} must be an lru_cache'd function or a mapping, got {type(cache).__name__}")


def sizes() -> dict[str, int]:
    """Entries per registered cache (the executables' own as "executables")."""
    return {"executables": len(_EXECUTABLES)} | {name: size() for name, (_, size) in _REGISTRY.items()}


def clear_compiled() -> None:
    """Drop every executable the package holds compiled, every cache a module registered (grids, triangle tables,
    targets, weights, ...) and JAX's own caches: their memory comes back, and the next call compiles again, or
    loads from the disk cache where it is on."""
    import jax  # here: registering a cache must not import JAX (the CPU physics path runs without it)

    _EXECUTABLES.clear()
    for clear, _ in _REGISTRY.values():
        clear()
    jax.clear_caches()
