"""How well a score ranks physics outcomes: ROC AUC pooled and within groups (the grasps of one object, or of one
synthesis call), first-grasp success, and a reliability curve. NumPy only; higher scores mean "more likely to pass".

Within-group figures are what ranking needs: a user gets one object's grasps, so telling objects apart (which
dominates a pooled AUC) does not put the grasp that holds first.
"""

import numpy as np


def _ranks(s: np.ndarray) -> np.ndarray:
    """1-based ranks of `s`, ties sharing their average rank."""
    order = np.argsort(s, kind="stable")
    sorted_s = s[order]
    first = np.r_[True, sorted_s[1:] != sorted_s[:-1]]
    starts = np.flatnonzero(first)
    ends = np.r_[starts[1:], len(s)]
    avg = (starts + ends + 1) / 2.0  # mean of the 1-based ranks starts+1 .. ends
    r = np.empty(len(s))
    r[order] = np.repeat(avg, ends - starts)
    return r


def auc(score: np.ndarray, label: np.ndarray) -> float:
    """P(a random positive scores above a random negative), ties half; NaN without both classes."""
    score, label = np.asarray(score, np.float64), np.asarray(label, bool)
    n1 = int(label.sum())
    n0 = len(label) - n1
    if not n1 or not n0:
        return float("nan")
    r = _ranks(score)
    return float((r[label].sum() - n1 * (n1 + 1) / 2) / (n1 * n0))


def within_auc(score: np.ndarray, label: np.ndarray, group: np.ndarray) -> tuple[float, int]:
    """(mean AUC over the groups that have both outcomes, how many groups that is)."""
    vals = [auc(score[group == g], label[group == g]) for g in np.unique(group)]
    vals = [v for v in vals if np.isfinite(v)]
    return (float(np.mean(vals)) if vals else float("nan")), len(vals)


def top_k(score: np.ndarray, label: np.ndarray, group: np.ndarray, k: int = 1) -> np.ndarray:
    """Per group (in np.unique order): does any of its k best-scored members pass? Ties go to the lower index,
    as `np.lexsort` orders them."""
    out = []
    for g in np.unique(group):
        idx = np.flatnonzero(group == g)
        best = idx[np.lexsort((idx, -score[idx]))][:k]
        out.append(bool(np.asarray(label)[best].any()))
    return np.asarray(out)


def first_valid_holds(score: np.ndarray, label: np.ndarray, group: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Per group (in np.unique order): does its best-scored valid member pass? A group without a valid member
    fails (a user offered nothing holds nothing)."""
    out = []
    for g in np.unique(group):
        rows = (group == g) & valid
        out.append(bool(rows.any() and top_k(score[rows], label[rows], group[rows]).any()))
    return np.asarray(out, bool)


def random_top1(label: np.ndarray, group: np.ndarray) -> np.ndarray:
    """Per group: the chance a random order puts a passing member first (its pass rate)."""
    return np.asarray([np.mean(np.asarray(label)[group == g]) for g in np.unique(group)])


def reliability(prob: np.ndarray, label: np.ndarray, bins: int = 10) -> dict:
    """Calibration: per equal-width probability bin the mean prediction, the observed pass rate and the count;
    and the expected calibration error (count-weighted |prediction - rate|)."""
    prob, label = np.asarray(prob, np.float64), np.asarray(label, np.float64)
    which = np.clip((prob * bins).astype(int), 0, bins - 1)
    rows = []
    for b in range(bins):
        m = which == b
        if m.any():
            rows.append((float(prob[m].mean()), float(label[m].mean()), int(m.sum())))
    ece = sum(n * abs(p - r) for p, r, n in rows) / max(len(prob), 1)
    return {"bins": rows, "ece": float(ece)}
