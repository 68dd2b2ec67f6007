"""What the success predictor costs a user: the whole `synthesize` call with and without it, side by side.

    python bench/predictor_cost.py [--mesh mug] [--n 32] [--runs 7]

Rows: `--rank energy` with no predictor loaded (the call as before the predictor), the default (`rank auto`: the
shipped predictor's `pred_success` computed on the device after the synthesis and used to rank), and the
prediction alone (`synthesis.prediction.predictions` on the call's arrays). Each row's first call (compiling, or
loading from JAX's cache) is reported apart; the figures are medians of the warm calls, alternating the two
configurations so both see the same machine state.
"""

import argparse
import dataclasses
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--mesh", default="mug")
    ap.add_argument("--n", type=int, default=32)
    ap.add_argument("--runs", type=int, default=7)
    args = ap.parse_args(argv)

    import jax

    from ffcgs_jax.geometry import mesh_io
    from ffcgs_jax.geometry import sdf as sdf_mod
    from ffcgs_jax.hand import kinematics as K
    from ffcgs_jax.synthesis import prediction
    from ffcgs_jax.synthesis.grasp import GraspConfig, synthesize

    hand = K.load_hand("svh")
    mesh = mesh_io.load_mesh(args.mesh)
    found = prediction.weights_for(hand)
    if found is None:
        raise SystemExit("predictor_cost: no predictor ships for the SVH")
    rows = {"rank energy (no predictor)": GraspConfig(n=args.n, rank="energy", evaluator=""),
            "default (predicted)": GraspConfig(n=args.n)}
    # "energy" with the shipped file present still predicts (stored, not ranked): time the call without it by
    # pointing the lookup at no file
    energy_only = prediction.weights_for
    first, warm = {}, {k: [] for k in rows}
    alone = []
    grid = sdf_mod.build_sdf(mesh, GraspConfig().sdf)
    for r in range(args.runs + 1):
        for name, cfg in rows.items():
            if cfg.rank == "energy":
                prediction.weights_for = lambda hand, path="": None
            t0 = time.perf_counter()
            gs = synthesize(hand, mesh, dataclasses.replace(cfg, seed=r), args.mesh)
            wall = time.perf_counter() - t0
            prediction.weights_for = energy_only
            (warm[name].append(wall) if r else first.__setitem__(name, (wall, float(gs["compile_s"]))))
        t0 = time.perf_counter()
        prediction.predictions(*found, hand, grid, gs.arrays)
        (alone.append(time.perf_counter() - t0) if r else first.__setitem__("prediction alone",
                                                                             (time.perf_counter() - t0, 0.0)))
    dev = jax.devices()[0]
    print(f"predictor_cost · {dev.platform} · {dev.device_kind} · mesh {args.mesh} · n {args.n} · "
          f"median of {args.runs} warm calls")
    print("| call | whole call, median (ms) | first call (s) |")
    print("|---|---|---|")
    for name in rows:
        print(f"| {name} | {1000 * statistics.median(warm[name]):.1f} | {first[name][0]:.2f} |")
    print(f"| prediction alone | {1000 * statistics.median(alone):.2f} | {first['prediction alone'][0]:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
