"""Grasp quality per sampler and method, on the built-in objects and the YCB test split (Table I / II style).

    python bench/eval_grasp.py [--ycb ../shared/objects/ycb] [--n 32] [--methods ours,paper] [--samplers geometric,random]
        [--iters 50] [--weights W.npz] [--lp-solver jax] [--save DIR]   # keep the grasps for bench/eval_physics.py

For every object, sampler and method (ours = the package defaults; paper = configs/paper.toml, Algorithm 1 as
published) it synthesises n grasps and reports: share of valid grasps, share of valid grasps with epsilon > 0 (force
closure on the mesh itself), and medians over valid grasps of E, E_g, E_c (cm), penetration (mm); and over all
sampled poses the medians of E and E_g (what the paper's Table I averages, before filtering). A Wilcoxon
signed-rank test compares the samplers' per-object median E as the paper does.
"""

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ffcgs_jax.evaluation import metrics
from ffcgs_jax.geometry import mesh_io, objects
from ffcgs_jax.hand import kinematics as K
from ffcgs_jax.synthesis import grasp_io
from ffcgs_jax.synthesis.config import EnergyConfig, OptimConfig, SamplerConfig
from ffcgs_jax.synthesis.grasp import GraspConfig, synthesize

REPO = Path(__file__).resolve().parents[1]
METHODS = {
    "ours": (EnergyConfig(), OptimConfig()),
    "paper": (EnergyConfig(a_pen=0.0, normal_grad=False), OptimConfig(iters=50, method="gd", wrist=False)),
}


def object_list(ycb: Path, every_file: bool = False) -> list[tuple[str, str]]:
    """The built-in objects, then the YCB test split (sorted index % 5 == 4), or every file of a folder that holds
    only the test split (`--every-file`, e.g. a copy of it on a machine without ../shared)."""
    return [(name, name) for name in objects.names()] + [(f.stem, str(f)) for f in ycb_test(ycb, every_file)]


def ycb_test(ycb: Path, every_file: bool = False) -> list[Path]:
    """The YCB test split of folder `ycb`: its sorted *.stl with index % 5 == 4, or all of them (`every_file`)."""
    files = sorted(ycb.glob("*.stl")) if ycb.is_dir() else []
    return [f for i, f in enumerate(files) if every_file or i % 5 == 4]


def run(args) -> list[dict]:
    hand = K.load_hand("svh")
    rows = []
    objs = object_list(Path(args.ycb), args.every_file)
    jobs = [(o, m, s) for o in objs for m in args.methods.split(",") for s in args.samplers.split(",")]
    meshes = {}
    for (name, src), method, sampler in tqdm(jobs, desc="grasps", unit="run"):
        if name not in meshes:
            meshes[name] = mesh_io.load_mesh(src)
        energy, optim = METHODS[method]
        if args.iters:
            optim = dataclasses.replace(optim, iters=args.iters)
        if args.lp_solver:
            energy = dataclasses.replace(energy, lp_solver=args.lp_solver)
        cfg = GraspConfig(n=args.n, sampler=sampler, seed=args.seed, energy=energy, optim=optim,
                          sampling=SamplerConfig(weights=args.weights, cvae_oversample=args.cvae_oversample))
        gs = synthesize(hand, meshes[name], cfg, name)
        if args.save:  # the grasps themselves, for bench/eval_physics.py
            Path(args.save).mkdir(parents=True, exist_ok=True)
            grasp_io.save_npz(gs, Path(args.save) / f"{name}__{method}__{sampler}.npz")
        a, v = gs.arrays, gs["valid"]
        med = lambda k, s=1.0: float(np.median(a[k][v]) * s) if v.any() else float("nan")  # noqa: E731
        rows.append({
            "object": name, "method": method, "sampler": sampler, "n": int(len(v)), "valid": int(v.sum()),
            "fc": int((a["epsilon"][v] > 0).sum()), "E": med("E"), "E_g": med("E_g"), "E_c_cm": med("E_c", 100),
            "pen_mm": med("penetration", 1000), "eps": med("epsilon"),
            "E_all": float(np.median(a["E"])), "E_g_all": float(np.median(a["E_g"])),
            "E_mean_all": float(np.mean(a["E"])), "E_g_mean_all": float(np.mean(a["E_g"])),
            "synthesis_s": float(a["synthesis_s"]), "compile_s": float(a["compile_s"]),
        })
    return rows


def report(rows: list[dict]) -> None:
    print("| object | method | sampler | valid | eps>0 | E | E_g | E_c (cm) | pen (mm) | E all | E_g all | time (s) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['object']} | {r['method']} | {r['sampler']} | {r['valid']}/{r['n']} | {r['fc']} | {r['E']:.3f} | "
              f"{r['E_g']:.3f} | {r['E_c_cm']:.2f} | {r['pen_mm']:.1f} | {r['E_all']:.3f} | {r['E_g_all']:.3f} | "
              f"{r['synthesis_s']:.2f} |")
    print()
    print("| method | sampler | objects | valid share | eps>0 share of valid | median E | median E_g | median E_c (cm) "
          "| median E (all) | median E_g (all) | mean E (all) | mean E_g (all) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    keys = sorted({(r["method"], r["sampler"]) for r in rows})
    for m, s in keys:
        rs = [r for r in rows if r["method"] == m and r["sampler"] == s]
        nv = sum(r["valid"] for r in rs)
        md = lambda k: np.nanmedian([r[k] for r in rs])  # noqa: E731
        print(f"| {m} | {s} | {len(rs)} | {nv / sum(r['n'] for r in rs):.1%} | "
              f"{sum(r['fc'] for r in rs) / max(nv, 1):.1%} | {md('E'):.3f} | {md('E_g'):.3f} | {md('E_c_cm'):.2f} | "
              f"{md('E_all'):.3f} | {md('E_g_all'):.3f} | {np.mean([r['E_mean_all'] for r in rs]):.3f} | "
              f"{np.mean([r['E_g_mean_all'] for r in rs]):.3f} |")
    samplers = sorted({r["sampler"] for r in rows})
    for m in sorted({r["method"] for r in rows}):
        for i, s1 in enumerate(samplers):
            for s2 in samplers[i + 1:]:
                a = [r["E_all"] for r in rows if r["method"] == m and r["sampler"] == s1]
                b = [r["E_all"] for r in rows if r["method"] == m and r["sampler"] == s2]
                if len(a) == len(b) and len(a) > 1:
                    stat, p = metrics.wilcoxon(np.array(a), np.array(b))
                    print(f"\nWilcoxon signed-rank, {m}: per-object median E (all poses), {s1} vs {s2}: "
                          f"statistic {stat:.1f}, p = {p:.2g} over {len(a)} objects")
    for s in sorted({r["sampler"] for r in rows}):
        a = [r["E_all"] for r in rows if r["method"] == "ours" and r["sampler"] == s]
        b = [r["E_all"] for r in rows if r["method"] == "paper" and r["sampler"] == s]
        if len(a) == len(b) and len(a) > 1:
            stat, p = metrics.wilcoxon(np.array(a), np.array(b))
            print(f"Wilcoxon signed-rank, {s}: per-object median E (all poses), ours vs paper: "
                  f"statistic {stat:.1f}, p = {p:.2g} over {len(a)} objects")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ycb", default=str(REPO.parent / "shared" / "objects" / "ycb"))
    ap.add_argument("--n", type=int, default=32)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--methods", default="ours,paper")
    ap.add_argument("--samplers", default="geometric,random")
    ap.add_argument("--json", help="also write the rows to this JSON file")
    ap.add_argument("--every-file", action="store_true", help="--ycb holds only the test split: take every file")
    ap.add_argument("--save", help="also write each run's grasps to DIR/OBJECT__METHOD__SAMPLER.npz")
    ap.add_argument("--iters", type=int, default=0, help="optimiser iterations for every method (0: each method's)")
    ap.add_argument("--weights", default="", help="cvae sampler weights (default: the shipped ones)")
    ap.add_argument("--lp-solver", default="", help="energy.lp_solver for every method (default: each method's)")
    ap.add_argument("--cvae-oversample", type=int, default=SamplerConfig().cvae_oversample,
                    help="cvae candidates decoded per pose (sampling.cvae_oversample)")
    args = ap.parse_args()
    t0 = time.perf_counter()
    rows = run(args)
    report(rows)
    print(f"\n{len(rows)} runs in {time.perf_counter() - t0:.0f} s")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
