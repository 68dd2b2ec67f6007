"""Diverse objects, each new to the process: 100 meshes of 1,000 to 200,000 faces to ranked grasps (issue 32).

    python bench/diverse_objects.py                          # build the set if it is not built, then run all 100
    python bench/diverse_objects.py --build-only             # the object set alone (`--rebuild`: from scratch)
    python bench/diverse_objects.py --quick --n 8            # smoke run: 6 objects spanning the range
    python bench/diverse_objects.py --iterator               # `fj.synthesize_many` instead of a loop, once it exists
    python bench/diverse_objects.py --compare --out d.json   # the loop and the iterator, each in a process of its own

The object set (deterministic; `--meshes DIR`, default `$XDG_CACHE_HOME/ffcgs-jax/diverse`, never committed): 100
face-count targets spaced log-uniformly from 1,000 to 200,000, slot i taking its source in turn from the YCB meshes
(slots i % 4 in {0, 2}: every sorted *.stl of `--ycb`, `$FFCGS_YCB` or ../shared/objects/ycb, test split and train
split alike since this measures speed; 3,000 faces, metres, 2-33 cm), the complex procedural family (i % 4 == 1:
`procedural.complex_shape(3200, k)`, 5-15 cm, about 3,000 faces) and the simple procedural shapes (i % 4 == 3:
`procedural.shape(3200, k)`, 12 to 1,280 faces). Each source is brought to its target count by manifold3d (already
a dependency of `geometry.procedural`): `refine_to_length` splits edges (linearly: every new vertex lies on the
original surface, nothing smoothed or jittered; trimesh's `subdivide` only multiplies by 4) and `simplify` merges
edges that change the surface by less than a tolerance (the decimation; at most a few mm, recorded as `tol_mm`),
each searched for the length or tolerance that lands within 5 % of the target. Both keep a manifold a manifold; a
mesh that is no longer watertight once vertices at one position are merged, as `fj.load_mesh` merges them (a thin
YCB tool, the spoon or the skillet lid, whose two sides meet when decimated), is refused and its slot goes to the
next source (recorded as `skipped`), so every mesh whose source was watertight is. Each mesh is then turned about
the vertical axis through its centre by its own seeded angle, so no two objects (nor the warm-up, the built-in
mug) share vertices and no cache inside the library can give one object another's results: each is taken as new.
The 50 YCB slots use all 44 objects, a few twice or thrice at other sizes; sizes stay those of the sources (5-32 cm
across, median 13 cm), the library's scale. The meshes are binary PLY files, with `manifest.json` naming each one's
source, target and content hash; a run rebuilds only what the recipe or the sources changed.

The run: one process, one hand (`--hand`, svh), `GraspConfig` defaults unless `--n`, `--iters`, `--sampler` or
`--seed` say otherwise. A warm-up object (the built-in mug, not one of the 100) pays the process's first compile;
then the objects back to back in a seeded order that mixes sizes, as a stream of new objects would. Per object the
whole call as the user waits for it is timed: the mesh file loaded (`fj.load_mesh`), `fj.synthesize`, the ranked
grasps (`gs.order()`). Compiles are counted twice: the call's own `compile_s`, and JAX's backend-compile events
(`jax.monitoring`, "/jax/core/compile/backend_compile_duration" less "/jax/compilation_cache/cache_hits": an
executable loaded from the persistent cache is not a compile). The totals include every compile after the
warm-up's, since the user waits for those too; "compile s" shows how much of each call they were.

`--iterator` takes the objects through `fj.synthesize_many(hand, files, cfg)` instead, which prepares the next
objects (mesh, triangle table, SDF) in threads while the current one synthesises; an object's time is the interval
between its result and the one before.

Targets (issue 32): one H100, the 100 objects in at most 20 s after the first compile and that compile at most
30 s; the 2-core CPU, at most 3 min after it. Judged only on a full run with n = 32 and default settings. The third
target, grasp quality unchanged, is the scoreboard's (bench/quality.py), not measured here.
"""

import argparse
import dataclasses
import functools
import hashlib
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from ffcgs_jax.core import files
from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.hand import spec

PROG = "bench/diverse_objects.py"
REPO = Path(__file__).resolve().parents[1]
COUNT = 100
FACES_LO, FACES_HI = 1_000, 200_000
SET_SEED = 3200  # procedural seed and turn angles: not a training seed (1000 and 2000 are other benches' unseen sets)
RECIPE = "diverse-1"  # bump when the recipe changes: every cached mesh is rebuilt
HIT = 0.05  # a built mesh lands within this fraction of its face-count target
LEAN = 1e-6  # of the object's size: a simplify tolerance that removes only flat or straight runs of faces
TRIES = 8  # sources a slot tries before the build gives up
QUICK = (0, 21, 39, 60, 81, 99)  # slots from 1,000 to 200,000 faces, two of each source
WARMUP = "mug"
BINS = (1_000, 2_000, 5_000, 10_000, 20_000, 50_000, 100_000, 200_000)
# Event names from jax/_src/dispatch.py and jax/_src/compiler.py (JAX 0.10-0.11); `jax.monitoring` has no constants.
BACKEND_COMPILE = "/jax/core/compile/backend_compile_duration"
TRACE = "/jax/core/compile/jaxpr_trace_duration"
CACHE_HIT = "/jax/compilation_cache/cache_hits"
TARGETS = {"gpu": (20.0, 30.0), "cpu": (180.0, None)}  # (total after the first compile, first compile), seconds


class Parser(argparse.ArgumentParser):
    def error(self, message):  # one line, no usage block, like the CLI's `ffcgs: error:`
        sys.stderr.write(f"{PROG}: error: {message} (see {PROG} --help)\n")
        sys.exit(2)


def default_meshes() -> Path:
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "ffcgs-jax" / "diverse"


def default_ycb() -> Path:
    return Path(os.environ.get("FFCGS_YCB") or REPO.parent / "shared" / "objects" / "ycb")


def parser() -> Parser:
    ap = Parser(prog=PROG, description=__doc__.splitlines()[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--meshes", type=Path, default=default_meshes(), help="folder of the object set (a cache)")
    ap.add_argument("--ycb", type=Path, default=default_ycb(), help="folder of the YCB *.stl (default $FFCGS_YCB "
                    "or ../shared/objects/ycb)")
    ap.add_argument("--build-only", action="store_true", help="build the object set, run nothing")
    ap.add_argument("--rebuild", action="store_true", help="build every mesh asked for anew")
    ap.add_argument("--quick", action="store_true", help=f"{len(QUICK)} objects spanning the range, not {COUNT}")
    ap.add_argument("--limit", type=int, default=0, metavar="K", help="only the first K objects of the run order")
    ap.add_argument("--hand", default="svh")
    ap.add_argument("--n", type=int, default=None, help="grasps per object (default: GraspConfig's, 32)")
    ap.add_argument("--iters", type=int, default=None, help="descent steps (default: OptimConfig's)")
    ap.add_argument("--sampler", default=None, help="default: GraspConfig's (auto)")
    ap.add_argument("--seed", type=int, default=None)
    ap.add_argument("--iterator", action="store_true", help="fj.synthesize_many instead of a loop of synthesize")
    ap.add_argument("--prefetch", type=int, default=None, metavar="K",
                    help="with --iterator: objects prepared ahead (default: synthesize_many's)")
    ap.add_argument("--compare", action="store_true", help="run the loop and the iterator, each in its own process")
    ap.add_argument("--out", type=Path, help="write every figure here (JSON)")
    return ap


def parse_args(argv=None) -> argparse.Namespace:
    ap = parser()
    args = ap.parse_args(argv)
    if args.limit < 0:
        ap.error(f"--limit must be >= 0, got {args.limit}")
    for flag, v, lo in (("--n", args.n, 1), ("--iters", args.iters, 1), ("--seed", args.seed, 0)):
        if v is not None and v < lo:
            ap.error(f"{flag} must be >= {lo}, got {v}")
    if args.iterator and args.compare:
        ap.error("--iterator and --compare: pick one (--compare runs both)")
    if args.out and not args.out.resolve().parent.is_dir():  # found out now, not after the run
        ap.error(f"--out: no such folder: {args.out.parent}")
    if args.meshes.exists() and not args.meshes.is_dir():
        ap.error(f"--meshes: not a folder: {args.meshes}")
    if not args.build_only:
        try:
            config(args)
            spec.load_spec(args.hand)
        except FfcgsError as e:
            ap.error(str(e))
        if (args.iterator or args.compare) and not has_iterator():
            ap.error("--iterator and --compare need ffcgs_jax.synthesize_many, which this ffcgs_jax does not have")
    return args


def has_iterator() -> bool:
    import ffcgs_jax as fj

    return hasattr(fj, "synthesize_many")


def config(args):
    """The GraspConfig of the run: the package defaults, changed only where a flag says."""
    from ffcgs_jax.synthesis.config import GraspConfig

    cfg = GraspConfig()
    over = {k: getattr(args, k) for k in ("n", "sampler", "seed") if getattr(args, k) is not None}
    if args.iters is not None:
        over["optim"] = dataclasses.replace(cfg.optim, iters=args.iters)
    cfg = dataclasses.replace(cfg, **over)
    cfg.check()
    return cfg


# --------------------------------------------------------------------------------------------------- object set


@dataclasses.dataclass(frozen=True)
class Slot:
    index: int  # by increasing target
    target: int
    kind: str  # "ycb", "complex" or "simple"
    k: int  # the k-th slot of its kind: which source it tries first
    angle: float  # radians about the vertical axis


def targets() -> np.ndarray:
    return np.rint(FACES_LO * (FACES_HI / FACES_LO) ** (np.arange(COUNT) / (COUNT - 1))).astype(int)


def slots() -> list[Slot]:
    """The recipe: slot i's target, kind of source and turn, from i alone."""
    angles = np.random.default_rng(SET_SEED).uniform(0, 2 * np.pi, COUNT)
    out, counts = [], {"ycb": 0, "complex": 0, "simple": 0}
    for i, target in enumerate(targets()):
        kind = ("ycb", "complex", "ycb", "simple")[i % 4]
        out.append(Slot(i, int(target), kind, counts[kind], float(angles[i])))
        counts[kind] += 1
    return out


def run_order(indices) -> list[int]:
    """The slots `indices` in a seeded shuffle: sizes and sources mixed, as new objects would come."""
    perm = np.random.default_rng(SET_SEED + 1).permutation(COUNT)
    rank = {int(s): r for r, s in enumerate(perm)}
    return sorted(indices, key=lambda i: rank[i])


def source_mesh(slot: Slot, attempt: int, ycb_names: list[str], ycb: Path):
    """(name, source mesh in metres) of a slot's `attempt`-th choice: YCB objects in a seeded order (so each
    object spreads over sizes rather than the set sorting by name), procedural indices k, k + 1000, ..."""
    from ffcgs_jax.geometry import mesh_io, procedural

    if slot.kind == "ycb":
        order = np.random.default_rng(SET_SEED).permutation(len(ycb_names))
        name = ycb_names[order[(slot.k + attempt) % len(ycb_names)]]
        return name, mesh_io.load_mesh(ycb / f"{name}.stl")
    make = procedural.complex_shape if slot.kind == "complex" else procedural.shape
    return make(SET_SEED, slot.k + 1000 * attempt)


def to_manifold(mesh):
    import manifold3d as mf

    solid = mf.Manifold(mf.Mesh(vert_properties=np.asarray(mesh.vertices, np.float32),
                                tri_verts=np.asarray(mesh.faces, np.uint32)))
    if solid.num_tri() != len(mesh.faces):
        raise FfcgsError(f"manifold3d took {solid.num_tri()} of {len(mesh.faces)} faces ({solid.status()}): the "
                         "source is not a closed manifold")
    return solid


def from_manifold(solid):
    """As `load_mesh` will see it: vertices at one position merged (a thin part simplified until its two sides
    meet is then no longer watertight)."""
    import trimesh

    m = solid.to_mesh()
    return trimesh.Trimesh(np.asarray(m.vert_properties, np.float64)[:, :3], np.asarray(m.tri_verts, np.int64))


def resize(mesh, target: int):
    """(mesh within HIT of `target` faces, watertight if `mesh` is, and the simplify tolerance in m), or None.

    Up: `refine_to_length` splits edges longer than a length, faces growing about as 1/length^2, so a few
    power-law steps land near the target, bisection keeping them inside the bracket. A source with flat or straight
    runs (the complex shapes' plates) is first rid of what `simplify` drops at LEAN, which changes nothing, so that
    refining spreads faces evenly. Down: `simplify` has no such law: bisection on log(tolerance)."""
    solid = to_manifold(mesh)
    size = float(np.ptp(mesh.vertices, axis=0).max())
    sealed = bool(mesh.is_watertight)

    def fits(got):
        if abs(got.num_tri() / target - 1) > HIT:
            return None
        m = from_manifold(got)
        return m if m.is_watertight or not sealed else None

    as_is = fits(solid)
    if as_is is not None:
        return as_is, 0.0
    lean = solid.simplify(LEAN * size)
    base = solid if solid.num_tri() <= target else lean
    if base.num_tri() <= target:
        x0 = float(np.sqrt(base.surface_area() / (0.433 * target)))  # equilateral triangles of the target count
        found = search(base.refine_to_length, fits, target, 1e-5 * size, size, x0, power=True)
        return None if found is None else (found[0], 0.0 if base is solid else LEAN * size)
    return search(solid.simplify, fits, target, LEAN * size, 0.2 * size, 1e-3 * size, power=False)


def search(make, fits, target: int, lo: float, hi: float, x: float, power: bool):
    """(mesh, x) of the first `make(x)` that `fits`, x in [lo, hi] (more faces at a smaller x), or None."""
    for _ in range(40):
        got = make(x)
        n = got.num_tri()
        found = fits(got)
        if found is not None:
            return found, x
        if n > target:
            lo = x
        else:
            hi = x
        if hi <= lo * (1 + 1e-6):
            return None
        step = x * float(np.sqrt(n / target)) if power else float(np.sqrt(lo * hi))
        x = step if lo < step < hi else float(np.sqrt(lo * hi))
    return None


def turned(mesh, angle: float):
    import trimesh

    lo, hi = mesh.bounds
    centre = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, 0.0])
    mesh = mesh.copy()
    mesh.apply_transform(trimesh.transformations.rotation_matrix(angle, [0, 0, 1], centre))
    return mesh


def ycb_digest(ycb: Path, names: list[str]) -> str:
    h = hashlib.sha256()
    for name in names:
        h.update(name.encode() + hashlib.sha256((ycb / f"{name}.stl").read_bytes()).digest())
    return h.hexdigest()


def slot_key(slot: Slot, digest: str) -> str:
    """What a cached mesh was built from: the recipe, the slot and, for YCB, the YCB files' content."""
    src = digest if slot.kind == "ycb" else f"seed {SET_SEED}"
    return hashlib.sha256(json.dumps([RECIPE, dataclasses.astuple(slot), src]).encode()).hexdigest()[:16]


def build_one(slot: Slot, ycb_names: list[str], ycb: Path, folder: Path, key: str) -> dict:
    """A slot's mesh from its first source that reaches the target (watertight if it was): a thin YCB tool whose
    two sides would meet when decimated gives its slot to the next object."""
    from ffcgs_jax.geometry import mesh_io

    t0 = time.perf_counter()
    skipped = []
    for attempt in range(TRIES):
        name, src = source_mesh(slot, attempt, ycb_names, ycb)
        got = resize(src, slot.target)
        if got is not None:
            break
        skipped.append(name)
    else:
        raise FfcgsError(f"slot {slot.index}: no source reached {slot.target} faces (tried {', '.join(skipped)})")
    mesh, tol = got
    mesh = turned(mesh, slot.angle)
    path = folder / f"{slot.index:03d}_{slot.kind}_{name}.ply"
    files.atomic_write(path, lambda f: mesh.export(f, file_type="ply"))
    loaded = mesh_io.load_mesh(path)  # what a run will see: float32 vertices, merged
    return {"slot": slot.index, "file": path.name, "name": name, "kind": slot.kind, "target": slot.target,
            "faces": len(loaded.faces), "source_faces": len(src.faces), "skipped": skipped,
            "watertight": bool(loaded.is_watertight), "source_watertight": bool(src.is_watertight),
            "tol_mm": 1e3 * tol, "extent_cm": round(100 * float(np.ptp(loaded.vertices, axis=0).max()), 2),
            "sha256": mesh_io.mesh_sha256(loaded), "key": key, "build_s": round(time.perf_counter() - t0, 3)}


def build(folder: Path, ycb: Path, wanted: list[int] | None = None, rebuild: bool = False,
          log=lambda line: None) -> dict:
    """The object set in `folder` (the slots `wanted`, default all): built where missing or stale. Returns the
    manifest {"recipe", "ycb", "objects": {slot: entry}} with the entries of the wanted slots."""
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "manifest.json"
    try:
        manifest = json.loads(path.read_text()) if path.is_file() else {}
    except ValueError:  # a manifest cut short (a killed build): rebuild what it named
        manifest = {}
    entries = manifest.get("objects", {}) if manifest.get("recipe") == RECIPE else {}
    chosen = [s for s in slots() if wanted is None or s.index in wanted]
    names = sorted(f.stem for f in ycb.glob("*.stl")) if ycb.is_dir() else []
    if not names:  # the cache alone will do when it holds everything asked for under this recipe
        have = [entries.get(str(s.index)) for s in chosen]
        if not rebuild and all(e and (folder / e["file"]).is_file() for e in have):
            return {"recipe": RECIPE, "ycb": manifest.get("ycb"), "objects": {str(e["slot"]): e for e in have}}
        raise FfcgsError(f"no YCB meshes in {ycb} to build the object set from: give --ycb DIR or set FFCGS_YCB")
    digest = ycb_digest(ycb, names)
    out = {}
    for slot in chosen:
        key, old = slot_key(slot, digest), entries.get(str(slot.index))
        if not rebuild and old and old["key"] == key and (folder / old["file"]).is_file():
            out[str(slot.index)] = old
            continue
        e = build_one(slot, names, ycb, folder, key)
        if old and old["file"] != e["file"] and (folder / old["file"]).is_file():
            (folder / old["file"]).unlink()
        out[str(slot.index)] = entries[str(slot.index)] = e
        log(f"built {e['file']}: {e['faces']} faces (target {e['target']}, source {e['source_faces']}"
            f"{', skipped ' + ', '.join(e['skipped']) if e['skipped'] else ''}) in {e['build_s']:.1f} s")
        files.write_text(path, json.dumps({"recipe": RECIPE, "ycb": str(ycb), "objects": entries}, indent=1))
    return {"recipe": RECIPE, "ycb": str(ycb), "objects": out}


def check_set(objects: dict, warmup_sha: str | None = None) -> list[str]:
    """What is wrong with a built set: a face count off its target, a watertight source that lost it, two
    meshes (or one and the warm-up) with the same vertices."""
    bad = []
    for e in objects.values():
        if abs(e["faces"] / e["target"] - 1) > HIT:
            bad.append(f"{e['file']}: {e['faces']} faces, target {e['target']}")
        if e["source_watertight"] and not e["watertight"]:
            bad.append(f"{e['file']}: not watertight, its source was")
    shas = [e["sha256"] for e in objects.values()] + ([warmup_sha] if warmup_sha else [])
    if len(set(shas)) < len(shas):
        bad.append("two meshes share their vertices")
    return bad


def histogram(faces) -> list[tuple[str, int]]:
    """Counts per bin of BINS (the first takes the few a little under 1,000, the last those a little over 200,000)."""
    edges = [0, *BINS[1:-1], np.inf]
    labels = [f"{a // 1000}k-{b // 1000}k" for a, b in zip(BINS[:-1], BINS[1:])]
    return [(label, int(sum(a <= f < b for f in faces))) for label, a, b in zip(labels, edges[:-1], edges[1:])]


def set_lines(objects: dict) -> list[str]:
    es = list(objects.values())
    kinds = {k: sum(e["kind"] == k for e in es) for k in ("ycb", "complex", "simple")}
    return [f"object set: {len(es)} meshes, {min(e['faces'] for e in es)} to {max(e['faces'] for e in es)} faces; "
            f"YCB {kinds['ycb']} ({len({e['name'] for e in es if e['kind'] == 'ycb'})} objects), complex "
            f"{kinds['complex']}, simple {kinds['simple']}; {sum(e['watertight'] for e in es)} watertight; "
            f"decimation tolerance worst {max(e['tol_mm'] for e in es):.2f} mm",
            "faces: " + ", ".join(f"{label} {n}" for label, n in histogram([e["faces"] for e in es]))]


# ------------------------------------------------------------------------------------------------------ the run


class Compiles:
    """JAX's compile events since the listener was registered: backend compiles (cache loads among them), cache
    hits, traces, and which functions compiled."""

    def __init__(self):
        import jax

        self.backend, self.hits, self.traces, self.seconds, self.names = 0, 0, 0, 0.0, []
        jax.monitoring.register_event_duration_secs_listener(self._duration)
        jax.monitoring.register_event_listener(self._event)

    def _duration(self, event: str, duration: float, **kw):
        if event == BACKEND_COMPILE:
            self.backend += 1
            self.seconds += duration
            self.names.append(str(kw.get("fun_name", "?")))
        elif event == TRACE:
            self.traces += 1

    def _event(self, event: str, **kw):
        if event == CACHE_HIT:
            self.hits += 1

    def mark(self) -> tuple:
        return self.backend, self.hits, self.traces, self.seconds, len(self.names)

    def since(self, mark: tuple) -> dict:
        b, h, t, s, k = mark
        return {"executables": (self.backend - b) - (self.hits - h), "cache_loads": self.hits - h,
                "traces": self.traces - t, "backend_compile_s": self.seconds - s, "compiled": self.names[k:]}


def row(name: str, entry: dict, load_s: float, whole_s: float, gs, compiles: dict) -> dict:
    n_valid = int(np.asarray(gs["valid"]).sum())
    return {"object": name, "file": entry.get("file"), "kind": entry.get("kind"), "source": entry.get("name"),
            "target": entry.get("target"), "faces": entry.get("faces"),
            "load_s": load_s, "whole_s": whole_s, "synthesize_s": whole_s - load_s,
            "compile_s": float(gs["compile_s"]), "sdf_s": float(gs["sdf_s"]), "device_s": float(gs["synthesis_s"]),
            "evaluation_s": float(gs["evaluation_s"]), "valid": n_valid, "n": int(np.asarray(gs["valid"]).size),
            **compiles}


def loop(hand, cfg, items, counter: Compiles, log) -> list[dict]:
    """`items` (name, path, entry): each loaded, synthesised and ranked in turn."""
    import ffcgs_jax as fj

    rows = []
    for name, path, entry in items:
        mark = counter.mark()
        t0 = time.perf_counter()
        mesh = fj.load_mesh(path)
        t1 = time.perf_counter()
        gs = fj.synthesize(hand, mesh, cfg, name)
        gs.order()
        rows.append(row(name, entry, t1 - t0, time.perf_counter() - t0, gs, counter.since(mark)))
        log(progress(rows[-1]))
    return rows


def iterate(hand, cfg, items, counter: Compiles, log, prefetch: int | None = None) -> list[dict]:
    """The same through `fj.synthesize_many` given the mesh files: it loads and prepares the next objects while the
    current one synthesises, so an object's time runs from the previous GraspSet to its own, ranked, and its load
    time is not its own (reported as 0)."""
    import ffcgs_jax as fj

    rows = []
    mark, t0 = counter.mark(), time.perf_counter()
    extra = {} if prefetch is None else {"prefetch": prefetch}
    stream = fj.synthesize_many(hand, [str(path) for _, path, _ in items], cfg, **extra)
    for (name, _, entry), result in zip(items, stream):
        if result.error is not None:
            raise FfcgsError(f"{name}: {result.error}")
        result.grasps.order()
        t1 = time.perf_counter()
        rows.append(row(name, entry, 0.0, t1 - t0, result.grasps, counter.since(mark)))
        log(progress(rows[-1]))
        mark, t0 = counter.mark(), t1
    if len(rows) != len(items):
        raise FfcgsError(f"fj.synthesize_many yielded {len(rows)} results for {len(items)} meshes")
    return rows


def progress(r: dict) -> str:
    return (f"{r['object']}: {r['faces']} faces, {r['whole_s']:.2f} s (load {r['load_s']:.2f}, compile "
            f"{r['compile_s']:.1f}, {r['executables']} executables), {r['valid']}/{r['n']} valid")


def machine() -> dict:
    import jax

    dev = jax.local_devices()[0]
    return {"backend": jax.default_backend(), "device": dev.device_kind, "cpus": os.cpu_count(),
            "jax": jax.__version__, "python": platform.python_version(), "date": time.strftime("%Y-%m-%d")}


def selected(args, manifest: dict) -> list[tuple[str, Path, dict]]:
    objs = manifest["objects"]
    items = [(Path(e["file"]).stem, args.meshes / e["file"], e)
             for e in (objs[str(i)] for i in run_order([int(i) for i in objs]))]
    return items[:args.limit] if args.limit else items


def wanted(args) -> list[int] | None:
    return list(QUICK) if args.quick else None


def run(args, log) -> dict:
    import ffcgs_jax as fj
    from ffcgs_jax.geometry import mesh_io
    from ffcgs_jax.synthesis.grasp import for_hand

    t0 = time.perf_counter()
    manifest = build(args.meshes, args.ycb, wanted(args), args.rebuild, log)
    build_s = time.perf_counter() - t0
    warm_mesh = mesh_io.load_mesh(WARMUP)
    bad = check_set(manifest["objects"], mesh_io.mesh_sha256(warm_mesh))
    if bad:
        raise FfcgsError("the object set is not as the recipe says: " + "; ".join(bad[:5]))
    items = selected(args, manifest)
    cfg = config(args)
    counter = Compiles()
    mark, t0 = counter.mark(), time.perf_counter()
    hand = fj.load_hand(args.hand)
    hand_load = {"hand_s": time.perf_counter() - t0, **counter.since(mark)}
    mode = "iterator" if args.iterator else "loop"
    go = functools.partial(iterate, prefetch=args.prefetch) if args.iterator else loop
    log(f"warm-up ({WARMUP}, the process's first compile) ...")
    warm = go(hand, cfg, [(WARMUP, WARMUP, {"file": None, "kind": "builtin", "faces": len(warm_mesh.faces)})],
              counter, log)[0]
    t1 = time.perf_counter()
    rows = go(hand, cfg, items, counter, log)
    wall = time.perf_counter() - t1
    defaults = args.hand == "svh" and all(getattr(args, k) is None for k in ("n", "iters", "sampler", "seed"))
    return {"command": "python " + " ".join([PROG, *sys.argv[1:]]), "machine": machine(), "mode": mode,
            "config": {"hand": args.hand, "n": cfg.n, "sampler": for_hand(cfg, hand).sampler,
                       "iters": cfg.optim.iters, "seed": cfg.seed, "defaults": defaults},
            "set": {"folder": str(args.meshes), "recipe": RECIPE, "count": len(items), "of": COUNT,
                    "build_s": build_s, "lines": set_lines({str(i): e for i, (_, _, e) in enumerate(items)})},
            "hand_load": hand_load, "warmup": warm, "rows": rows, "wall_s": wall, "summary": summary(warm, rows, wall)}


def summary(warm: dict, rows: list[dict], wall: float) -> dict:
    whole = [r["whole_s"] for r in rows]
    worst = max(rows, key=lambda r: r["whole_s"]) if rows else None
    compiled = [n for r in rows for n in r["compiled"]]
    return {"objects": len(rows), "total_s": wall, "sum_whole_s": sum(whole),
            "median_s": statistics.median(whole) if rows else None, "worst_s": worst["whole_s"] if rows else None,
            "worst_object": worst["object"] if rows else None,
            "compile_s": sum(r["compile_s"] for r in rows), "executables": sum(r["executables"] for r in rows),
            "objects_compiling": sum(r["executables"] > 0 for r in rows),
            "functions_compiled": {n: compiled.count(n) for n in dict.fromkeys(compiled)},
            "valid": sum(r["valid"] for r in rows), "grasps": sum(r["n"] for r in rows),
            "first_compile_s": warm["compile_s"], "first_call_s": warm["whole_s"],
            "first_executables": warm["executables"]}


def target_lines(report: dict) -> list[str]:
    s, m, c = report["summary"], report["machine"], report["config"]
    full = report["set"]["count"] == COUNT and c["defaults"]
    why = "" if full else (f" ({report['set']['count']} of {COUNT} objects"
                           f"{'' if c['defaults'] else ', not the default config'})")
    total_max, first_max = TARGETS["gpu" if m["backend"] == "gpu" else "cpu"]
    where = "one H100" if m["backend"] == "gpu" else "the 2-core CPU"
    if m["backend"] == "gpu" and "H100" not in m["device"]:
        why = why or f" (on {m['device']}, not the target's H100)"
    elif m["backend"] == "cpu" and m["cpus"] != 2:
        why = why or f" (on {m['cpus']} cores, not the target's 2)"

    def verdict(ok: bool) -> str:
        return ("met" if ok else "missed") if not why else "not judged" + why

    lines = [f"target, {where}: {COUNT} objects in <= {total_max:.0f} s after the first compile: "
             f"{s['total_s']:.1f} s, {verdict(s['total_s'] <= total_max)}"]
    if first_max is not None:
        lines.append(f"target, {where}: the first compile <= {first_max:.0f} s: {s['first_compile_s']:.1f} s, "
                     f"{verdict(s['first_compile_s'] <= first_max)}")
    lines.append("target: quality unchanged on the scoreboard: not measured here (bench/quality.py)")
    return lines


def table(report: dict) -> str:
    s, m, c, w = report["summary"], report["machine"], report["config"], report["warmup"]
    h = report.get("hand_load")
    lines = [f"diverse objects · {m['device']} ({m['backend']}, {m['cpus']} CPUs, JAX {m['jax']}) · "
             f"{report['mode']} · hand {c['hand']} · n {c['n']} · sampler {c['sampler']} · {c['iters']} steps · "
             f"`{report['command']}`",
             "", *report["set"]["lines"], "",
             f"warm-up ({w['object']}, {w['faces']} faces): {w['whole_s']:.1f} s, compile {w['compile_s']:.1f} s, "
             f"{w['executables']} executables"
             + (f" (loading the hand before it: {h['hand_s']:.1f} s, {h['executables']} executables)" if h else ""),
             "",
             "| object | faces | source | load s | whole s | compile s | executables | valid |",
             "|---|---|---|---|---|---|---|---|"]
    for r in report["rows"]:
        lines.append(f"| {r['object']} | {r['faces']} | {r['kind']} | {r['load_s']:.3f} | {r['whole_s']:.3f} | "
                     f"{r['compile_s']:.2f} | {r['executables']} | {r['valid']}/{r['n']} |")
    if not report["rows"]:
        return "\n".join(lines) + "\n"
    lines += ["", f"total after the first compile: {s['total_s']:.2f} s for {s['objects']} objects "
              f"(median {s['median_s']:.3f} s, worst {s['worst_s']:.3f} s: {s['worst_object']})",
              f"compile after the warm-up: {s['compile_s']:.1f} s, {s['executables']} executables on "
              f"{s['objects_compiling']} of {s['objects']} objects"
              + (": " + ", ".join(f"{k} ×{v}" for k, v in s["functions_compiled"].items())
                 if s["functions_compiled"] else ""),
              f"valid grasps: {s['valid']} of {s['grasps']}", "", *target_lines(report)]
    return "\n".join(lines) + "\n"


def compare(args, log) -> dict:
    """Each mode in a process of its own, so each pays its own first compile and sees every object as new."""
    reports = {}
    with tempfile.TemporaryDirectory() as tmp:
        for mode in ("loop", "iterator"):
            out = Path(tmp) / f"{mode}.json"
            cmd = [sys.executable, __file__, "--meshes", str(args.meshes), "--ycb", str(args.ycb), "--hand",
                   args.hand, "--out", str(out)]
            for flag in ("n", "iters", "sampler", "seed"):
                if getattr(args, flag) is not None:
                    cmd += [f"--{flag}", str(getattr(args, flag))]
            cmd += ["--quick"] * args.quick + (["--limit", str(args.limit)] if args.limit else [])
            cmd += ["--iterator"] if mode == "iterator" else []
            cmd += ["--prefetch", str(args.prefetch)] if mode == "iterator" and args.prefetch is not None else []
            log(f"{mode}: {' '.join(cmd[1:])}")
            if subprocess.run(cmd).returncode != 0:
                raise FfcgsError(f"the {mode} run failed")
            reports[mode] = json.loads(out.read_text())
    return reports


def main(argv=None) -> int:
    args = parse_args(argv)

    def log(line: str):
        print(line, file=sys.stderr, flush=True)

    try:
        if args.build_only:
            manifest = build(args.meshes, args.ycb, wanted(args), args.rebuild, log)
            bad = check_set(manifest["objects"])
            print("\n".join(set_lines(manifest["objects"]) + [f"in {args.meshes}"] + [f"problem: {b}" for b in bad]))
            return 1 if bad else 0
        if args.compare:
            reports = compare(args, log)
            print("| mode | total after the first compile (s) | median (s) | worst (s) | first compile (s) | "
                  "executables after it |\n|---|---|---|---|---|---|")
            for mode, rep in reports.items():
                s = rep["summary"]
                print(f"| {mode} | {s['total_s']:.2f} | {s['median_s']:.3f} | {s['worst_s']:.3f} | "
                      f"{s['first_compile_s']:.1f} | {s['executables']} |")
            report = {"command": "python " + " ".join([PROG, *sys.argv[1:]]), "modes": reports}
        else:
            report = run(args, log)
            print(table(report), end="")
    except (FfcgsError, OSError) as e:  # a bad source, an unwritable --meshes: one line, no traceback
        print(f"{PROG}: error: {e}", file=sys.stderr)
        return 2
    if args.out:
        files.write_text(args.out, json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
