"""The data engine's throughput, end to end: objects in, labelled records on disk (`ffcgs dataset build --keep all`).

    python bench/data_engine.py --procedural 48 --complex 16 --per-object 256 --engines ray
    python bench/data_engine.py --procedural 4 --per-object 16 --engines plain ray     # a small CPU run

Each engine builds the same objects into a fresh output (the time from the command's start to the merged file,
Ray's start-up included), after a warm-up build of one other object that fills the persistent compilation cache,
so the table holds no compilation (`--cold` skips the warm-up: then the first object of every worker compiles).
A labelled grasp is one candidate with the outcome of every protocol asked for (record 0 of each object: the
rotated copies, `--rotations`, are not counted). The stages come from the build's timing log: synthesis (SDF and
candidates, on the JAX device), physics (collision geometry and every protocol), write (records to MCAP); "busy"
is their sum over objects against wall x tasks in flight, and the bound is the stage with the largest share.
"""

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

PROG = "bench/data_engine.py"


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n")[0])
    p.add_argument("--procedural", type=int, default=8, help="generated simple shapes")
    p.add_argument("--complex", type=int, default=4, help="generated complex shapes")
    p.add_argument("--objects", default="", help="a mesh folder too (its train split), e.g. shared/objects/ycb")
    p.add_argument("--seed", type=int, default=100, help="the generated shapes' seed (a training seed)")
    p.add_argument("--per-object", type=int, default=64, help="candidates per object")
    p.add_argument("--sampler", default="cvae")
    p.add_argument("--protocols", default="lift-shake,six-dir,dexgraspbench")
    p.add_argument("--engines", nargs="+", default=["ray"], choices=("plain", "ray"))
    p.add_argument("--task-cpus", type=int, default=4)
    p.add_argument("--cpus", type=int, default=0, help="cores the local Ray instance takes (0: all)")
    p.add_argument("--gpus", type=int, default=-1, help="GPUs the local Ray instance takes (-1: all)")
    p.add_argument("--backend", default="auto", help="physics backend (auto: warp where it pays)")
    p.add_argument("--extra", nargs=argparse.REMAINDER, default=[], help="more `ffcgs dataset build` flags")
    p.add_argument("--cold", action="store_true", help="no warm-up build")
    p.add_argument("--keep", default=None, help="keep the outputs in this folder (default: a temporary one)")
    p.add_argument("--json", default=None, help="also write the figures here")
    return p.parse_args(argv)


def build_argv(args, out: Path, engine: str, procedural: int, complex_: int, objects: str, seed: int) -> list[str]:
    argv = [sys.executable, "-m", "ffcgs_jax.cli", "dataset", "build", "--keep", "all", "--rotations", "1",
            "--per-object", str(args.per_object), "--sampler", args.sampler, "--protocols", args.protocols,
            "--procedural", str(procedural), "--complex", str(complex_), "--seed", str(seed),
            "--engine", engine, "--task-cpus", str(args.task_cpus), "--physics.backend", args.backend,
            "--cpus", str(args.cpus), "--gpus", str(args.gpus), "--out", str(out)]
    if objects:
        argv += ["--objects", objects, "--split", "train"]
    return argv + list(args.extra)


def run(argv: list[str]) -> float:
    t0 = time.perf_counter()
    p = subprocess.run(argv, stdout=subprocess.PIPE, stderr=sys.stderr, text=True)
    if p.returncode:
        raise SystemExit(f"{PROG}: the build failed ({p.returncode}): {' '.join(argv[2:])}")
    print(p.stdout.strip().splitlines()[-1], file=sys.stderr)
    return time.perf_counter() - t0


def summarise(engine: str, wall: float, out: Path, tasks: int) -> dict:
    parts = Path(str(out) + ".parts")
    rows = [json.loads(line) for line in (parts / "timing.jsonl").read_text().splitlines()]
    labelled = sum(r["candidates"] for r in rows)
    stages = {k: sum(r.get(f"{k}_s", 0.0) for r in rows) for k in ("synthesis", "physics", "write")}
    busy = sum(stages.values()) / (wall * tasks)
    bound = max(stages, key=stages.get)
    return {"engine": engine, "objects": len(rows), "labelled": labelled, "wall_s": wall,
            "grasps_per_s": labelled / wall, "passed_all": sum(r["passed_all"] for r in rows),
            "valid": sum(r["valid"] for r in rows), "tasks": tasks, "busy": busy, "bound": bound,
            **{f"{k}_s": v for k, v in stages.items()},
            "physics_backends": sorted({r["physics_backend"] for r in rows}),
            "size_mb": out.stat().st_size / 1e6}


def tasks_in_flight(engine: str, args) -> int:
    if engine == "plain":
        return 1
    cores = args.cpus or os.cpu_count() or 1
    return max(1, cores // max(1, min(args.task_cpus, cores // 2)))  # as `engine.task_resources` splits them


def machine(args) -> str:
    import jax

    dev = jax.devices()[0]
    name = getattr(dev, "device_kind", dev.platform)
    used = (f"; the builds took {args.cpus or 'all'} cores and "
            f"{'all' if args.gpus < 0 else args.gpus} GPU(s)")
    return f"{dev.platform} {name} x {jax.device_count()}, {os.cpu_count()} cores{used}"


def table(rows: list[dict]) -> str:
    head = ("| engine | objects | labelled grasps | wall (s) | **grasps/s** | pass all | synthesis (s) | physics (s) | "
            "write (s) | busy | bound |")
    lines = [head, "|" + "---|" * 11]
    for r in rows:
        lines.append(f"| {r['engine']} ({r['tasks']} in flight) | {r['objects']} | {r['labelled']} | "
                     f"{r['wall_s']:.1f} | **{r['grasps_per_s']:.1f}** | {r['passed_all']} | {r['synthesis_s']:.1f} | "
                     f"{r['physics_s']:.1f} | {r['write_s']:.1f} | {r['busy']:.0%} | {r['bound']} |")
    return "\n".join(lines)


def main(argv=None) -> None:
    args = parse_args(argv)
    root = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="ffcgs-engine-"))
    root.mkdir(parents=True, exist_ok=True)
    if not args.cold:  # one object of another seed: compiles what every build below runs
        print(f"{PROG}: warm-up build (compiles)", file=sys.stderr)
        warm = run(build_argv(args, root / "warm.mcap", "plain", 1, 0, "", args.seed + 1))
        print(f"{PROG}: warm-up {warm:.1f} s", file=sys.stderr)
    rows = []
    for engine in args.engines:
        out = root / f"{engine}.mcap"
        for stale in (out, Path(str(out) + ".parts")):
            if stale.is_dir():
                shutil.rmtree(stale)
            elif stale.exists():
                stale.unlink()
        wall = run(build_argv(args, out, engine, args.procedural, args.complex, args.objects, args.seed))
        rows.append(summarise(engine, wall, out, tasks_in_flight(engine, args)))
        print(table(rows[-1:]), file=sys.stderr)
    print(f"\n{machine(args)} · {args.per_object} candidates per object, sampler {args.sampler}, protocols "
          f"{args.protocols}, physics backend {args.backend} ({', '.join(rows[0]['physics_backends'])})\n")
    print(table(rows))
    if args.json:
        Path(args.json).write_text(json.dumps({"machine": machine(args), "args": vars(args), "rows": rows}, indent=1))
    if not args.keep:
        shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    main()
