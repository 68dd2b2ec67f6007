"""Benchmark the physics test: CPU MuJoCo (`mujoco.rollout` threads) against MJX and MuJoCo Warp, n grasps.

    python bench/bench_physics.py [--object ball] [--n 1024] [--backend both] [--protocol six-dir] [--repeats 3]
                                  [--grasps FILE.npz] [--workers 0] [--short]
    python bench/bench_physics.py --object mug --backend warp --protocol both --n 64 512 4096

`--backend` is cpu, mjx, warp, both (cpu and mjx) or a comma list; `--protocol both` times the two protocols as
one evaluation (what `ffcgs eval` runs), several `--n` give a row each.

Grasps: `--grasps` (an npz with wrist_pose (B, 4, 4) and q (B, Q), e.g. from `ffcgs grasp`), else a quick
synthesis of 8 (the valid ones when there are any), tiled to n. Prints a Markdown table per backend: first run
(MJX: compilation included), median warm run of `--repeats`, grasps and simulated grasp-steps per second, success
rate. `--short` shrinks every phase (smoke tests: 0.1 s closing, 0.1 s pushes, a 2 cm lift and one short shake).
"""

import argparse
import os
import platform
import statistics
import time

import jax
import numpy as np

from ffcgs_jax.geometry import mesh_io
from ffcgs_jax.hand import spec as hand_spec
from ffcgs_jax.physics import backend_cpu
from ffcgs_jax.physics import protocols as physics_protocols
from ffcgs_jax.physics import runner as physics
from ffcgs_jax.physics.config import PROTOCOLS, PhysicsConfig

SHORT = {"close_time": 0.1, "settle_time": 0.05, "push_time": 0.1, "lift_height": 0.02, "shake_amplitude": 0.01,
         "shake_cycles": 1}


def load_grasps(args, mesh) -> tuple[np.ndarray, np.ndarray]:
    if args.grasps:
        data = np.load(args.grasps)
        T, q = data["wrist_pose"], data["q"]
    else:
        from ffcgs_jax.hand import kinematics as K
        from ffcgs_jax.synthesis import grasp
        from ffcgs_jax.synthesis.config import GraspConfig

        gs = grasp.synthesize(K.load_hand("svh"), mesh, GraspConfig(n=8), args.object)
        keep = np.flatnonzero(gs["valid"]) if gs["valid"].any() else np.arange(len(gs["valid"]))
        T, q = gs["wrist_pose"][keep], gs["q"][keep]
    return T, q


def steps_per_grasp(batch, cfg: PhysicsConfig, protocol: str) -> int:
    segs = physics_protocols.closing(batch, cfg)
    if protocol == "lift-shake":
        segs += physics_protocols.lift_shake(batch, cfg)
    else:
        segs += [physics_protocols.push(batch, cfg, d, 1.0) for d in physics_protocols.DIRECTIONS]
    return sum(s.n for s in segs)


def make_sim(backend: str, scene, cfg: PhysicsConfig, n: int):
    if backend == "cpu":
        return backend_cpu.CpuSim(scene, cfg.workers)
    if backend == "mjx":
        from ffcgs_jax.physics.backend_mjx import MjxSim

        return MjxSim(scene)
    if backend == "warp":
        from ffcgs_jax.physics.backend_warp import WarpSim

        return WarpSim(scene, n)
    raise SystemExit(f"unknown backend {backend!r}: cpu, mjx, warp")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--object", default="ball", help="built-in object name or mesh path")
    ap.add_argument("--n", type=int, nargs="+", default=[1024], help="grasps per batch (several: a row each)")
    ap.add_argument("--backend", default="both", help="cpu, mjx, warp, both (= cpu,mjx) or a comma list")
    ap.add_argument("--protocol", choices=(*PROTOCOLS, "both"), default="six-dir")
    ap.add_argument("--repeats", type=int, default=3, help="warm runs after the first")
    ap.add_argument("--grasps", help="npz with wrist_pose and q (else a quick synthesis of 8, tiled)")
    ap.add_argument("--workers", type=int, default=0, help="CPU threads (0: all cores)")
    ap.add_argument("--short", action="store_true", help="shrink every phase, for smoke tests")
    args = ap.parse_args()
    cfg = PhysicsConfig(workers=args.workers, **(SHORT if args.short else {}))
    spec, mesh = hand_spec.load_spec("svh"), mesh_io.load_mesh(args.object)
    wrist_all, q_all = load_grasps(args, mesh)
    protocols = PROTOCOLS if args.protocol == "both" else (args.protocol,)
    backends = ("cpu", "mjx") if args.backend == "both" else tuple(args.backend.split(","))
    rows = []
    for n in args.n:
        idx = np.arange(n) % len(q_all)
        wrist_pose, q = wrist_all[idx], q_all[idx]
        scenes = physics.scenes(spec, mesh, cfg, protocols)
        batch, depth, _ = physics.prepare(scenes[protocols[0]], mesh, wrist_pose, q, cfg)
        steps = sum(steps_per_grasp(batch, cfg, p) for p in protocols)
        for backend in backends:
            sims, t0 = {}, time.perf_counter()
            for p in protocols:
                sims[p] = make_sim(backend, scenes[p], cfg, n)
            results = {p: physics_protocols.run_protocol(sims[p], batch, depth, cfg, p) for p in protocols}
            first = time.perf_counter() - t0
            times = []
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                for p in protocols:
                    physics_protocols.run_protocol(sims[p], batch, depth, cfg, p)
                times.append(time.perf_counter() - t0)
            warm = statistics.median(times) if times else first
            ok = np.logical_and.reduce([results[p]["success"] for p in protocols]).mean()
            rows.append((backend, n, first, warm, n / warm, n * steps / warm, ok))
            print(f"{backend} n={n}: first {first:.1f} s, warm {warm:.2f} s", flush=True)
    dev = jax.devices()[0]
    workers = cfg.workers or os.cpu_count()
    print(f"device: {dev.platform} ({dev.device_kind}), jax {jax.__version__}, {platform.machine()}, "
          f"{workers} CPU threads; object {args.object}, protocol {args.protocol}{' (short)' if args.short else ''}, "
          f"{steps} steps per grasp, cone {cfg.cone}, {args.repeats} warm repeats; success = every protocol passed")
    print()
    print("| backend | n | first run (s) | warm median (s) | grasps/s | grasp-steps/s | success |")
    print("|---|---|---|---|---|---|---|")
    for backend, n, first, warm, gps, sps, ok in rows:
        print(f"| {backend} | {n} | {first:.1f} | {warm:.2f} | {gps:.2f} | {sps:.3g} | {100 * ok:.1f} % |")


if __name__ == "__main__":
    main()
