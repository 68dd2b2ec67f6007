"""The one order in which grasps are offered: the order of `GraspSet.order`, the viewer, pictures and logs.

Grasps that passed every physics protocol they were checked with (`physics_passed`, written by
`physics.validate.validate`) come first, then valid grasps, then the rest; within each group by increasing E (the
analytic order: within one object E ranked physics outcomes better than `score` on the training objects,
bench/RESULTS.md "Grasp quality"), ties by index, so the same grasps always give the same order.
"""

import numpy as np


def ranked(arrays: dict) -> np.ndarray:
    """Grasp indices in the offered order (module docstring) of a grasp set's or a grasp file's arrays; files
    without `valid` or `E` count every grasp valid and equal."""
    n = len(arrays["valid"] if "valid" in arrays else arrays["q"])
    valid = np.asarray(arrays.get("valid", np.ones(n, bool)), bool)
    E = np.asarray(arrays.get("E", np.zeros(n)), float)
    passed = np.asarray(arrays.get("physics_passed", np.zeros(n, bool)), bool)
    return np.lexsort((np.arange(n), E, ~valid, ~passed))
