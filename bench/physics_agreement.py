"""Per-grasp agreement of two physics backends (default: cpu against warp) on the same grasps.

    python bench/eval_grasp.py --methods ours --samplers cvae --iters 50 --save DIR   # the grasps
    python bench/physics_agreement.py --grasps DIR [--backends cpu,warp] [--friction 0.6] [--json out.json]

The valid grasps of every DIR/OBJECT__METHOD__SAMPLER.npz (what `ffcgs grasp` returns) are tested with both
backends, both protocols. Prints per protocol the agreement matrix (pass/fail on one backend against the other),
the share of identical outcomes and of identical failure reasons, the largest move difference among agreeing
passes, and each backend's wall time (compilation included: what a user waits for).
"""

import argparse
import json
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


def report(rows: list[dict], a: str, b: str, seconds: dict, friction: float) -> None:
    print(f"\n{len(rows)} valid grasps, friction {friction}; wall time {a} {seconds[a]:.1f} s, "
          f"{b} {seconds[b]:.1f} s (compilation included)\n")
    print(f"| protocol | both pass | {a} only | {b} only | both fail | identical outcome | identical reason |"
          " max move difference, both pass (mm) |")
    print("|---|---|---|---|---|---|---|---|")
    for p in PROTOCOLS:
        sa = np.array([r[f"{a}_{result_key(p, 'success')}"] for r in rows], bool)
        sb = np.array([r[f"{b}_{result_key(p, 'success')}"] for r in rows], bool)
        ra = np.array([r[f"{a}_{result_key(p, 'reason')}"] for r in rows])
        rb = np.array([r[f"{b}_{result_key(p, 'reason')}"] for r in rows])
        ma = np.array([r[f"{a}_{result_key(p, 'move')}"] for r in rows])
        mb = np.array([r[f"{b}_{result_key(p, 'move')}"] for r in rows])
        both = sa & sb
        dmove = 1000 * np.abs(ma - mb)[both].max() if both.any() else float("nan")
        print(f"| {p} | {int(both.sum())} | {int((sa & ~sb).sum())} | {int((~sa & sb).sum())} | "
              f"{int((~sa & ~sb).sum())} | {100 * (sa == sb).mean():.1f} % | {100 * (ra == rb).mean():.1f} % | "
              f"{dmove:.2f} |")
        for r1 in range(len(REASONS)):
            for r2 in range(len(REASONS)):
                k = int(((ra == r1) & (rb == r2)).sum())
                if k and r1 != r2:
                    print(f"    {p}: {a} {REASONS[r1]} / {b} {REASONS[r2]}: {k}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--grasps", required=True, help="folder of OBJECT__METHOD__SAMPLER.npz from eval_grasp --save")
    ap.add_argument("--ycb", default=str(REPO.parent / "shared" / "objects" / "ycb"))
    ap.add_argument("--backends", default="cpu,warp")
    ap.add_argument("--friction", type=float, default=0.6)
    ap.add_argument("--json", help="write the per-grasp outcomes here")
    ap.add_argument("--running", action="store_true", help="print the table after every object as well")
    args = ap.parse_args()
    a, b = args.backends.split(",")
    cfg = PhysicsConfig(friction=args.friction)
    spec = hand_spec.load_spec("svh")
    rows, seconds = [], {a: 0.0, b: 0.0}
    for path in sorted(Path(args.grasps).glob("*.npz")):
        data = grasp_io.load_npz(path)
        keep = np.flatnonzero(data["valid"])
        if len(keep) == 0:
            continue
        name = path.stem.split("__")[0]
        mesh = mesh_io.load_mesh(mesh_source(name, Path(args.ycb)))
        res = {}
        for backend in (a, b):
            t0 = time.perf_counter()
            res[backend] = physics.evaluate(spec, mesh, data["wrist_pose"][keep], data["q"][keep], cfg, PROTOCOLS,
                                            backend)
            seconds[backend] += time.perf_counter() - t0
        for i in range(len(keep)):
            row = {"object": name, "grasp": int(keep[i])}
            for backend in (a, b):
                for p in PROTOCOLS:
                    for f in ("success", "reason", "move"):
                        v = res[backend][result_key(p, f)][i]
                        row[f"{backend}_{result_key(p, f)}"] = v.item()
            rows.append(row)
        print(f"{name}: {len(keep)} grasps", flush=True)
        if args.running:
            report(rows, a, b, seconds, args.friction)
    report(rows, a, b, seconds, args.friction)
    if args.json:
        Path(args.json).write_text(json.dumps({"seconds": seconds, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
