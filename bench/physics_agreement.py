"""Per-grasp agreement of physics runs (a backend and settings) with a reference run, on the same grasps.

    python bench/eval_grasp.py --methods ours --samplers cvae --iters 50 --save DIR   # the grasps
    python bench/physics_agreement.py --grasps DIR [DIR ...] [--runs cpu warp] [--friction 0.6] [--json out.json]
    python bench/physics_agreement.py --grasps DIR --runs "cpu:timestep=0.002,shake_cycles=6,push_time=2" cpu

A run is a backend (cpu, mjx, warp), optionally followed by `:KEY=VALUE,...` overrides of `PhysicsConfig`; the
first run is the reference. The valid grasps of every DIR/OBJECT__METHOD__SAMPLER.npz (what `ffcgs grasp`
returns) are tested by every run, both protocols. Prints, for each other run and protocol, the agreement matrix
(pass/fail against the reference), the share of identical outcomes and failure reasons, the largest move difference
among grasps both pass, and per run the wall time and core-seconds per grasp (compilation and scene building
included, the convex decomposition cached beforehand: what a user waits for on a known object).
"""

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

from ffcgs_jax.geometry import mesh_io
from ffcgs_jax.hand import spec as hand_spec
from ffcgs_jax.physics import runner as physics
from ffcgs_jax.physics.config import PROTOCOLS, PhysicsConfig
from ffcgs_jax.physics.protocols import REASONS, result_key
from ffcgs_jax.synthesis import grasp_io

from eval_physics import mesh_source  # noqa: E402 - the sibling script's YCB/built-in lookup

REPO = Path(__file__).resolve().parents[1]


def parse_run(text: str, base: PhysicsConfig) -> tuple[str, PhysicsConfig]:
    backend, _, rest = text.partition(":")
    fields = {f: type(getattr(base, f)) for f in base.__dataclass_fields__}
    overrides = {}
    for item in filter(None, rest.split(",")):
        key, _, value = item.partition("=")
        if key not in fields:
            raise SystemExit(f"unknown physics setting {key!r} in run {text!r}")
        overrides[key] = fields[key](value)
    return backend, PhysicsConfig(**{**base.__dict__, **overrides})


def column(rows: list[dict], run: str, p: str, field: str) -> np.ndarray:
    return np.array([r[run][result_key(p, field)] for r in rows])


def report(rows: list[dict], runs: list[str], seconds: dict, threads: int, friction: float) -> None:
    ref = runs[0]
    print(f"\n{len(rows)} valid grasps, friction {friction}; reference run: {ref}\n")
    print("| run | wall time (s) | core-seconds per grasp | speed-up |")
    print("|---|---|---|---|")
    for r in runs:
        cps = seconds[r] * threads / max(len(rows), 1)
        print(f"| {r} | {seconds[r]:.1f} | {cps:.2f} | {seconds[ref] / max(seconds[r], 1e-9):.2f}x |")
    for r in runs[1:]:
        print(f"\n{r} against {ref}:\n")
        print("| protocol | both pass | ref only | run only | both fail | identical outcome | identical reason |"
              " max move difference, both pass (mm) |")
        print("|---|---|---|---|---|---|---|---|")
        for p in PROTOCOLS:
            sa, sb = column(rows, ref, p, "success").astype(bool), column(rows, r, p, "success").astype(bool)
            ra, rb = column(rows, ref, p, "reason"), column(rows, r, p, "reason")
            ma, mb = column(rows, ref, p, "move"), column(rows, r, p, "move")
            both = sa & sb
            dmove = 1000 * np.abs(ma - mb)[both].max() if both.any() else float("nan")
            print(f"| {p} | {int(both.sum())} | {int((sa & ~sb).sum())} | {int((~sa & sb).sum())} | "
                  f"{int((~sa & ~sb).sum())} | {100 * (sa == sb).mean():.1f} % | {100 * (ra == rb).mean():.1f} % | "
                  f"{dmove:.2f} |")
            for r1 in range(len(REASONS)):
                for r2 in range(len(REASONS)):
                    k = int(((ra == r1) & (rb == r2)).sum())
                    if k and r1 != r2:
                        print(f"    {p}: reference {REASONS[r1]} / run {REASONS[r2]}: {k}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--grasps", nargs="+", required=True,
                    help="folders of OBJECT__METHOD__SAMPLER.npz from eval_grasp --save")
    ap.add_argument("--ycb", default=str(REPO.parent / "shared" / "objects" / "ycb"))
    ap.add_argument("--runs", nargs="+", default=["cpu", "warp"],
                    help="BACKEND[:KEY=VALUE,...] each; the first is the reference")
    ap.add_argument("--friction", type=float, default=0.6)
    ap.add_argument("--json", help="write the per-grasp outcomes here")
    ap.add_argument("--reference-json", help="a previous --json output whose first run is the reference (e.g. "
                    "from another version of the package: PYTHONPATH=OLD_CHECKOUT python bench/...)")
    ap.add_argument("--running", action="store_true", help="print the tables after every object as well")
    args = ap.parse_args()
    base = PhysicsConfig(sim_friction=args.friction)
    runs = {text: parse_run(text, base) for text in args.runs}
    spec = hand_spec.load_spec("svh")
    threads = base.workers or os.cpu_count() or 1
    rows, seconds = [], dict.fromkeys(runs, 0.0)
    reference = None
    if args.reference_json:
        old = json.loads(Path(args.reference_json).read_text())
        name = f"{old['runs'][0]} ({Path(args.reference_json).name})"
        reference = (name, {(r["file"], r["grasp"]): r[old["runs"][0]] for r in old["rows"]})
        seconds[name] = old["seconds"][old["runs"][0]]
    names = ([reference[0]] if reference else []) + list(runs)
    for path in sorted(p for folder in args.grasps for p in Path(folder).glob("*.npz")):
        data = grasp_io.load_npz(path)
        keep = np.flatnonzero(data["valid"])
        if len(keep) == 0:
            continue
        name = path.stem.split("__")[0]
        mesh = mesh_io.load_mesh(mesh_source(name, Path(args.ycb)))
        res = {}
        for text, (backend, cfg) in runs.items():
            physics.scenes(spec, mesh, cfg, PROTOCOLS)  # the convex parts, cached on disk: not what is compared
            t0 = time.perf_counter()
            res[text] = physics.evaluate(spec, mesh, data["wrist_pose"][keep], data["q"][keep], cfg, PROTOCOLS,
                                         backend)
            seconds[text] += time.perf_counter() - t0
        for i in range(len(keep)):
            row = {"object": name, "file": f"{path.parent.name}/{path.name}", "grasp": int(keep[i])}
            for text in runs:
                row[text] = {result_key(p, f): res[text][result_key(p, f)][i].item()
                             for p in PROTOCOLS for f in ("success", "reason", "move")}
            if reference is not None:
                row[reference[0]] = reference[1][(row["file"], row["grasp"])]
            rows.append(row)
        print(f"{path.parent.name}/{name}: {len(keep)} grasps", flush=True)
        if args.running:
            report(rows, names, seconds, threads, args.friction)
    report(rows, names, seconds, threads, args.friction)
    if args.json:
        Path(args.json).write_text(json.dumps({"runs": names, "seconds": seconds, "threads": threads, "rows": rows},
                                              indent=1))


if __name__ == "__main__":
    main()
