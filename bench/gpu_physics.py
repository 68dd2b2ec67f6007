"""The GPU physics engine (`physics.worlds` on MuJoCo Warp) beside the CPU backend, in one run (issue 43).

    python bench/gpu_physics.py                                   # one H100 host: every part, about 7 minutes
    python bench/gpu_physics.py --parts 2 --objects 64 --out gpu.json
    python bench/gpu_physics.py --smoke                           # a tiny run on a CPU (Warp's CPU device)

Objects: complex procedural shapes (`procedural.complex_shape`, seed 2000: the family no build trains on), each part
its own; candidates from `fj.synthesize` (all of them labelled, valid or not, as a labelled build does). Every
timed physics call starts with an empty convex-parts cache (a fresh `FFCGS_CACHE_DIR`), so geometry is built anew.
A warm-up first (its own line): the synthesis compiles, Warp's kernels load and the engines start.

1. world-steps/s: `runner.evaluate_many` on b objects x `--grasps`, the engines' `worlds.Stats`: busy = world-steps
   of running programmes, stepped = every stepped world (free ones too), over the seconds from launch to status
   read (GPU s). Grasp-steps: each grasp's full programme (closing + lift + shake; closing + six pushes;
   DexGraspBench's squeeze + six pushes), the steps the CPU would take without early stops: a like-for-like rate.
2. labelled grasps/s, end to end (geometry included): each protocol alone and all together, N objects on the GPU
   engine; the CPU backend (all cores) on the first `--cpu-objects` and scaled to N; same outcome = the share of
   those objects' grasps whose pass-every-protocol verdict both backends give alike.
3. a 32-grasp check of a new object, part by part: geometry (collision parts, scenes, plans: `geometry_s`), upload
   (placing worlds, objects and engine start: `place_s + setup_s`), simulation (`step_s`), copy back (`read_s`),
   the whole call; on the CPU, simulation is the call less geometry. Median and worst over the objects.
4. new object to a physics-checked first grasp: `fj.synthesize` (`--first-n` candidates) then
   `fj.validate(..., need=1)`, the whole as a user waits; backend auto (what it chose is printed) and cpu; the
   first object of each is apart (compiles, engine start).
"""

import argparse
import contextlib
import dataclasses
import datetime
import importlib.metadata
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

PROG = "gpu_physics.py"
COMPLEX_SEED = 2000  # bench/quality.py's unseen complex family
ALL3 = "lift-shake,six-dir,dexgraspbench"
# sizes: an H100 host in about 7 minutes; --smoke: a 2-core CPU with Warp on its CPU device in under 3
DEFAULTS = dict(batches="1,8,32", grasps=128, objects=32, cpu_objects=2, latency_objects=8, latency_grasps=32,
                first_objects=8, first_n=32, protocols=ALL3, first_protocols="lift-shake,six-dir")
SMOKE = dict(batches="1", grasps=1, objects=1, cpu_objects=1, latency_objects=1, latency_grasps=1, first_objects=1,
             first_n=1, protocols="lift-shake,six-dir", first_protocols="lift-shake,six-dir")
# --smoke's physics: short phases (a Warp world-step on a CPU costs about a millisecond) and coarse geometry
SHORT = dict(sim_friction=1.0, close_time=0.2, settle_time=0.1, lift_height=0.03, shake_cycles=1, shake_amplitude=0.02,
             push_time=0.2, voxel_cells=32, max_hulls=8)


class Parser(argparse.ArgumentParser):
    def error(self, message):
        sys.stderr.write(f"{PROG}: error: {message} (see {PROG} --help)\n")
        sys.exit(2)


def parser() -> Parser:
    p = Parser(prog=PROG, description=__doc__.split("\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter,
               epilog="\n".join(__doc__.split("\n")[1:]))
    p.add_argument("--parts", default="1,2,3,4", help="comma list of 1 (world-steps/s), 2 (grasps/s), "
                   "3 (a new object's check, part by part), 4 (new object to a first grasp)")
    p.add_argument("--batches", help=f"part 1: objects per batch, comma list (default {DEFAULTS['batches']})")
    p.add_argument("--grasps", type=int, help=f"parts 1-2: candidates per object (default {DEFAULTS['grasps']})")
    p.add_argument("--objects", type=int, help=f"part 2: objects on the GPU (default {DEFAULTS['objects']})")
    p.add_argument("--cpu-objects", type=int, help=f"part 2: of those on the CPU (default {DEFAULTS['cpu_objects']})")
    p.add_argument("--latency-objects", type=int, help=f"part 3: objects (default {DEFAULTS['latency_objects']})")
    p.add_argument("--latency-grasps", type=int,
                   help=f"part 3: the synthesis's best grasps checked (default {DEFAULTS['latency_grasps']})")
    p.add_argument("--first-objects", type=int, help=f"part 4: objects counted (default {DEFAULTS['first_objects']})")
    p.add_argument("--first-n", type=int, help=f"part 4: candidates synthesised (default {DEFAULTS['first_n']})")
    p.add_argument("--protocols", help=f"parts 1-3, comma list (default {DEFAULTS['protocols']})")
    p.add_argument("--first-protocols", help=f"part 4, comma list (default {DEFAULTS['first_protocols']})")
    p.add_argument("--seed", type=int, default=COMPLEX_SEED, help="the complex shapes' seed")
    p.add_argument("--workers", type=int, default=0, help="CPU backend threads (0: all cores)")
    p.add_argument("--gpu", choices=("auto", "on", "off"), default="auto",
                   help="the GPU engine: auto = on a CUDA device (and with --smoke on Warp's CPU device), on = "
                        "wherever Warp runs, off = the CPU backend only")
    p.add_argument("--smoke", action="store_true", help="tiny sizes and short phases (tests; a CPU machine)")
    p.add_argument("--out", metavar="FILE", help="also write the tables (after every part): .json, else markdown")
    return p


def parse_args(argv=None) -> argparse.Namespace:
    from ffcgs_jax.physics.config import ALL_PROTOCOLS

    p = parser()
    a = p.parse_args(argv)
    for k, v in (SMOKE if a.smoke else DEFAULTS).items():
        if getattr(a, k) is None:
            setattr(a, k, v)
    try:
        a.parts = sorted({int(x) for x in a.parts.split(",")})
        a.batches = [int(x) for x in a.batches.split(",")]
    except ValueError:
        p.error("--parts and --batches: expected comma lists of integers")
    if not a.parts or not set(a.parts) <= {1, 2, 3, 4}:
        p.error(f"--parts: expected a comma list of 1, 2, 3, 4, got {','.join(map(str, a.parts))}")
    for k in ("grasps", "objects", "cpu_objects", "latency_objects", "latency_grasps", "first_objects", "first_n"):
        if not 1 <= getattr(a, k) <= 100_000:
            p.error(f"--{k.replace('_', '-')} must be between 1 and 100000, got {getattr(a, k)}")
    if min(a.batches) < 1:
        p.error("--batches: every batch needs at least one object")
    if a.cpu_objects > a.objects:
        p.error(f"--cpu-objects ({a.cpu_objects}) must not exceed --objects ({a.objects})")
    if a.latency_grasps > a.grasps:
        p.error(f"--latency-grasps ({a.latency_grasps}) must not exceed --grasps ({a.grasps}): they are its best")
    a.protocols, a.first_protocols = a.protocols.split(","), a.first_protocols.split(",")
    bad = [x for x in a.protocols + a.first_protocols if x not in ALL_PROTOCOLS]
    if bad:
        p.error(f"unknown protocol {bad[0]!r}; protocols: {', '.join(ALL_PROTOCOLS)}")
    if a.workers < 0:
        p.error("--workers must be >= 0")
    return a


# -----------------------------------------------------------------------------------------------------------------
# the machine


def versions() -> dict:
    out = {}
    for name in ("mujoco", "mujoco-warp", "warp-lang", "jax"):
        try:
            out[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            out[name] = "missing"
    return out


def gpu_names() -> str:
    if shutil.which("nvidia-smi") is None:
        return "no GPU (no nvidia-smi)"
    try:
        r = subprocess.run(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"], capture_output=True,
                           text=True, timeout=30)
    except (OSError, subprocess.TimeoutExpired) as e:
        return f"nvidia-smi failed ({e})"
    names = [n.strip() for n in r.stdout.splitlines() if n.strip()]
    return " + ".join(f"{names.count(n)} x {n}" for n in dict.fromkeys(names)) if names else "no GPU listed"


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine(engine_device: str | None) -> dict:
    import jax

    return {"gpu": gpu_names(), "cores": os.cpu_count(), "cpu": cpu_model(), "versions": versions(),
            "jax_backend": jax.default_backend(), "engine_device": engine_device or "none",
            "date": datetime.date.today().isoformat()}


def header(m: dict) -> str:
    v = m["versions"]
    return (f"machine: {m['gpu']} · {m['cores']} cores ({m['cpu']}) · GPU engine on "
            f"{m['engine_device']} · mujoco {v['mujoco']}, mujoco-warp {v['mujoco-warp']}, warp-lang "
            f"{v['warp-lang']}, jax {v['jax']} ({m['jax_backend']}) · {m['date']}")


def engine_device(choice: str, smoke: bool) -> tuple[str | None, str | None]:
    """Where the GPU engine runs (a Warp device name) or None, and why not."""
    from ffcgs_jax.physics import backend_warp

    if choice == "off":
        return None, "--gpu off"
    why = backend_warp.unavailable()
    if why:
        return None, why
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING  # no module-load lines among the tables
    cuda = backend_warp.no_cuda() is None
    if not cuda and choice == "auto" and not smoke:
        return None, "no CUDA device (--gpu on runs the engine on Warp's CPU device: slow)"
    return str(wp.get_device("cuda:0" if cuda else "cpu")), None


# -----------------------------------------------------------------------------------------------------------------
# measuring


@contextlib.contextmanager
def fresh_cache():
    """An empty convex-parts cache for the block: every object's collision geometry is built anew."""
    old = os.environ.get("FFCGS_CACHE_DIR")
    with tempfile.TemporaryDirectory(prefix="ffcgs-gpu-bench-") as d:
        os.environ["FFCGS_CACHE_DIR"] = d
        try:
            yield
        finally:
            if old is None:
                os.environ.pop("FFCGS_CACHE_DIR", None)
            else:
                os.environ["FFCGS_CACHE_DIR"] = old


def engines_of(stats: dict) -> dict[str, dict]:
    """The engines' `worlds.Stats` in a run's stats, by kind, as dicts."""
    return {k: dataclasses.asdict(v) for k, v in stats.items() if dataclasses.is_dataclass(v)}


def total(engines: dict[str, dict]) -> dict:
    keys = ("steps", "world_steps", "busy_steps", "objects", "place_s", "step_s", "read_s", "setup_s")
    return {k: sum(e[k] for e in engines.values()) for k in keys}


def nominal_steps(protocol: str, cfg, nu: int) -> int:
    """Steps of one grasp's whole programme under `protocol` (no early stop)."""
    from ffcgs_jax.physics import protocols as P
    from ffcgs_jax.physics.backend import Batch

    z = np.zeros((1, nu))
    one = Batch(np.zeros((1, 3)), np.array([[1.0, 0, 0, 0]]), z, z, z)
    if P.get(protocol).kind == "dexgraspbench":
        c = P.get(protocol).settings(cfg)
        return (sum(s.n for s in P.grasp_and_squeeze(one, c))
                + sum(P.bench_push(one, c, d, 1.0).n for d in P.DIRECTIONS))
    close = sum(s.n for s in P.closing(one, cfg))
    if protocol == "lift-shake":
        return close + sum(s.n for s in P.lift_shake(one, cfg))
    return close + sum(P.push(one, cfg, d, 1.0).n for d in P.DIRECTIONS)


class Bench:
    """The run's hand, config, objects and report; each part adds its rows and markdown."""

    def __init__(self, args):
        import ffcgs_jax as fj
        from ffcgs_jax.physics.config import PhysicsConfig

        self.args, self.fj = args, fj
        self.hand = fj.load_hand("svh")
        self.spec = self.hand.spec
        self.cfg = PhysicsConfig(workers=args.workers, **(SHORT if args.smoke else {}))
        self.device, self.no_gpu = engine_device(args.gpu, args.smoke)
        self.cores = args.workers or os.cpu_count() or 1
        self.report = {"command": "python bench/gpu_physics.py " + " ".join(sys.argv[1:]),
                       "machine": machine(self.device), "no_gpu": self.no_gpu, "config": dataclasses.asdict(self.cfg),
                       "args": {k: v for k, v in vars(args).items()}, "parts": {}}
        self.pool: list[tuple[str, object, dict]] = []  # (name, mesh, candidates)
        self.next_index = 0

    # objects --------------------------------------------------------------------------------------------------

    def shapes(self, count: int) -> list[tuple[str, object]]:
        """`count` complex shapes not used before in this run."""
        from ffcgs_jax.geometry import procedural

        out = [procedural.complex_shape(self.args.seed, self.next_index + i) for i in range(count)]
        self.next_index += count
        return out

    def candidates(self, name: str, mesh, n: int) -> dict:
        gs = self.fj.synthesize(self.hand, mesh, self.fj.GraspConfig(n=n), name)
        return {k: np.asarray(gs[k]) for k in ("wrist_pose", "q", "squeeze_dir", "valid")} | {
            "compile_s": float(gs["compile_s"])}

    def prepare_pool(self, count: int) -> None:
        t0 = time.perf_counter()
        for name, mesh in self.shapes(count):
            self.pool.append((name, mesh, self.candidates(name, mesh, self.args.grasps)))
        log(f"{count} objects and their {self.args.grasps} candidates each: {time.perf_counter() - t0:.1f} s")

    def items(self, objs, k: int | None = None) -> list:
        from ffcgs_jax.physics import runner

        k = k or self.args.grasps
        return [runner.Item(mesh, c["wrist_pose"][:k], c["q"][:k], c["squeeze_dir"][:k]) for _, mesh, c in objs]

    def evaluate(self, items, protocols, backend: str) -> tuple[list, dict, float]:
        """One `evaluate_many` on a fresh geometry cache: results, stats, wall seconds."""
        from ffcgs_jax.physics import runner

        stats: dict = {}
        with fresh_cache():
            t0 = time.perf_counter()
            res = runner.evaluate_many(self.spec, items, self.cfg, protocols, backend=backend, stats=stats)
            wall = time.perf_counter() - t0
        if stats.get("backend") != backend:
            log(f"note: asked for {backend}, the run went to {stats.get('backend')}")
        return res, stats, wall

    def nominal(self, protocols) -> int:
        return sum(nominal_steps(p, self.cfg, len(self.spec.channel_names)) for p in protocols)

    # warm-up --------------------------------------------------------------------------------------------------

    def warm_up(self) -> None:
        from ffcgs_jax.geometry import procedural

        a = self.args
        name, mesh = procedural.complex_shape(a.seed + 1, 0)  # another seed: no part's object
        t0 = time.perf_counter()
        c = self.candidates(name, mesh, a.grasps)
        synth = time.perf_counter() - t0
        obj = [(name, mesh, c)]
        k = min(8, a.grasps)
        row = {"synthesis_s": synth, "synthesis_compile_s": c["compile_s"]}
        if self.device:
            _, st, row["gpu_s"] = self.evaluate(self.items(obj, k), a.protocols, "warp")
            row["gpu_setup_s"] = total(engines_of(st))["setup_s"]
        _, _, row["cpu_s"] = self.evaluate(self.items(obj, k), a.protocols, "cpu")
        self.report["warmup"] = row
        gpu = (f"; GPU engine {row['gpu_s']:.1f} s (engine start {row['gpu_setup_s']:.1f} s)" if self.device
               else "")
        out(f"first calls (not counted anywhere below): synthesis of {a.grasps} candidates {synth:.1f} s (compile "
            f"{c['compile_s']:.1f} s){gpu}; CPU backend {row['cpu_s']:.1f} s; {k} grasps of {name}, "
            f"{'+'.join(a.protocols)}\n")

    # part 1 ---------------------------------------------------------------------------------------------------

    def part1(self) -> None:
        from ffcgs_jax.physics import world_model

        a, rows = self.args, []
        for b in a.batches if self.device else []:
            _, st, wall = self.evaluate(self.items(self.pool[:b]), a.protocols, "warp")
            eng = engines_of(st)
            for kind, e in [*eng.items(), *([("all", total(eng))] if len(eng) > 1 else [])]:
                prots = [p for p in a.protocols if kind == "all" or world_model.protocol_kind(p) == kind]
                rows.append(dict(backend=f"warp ({self.device})", batch=b, grasps=a.grasps, engine=kind, **e,
                                 nominal=b * a.grasps * self.nominal(prots), wall_s=wall,
                                 geometry_s=st["geometry_s"]))
            log(f"part 1: {b} x {a.grasps} on the GPU engine: {wall:.1f} s")
        _, st, wall = self.evaluate(self.items(self.pool[:1]), a.protocols, "cpu")
        rows.append(dict(backend=f"cpu ({self.cores} threads)", batch=1, grasps=a.grasps, engine="-",
                         step_s=wall - st["geometry_s"], nominal=a.grasps * self.nominal(a.protocols), wall_s=wall,
                         geometry_s=st["geometry_s"]))
        log(f"part 1: 1 x {a.grasps} on the CPU: {wall:.1f} s")
        self.add_part(1, rows, table1(rows, a, self.no_gpu))

    # part 2 ---------------------------------------------------------------------------------------------------

    def part2(self) -> None:
        from ffcgs_jax.physics.protocols import result_key

        a, rows = self.args, []
        sets = [[p] for p in a.protocols] + ([a.protocols] if len(a.protocols) > 1 else [])
        objs, sub = self.pool[:a.objects], self.pool[:a.cpu_objects]
        for prots in sets:
            row = {"protocols": "+".join(prots), "objects": a.objects, "cpu_objects": a.cpu_objects,
                   "grasps": a.grasps}
            passed = lambda r: np.logical_and.reduce([r[result_key(p, "success")] for p in prots])  # noqa: E731
            if self.device:
                res, st, wall = self.evaluate(self.items(objs), prots, "warp")
                t = total(engines_of(st))
                row.update(gpu_wall_s=wall, gpu_geometry_s=st["geometry_s"], gpu_step_s=t["step_s"],
                           gpu_setup_s=t["setup_s"], gpu_busy_steps=t["busy_steps"],
                           gpu_gps=a.objects * a.grasps / wall,
                           gpu_pass=float(np.mean(np.concatenate([passed(r) for r in res]))))
                log(f"part 2: {row['protocols']} on the GPU engine, {a.objects} objects: {wall:.1f} s")
            cres, st, wall = self.evaluate(self.items(sub), prots, "cpu")
            row.update(cpu_wall_s=wall, cpu_geometry_s=st["geometry_s"], cpu_gps=a.cpu_objects * a.grasps / wall,
                       cpu_wall_scaled_s=wall * a.objects / a.cpu_objects,
                       cpu_pass=float(np.mean(np.concatenate([passed(r) for r in cres]))))
            if self.device:
                same = np.concatenate([passed(g) == passed(c) for g, c in zip(res, cres)])
                row["same_outcome"] = float(same.mean())
            log(f"part 2: {row['protocols']} on the CPU, {a.cpu_objects} objects: {wall:.1f} s")
            rows.append(row)
        self.add_part(2, rows, table2(rows, self))

    # part 3 ---------------------------------------------------------------------------------------------------

    def part3(self) -> None:
        a = self.args
        objs = [(n, m, self.candidates(n, m, a.grasps)) for n, m in self.shapes(a.latency_objects)]
        rows = []
        for backend in (["warp"] if self.device else []) + ["cpu"]:
            for name, mesh, c in objs:  # each call a fresh cache: every object's geometry is built anew
                _, st, wall = self.evaluate(self.items([(name, mesh.copy(), c)], a.latency_grasps), a.protocols,
                                            backend)
                r = {"backend": backend, "object": name, "geometry": st["geometry_s"], "whole": wall}
                if backend == "warp":
                    t = total(engines_of(st))
                    r.update(upload=t["place_s"] + t["setup_s"], setup=t["setup_s"], simulation=t["step_s"],
                             copy_back=t["read_s"], objects_uploaded=t["objects"],
                             engines=len(engines_of(st)))
                    r["other"] = wall - st["geometry_s"] - r["upload"] - t["step_s"] - t["read_s"]
                else:
                    r["simulation"] = wall - st["geometry_s"]
                    r["other"] = 0.0
                rows.append(r)
                log(f"part 3: {name} on {backend}: {wall:.2f} s")
        self.add_part(3, rows, table3(rows, self))

    # part 4 ---------------------------------------------------------------------------------------------------

    def part4(self) -> None:
        a, fj = self.args, self.fj
        objs = self.shapes(a.first_objects + 1)  # the first: compiles (its n), starts the engine; apart
        gcfg = fj.GraspConfig(n=a.first_n)
        rows = []
        for backend in ("auto", "cpu"):
            pcfg = dataclasses.replace(self.cfg, backend=backend)
            with fresh_cache():
                for i, (name, mesh) in enumerate(objs):
                    mesh = mesh.copy()  # new to every cache keyed by the mesh object
                    t0 = time.perf_counter()
                    gs = fj.synthesize(self.hand, mesh, gcfg, name)
                    t1 = time.perf_counter()
                    checked = fj.validate(self.hand, mesh, gs, pcfg, protocols=a.first_protocols, need=1)
                    t2 = time.perf_counter()
                    first = int(checked.order()[0])
                    rows.append({"backend": backend, "object": name, "first": i == 0, "synthesis": t1 - t0,
                                 "physics": t2 - t1, "whole": t2 - t0, "compile": float(gs["compile_s"]),
                                 "chose": str(checked["physics_backend"]), "valid": int(gs["valid"].sum()),
                                 "tested": int(np.asarray(checked["physics_tested"]).sum()),
                                 "first_passes": bool(checked["physics_passed"][first])})
                    log(f"part 4: {name} with {backend} ({rows[-1]['chose']}): {t2 - t0:.2f} s"
                        f"{' (first: apart)' if i == 0 else ''}")
        self.add_part(4, rows, table4(rows, self))

    def add_part(self, k: int, rows: list[dict], md: str) -> None:
        self.report["parts"][str(k)] = {"rows": rows, "markdown": md}
        out(md)
        self.write()

    def write(self) -> None:
        if not self.args.out:
            return
        from ffcgs_jax.core import files

        if self.args.out.endswith(".json"):
            files.write_text(self.args.out, json.dumps(self.report, indent=1, default=float))
        else:
            files.write_text(self.args.out, markdown(self.report))


# -----------------------------------------------------------------------------------------------------------------
# tables


def _rate(n: float, s: float) -> str:
    return f"{n / s:.3g}" if s > 0 else "-"


def table1(rows: list[dict], a, no_gpu: str | None) -> str:
    lines = [f"### 1. World-steps per second ({'+'.join(a.protocols)}, {a.grasps} grasps per object)", "",
             "| backend | objects x grasps | engine | busy world-steps | stepped world-steps | GPU s | "
             "**busy world-steps/s** | stepped world-steps/s | grasp-steps/s | engine start s | objects uploaded | "
             "wall s |", "|" + "---|" * 12]
    for r in rows:
        if "world_steps" in r:
            gpu = (f"{r['busy_steps']} | {r['world_steps']} | {r['step_s']:.2f} | "
                   f"**{_rate(r['busy_steps'], r['step_s'])}** | {_rate(r['world_steps'], r['step_s'])}")
            tail = f"{r['setup_s']:.2f} | {r['objects']}"
        else:
            gpu, tail = f"- | - | {r['step_s']:.2f} (call less geometry) | - | -", "- | -"
        lines.append(f"| {r['backend']} | {r['batch']} x {r['grasps']} | {r['engine']} | {gpu} | "
                     f"{_rate(r['nominal'], r['step_s'])} | {tail} | {r['wall_s']:.2f} |")
    lines += ["", "GPU s: launch to status read (`Stats.step_s`); busy: world-steps of running programmes, stepped: "
              "of every stepped world; grasp-steps: every grasp's whole programme, as the CPU would step it without "
              "early stops (a like-for-like rate)."]
    short = [r for r in rows if "world_steps" in r and r["engine"] != "all" and r["objects"] < r["batch"]]
    if short:
        lines.append(f"Warning: {len(short)} engine runs uploaded fewer objects than their batch held (an engine "
                     f"took an earlier call's object for a new one).")
    if no_gpu:
        lines.append(f"No GPU engine: {no_gpu}.")
    return "\n".join(lines) + "\n"


def _pct(x: float | None) -> str:
    return "-" if x is None else f"{100 * x:.1f} %"


def table2(rows: list[dict], b: Bench) -> str:
    a = b.args
    lines = [f"### 2. Labelled grasps per second, end to end (geometry included): {a.objects} objects x {a.grasps} "
             f"candidates on the GPU engine, the CPU backend ({b.cores} threads) on {a.cpu_objects} of them, scaled",
             "", "| protocols | GPU wall s | GPU geometry s (threads) | GPU s | **GPU grasps/s** | CPU grasps/s | "
             f"CPU wall for {a.objects} objects (est.) s | GPU / CPU | pass GPU | pass CPU | same outcome |",
             "|" + "---|" * 11]
    for r in rows:
        if "gpu_gps" in r:
            gpu = (f"{r['gpu_wall_s']:.1f} | {r['gpu_geometry_s']:.1f} | {r['gpu_step_s']:.1f} | "
                   f"**{r['gpu_gps']:.1f}**")
            ratio = f"{r['gpu_gps'] / r['cpu_gps']:.1f}x"
        else:
            gpu, ratio = "- | - | - | -", "-"
        lines.append(f"| {r['protocols']} | {gpu} | {r['cpu_gps']:.2f} | {r['cpu_wall_scaled_s']:.1f} | {ratio} | "
                     f"{_pct(r.get('gpu_pass'))} | {_pct(r['cpu_pass'])} | {_pct(r.get('same_outcome'))} |")
    lines += ["", f"pass: the share of candidates passing every protocol of the row; same outcome: of the "
              f"{a.cpu_objects} objects' grasps both backends ran, those with the same verdict."]
    if b.no_gpu:
        lines.append(f"No GPU engine: {b.no_gpu}.")
    return "\n".join(lines) + "\n"


PARTS3 = (("geometry", "geometry"), ("upload", "upload (place + engine start)"),
          ("setup", "of which engine start (and first round)"), ("simulation", "simulation"),
          ("copy_back", "copy back"), ("other", "other"), ("whole", "**whole call**"))


def table3(rows: list[dict], b: Bench) -> str:
    a = b.args
    backends = list(dict.fromkeys(r["backend"] for r in rows))
    head = " | ".join(f"{x} median s | {x} worst s" for x in backends)
    lines = [f"### 3. Checking {a.latency_grasps} grasps of a new object ({'+'.join(a.protocols)}), part by part, "
             f"{a.latency_objects} objects", "", f"| part | {head} |", "|" + "---|" * (1 + 2 * len(backends))]
    for key, label in PARTS3:
        cells = []
        for x in backends:
            v = np.array([r[key] for r in rows if r["backend"] == x and key in r])
            cells += [f"{np.median(v):.3f}", f"{v.max():.3f}"] if len(v) else ["-", "-"]
        lines.append(f"| {label} | {' | '.join(cells)} |")
    lines += ["", "CPU simulation: the call less geometry. Upload, simulation and copy back are the engines' "
              "`Stats` (place_s + setup_s, step_s, read_s) summed over the engines a call used; setup_s holds the "
              "step rounds that captured a graph (kernel loads, graph capture), which step_s leaves out; other = "
              "whole less the parts above."]
    gpu = [r for r in rows if r["backend"] == "warp"]
    if gpu:
        lines.append(f"Engines started per call: {sorted({r['engines'] for r in gpu})}; objects uploaded per call: "
                     f"{sorted({r['objects_uploaded'] for r in gpu})} (the protocols' engines each upload the "
                     f"object; 0 would mean an engine took an earlier call's object for this one).")
    if b.no_gpu:
        lines.append(f"No GPU engine: {b.no_gpu}.")
    return "\n".join(lines) + "\n"


def table4(rows: list[dict], b: Bench) -> str:
    a = b.args
    lines = [f"### 4. New object to a physics-checked first grasp: `fj.synthesize` ({a.first_n} candidates) then "
             f"`fj.validate(..., need=1)`, {'+'.join(a.first_protocols)}, {a.first_objects} objects", "",
             "| backend | synthesis median s | physics median s | **whole median s** | **whole worst s** | "
             "compile in counted calls s | ran on | first grasp passes | first object (apart) s |",
             "|" + "---|" * 9]
    for x in ("auto", "cpu"):
        rs = [r for r in rows if r["backend"] == x and not r["first"]]
        first = [r for r in rows if r["backend"] == x and r["first"]]
        if not rs:
            continue
        med = lambda k: float(np.median([r[k] for r in rs]))  # noqa: E731
        chose = ", ".join(f"{c} {sum(r['chose'] == c for r in rs)}" for c in sorted({r["chose"] for r in rs}))
        lines.append(f"| {x} | {med('synthesis'):.2f} | {med('physics'):.2f} | **{med('whole'):.2f}** | "
                     f"**{max(r['whole'] for r in rs):.2f}** | {sum(r['compile'] for r in rs):.1f} | {chose} | "
                     f"{sum(r['first_passes'] for r in rs)} of {len(rs)} | "
                     f"{first[0]['whole']:.1f} (compile {first[0]['compile']:.1f}) |")
    lines += ["", "Whole: synthesis and validate as a user waits, compile included (the first object pays it and "
              "is apart). Target (issue 43): <= 1.5 s median, <= 3 s worst on one H100 host."]
    return "\n".join(lines) + "\n"


def markdown(report: dict) -> str:
    w = report.get("warmup")
    head = [f"## GPU physics bench · `{report['command']}`", "", header(report["machine"]), ""]
    if w:
        head.append(f"warm-up (apart): synthesis {w['synthesis_s']:.1f} s (compile {w['synthesis_compile_s']:.1f} s)"
                    + (f", GPU engine {w['gpu_s']:.1f} s" if "gpu_s" in w else "") + f", CPU {w['cpu_s']:.1f} s\n")
    return "\n".join(head + [report["parts"][k]["markdown"] for k in sorted(report["parts"])])


def out(text: str) -> None:
    print(text, flush=True)


def log(text: str) -> None:
    print(f"{PROG}: {text}", file=sys.stderr, flush=True)


def main(argv=None) -> int:
    args = parse_args(argv)
    from ffcgs_jax.core.errors import FfcgsError

    t0 = time.perf_counter()
    try:
        import ffcgs_jax as fj

        fj.enable_compilation_cache()  # as the CLI: a second run loads its executables (FFCGS_JAX_CACHE=off: not)
        b = Bench(args)
        out(header(b.report["machine"]) + (f" · {'smoke: short phases' if args.smoke else 'default phases'}"))
        if b.no_gpu:
            out(f"no GPU engine: {b.no_gpu}; the CPU backend only")
        b.warm_up()
        if {1, 2} & set(args.parts):
            b.prepare_pool(max([*(args.batches if 1 in args.parts else []),
                                *([args.objects] if 2 in args.parts else [])]))
        for k in args.parts:
            getattr(b, f"part{k}")()
    except FfcgsError as e:
        print(f"{PROG}: error: {e}", file=sys.stderr)
        return 2
    log(f"done in {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
