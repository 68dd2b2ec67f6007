"""Seconds JAX spends compiling inside a block of code (tracing, lowering to MLIR, the XLA compile), read from
`jax.monitoring`'s compile events.

`synthesize` times its ahead-of-time compiles itself, but the first call in a process also compiles on the way: the
SDF build, the target's centre and cells, the results' packing. Without this those seconds were counted as SDF,
synthesis or evaluation time (a fresh `ffcgs grasp` reported a 2 s whole call for 0.5 s of synthesis)."""

import contextlib
import threading
from collections.abc import Iterator

from jax import monitoring

_EVENTS = frozenset(("/jax/core/compile/jaxpr_trace_duration", "/jax/core/compile/jaxpr_to_mlir_module_duration",
                     "/jax/core/compile/backend_compile_duration"))
_local = threading.local()  # JAX compiles on the calling thread: each thread counts its own
_lock = threading.Lock()
_registered = False


def _listener(event: str, duration: float, **_) -> None:
    if event in _EVENTS:
        for acc in getattr(_local, "open", ()):
            acc[0] += duration


@contextlib.contextmanager
def compiling() -> Iterator[list[float]]:
    """A one-item list holding the compile seconds spent in the block so far (nested blocks each count them)."""
    global _registered
    with _lock:
        if not _registered:  # once per process: jax.monitoring has no public way to remove a listener
            monitoring.register_event_duration_secs_listener(_listener)
            _registered = True
    acc = [0.0]
    blocks = _local.__dict__.setdefault("open", [])
    blocks.append(acc)
    try:
        yield acc
    finally:
        del blocks[next(i for i, b in enumerate(blocks) if b is acc)]  # by identity: equal lists are other blocks
