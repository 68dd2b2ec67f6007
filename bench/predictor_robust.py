"""Success predictors side by side on held-out robust labels: how each ranks the candidates of objects it never
saw, against the robust verdict (`physics.robust`: 8 perturbed trials, a grasp holds at 7 or 8 of 8).

    ffcgs dataset build --objects YCB --split test --allow-test --keep all --sampler cvae --per-object 64 \\
        --rotations 1 --out held_ycb.mcap
    ffcgs dataset build --split train --complex 40 --seed 4500 --allow-test --keep all --sampler cvae \\
        --per-object 64 --rotations 1 --out held_cplx.mcap
    python bench/predictor_robust.py held_ycb.mcap held_cplx.mcap --weights shipped new/weights.npz [--json f]

Per labels file and predictor, over the valid candidates (what a user is offered) of each object:
    - within-object AUC of the "all" head against holding lift-shake and six-dir (the issue's figure), and against
      the joint pass rate's order (Spearman-free: AUC of "rate >= 0.5");
    - top-1: the object's first valid candidate by the predictor holds both; by E; a random order's expectation;
    - DexGraspBench: top-1 by the predictor's dexgraspbench head where it has one, else by its "all" head;
    - pooled AUC of each protocol head the predictor has.
"""

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from ffcgs_jax.evaluation import rank_metrics as M  # noqa: E402
from ffcgs_jax.hand import kinematics as K  # noqa: E402
from ffcgs_jax.learning.weights import load_evaluator, shipped_evaluator  # noqa: E402
from ffcgs_jax.training import evaluator_data, evaluator_train  # noqa: E402


def columns(weights_meta: dict, heads: tuple[str, ...], prob: np.ndarray) -> dict[str, np.ndarray]:
    """The predictor's probability per head name of the labels ("all" as is; a missing protocol: None)."""
    own = list(weights_meta["heads"])
    return {h: (prob[:, own.index(h)] if h in own else None) for h in heads}


def figures(data: evaluator_data.LabelData, col: dict) -> dict:
    hit = evaluator_data.positives(data)
    v, obj = data.valid, data.objects
    heads = list(data.heads)
    both, p = hit[:, -1], col["all"]
    out = {"objects": int(len(np.unique(obj))), "candidates": int(len(obj)), "valid": int(v.sum()),
           "holds_both": int(both[v].sum()), "objects_with_holder": int(sum(both[v & (obj == o)].any()
                                                                            for o in np.unique(obj)))}
    out["within_auc"], out["within_objects"] = M.within_auc(p[v], both[v], obj[v])
    out["within_auc_rate50"], _ = M.within_auc(p[v], data.y[v, -1] >= 0.5, obj[v])
    out["within_auc_E"], _ = M.within_auc(-data.E[v], both[v], obj[v])
    # an object without a valid candidate counts as a failure of every order
    per = lambda s, lab: int(M.first_valid_holds(s, lab, obj, v).sum())  # noqa: E731
    n = out["objects"]
    out["top1_pred"] = per(p, both) / n
    out["top1_E"] = per(-data.E, both) / n
    out["top1_random"] = float(sum(M.random_top1(both[v], obj[v]))) / n
    if "dexgraspbench" in heads:
        d = hit[:, heads.index("dexgraspbench")]
        own = col["dexgraspbench"]
        out["dgb_top1_pred"] = per(own if own is not None else p, d) / n
        out["dgb_head"] = own is not None
        out["dgb_top1_E"] = per(-data.E, d) / n
    for h in heads[:-1]:
        if col[h] is not None:
            out[f"auc_{h}"] = M.auc(col[h], hit[:, heads.index(h)])
    return out


def concat(parts: list[evaluator_data.LabelData]) -> evaluator_data.LabelData:
    """Label sets of one build's kind as one (objects keep their names: files must not share one)."""
    if len({d.heads for d in parts}) > 1:
        raise SystemExit("the labels files carry different protocols")
    names = [set(d.objects.tolist()) for d in parts]
    if sum(map(len, names)) != len(set().union(*names)):
        raise SystemExit("two labels files share an object name")
    return evaluator_data.LabelData(*(np.concatenate([getattr(d, f) for d in parts]) if f != "heads" else parts[0].heads
                                      for f in evaluator_data.LabelData._fields))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("labels", nargs="+", help="held-out labelled dataset files (robust builds)")
    ap.add_argument("--weights", nargs="+", default=["shipped"], help="predictor files; 'shipped' is the package's")
    ap.add_argument("--hand", default="svh")
    ap.add_argument("--json", default="")
    a = ap.parse_args()
    hand = K.load_hand(a.hand)
    rows = []
    sets = [(Path(p).name, evaluator_data.load(p, hand, progress=False, held_out=True)) for p in a.labels]
    if len(sets) > 1:
        sets.append(("all files", concat([d for _, d in sets])))
    for name, data in sets:
        for w in a.weights:
            wpath = shipped_evaluator(hand.spec.name) if w == "shipped" else Path(w)
            weights, meta = load_evaluator(wpath, hand)
            prob = evaluator_train.predict_rows(weights, data.x)
            rows.append({"labels": name, "weights": w, "heads": meta["heads"]}
                        | figures(data, columns(meta, data.heads, prob)))
    print("| labels | predictor | objects | within-object AUC, holds both (valid) | E's | top-1 holds both: "
          "predicted / E / random | some valid candidate holds both | top-1 holds DexGraspBench: predicted / E |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        dgb = (f"{r['dgb_top1_pred']:.1%}{'' if r['dgb_head'] else ' (all head)'} / {r['dgb_top1_E']:.1%}"
               if "dgb_top1_pred" in r else "-")
        print(f"| {r['labels']} | {r['weights']} | {r['objects']} ({r['within_objects']} ranked) | "
              f"{r['within_auc']:.3f} | {r['within_auc_E']:.3f} | {r['top1_pred']:.1%} / {r['top1_E']:.1%} / "
              f"{r['top1_random']:.1%} | {r['objects_with_holder'] / r['objects']:.1%} | {dgb} |")
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1, default=float))


if __name__ == "__main__":
    main()
