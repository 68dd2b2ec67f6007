"""`score`: the probability that a grasp passes both physics tests, from what synthesis already knows.

A logistic model over analytic features of each grasp (`FEATURES`: Ferrari-Canny epsilon with touching fingertips,
its square root, the fingertip distances, penetration into the object and the table, the joint-limit term),
fitted by `bench/fit_score.py` on physics outcomes (lift-shake and six-dir, friction 0.6) of grasps on the YCB
training objects only (sorted index % 5 != 4), never the test split. Its coefficients ship as
`assets/score.json`.

What it is good for: telling likely from unlikely grasps across objects (on 2,358 physics-tested training grasps,
AUC 0.74 leave-one-object-out, where E reaches 0.62 and epsilon 0.73; 0.70 on the test split), e.g. a threshold on
what to execute. What it is not: a better order within one object. There every analytic figure tried is weak
(within-call AUC 0.54 for the score, 0.56 for E; `bench/fit_score.py`), E slightly the better, so `GraspSet.order` keeps E (bench/RESULTS.md, "Grasp quality").
"""

import functools
import json
from importlib import resources

import numpy as np

from ffcgs_jax.core.errors import FfcgsError

FEATURES = ("epsilon", "sqrt_epsilon", "E_c_mm", "penetration_mm", "E_q", "table_penetration_mm", "contact_max_mm")


def features(arrays: dict) -> np.ndarray:
    """(G, F) feature matrix, columns as `FEATURES`, from a GraspSet's arrays (or any dict with its fields)."""
    eps = np.asarray(arrays["epsilon"], np.float64)
    cmax = np.abs(np.asarray(arrays["contact_dist"], np.float64)).max(axis=1)
    return np.column_stack([eps, np.sqrt(np.maximum(eps, 0.0)), 1000 * np.asarray(arrays["E_c"], np.float64),
                            1000 * np.asarray(arrays["penetration"], np.float64), np.asarray(arrays["E_q"], np.float64),
                            1000 * np.asarray(arrays["table_penetration"], np.float64), 1000 * cmax])


@functools.lru_cache(maxsize=1)
def model() -> dict:
    """The shipped model: {"features", "mean", "scale", "weights", "bias", ...provenance}."""
    m = json.loads(resources.files("ffcgs_jax.evaluation").joinpath("assets/score.json").read_text())
    if tuple(m["features"]) != FEATURES:
        raise FfcgsError(f"assets/score.json was fitted on features {m['features']}, this code computes {FEATURES}")
    return m


def logit(F: np.ndarray, m: dict) -> np.ndarray:
    return ((F - np.asarray(m["mean"])) / np.asarray(m["scale"])) @ np.asarray(m["weights"]) + m["bias"]


def score(arrays: dict, m: dict | None = None) -> np.ndarray:
    """(G,) predicted probability of passing both physics tests; 0 where a feature is not finite."""
    F = features(arrays)
    p = 1.0 / (1.0 + np.exp(-logit(np.nan_to_num(F), model() if m is None else m)))
    return np.where(np.isfinite(F).all(axis=1), p, 0.0)
