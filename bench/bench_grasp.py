"""Benchmark grasp synthesis: B wrist poses x T iterations, sampling + descent + filters (the device part).

    python bench/bench_grasp.py [--object mug] [--batches 32,1024] [--repeats 5] [--methods ours,paper]
        [--iters 50] [--lp-solvers proxsuite,jax] [--sampler cvae] [--max-proxsuite-batch 1024]

Prints a Markdown table: compile time (first call), median warm time of `--repeats` calls, grasps per second.
The host-side evaluation (Ferrari-Canny epsilon with Qhull) is not timed: it is a check, not part of synthesis.
"""

import argparse
import dataclasses
import itertools
import platform

import jax

from ffcgs_jax.cli.benchmark import time_synthesis
from ffcgs_jax.geometry import mesh_io, sdf
from ffcgs_jax.hand import kinematics as K
from ffcgs_jax.synthesis.config import EnergyConfig, OptimConfig
from ffcgs_jax.synthesis.energy import make_target
from ffcgs_jax.synthesis.grasp import GraspConfig

METHODS = {
    "ours": (EnergyConfig(), OptimConfig()),
    "paper": (EnergyConfig(a_pen=0.0, normal_grad=False), OptimConfig(iters=50, method="gd", wrist=False)),
}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--object", default="mug")
    ap.add_argument("--batches", default="32,1024")
    ap.add_argument("--iters", type=int, default=None, help="override both methods' iteration counts")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--methods", default="ours,paper")
    ap.add_argument("--lp-solvers", default="proxsuite,jax")
    ap.add_argument("--sampler", default=GraspConfig().sampler)
    ap.add_argument("--max-proxsuite-batch", type=int, default=1 << 30,
                    help="skip the ProxSuite path above this batch (it is host-bound: minutes per call)")
    args = ap.parse_args()
    hand = K.load_hand("svh")
    mesh = mesh_io.load_mesh(args.object)
    grid = sdf.build_sdf(mesh)
    target = make_target(grid)
    rows = []
    for method in args.methods.split(","):
        energy, optim = METHODS[method]
        if args.iters is not None:
            optim = OptimConfig(**{**optim.__dict__, "iters": args.iters})
        for solver, b in itertools.product(args.lp_solvers.split(","), map(int, args.batches.split(","))):
            if solver == "proxsuite" and b > args.max_proxsuite_batch:
                continue
            cfg = GraspConfig(n=b, sampler=args.sampler, energy=dataclasses.replace(energy, lp_solver=solver),
                              optim=optim)
            row = time_synthesis(hand, target, cfg, args.repeats)  # the first call warms caches and is dropped
            rows.append((method, solver, b, row.compile_s, row.median_s, row.rate))
            print(rows[-1], flush=True)
    dev = jax.devices()[0]
    print(f"device: {dev.platform} ({dev.device_kind}), jax {jax.__version__}, {platform.machine()}; "
          f"object {args.object} ({len(mesh.faces)} faces), SDF 32^3, {args.sampler} sampler, iterations: ours "
          f"{args.iters or OptimConfig().iters}, paper {args.iters or 50}; median of {args.repeats} warm calls")
    print()
    print("| method | LP solver | poses B | compile (s) | warm median (s) | grasps/s |")
    print("|---|---|---|---|---|---|")
    for method, solver, b, c, w, r in rows:
        print(f"| {method} | {solver} | {b} | {c:.1f} | {w:.4f} | {r:.1f} |")


if __name__ == "__main__":
    main()
