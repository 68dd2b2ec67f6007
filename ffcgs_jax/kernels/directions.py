"""Unit wrench directions on S^5 shared by every Q-distance: the float64 reference (`evaluation.metrics`), the
device evaluation and the in-graph LP (`kernels.quality.basis`). NumPy only."""

import numpy as np
from jaxtyping import Float

from ffcgs_jax.core.errors import FfcgsError

N_FIXED = 12  # the ±e_i that open every `sphere_basis`
REPULSION_STEPS = 200  # iterations of `sphere_basis`'s repulsion; part of its definition, do not change casually


def sphere_basis(K: int, seed: int = 0) -> Float[np.ndarray, "6 K"]:
    """K unit directions on S^5 for the Q-distance: ±e_1..±e_6, then K-12 well-spread points.

    The first 12 columns are e_1, -e_1, ..., e_6, -e_6 (so the set positively spans R^6 whatever follows). The
    other K-12 start as normalised `np.random.default_rng(seed).standard_normal((K-12, 6))` and take
    `REPULSION_STEPS` steps of Coulomb repulsion (1/r potential) from all other points and their antipodes,
    projected on the sphere, with a step shrinking linearly from 0.1 to 0.01 rad while the 12 axes stay fixed.
    Pure float64 NumPy with a fixed number of operations: the same K and seed give the same array on a given
    NumPy (the PCG64 normal stream has been stable since NumPy 1.17). The JAX path must use this function.

    Args:
        K: number of directions, >= 12.
        seed: seed of the starting points.

    Returns:
        (6, K) unit columns.
    """
    if isinstance(K, bool) or not isinstance(K, (int, np.integer)) or K < N_FIXED:
        raise FfcgsError(f"sphere_basis needs an integer K >= {N_FIXED}, got {K!r}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise FfcgsError(f"seed must be an integer >= 0, got {seed!r}")
    fixed = np.zeros((N_FIXED, 6))
    fixed[0::2] = np.eye(6)
    fixed[1::2] = -np.eye(6)
    free = np.random.default_rng(int(seed)).standard_normal((int(K) - N_FIXED, 6))
    free /= np.linalg.norm(free, axis=1, keepdims=True)
    nf = len(free)
    if nf > 0:
        eye = np.eye(nf, dtype=bool)
        for step in np.linspace(0.1, 0.01, REPULSION_STEPS):
            force = np.zeros_like(free)
            for others, self_rows in ((free, eye), (-free, None), (fixed, None)):
                diff = free[:, None, :] - others[None, :, :]
                r = np.linalg.norm(diff, axis=2)
                if self_rows is not None:
                    r = np.where(self_rows, np.inf, r)
                r = np.maximum(r, 1e-9)
                force += (diff / r[..., None] ** 3).sum(axis=1)
            force -= (force * free).sum(axis=1, keepdims=True) * free  # tangent part
            size = np.linalg.norm(force, axis=1, keepdims=True)
            free = free + step * force / np.maximum(size.max(), 1e-300)
            free /= np.linalg.norm(free, axis=1, keepdims=True)
    return np.concatenate([fixed, free], axis=0).T.copy()
