"""Batches padded to a fixed size, so that compiled work sees one shape and is reused: the SDF builder's jitted
kernels (`geometry.sdf_build`) and the physics backends' fixed world counts (`physics.backend_mjx`,
`physics.backend_warp`), and the success predictor's calls (`synthesis.prediction`)."""

import numpy as np


def pad_rows(x, n: int) -> np.ndarray:
    """`x` with its first row repeated up to n rows (`x` itself if it has n or more). The padding rows are real
    inputs, so kernels and simulations run them without special cases; callers drop their results."""
    x = np.asarray(x)
    return np.concatenate([x, np.repeat(x[:1], n - len(x), axis=0)]) if len(x) < n else x
