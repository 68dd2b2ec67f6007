"""How well each order puts a grasp that holds first, on objects no score or network was fitted on.

    python bench/quality.py --objects ycb-test,builtin,procedural,complex --complex 40 --samplers cvae \\
        --protocols lift-shake,six-dir,dexgraspbench --backend cpu --save-grasps grasps/ --json q.json
    python bench/rank_quality.py grasps/cvae --ycb YCB [--evaluator weights.npz] [--png reliability.png]

Reads the grasp files `bench/quality.py --save-grasps` wrote (every returned grasp physics-tested, outcomes beside
the grasps), computes the success predictor's `pred_success` on each object's SDF (built here from the same mesh
and SDF settings as the synthesis), and reports per object set, over the returned (valid) grasps, without physics
in the loop:
    - top-1 / top-5: the object's first (any of its first five) returned grasps pass lift-shake and six-dir (and,
      apart, dexgraspbench), ordered by the predictor, by E (the analytic order), and a random order's
      expectation; an object without a returned grasp counts as a failure;
    - within-object AUC (mean over objects with both outcomes) and pooled AUC of the predictor and of each
      analytic figure (DexGraspBench-style: each metric's ROC AUC against the simulated outcome, sign chosen so
      that higher means better), and the predictor's calibration (expected calibration error, reliability curve).
Object groups are recognised by name: the YCB test split (files of --ycb), the built-ins, `proc_*` (seed 1000) and
`cplx_*` (seed 2000), the held-out sets of bench/quality.py.
"""

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from ffcgs_jax.core import files  # noqa: E402
from ffcgs_jax.evaluation import rank_metrics as M  # noqa: E402

BOTH = ("lift_shake", "six_dir")
ANALYTIC = {"epsilon": 1, "E": -1, "E_g": -1, "E_c": -1, "E_q": -1, "E_m": -1, "support_min": 1, "penetration": -1}


def group_of(name: str, ycb: Path | None) -> str:
    if name.startswith("cplx_"):
        return "complex"
    if name.startswith("proc_"):
        return "procedural"
    if ycb is not None and (ycb / f"{name}.stl").is_file():
        return "ycb-test"
    return "builtin"


def mesh_of(name: str, group: str, ycb: Path | None):
    from ffcgs_jax.geometry import mesh_io, objects, procedural

    if group == "complex":
        return procedural.complex_shape(2000, int(name.split("_")[1]))[1]
    if group == "procedural":
        return procedural.shape(1000, int(name.split("_")[1]))[1]
    if group == "ycb-test":
        return mesh_io.load_mesh(ycb / f"{name}.stl")
    return mesh_io.load_mesh(objects.path(name))


def load(folder: Path, ycb: Path | None, evaluator: str) -> list[dict]:
    """Per object: its group, arrays and the predictor's output."""
    from ffcgs_jax.geometry import sdf as sdf_mod
    from ffcgs_jax.hand import kinematics as K
    from ffcgs_jax.synthesis import prediction
    from ffcgs_jax.synthesis.grasp import load_grasps

    hand = K.load_hand("svh")
    predictor = prediction.weights_for(hand, evaluator)
    if predictor is None:
        raise SystemExit("rank_quality: no success predictor ships for the SVH; pass --evaluator")
    out = []
    for path in sorted(folder.glob("*.npz")):
        gs = load_grasps(path)
        group = group_of(gs.object_name, ycb)
        a = dict(gs.arrays)
        if len(a["q"]):
            grid = sdf_mod.build_sdf(mesh_of(gs.object_name, group, ycb), gs.config.sdf)
            a |= prediction.predictions(*predictor, hand, grid, a)
        out.append({"name": gs.object_name, "group": group, "arrays": a})
    return out


def object_rows(objs: list[dict], label_keys: tuple[str, ...]) -> dict:
    """Pooled per-grasp arrays of the returned grasps (score columns, label, object id) of `objs`."""
    cols = {k: [] for k in ("pred", *ANALYTIC)}
    y, gid = [], []
    for i, o in enumerate(objs):
        a = o["arrays"]
        v = np.asarray(a["valid"], bool) & np.asarray(a.get("physics_tested", a["valid"]), bool)
        ok = np.ones(len(v), bool)
        for k in label_keys:  # an object without a returned grasp was not simulated: nothing of it passes
            ok &= np.asarray(a.get(f"physics_{k}_success", np.zeros(len(v), bool)), bool)
        cols["pred"].append(np.asarray(a.get("pred_success", np.zeros(len(v))))[v])
        for k, sign in ANALYTIC.items():
            cols[k].append(sign * np.asarray(a[k], float)[v])
        y.append(ok[v])
        gid.append(np.full(int(v.sum()), i))
    return {k: np.concatenate(v) for k, v in cols.items()} | {"y": np.concatenate(y), "gid": np.concatenate(gid)}


def first_k(objs: list[dict], rows: dict, key: str, k: int) -> int:
    """Objects whose k best returned grasps by `key` include one that passes (no returned grasp: a failure)."""
    hits = M.top_k(rows[key], rows["y"], rows["gid"], k) if len(rows["y"]) else np.zeros(0, bool)
    return int(hits.sum())


def report(objs: list[dict], name: str) -> tuple[list[str], dict]:
    n = len(objs)
    fig = {"objects": n}
    lines = []
    for labels, tag in ((BOTH, "lift-shake and six-dir"), (("dexgraspbench",), "dexgraspbench")):
        if not any(f"physics_{labels[0]}_success" in o["arrays"] for o in objs):
            continue
        rows = object_rows(objs, labels)
        rand1 = float(M.random_top1(rows["y"], rows["gid"]).sum()) if len(rows["y"]) else 0.0
        cells = []
        for key, label in (("pred", "predicted"), ("E", "E")):
            t1, t5 = first_k(objs, rows, key, 1), first_k(objs, rows, key, 5)
            w, nw = M.within_auc(rows[key], rows["y"], rows["gid"])
            fig[f"{tag}:{key}"] = {"top1": t1, "top5": t5, "within_auc": w, "pooled_auc": M.auc(rows[key], rows["y"])}
            cells.append(f"{t1} / {t5} / {w:.3f}")
        fig[f"{tag}:random_top1"] = rand1
        fig[f"{tag}:any"] = int(sum(bool(rows["y"][rows["gid"] == i].any()) for i in range(n)))
        lines.append(f"| {name} | {tag} | {n} | {' | '.join(cells)} | {rand1:.1f} | {fig[f'{tag}:any']} |")
        if labels == BOTH:
            fig["auc_table"] = {k: (M.auc(rows[k], rows["y"]), M.within_auc(rows[k], rows["y"], rows["gid"])[0])
                                for k in ("pred", *ANALYTIC)}
            fig["reliability"] = M.reliability(rows["pred"], rows["y"])
    return lines, fig


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("folder", help="a --save-grasps row folder of bench/quality.py (e.g. grasps/cvae)")
    ap.add_argument("--ycb", default=None, help="the YCB folder (to recognise test-split objects and load them)")
    ap.add_argument("--evaluator", default="", help="predictor weights (default: the shipped ones)")
    ap.add_argument("--json", default=None)
    ap.add_argument("--png", default=None, help="draw the reliability curve here")
    args = ap.parse_args(argv)
    ycb = Path(args.ycb) if args.ycb else None
    objs = load(Path(args.folder), ycb, args.evaluator)
    sets = {"scoreboard (ycb-test, builtin, procedural)": [o for o in objs if o["group"] != "complex"],
            "complex (seed 2000)": [o for o in objs if o["group"] == "complex"], "all": objs}
    print("| objects | passes | n | predicted: top-1 / top-5 / within-AUC | E | random top-1 (expected) | "
          "objects with any passing |")
    print("|---|---|---|---|---|---|---|")
    out = {}
    for name, sel in sets.items():
        if not sel:
            continue
        lines, fig = report(sel, name)
        out[name] = fig
        print("\n".join(lines))
    allfig = out["all"]
    print("\nAUC against passing lift-shake and six-dir, returned grasps of every object (pooled / within-object):")
    for k, (pooled, within) in allfig["auc_table"].items():
        print(f"  {'predictor' if k == 'pred' else k:<12} {pooled:.3f} / {within:.3f}")
    print(f"calibration: ECE {allfig['reliability']['ece']:.3f}")
    if args.json:
        files.write_text(args.json, json.dumps(out, indent=1, default=float))
    if args.png:
        draw(allfig["reliability"], args.png)
    return 0


def draw(rel: dict, png: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    p, r, n = (np.array(v) for v in zip(*rel["bins"]))
    fig, ax = plt.subplots(figsize=(4, 4))
    ax.plot([0, 1], [0, 1], c="gray", lw=0.8)
    ax.scatter(p, r, s=10 + 80 * n / n.max())
    for x, yv, c in zip(p, r, n):
        ax.annotate(str(c), (x, yv), fontsize=6, xytext=(3, -8), textcoords="offset points")
    ax.set(xlabel="predicted P(lift-shake and six-dir)", ylabel="observed pass rate", xlim=(0, 1), ylim=(0, 1),
           title=f"held-out objects, returned grasps (ECE {rel['ece']:.3f})")
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
