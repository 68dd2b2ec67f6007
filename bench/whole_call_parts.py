"""Where a whole `synthesize` call's time goes, stage by stage, from a mesh to ranked grasps.

    python bench/whole_call_parts.py OBJECT.stl [--n 32] [--repeats 10]

Each stage runs as `synthesize` runs it, then waits for the device (`block_until_ready`) so that its time is its
own; the waits add a few launches of latency that the real call overlaps, so the sum is an upper bound of the call.
Stages: the SDF (built anew, or looked up in the cache), the target (extent and cell table), the device part's
lookup and run, the triangle table (built anew, or cached), the evaluation's lookup and run, the copy back and the
host-side finish (validity, squeeze directions, predictions). `synthesize` builds the triangle table while the device
part runs, so on a GPU it costs the call nothing (a CPU backend shares the cores). Medians of `repeats` warm calls, milliseconds.
"""

import argparse
import statistics
import time

import jax

from ffcgs_jax.evaluation import device_metrics
from ffcgs_jax.geometry import mesh_io
from ffcgs_jax.geometry import sdf as S
from ffcgs_jax.hand import kinematics as K
from ffcgs_jax.runtime import fetch
from ffcgs_jax.synthesis import grasp
from ffcgs_jax.synthesis.config import GraspConfig, OptimConfig
from ffcgs_jax.synthesis.energy import make_target


def stages(hand, mesh, cfg, fresh: bool) -> dict[str, float]:
    t = {}

    def timed(name, fn):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn())
        t[name] = 1e3 * (time.perf_counter() - t0)
        return out

    if fresh:
        S.clear_cache()
        device_metrics.clear_cache()
    start = time.perf_counter()
    grid = timed("sdf", lambda: S.build_sdf(mesh, cfg.sdf))
    target = timed("target", lambda: make_target(grid))
    run, _ = timed("device lookup", lambda: grasp.compile_device(hand, target, cfg))
    out = timed("device run", lambda: run(jax.random.PRNGKey(0)))
    surface = timed("triangle table", lambda: grasp.surface_of(mesh))
    run_eval, _ = timed("evaluation lookup", lambda: grasp.prepare_evaluation(hand, surface, target, cfg, out))
    ev = timed("evaluation run", run_eval)
    timed("copy back", lambda: fetch.device_get((out, ev)))
    t0 = time.perf_counter()
    grasp.finish(hand, target, cfg, out, lambda: ev, 0.0, "object").order()  # copies back again: subtract
    t["finish (host)"] = 1e3 * (time.perf_counter() - t0) - t["copy back"]
    t["sum of stages"] = 1e3 * (time.perf_counter() - start) - t["copy back"]
    return t


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("object")
    ap.add_argument("--n", type=int, default=32)
    ap.add_argument("--iters", type=int, default=100)
    ap.add_argument("--repeats", type=int, default=10)
    a = ap.parse_args()
    hand = K.load_hand("svh")
    mesh = mesh_io.load_mesh(a.object)
    cfg = GraspConfig(n=a.n, devices=1, optim=OptimConfig(iters=a.iters))
    grasp.synthesize(hand, mesh, cfg)  # compiles
    rows = {True: [], False: []}
    for _ in range(a.repeats):
        for fresh in rows:
            rows[fresh].append(stages(hand, mesh, cfg, fresh))
    whole = {fresh: [] for fresh in rows}
    for i in range(a.repeats):
        for fresh in whole:
            if fresh:
                S.clear_cache()
                device_metrics.clear_cache()
            t0 = time.perf_counter()
            grasp.synthesize(hand, mesh, cfg).order()
            whole[fresh].append(1e3 * (time.perf_counter() - t0))
    print(f"{jax.devices()[0].device_kind}, {a.object}: {len(mesh.faces)} faces, n {a.n}; median ms of "
          f"{a.repeats} warm calls")
    print(f"{'stage':<20} {'first seen':>11} {'cached':>8}")
    for k in rows[True][0]:
        print(f"{k:<20} {statistics.median(r[k] for r in rows[True]):>11.2f} "
              f"{statistics.median(r[k] for r in rows[False]):>8.2f}")
    print(f"{'synthesize (whole)':<20} {statistics.median(whole[True]):>11.2f} {statistics.median(whole[False]):>8.2f}")


if __name__ == "__main__":
    main()
