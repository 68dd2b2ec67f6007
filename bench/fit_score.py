"""Fit the grasp `score` (ffcgs_jax/evaluation/score.py) on physics outcomes of the YCB training objects.

    python bench/quality.py --objects ycb-train --samplers cvae --json train.json     # physics on every returned grasp
    python bench/fit_score.py train.json [more.json ...] --out ffcgs_jax/evaluation/assets/score.json

Reads the per-grasp records of `bench/quality.py` JSONs (only the `ycb-train` group: a record of another group is
refused, so the test split can never leak into the fit), labels each tested grasp by "passed both protocols",
standardises the features and fits an L2-regularised logistic regression by Newton's method. Prints the AUC of each
feature alone, of the fit on its own data, and leave-one-object-out (the honest estimate).
"""

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from scipy.stats import rankdata

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from ffcgs_jax import files  # noqa: E402
from ffcgs_jax.evaluation import score as S  # noqa: E402

L2 = 1e-2


def auc(s: np.ndarray, y: np.ndarray) -> float:
    """Probability that a random passing grasp scores above a random failing one (ties count half)."""
    r = rankdata(s)
    n1 = y.sum()
    n0 = len(y) - n1
    return float((r[y].sum() - n1 * (n1 + 1) / 2) / (n1 * n0)) if n1 and n0 else float("nan")


def dataset(paths: list[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Features (N, F), labels (N,) and object names (N,) of every physics-tested grasp in the JSONs."""
    X, y, obj = [], [], []
    for path in paths:
        report = json.loads(Path(path).read_text())
        for rec in report["records"]:
            if rec["group"] != "ycb-train":
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
            obj += [rec["object"]] * len(t)
    return np.concatenate(X), np.concatenate(y), np.asarray(obj)


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
    args = ap.parse_args(argv)
    F, y, obj = dataset(args.reports)
    print(f"{len(y)} grasps on {len(set(obj))} objects, {y.mean():.1%} pass both protocols")
    for i, name in enumerate(S.FEATURES):
        print(f"  AUC of {name:<22} {auc(F[:, i], y):.3f}")
    cv = np.zeros(len(y))
    for o in np.unique(obj):
        held = obj == o
        cv[held] = S.logit(F[held], fit(F[~held], y[~held]))
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
