"""Sampling time of the wrist-pose samplers (Table I's "Time" row): n poses from a Gradient-SDF, per sampler.

    python bench/bench_sampler.py [--n 32] [--runs 20] [--weights FILE.npz] [--samplers cvae,geometric,random]

Per built-in object and sampler: compile time (first call) and the median of `runs` warm calls (each a new key,
blocked until the poses are ready), plus the share of the n poses that pass the pose filters. Prints a Markdown
table with the backend and device.
"""

import argparse
import statistics
import time

import jax
import numpy as np

from ffcgs_jax.geometry import mesh_io, objects, sdf
from ffcgs_jax.geometry.config import SDFConfig
from ffcgs_jax.hand import kinematics as K
from ffcgs_jax.synthesis import filters as F
from ffcgs_jax.synthesis import samplers
from ffcgs_jax.synthesis.config import SamplerConfig


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=32)
    ap.add_argument("--runs", type=int, default=20)
    ap.add_argument("--weights", default="", help="cvae weights (default: the shipped ones)")
    ap.add_argument("--samplers", default="cvae,geometric,random")
    ap.add_argument("--cvae-oversample", default="", help="comma list: also time the cvae at these oversamplings")
    args = ap.parse_args()
    hand = K.load_hand("svh")
    cfg = SamplerConfig(weights=args.weights)
    names = args.samplers.split(",")
    fns = {s: samplers.make_sampler(s, hand, cfg) for s in names}
    for k in filter(None, args.cvae_oversample.split(",")):
        names.append(f"cvae x{k}")
        fns[names[-1]] = samplers.make_sampler("cvae", hand, SamplerConfig(weights=args.weights,
                                                                           cvae_oversample=int(k)))
    rows = []
    for obj in objects.names():
        grid = sdf.build_sdf(mesh_io.load_mesh(obj), SDFConfig(res=32))
        for s in names:
            t0 = time.perf_counter()
            jax.block_until_ready(fns[s](jax.random.key(0), grid, args.n))
            compile_s = time.perf_counter() - t0
            times = []
            for r in range(args.runs):
                t0 = time.perf_counter()
                poses = jax.block_until_ready(fns[s](jax.random.key(r + 1), grid, args.n))
                times.append(time.perf_counter() - t0)
            ok = np.asarray(samplers.pose_verdicts(hand, grid, poses, F.FilterConfig())[0])
            rows.append((obj, s, compile_s, statistics.median(times), float(ok.mean())))
    dev = jax.devices()[0]
    print(f"backend {jax.default_backend()}, device {dev.device_kind}, jax {jax.__version__}, n = {args.n}, "
          f"median of {args.runs} warm runs")
    print("| object | sampler | compile (s) | time (ms) | pass pose filters |")
    print("|---|---|---|---|---|")
    for obj, s, c, t, ok in rows:
        print(f"| {obj} | {s} | {c:.2f} | {1000 * t:.2f} | {100 * ok:.0f}% |")
    for s in names:
        t = [r[3] for r in rows if r[1] == s]
        print(f"| all | {s} | | {1000 * statistics.median(t):.2f} (median over objects) | "
              f"{100 * np.mean([r[4] for r in rows if r[1] == s]):.0f}% |")


if __name__ == "__main__":
    main()
