"""Fit the grasp `score` (ffcgs_jax/evaluation/score.py) on physics outcomes of the YCB training objects.

    python bench/quality.py --objects ycb-train --samplers cvae --json train.json     # physics on every returned grasp
    python bench/fit_score.py train.json [more.json ...] --out ffcgs_jax/evaluation/assets/score.json
    python bench/fit_score.py --evaluate test.json      # the shipped score on any objects (e.g. the test split)

Reads the per-grasp records of `bench/quality.py` JSONs (only the `ycb-train` group: a record of another group is
refused, so the test split can never leak into the fit), labels each tested grasp by "passed both protocols",
standardises the features and fits an L2-regularised logistic regression by Newton's method. Prints the AUC of each
feature alone, of the fit on its own data, and leave-one-object-out (the honest estimate); and how well the score
(leave-one-object-out), E and a random order rank the grasps of one synthesis call: mean within-call AUC and top-1.
"""

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from ffcgs_jax.core import files  # noqa: E402
from ffcgs_jax.evaluation import rank_metrics as M  # noqa: E402
from ffcgs_jax.evaluation import score as S  # noqa: E402

L2 = 1e-2


auc = M.auc  # the project's one AUC (ties count half); kept under this name for the script's callers


def dataset(paths: list[str], train_only: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Features (N, F), labels (N,), groups (N,: one per object and run, the grasps one synthesis call returned)
    and E (N,) of every physics-tested grasp in the JSONs."""
    X, y, obj, E = [], [], [], []
    for path in paths:
        report = json.loads(Path(path).read_text())
        for rec in report["records"]:
            if train_only and rec["group"] != "ycb-train":
                raise SystemExit(f"fit_score: {path} holds {rec['object']} of group {rec['group']}: fit on "
                                 "ycb-train only")
            t = np.asarray(rec["tested"], int)
            if not len(t):
                continue
            ok = np.ones(len(t), bool)
            for p in ("lift_shake", "six_dir"):
                ok &= np.asarray(rec["physics"][f"{p}_success"], bool)
            arrays = {k: np.asarray(rec[k], float)[t] for k in ("epsilon", "E_c", "penetration", "E_q",
                                                                  "table_penetration", "contact_dist")}
            X.append(S.features(arrays))
            y.append(ok)
            E.append(np.asarray(rec["E"], float)[t])
            obj += [f"{rec['object']}@{Path(path).name}:{rec['row']}"] * len(t)
    return np.concatenate(X), np.concatenate(y), np.asarray(obj), np.concatenate(E)


def within(s: np.ndarray, y: np.ndarray, groups: np.ndarray) -> tuple[float, float]:
    """How well `s` (higher = better) ranks grasps within one call: mean AUC over groups with both outcomes, and the
    share of groups whose best-scored grasp passes (top-1)."""
    return M.within_auc(s, y, groups)[0], float(M.top_k(s, y, groups, 1).mean())


def fit(F: np.ndarray, y: np.ndarray) -> dict:
    mean, scale = F.mean(0), F.std(0) + 1e-12
    Z = np.column_stack([(F - mean) / scale, np.ones(len(F))])
    reg = L2 * np.r_[np.ones(F.shape[1]), 0.0]
    w = np.zeros(Z.shape[1])
    for _ in range(100):
        p = 1 / (1 + np.exp(-Z @ w))
        step = np.linalg.solve((Z * (p * (1 - p))[:, None]).T @ Z + np.diag(reg), Z.T @ (p - y) + reg * w)
        w -= step
        if np.abs(step).max() < 1e-10:
            break
    return {"features": list(S.FEATURES), "mean": mean.tolist(), "scale": scale.tolist(),
            "weights": w[:-1].tolist(), "bias": float(w[-1])}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("reports", nargs="+", help="bench/quality.py --json files of the ycb-train group")
    ap.add_argument("--out", help="write the model JSON here")
    ap.add_argument("--evaluate", action="store_true", help="no fit: how the shipped score ranks these grasps")
    args = ap.parse_args(argv)
    if args.evaluate:
        F, y, groups, E = dataset(args.reports, train_only=False)
        s = S.logit(F, S.model())
        print(f"{len(y)} grasps, {y.mean():.1%} pass both protocols; AUC: score {auc(s, y):.3f}, epsilon "
              f"{auc(F[:, 0], y):.3f}, -E {auc(-E, y):.3f}")
        for name, v in (("score", s), ("-E (the order of GraspSet.order)", -E)):
            a, top = within(v, y, groups)
            print(f"  within one call, {name:<34} AUC {a:.3f}  top-1 {top:.1%}")
        return 0
    F, y, groups, E = dataset(args.reports)
    obj = np.asarray([g.split("@")[0] for g in groups])
    print(f"{len(y)} grasps on {len(set(obj))} objects, {y.mean():.1%} pass both protocols")
    for i, name in enumerate(S.FEATURES):
        print(f"  AUC of {name:<22} {auc(F[:, i], y):.3f}")
    cv = np.zeros(len(y))
    for o in np.unique(obj):
        held = obj == o
        cv[held] = S.logit(F[held], fit(F[~held], y[~held]))
    rank = {"score (leave-one-object-out)": within(cv, y, groups),
            "-E (the order of GraspSet.order)": within(-E, y, groups),
            "random order": (0.5, float(np.mean([y[groups == g].mean() for g in np.unique(groups)])))}
    for name, (a, top) in rank.items():
        print(f"  within one call, {name:<34} AUC {a:.3f}  top-1 {top:.1%}")
    m = fit(F, y)
    m.update(grasps=int(len(y)), objects=int(len(set(obj))), pass_rate=float(y.mean()),
             auc_fit=auc(S.logit(F, m), y), auc_leave_one_object_out=auc(cv, y), sources=[Path(p).name for p in
                                                                                          args.reports])
    print(f"score AUC: {m['auc_fit']:.3f} on its own data, {m['auc_leave_one_object_out']:.3f} leave-one-object-out")
    if args.out:
        files.write_text(args.out, json.dumps(m, indent=1) + "\n")
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
