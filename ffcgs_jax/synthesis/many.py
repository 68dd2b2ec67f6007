"""Grasps of many objects, one after another on the device, as an iterator (`synthesize_many`).

Each object's preparation (reading the mesh, `geometry.mesh_io.load_mesh`; its triangle table for the evaluation,
`evaluation.device_metrics.mesh_table`; its SDF, `geometry.sdf.build_sdf`) runs in background threads while the
object before it is synthesised, so the device waits for a mesh only when preparing it takes longer than
synthesising the one before. What `synthesize` compiled for the first object serves every later one, whatever its
size, so the objects run back to back.

An object that cannot be loaded or synthesised (a broken file, a mesh with no volume) is one result with its error
line, and the loop goes on: one bad file in a folder of hundreds must not cost the others.
"""

import os
import time
from collections import deque
from collections.abc import Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import NamedTuple

import trimesh

from ffcgs_jax.core.config import check_all
from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.evaluation.device_metrics import mesh_table
from ffcgs_jax.geometry import objects as builtin
from ffcgs_jax.geometry.config import SDFConfig
from ffcgs_jax.geometry.mesh_io import FORMATS, load_mesh
from ffcgs_jax.geometry.sdf import build_sdf
from ffcgs_jax.hand.kinematics import Hand
from ffcgs_jax.synthesis.config import GraspConfig
from ffcgs_jax.synthesis.grasp import GraspSet, synthesize

MESH_SUFFIXES = tuple(f".{s}" for s in FORMATS)


class ObjectSource(NamedTuple):
    """One object to grasp: `name` (a file's stem, a built-in name, or a given mesh's name) and `source`, a built-in
    name, a mesh file's path, or a `trimesh.Trimesh` already loaded."""

    name: str
    source: str | trimesh.Trimesh


class ObjectResult(NamedTuple):
    """What `synthesize_many` yields for one object.

    Attributes:
        name: the object's name (`ObjectSource.name`): the stem its grasp file is named after.
        source: the built-in name or mesh file as given, or "" for a mesh passed in.
        grasps: its grasps, or None when it failed.
        mesh: the mesh as loaded (what the grasps were measured on; for `validate`), or None when loading failed.
        error: one line saying why it failed, naming the file, or None.
        seconds: wall time of its turn: waiting for its mesh (when the prefetch had not finished) and `synthesize`.
    """

    name: str
    source: str
    grasps: GraspSet | None
    mesh: trimesh.Trimesh | None
    error: str | None
    seconds: float


def expand_objects(objects: Iterable) -> list[ObjectSource]:
    """The objects of `objects`, in order: a built-in name, a mesh file (str or Path), a folder (its mesh files,
    sorted by name, not its subfolders or hidden files), a `(name, trimesh.Trimesh)` pair or an `ObjectSource`
    (this function's own output, so a caller may expand, filter, then pass the rest to `synthesize_many`).

    Raises:
        FfcgsError: a folder with no mesh files, an item of another type, one object given twice (the same
            built-in name or file, by any path), or two objects of one name (each object's grasp file is named
            after it).
    """
    out: list[ObjectSource] = []
    for item in objects:
        if isinstance(item, ObjectSource):
            out.append(item)
        elif isinstance(item, str) and item in builtin.names():  # before files, as `load_mesh` reads it
            out.append(ObjectSource(item, item))
        elif isinstance(item, (str, os.PathLike)) and Path(item).is_dir():
            found = sorted(p for p in Path(item).iterdir()
                           if p.is_file() and not p.name.startswith(".") and p.suffix.lower() in MESH_SUFFIXES)
            if not found:
                raise FfcgsError(f"folder {item} holds no mesh files ({', '.join(FORMATS)})")
            out += [ObjectSource(p.stem, str(p)) for p in found]
        elif isinstance(item, (str, os.PathLike)):
            out.append(ObjectSource(Path(item).stem, os.fspath(item)))
        elif isinstance(item, tuple) and len(item) == 2 and isinstance(item[0], str) and \
                isinstance(item[1], trimesh.Trimesh):
            out.append(ObjectSource(*item))
        else:
            raise FfcgsError(f"an object is a built-in name, a mesh file, a folder or a (name, trimesh.Trimesh) "
                             f"pair, got {type(item).__name__}")
    seen: dict[str, ObjectSource] = {}
    for o in out:
        if o.name in seen:
            if _same(seen[o.name], o):
                twice = f"{_said(o)!r}" if _said(o) == _said(seen[o.name]) else \
                    f"{_said(seen[o.name])!r} (also as {_said(o)!r})"
                raise FfcgsError(f"the same object {twice} is given twice: give each object once")
            raise FfcgsError(f"two objects are named {o.name!r} ({_said(seen[o.name])} and {_said(o)}): each "
                             "object's grasps are named after it, so rename one")
        seen[o.name] = o
    return out


def _said(o: ObjectSource) -> str:
    return o.source if isinstance(o.source, str) else "a given mesh"


def _same(a: ObjectSource, b: ObjectSource) -> bool:
    """Whether two objects are one: the same built-in name, the same file (by any path to it) or the same mesh."""
    if not (isinstance(a.source, str) and isinstance(b.source, str)):
        return a.source is b.source
    if a.source in builtin.names() or b.source in builtin.names():
        return a.source == b.source
    try:
        return os.path.samefile(a.source, b.source)
    except OSError:  # a file that is not there: its load says so
        return Path(a.source).expanduser().resolve() == Path(b.source).expanduser().resolve()


def synthesize_many(hand: Hand, objects: Iterable, cfg: GraspConfig = GraspConfig(), *,
                    prefetch: int | None = None) -> Iterator[ObjectResult]:
    """Grasps of each of `objects` (`expand_objects`), one `ObjectResult` per object in order, as each is done.

    `synthesize(hand, mesh, cfg, object_name=name)` runs for one object while the next `prefetch` objects are
    loaded, and their triangle tables and SDFs built, in background threads (one each); `prefetch=0` prepares each
    in turn; None (the default) takes `default_prefetch()`. Meshes load with `cfg.sdf.scale`. To resume a
    run, pass only the objects not done yet.

    The objects and `cfg` are checked here, before the first object: a config error or a name used twice raises
    now, not once per object. An object that fails to load or to synthesise (FfcgsError; any failure to read its
    file) is a result with `error` set; other errors propagate.

        for r in fj.synthesize_many(hand, ["mug", "meshes/"], fj.GraspConfig(n=32)):
            print(r.name, r.error or f"{r.grasps['valid'].sum()} valid")
    """
    check_all(cfg)
    prefetch = default_prefetch() if prefetch is None else prefetch
    if isinstance(prefetch, bool) or not isinstance(prefetch, int) or prefetch < 0:
        raise FfcgsError(f"prefetch must be an integer >= 0, got {prefetch!r}")
    return _run(hand, expand_objects(objects), cfg, prefetch)


def default_prefetch() -> int:
    """Objects prepared ahead: half the host's cores, 2 to 8. On one H200 with 16 cores, 100 objects of up to
    200,000 faces took 21.7 s with 2 ahead, 16.4 s with 4 and 12.1 s with 8 (bench/RESULTS.md, "Diverse objects");
    on a 2-core host more threads than cores only compete with the synthesis."""
    return min(8, max(2, (os.cpu_count() or 2) // 2))


def _prepare(o: ObjectSource, sdf_cfg: SDFConfig) -> tuple[trimesh.Trimesh | None, str | None]:
    """The work of one object before its synthesis: its mesh, its triangle table and its SDF (both cached, by
    `mesh_table` and `build_sdf`, which `synthesize` asks for again); or (None, the error line). For a large mesh
    this is most of the call (on one GPU, 0.9 s of host work for 160,000 faces against 0.1 s of device work)."""
    try:
        mesh = o.source if isinstance(o.source, trimesh.Trimesh) else load_mesh(o.source, scale=sdf_cfg.scale)
        mesh_table(mesh)
        build_sdf(mesh, sdf_cfg)
        return mesh, None
    except FfcgsError as e:
        return None, str(e)
    except Exception as e:  # noqa: BLE001 - host work on the caller's file: any failure is that object's
        return None, f"cannot load {_said(o)}: {type(e).__name__}: {e}"


def _run(hand: Hand, todo: list[ObjectSource], cfg: GraspConfig, prefetch: int) -> Iterator[ObjectResult]:
    # one thread per object ahead: NumPy's sorts and ufuncs and the mesh parsing release the GIL for large arrays
    pool = ThreadPoolExecutor(prefetch, thread_name_prefix="ffcgs-prefetch") if prefetch else None
    queue: deque[tuple[ObjectSource, Future | None]] = deque()
    upcoming = iter(todo)

    def ahead() -> None:
        o = next(upcoming, None)
        if o is not None:
            queue.append((o, pool.submit(_prepare, o, cfg.sdf) if pool else None))

    try:
        for _ in range(max(prefetch, 1)):
            ahead()
        while queue:
            o, pending = queue.popleft()
            t0 = time.perf_counter()
            mesh, error = pending.result() if pending else _prepare(o, cfg.sdf)
            ahead()  # before this object's device work, so the next one loads meanwhile
            gs = None
            if error is None:
                try:
                    gs = synthesize(hand, mesh, cfg, object_name=o.name)
                except FfcgsError as e:
                    error = str(e)
            yield ObjectResult(o.name, o.source if isinstance(o.source, str) else "", gs, mesh, error,
                               time.perf_counter() - t0)
    finally:
        if pool is not None:  # an interrupted loop must not wait for a mesh it will not use
            pool.shutdown(wait=False, cancel_futures=True)
