"""Traced programs kept on disk, so that a process that finds its executables in the compilation cache skips
tracing too.

JAX's persistent compilation cache (`runtime.jax_cache`) keeps compiled executables, but finds them by a key computed
from the lowered program, so every process still traces: on a 2-core CPU that was about 14 s of a warm `ffcgs grasp`
start, the device part's and the evaluation's traces (bench/RESULTS.md, "First grasp"). Where that cache is on,
`lower` also keeps each traced function as a `jax.export` artifact (StableHLO in a flatbuffer: no pickle) in
`ffcgs-traced/` beside it, named by a hash of everything the trace depends on: the function's name and static
arguments, the inputs' tree structure, shapes and dtypes, the backend and device kind, the versions of jax, jaxlib,
mujoco and mujoco-mjx, and this package's source. A later process lowers the stored program instead of tracing
the function, and its compilation finds the executable in the persistent cache as before.

Whatever cannot be stored is traced as before, with the same results: a program that calls back to the host (the
"proxsuite" LP), one that spans several devices, and any export or file error (said once, and marked in the
folder so that later processes trace without trying again).
"""

import functools
import hashlib
import importlib.metadata
import os
import re
import tempfile
import warnings
from collections.abc import Callable, Hashable
from pathlib import Path
from typing import Any

import jax

from ffcgs_jax.core import version as package_version
from ffcgs_jax.runtime import compiled

_ADDRESS = re.compile(r" at 0x[0-9a-fA-F]+")
_REGISTERED: set[type] = set()


def folder() -> Path | None:
    """Where stored traces go: `ffcgs-traced/` in JAX's compilation-cache folder, or None while that cache is off."""
    where = jax.config.jax_compilation_cache_dir
    if not where or not jax.config.jax_enable_compilation_cache:
        return None
    return Path(where) / "ffcgs-traced"


@functools.cache
def _source_hash() -> str:
    h = hashlib.sha256()
    root = Path(package_version.__file__).parent.parent  # the whole package
    for p in sorted(root.rglob("*.py")):
        h.update(p.relative_to(root).as_posix().encode())
        h.update(p.read_bytes())
    for dist in ("jax", "jaxlib", "mujoco", "mujoco-mjx"):
        try:
            h.update(f"{dist}={importlib.metadata.version(dist)}".encode())
        except importlib.metadata.PackageNotFoundError:
            pass
    return h.hexdigest()


compiled.register("runtime.traced_store source hash", _source_hash)


def key(name: str, static: Hashable, leaves, treedef) -> str:
    """The file name of a trace: a hash of what it depends on (see the module docstring)."""
    h = hashlib.sha256()
    shapes = [(tuple(x.shape), str(x.dtype)) for x in leaves]
    for part in (name, repr(static), _ADDRESS.sub("", str(treedef)), str(shapes), jax.default_backend(),
                 jax.devices()[0].device_kind, _source_hash()):
        h.update(part.encode())
        h.update(b"\0")
    return f"{name}-{h.hexdigest()[:40]}.jaxexport"


def register_outputs(*types: type) -> None:
    """Let NamedTuple output types be stored (their field names travel with the program)."""
    for t in types:
        if t not in _REGISTERED:
            jax.export.register_namedtuple_serialization(t, serialized_name=f"{t.__module__}.{t.__qualname__}")
            _REGISTERED.add(t)


def lower(name: str, fn: Callable[..., Any], args: tuple, static: Hashable = None, store: bool = True):
    """`fn(*args)` lowered, and how to call what it compiles to: (lowered, call) with `call(compiled, *args)`.

    `fn` has its static arguments bound already; `static` names them for the key. With the compilation cache on
    and `store` True, the trace is read from `folder()` when stored there, else traced, exported and stored; the
    lowered program then takes the flattened arguments. Otherwise `jax.jit(fn).lower(*args)`."""
    where = folder()
    if where is None or not store:
        return jax.jit(fn).lower(*args), lambda compiled, *a: compiled(*a)
    leaves, treedef = jax.tree.flatten(args)
    path = where / key(name, static, leaves, treedef)
    failed = path.with_suffix(".failed")  # an earlier process could not store this trace: trace, say nothing
    if failed.exists():
        return jax.jit(fn).lower(*args), lambda compiled, *a: compiled(*a)
    exported = _read(path) if path.exists() else None
    try:
        if exported is None:
            flat = jax.jit(lambda *xs: fn(*jax.tree.unflatten(treedef, xs)))
            specs = [jax.ShapeDtypeStruct(x.shape, x.dtype) for x in leaves]
            # Every custom call allowed (the GPU's Pallas kernels, cuSOLVER): export refuses those whose format may
            # change between jax releases, but a stored trace is only read by the same jax, jaxlib and device kind.
            exported = jax.export.export(flat, disabled_checks=[jax.export.DisabledSafetyCheck.custom_call("ALL")]
                                         )(*specs)
            _write(path, exported.serialize())
        return jax.jit(exported.call).lower(*leaves), lambda compiled, *a: compiled(*jax.tree.leaves(a))
    except Exception as e:  # noqa: BLE001 - any failure here only costs the trace the store would have saved
        why = f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}"
        warnings.warn(f"{name}: traced in every process, its trace cannot be stored ({why})", stacklevel=2)
        try:
            _write(failed, why.encode())
        except OSError:
            pass
        return jax.jit(fn).lower(*args), lambda compiled, *a: compiled(*a)


def _read(path: Path):
    try:
        return jax.export.deserialize(bytearray(path.read_bytes()))
    except Exception:  # noqa: BLE001 - a damaged or foreign file: trace again and replace it
        return None


def _write(path: Path, data: bytes | bytearray) -> None:
    """Atomically, so that a process reading it meanwhile sees all of it or nothing."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".tmp-")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(bytes(data))
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
