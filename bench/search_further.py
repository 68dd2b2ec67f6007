"""Searching further on hard objects (`GraspConfig.search`): each object's grasps without it (`max_rounds = 1`,
the first batch alone, as before) and with it (the defaults, or the flags below), side by side, as a markdown
table: valid grasps, the best valid grasp's predicted success, batches run, the extra seconds, why it searched and
why it stopped; `--physics` also asks whether the first offered grasp passes lift-shake and six-dir (CPU MuJoCo).

    python bench/search_further.py --objects 4 --n 8 --iters 40 [--seed 7000] [--physics]
    python bench/search_further.py --objects 40 --n 32 --physics          # the issue's size, on a GPU machine

Objects: complex procedural shapes (`procedural.complex_shape`) of `--seed`, 7000 by default: a seed no build
trains on. The first batch of both runs is the same call (the same seed and executables), so "before" is what the
search started from.
"""

import argparse
import dataclasses
import time

import numpy as np

import ffcgs_jax as fj
from ffcgs_jax.geometry import procedural
from ffcgs_jax.synthesis.config import SearchConfig


def best_predicted(gs) -> float:
    """The best valid grasp's predicted success; NaN with no valid grasp (or no predictor)."""
    v = np.asarray(gs["valid"], bool)
    return float(np.max(gs["pred_success"][v])) if "pred_success" in gs and v.any() else float("nan")


def show(p: float) -> str:
    return "-" if np.isnan(p) else f"{p:.2f}"


def first_holds(hand, mesh, gs) -> str:
    first = int(gs.order()[0])
    res = fj.evaluate_physics(hand, mesh, gs, which=[first])
    return "yes" if bool(res.passed[0]) else "no"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--objects", type=int, default=4)
    ap.add_argument("--first", type=int, default=0, help="index of the first object")
    ap.add_argument("--seed", type=int, default=7000)
    ap.add_argument("--n", type=int, default=32)
    ap.add_argument("--iters", type=int, default=100)
    ap.add_argument("--min-valid", type=int, default=SearchConfig.min_valid)
    ap.add_argument("--min-predicted", type=float, default=SearchConfig.min_predicted)
    ap.add_argument("--max-rounds", type=int, default=SearchConfig.max_rounds)
    ap.add_argument("--budget", type=float, default=SearchConfig.budget)
    ap.add_argument("--physics", action="store_true", help="simulate the first offered grasp of each run")
    args = ap.parse_args()

    hand = fj.load_hand("svh")
    on = SearchConfig(args.min_valid, args.min_predicted, args.max_rounds, args.budget)
    base = fj.GraspConfig(n=args.n, optim=fj.OptimConfig(iters=args.iters), search=on)
    off = dataclasses.replace(base, search=dataclasses.replace(on, max_rounds=1))
    t0 = time.perf_counter()
    fj.synthesize(hand, procedural.complex_shape(args.seed, args.first)[1], off)  # compiles what both runs reuse
    print(f"compile and first call: {time.perf_counter() - t0:.1f} s; search {on}\n")
    head = ["object", "valid before", "valid after", "best pred. before", "best pred. after", "rounds",
            "extra s", "first-batch s"]
    if args.physics:
        head += ["first holds before", "first holds after"]
    head += ["why", "stop"]
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    searched, gained = 0, 0
    for i in range(args.first, args.first + args.objects):
        name, mesh = procedural.complex_shape(args.seed, i)
        a = fj.synthesize(hand, mesh, off, name)
        b = fj.synthesize(hand, mesh, base, name)
        rounds = int(b["search_rounds"])
        searched += rounds > 1
        pa, pb = best_predicted(a), best_predicted(b)
        gained += int(b["valid"].sum()) > int(a["valid"].sum()) or pb > pa or (np.isnan(pa) and not np.isnan(pb))
        row = [name, int(a["valid"].sum()), int(b["valid"].sum()), show(pa), show(pb), rounds,
               f"{float(b['search_s']):.2f}", f"{float(a['synthesis_s']) + float(a['evaluation_s']):.2f}"]
        if args.physics:
            row += [first_holds(hand, mesh, a), first_holds(hand, mesh, b)]
        row += [str(b["search_why"]) or "-", str(b["search_stop"])]
        print("| " + " | ".join(map(str, row)) + " |", flush=True)
    print(f"\nsearched further on {searched} of {args.objects} objects; more valid or a better best prediction on "
          f"{gained}")


if __name__ == "__main__":
    main()
