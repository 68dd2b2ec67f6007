"""The one order in which grasps are offered: the order of `GraspSet.order`, the viewer, pictures and logs.

Grasps that passed every physics protocol they were checked with (`physics_passed`, written by
`physics.validate.validate`) come first, then valid grasps, then the rest; within each group by decreasing
predicted success (`pred_success`, the learned predictor of `synthesis.prediction`) when the arrays were ranked
"predicted" (`rank_by`), else by increasing E (the analytic order); ties by index, so the same grasps always give
the same order. Arrays without `rank_by` (files from before the predictor) rank by E. A robust check
(`physics_rate_low`, the lower bound of the rate of passing every protocol over perturbed trials) orders each of the
first two groups by that bound, highest first, before the rest of the key: the grasp most sure to hold first.
Files without it rank as before.
"""

import numpy as np


def ranked(arrays: dict) -> np.ndarray:
    """Grasp indices in the offered order (module docstring) of a grasp set's or a grasp file's arrays; files
    without `valid` or `E` count every grasp valid and equal."""
    n = len(arrays["valid"] if "valid" in arrays else arrays["q"])
    valid = np.asarray(arrays.get("valid", np.ones(n, bool)), bool)
    E = np.asarray(arrays.get("E", np.zeros(n)), float)
    passed = np.asarray(arrays.get("physics_passed", np.zeros(n, bool)), bool)
    key = -np.asarray(arrays["pred_success"], float) if rank_by(arrays) == "predicted" else E
    if "physics_rate_low" in arrays:  # robust trials: the surer a grasp holds, the sooner; untested ones last
        surety = np.nan_to_num(-np.asarray(arrays["physics_rate_low"], float), nan=1.0)
        return np.lexsort((np.arange(n), key, ~valid, surety, ~passed))
    return np.lexsort((np.arange(n), key, ~valid, ~passed))


def rank_by(arrays: dict) -> str:
    """"predicted" or "energy": how these arrays are ranked (`rank_by` as written, "energy" without predictions)."""
    how = str(arrays.get("rank_by", "energy"))
    return "predicted" if how == "predicted" and "pred_success" in arrays else "energy"
