"""Physics success of synthesised grasps per sampler, friction and protocol (issue 4's report; paper Table III).

    python bench/eval_grasp.py --methods ours --save .bench_data/grasps      # the grasps (built-ins + YCB test)
    python bench/eval_physics.py --grasps .bench_data/grasps [--frictions 0.6,0.2] [--json out.json]

Every grasp in every DIR/OBJECT__METHOD__SAMPLER.npz is tested (lift-shake and six-dir, CPU MuJoCo threads), so
rates are given over the valid grasps (what `ffcgs grasp` returns) and over all sampled poses. Rates come with
95 % Wilson intervals; a Wilcoxon signed-rank test pairs the objects to compare the samplers' per-object success
rate over all poses (the valid sets of the random sampler are too small to pair), as the paper compares
samplers. The same grasps' E, E_g, E_c and epsilon (medians over valid grasps) come from the npz files.
"""

import argparse
import json
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ffcgs_jax.evaluation import metrics
from ffcgs_jax.geometry import mesh_io, objects
from ffcgs_jax.hand import spec as hand_spec
from ffcgs_jax.physics import protocols as physics_protocols
from ffcgs_jax.physics import runner as physics
from ffcgs_jax.physics.config import PhysicsConfig
from ffcgs_jax.synthesis import grasp_io

REPO = Path(__file__).resolve().parents[1]


def mesh_source(name: str, ycb: Path) -> str:
    if name in objects.names():
        return name
    path = ycb / f"{name}.stl"
    if not path.is_file():
        raise SystemExit(f"no mesh for {name}: looked for {path}")
    return str(path)


def run(args) -> list[dict]:
    spec = hand_spec.load_spec("svh")
    files = sorted(Path(args.grasps).glob("*.npz"))
    if not files:
        raise SystemExit(f"no grasp files in {args.grasps}")
    frictions = [float(f) for f in args.frictions.split(",")]
    protocols = tuple(args.protocols.split(","))
    rows = []
    for f in tqdm(files, desc="objects x samplers", unit="file"):
        name, method, sampler = f.stem.split("__")
        g = grasp_io.load_npz(f)
        mesh = mesh_io.load_mesh(mesh_source(name, Path(args.ycb)))
        for mu in frictions:
            t0 = time.perf_counter()
            cfg = PhysicsConfig(sim_friction=mu, workers=args.workers)
            res = physics.evaluate(spec, mesh, g["wrist_pose"], g["q"], cfg, protocols)
            seconds = time.perf_counter() - t0
            rows.append({
                "object": name, "method": method, "sampler": sampler, "friction": mu, "seconds": seconds,
                "trials": len(g["q"]) * len(protocols),
                "valid": g["valid"].tolist(), "epsilon": g["epsilon"].tolist(), "E": g["E"].tolist(),
                "E_g": g["E_g"].tolist(), "E_c": g["E_c"].tolist(),
                **{k: np.asarray(v).tolist() for k, v in res.items()},
            })
    return rows


def _rate(ok: np.ndarray) -> str:
    k, n = int(ok.sum()), len(ok)
    if n == 0:
        return "- (0)"
    lo, hi = physics_protocols.wilson(k, n)
    return f"{100 * k / n:.1f} % ({k}/{n}; {100 * lo:.0f}-{100 * hi:.0f})"


def report(rows: list[dict]) -> None:
    keys = sorted({(r["sampler"], r["friction"]) for r in rows}, key=lambda x: (x[0], -x[1]))
    print("Success rate (95 % Wilson interval), valid grasps and all sampled poses:\n")
    print("| sampler | friction | lift-shake (valid) | six-dir (valid) | both (valid) | lift-shake (all) "
          "| six-dir (all) |")
    print("|---|---|---|---|---|---|---|")
    for s, mu in keys:
        rs = [r for r in rows if r["sampler"] == s and r["friction"] == mu]
        cat = lambda k: np.concatenate([np.asarray(r[k], bool) for r in rs])  # noqa: E731
        v, ls, sd = cat("valid"), cat("lift_shake_success"), cat("six_dir_success")
        print(f"| {s} | {mu} | {_rate(ls[v])} | {_rate(sd[v])} | {_rate((ls & sd)[v])} | {_rate(ls)} | {_rate(sd)} |")
    print("\nFailure reasons over valid grasps (penetration / lost / slip / unstable), and palm contact among failures:\n")
    print("| sampler | friction | protocol | penetration | lost | slip | palm touching at start |")
    print("|---|---|---|---|---|---|---|")
    for s, mu in keys:
        rs = [r for r in rows if r["sampler"] == s and r["friction"] == mu]
        v = np.concatenate([np.asarray(r["valid"], bool) for r in rs])
        palm = np.concatenate([np.asarray(r["palm_contact"], bool) for r in rs])
        for p in ("lift_shake", "six_dir"):
            reason = np.concatenate([np.asarray(r[f"{p}_reason"]) for r in rs])[v]
            fail = reason > 0
            counts = " | ".join(str(int((reason == i).sum())) for i in (1, 2, 3, 4))
            print(f"| {s} | {mu} | {p.replace('_', '-')} | {counts} | {int(palm[v][fail].sum())}/{int(fail.sum())} |")
    print("\nQuality of the same grasps (medians over valid grasps; E_c in cm):\n")
    print("| sampler | valid | E | E_g | E_c | epsilon | epsilon > 0 |")
    print("|---|---|---|---|---|---|---|")
    for s in sorted({r["sampler"] for r in rows}):
        rs = [r for r in rows if r["sampler"] == s and r["friction"] == keys[0][1]]
        cat = lambda k: np.concatenate([np.asarray(r[k], float) for r in rs])  # noqa: E731
        v = np.concatenate([np.asarray(r["valid"], bool) for r in rs])
        md = lambda k, sc=1.0: f"{np.median(cat(k)[v]) * sc:.3f}" if v.any() else "-"  # noqa: E731
        print(f"| {s} | {int(v.sum())}/{len(v)} | {md('E')} | {md('E_g')} | {md('E_c', 100)} | {md('epsilon')} | "
              f"{(cat('epsilon')[v] > 0).mean():.1%} |")
    if any(r["sampler"] == "geometric" for r in rows):  # the geometric sampler's sections need its rows
        print("\nDoes force closure on the mesh predict physics? Geometric sampler, pass rates by epsilon:\n")
        print("| friction | protocol | valid, epsilon > 0 | valid, epsilon = 0 | not valid |")
        print("|---|---|---|---|---|")
        for mu in sorted({r["friction"] for r in rows}, reverse=True):
            rs = [r for r in rows if r["sampler"] == "geometric" and r["friction"] == mu]
            cat = lambda k: np.concatenate([np.asarray(r[k]) for r in rs])  # noqa: E731
            v, fc = cat("valid").astype(bool), cat("epsilon") > 0
            for p in ("lift_shake", "six_dir"):
                ok = cat(f"{p}_success").astype(bool)
                print(f"| {mu} | {p.replace('_', '-')} | {_rate(ok[v & fc])} | {_rate(ok[v & ~fc])} | {_rate(ok[~v])} |")
        print("\nPer object, geometric sampler, valid grasps: lift-shake / six-dir passes of n\n")
        for mu in sorted({r["friction"] for r in rows}, reverse=True):
            cells = []
            for r in sorted((r for r in rows if r["sampler"] == "geometric" and r["friction"] == mu),
                            key=lambda r: r["object"]):
                v = np.asarray(r["valid"], bool)
                ls, sd = (int(np.asarray(r[f"{p}_success"], bool)[v].sum()) for p in ("lift_shake", "six_dir"))
                cells.append(f"{r['object']} {ls}/{sd} of {int(v.sum())}")
            print(f"- friction {mu}: " + ", ".join(cells))
    print()
    for mu in sorted({r["friction"] for r in rows}, reverse=True):
        for p in ("lift_shake", "six_dir"):
            per = {}
            for r in rows:
                if r["friction"] == mu:
                    per[(r["object"], r["sampler"])] = float(np.mean(r[f"{p}_success"]))
            objs = sorted({o for o, _ in per})
            if all((o, s) in per for o in objs for s in ("geometric", "random")) and len(objs) > 1:
                a = np.array([per[(o, "geometric")] for o in objs])
                b = np.array([per[(o, "random")] for o in objs])
                if np.any(a != b):
                    stat, pv = metrics.wilcoxon(a, b)
                    print(f"Wilcoxon signed-rank, friction {mu}, {p.replace('_', '-')}: per-object success over all "
                          f"poses, geometric (median {np.median(a):.2f}) vs random ({np.median(b):.2f}): "
                          f"statistic {stat:.1f}, p = {pv:.2g} over {len(objs)} objects")
    total = sum(r["seconds"] for r in rows)
    trials = sum(r.get("trials", 2 * len(r["valid"])) for r in rows)
    print(f"\n{trials} trials in {total:.0f} s of physics (the last run): {trials / total:.1f} trials/s")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--grasps", required=True, help="folder of OBJECT__METHOD__SAMPLER.npz from eval_grasp --save")
    ap.add_argument("--ycb", default=str(REPO.parent / "shared" / "objects" / "ycb"))
    ap.add_argument("--frictions", default="0.6,0.2")
    ap.add_argument("--protocols", default="lift-shake,six-dir")
    ap.add_argument("--update", help="merge into the rows of this earlier JSON (same grasps), e.g. one protocol re-run")
    ap.add_argument("--workers", type=int, default=0, help="MuJoCo threads (0 = all cores)")
    ap.add_argument("--json", help="write the per-grasp rows to this JSON file")
    ap.add_argument("--report", help="only print the report of a JSON file written before")
    args = ap.parse_args()
    if args.report:
        report(json.loads(Path(args.report).read_text()))
        return
    rows = run(args)
    if args.update:  # keep the other protocol's results from an earlier run of the same grasps
        old = {(r["object"], r["sampler"], r["friction"]): r for r in json.loads(Path(args.update).read_text())}
        rows = [{**old[(r["object"], r["sampler"], r["friction"])], **r} for r in rows]
    if args.json:
        Path(args.json).write_text(json.dumps(rows))
    report(rows)


if __name__ == "__main__":
    main()
