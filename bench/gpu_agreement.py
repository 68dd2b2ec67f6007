"""GPU physics (the worlds of `physics.worlds`) against CPU MuJoCo on the same grasps and the same collision
geometry: the share of identical outcomes per protocol, the disagreements by direction, and the failure reasons.

    python bench/gpu_agreement.py --objects 8 --per-object 64 [--seed 900] [--protocols lift-shake six-dir dexgraspbench]

Grasps: every candidate (valid or not, as a labelled build takes them) of `fj.synthesize` with `--per-object`
poses on `--objects` complex procedural shapes of seed `--seed` (objects the package was never tuned on). Both
runs read the same convex parts (`convex.decompose`, cached after the first run). Needs a CUDA device and
warp-lang / mujoco-warp; `--device cpu` runs Warp on the CPU (slow: a smoke test).
"""

import argparse
import json
import time

import numpy as np

import ffcgs_jax as fj
from ffcgs_jax.geometry import procedural
from ffcgs_jax.physics import runner, worlds
from ffcgs_jax.physics.config import PhysicsConfig
from ffcgs_jax.physics.protocols import REASONS, result_key


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--objects", type=int, default=8)
    ap.add_argument("--per-object", type=int, default=64)
    ap.add_argument("--seed", type=int, default=900)
    ap.add_argument("--protocols", nargs="+", default=["lift-shake", "six-dir", "dexgraspbench"])
    ap.add_argument("--device", default=None, help="Warp device (default: its default, the GPU where present)")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()

    hand = fj.load_hand("svh")
    items = []
    t0 = time.perf_counter()
    for i in range(args.objects):
        _, mesh = procedural.complex_shape(args.seed, i)
        gs = fj.synthesize(hand, mesh, fj.GraspConfig(n=args.per_object, seed=i))
        items.append(runner.Item(mesh, np.asarray(gs["wrist_pose"]), np.asarray(gs["q"]),
                                 np.asarray(gs["squeeze_dir"])))
    print(f"synthesis: {len(items)} objects x {args.per_object} candidates in {time.perf_counter() - t0:.1f} s")
    cfg = PhysicsConfig()
    runs, seconds = {}, {}
    for backend in ("cpu", "warp"):
        if backend == "warp" and args.device:
            worlds.clear()
            run = _on_device(args.device)
        else:
            run = runner.evaluate_many
        t0 = time.perf_counter()
        runs[backend] = run(hand.spec, items, cfg, tuple(args.protocols), backend=backend)
        seconds[backend] = time.perf_counter() - t0
        print(f"{backend}: {seconds[backend]:.1f} s")
    report(runs, args.protocols, seconds, args.json)


def _on_device(device: str):
    def run(spec, items, cfg, protocols, backend):
        old = worlds.run_jobs

        def pinned(*a, **k):
            return old(*a, **{**k, "device": device, "nworld": 256 if device == "cpu" else worlds.MAX_WORLDS})

        worlds.run_jobs = pinned
        try:
            return runner.evaluate_many(spec, items, cfg, protocols, backend=backend)
        finally:
            worlds.run_jobs = old

    return run


def report(runs: dict, protocols, seconds: dict, out: str | None) -> None:
    cat = {b: {k: np.concatenate([r[k] for r in res]) for k in res[0]} for b, res in runs.items()}
    n = len(cat["cpu"]["initial_penetration"])
    rerun = int(cat["warp"].get("physics_rerun_cpu", np.zeros(n, bool)).sum())
    print(f"\n{n} grasps ({rerun} re-run on the CPU after a buffer overflow); reference: CPU MuJoCo\n")
    print("| protocol | identical outcome | CPU pass | GPU pass | pass CPU only | pass GPU only | same reason |")
    print("|---|---|---|---|---|---|---|")
    table = {}
    for p in protocols:
        a, b = cat["cpu"][result_key(p, "success")], cat["warp"][result_key(p, "success")]
        ra, rb = cat["cpu"][result_key(p, "reason")], cat["warp"][result_key(p, "reason")]
        same = float(np.mean(a == b))
        row = dict(identical=same, cpu_pass=int(a.sum()), gpu_pass=int(b.sum()), cpu_only=int((a & ~b).sum()),
                   gpu_only=int((b & ~a).sum()), same_reason=float(np.mean(ra == rb)))
        table[p] = row
        print(f"| {p} | **{100 * same:.1f} %** ({int((a == b).sum())}/{n}) | {row['cpu_pass']} | {row['gpu_pass']} "
              f"| {row['cpu_only']} | {row['gpu_only']} | {100 * row['same_reason']:.1f} % |")
        flips = [(REASONS[x], REASONS[y]) for x, y in zip(ra, rb) if x != y]
        if flips:
            kinds: dict = {}
            for f in flips:
                kinds[f] = kinds.get(f, 0) + 1
            print(f"|  | reasons CPU -> GPU: " + ", ".join(f"{x}->{y} {c}" for (x, y), c in sorted(kinds.items()))
                  + " | | | | | |")
    print(f"\nwall: CPU {seconds['cpu']:.1f} s, GPU {seconds['warp']:.1f} s (geometry cached after the first run)")
    if out:
        with open(out, "w") as f:
            json.dump({"grasps": n, "rerun_cpu": rerun, "protocols": table, "seconds": seconds}, f, indent=1)


if __name__ == "__main__":
    main()
