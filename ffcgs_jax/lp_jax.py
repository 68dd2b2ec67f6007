"""The Q-distance LP solved inside the compiled graph: a dense revised simplex with a fixed pivot budget.

Same LP and interface as `lp_host.py` (the ProxSuite reference path), in standard form:

    E_g = min c^T x   s.t.   A x = b,  x >= 0,    x = [rho (K), alpha (N)],   c = [1 (K), 0 (N)]
    A = [[U, -W], [0, 1^T]]  (7 x (K + N)),     b = [0 (6), 1]

Its dual is lp_host's: max t s.t. U^T lam <= 1, t <= w_i^T lam, with y = [lam, t] the simplex multipliers. So one
basis gives the value, lam (the separating direction) and alpha (the hull weights), and the backward pass is the
same envelope-theorem gradient dE_g/dW = lam alpha^T.

Why a simplex: the LP has 7 rows, so a basis is a 7 x 7 matrix and a pivot costs three 7 x 7 solves. It ends at
an exact vertex (values agree with HiGHS to rounding), where a first-order method would need thousands of steps
to reach 1e-6 on the degenerate instances (origin inside the hull) that force closure produces.

Start without phase 1: U holds +-e_i (`quality.basis`), so {sign(w_0i) e_i for i < 6} plus alpha_0 is a feasible
basis: rho_i = |w_0i|, alpha_0 = 1.

Pivoting: Dantzig's rule (most negative reduced cost), switching to Bland's rule (lowest index) after
`_BLAND_AFTER` consecutive degenerate pivots, which rules out cycling. A solve that has not reached optimality
within `max_iter` pivots returns ok = False (callers mask it, as for the host path).
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.linalg import lu_factor, lu_solve

from ffcgs_jax.types import Array, Bool, Float

MAX_ITER = 100  # pivots; instances of this size took at most about 40 (tests/test_lp_jax.py)
_BLAND_AFTER = 8


def _tol(dtype) -> float:
    """Optimality / pivot tolerance: a few hundred ulps of the O(1) entries."""
    return 1e-9 if jnp.finfo(dtype).bits == 64 else 1e-5


def _axis_columns(U: np.ndarray) -> np.ndarray:
    """Indices (2, 6) of the +e_i and -e_i columns of U."""
    out = np.zeros((2, 6), np.int32)
    for s, sign in enumerate((1.0, -1.0)):
        for i in range(6):
            hits = np.flatnonzero(np.all(np.isclose(U, sign * np.eye(6)[:, i:i + 1], atol=1e-12), axis=0))
            if not len(hits):
                raise ValueError("the LP basis U must contain +-e_i for a phase-1-free start")
            out[s, i] = hits[0]
    return out


def solve(W: Float[Array, "6 N"], U: Float[Array, "6 K"], axes: np.ndarray, max_iter: int = MAX_ITER):
    """One LP; see the module docstring. Returns (value, lam (6,), alpha (N,), ok). vmap batches it."""
    dt = W.dtype
    K, N = U.shape[1], W.shape[1]
    tol = _tol(dt)
    A = jnp.concatenate([jnp.concatenate([U.astype(dt), -W], 1),
                         jnp.concatenate([jnp.zeros((1, K), dt), jnp.ones((1, N), dt)], 1)], 0)
    c = jnp.concatenate([jnp.ones(K, dt), jnp.zeros(N, dt)])
    b = jnp.zeros(7, dt).at[6].set(1.0)
    basis0 = jnp.concatenate([jnp.where(W[:, 0] >= 0, axes[0], axes[1]), jnp.array([K], jnp.int32)])
    cols = jnp.arange(K + N)

    def step(state):
        basis, it, degenerate, done, ok = state
        lu = lu_factor(A[:, basis])
        xB = lu_solve(lu, b)
        y = lu_solve(lu, c[basis], trans=1)
        d = c - A.T @ y
        d = jnp.where(jnp.isin(cols, basis), 0.0, d)
        neg = d < -tol
        optimal = ~jnp.any(neg)
        enter = jnp.where(degenerate >= _BLAND_AFTER, jnp.argmax(neg), jnp.argmin(d))
        u = lu_solve(lu, A[:, enter])
        pos = u > tol
        ratio = jnp.where(pos, jnp.maximum(xB, 0.0) / jnp.where(pos, u, 1.0), jnp.inf)
        best = jnp.min(ratio)
        # ties: the lowest basis index leaves (Bland); otherwise the first row attaining the minimum
        tied = ratio <= best + tol
        leave = jnp.argmin(jnp.where(tied, basis, K + N))
        unbounded = ~jnp.any(pos)
        new_basis = basis.at[leave].set(enter.astype(basis.dtype))
        stop = optimal | unbounded
        return (jnp.where(stop, basis, new_basis), it + 1, jnp.where(best <= tol, degenerate + 1, 0),
                stop, optimal)

    def cond(state):
        _, it, _, done, _ = state
        return ~done & (it < max_iter)

    init = (basis0, jnp.zeros((), jnp.int32), jnp.zeros((), jnp.int32), jnp.zeros((), bool), jnp.zeros((), bool))
    basis, _, _, _, ok = jax.lax.while_loop(cond, step, init)
    lu = lu_factor(A[:, basis])
    xB = jnp.maximum(lu_solve(lu, b), 0.0)
    y = lu_solve(lu, c[basis], trans=1)
    value = jnp.maximum(y[6], 0.0)
    alpha = jnp.zeros(K + N, dt).at[basis].set(xB)[K:]
    s = jnp.sum(alpha)
    ok = ok & jnp.isfinite(value) & (s > 0.5)
    alpha = jnp.where(ok, alpha / jnp.where(s > 0, s, 1.0), 0.0)
    lam = jnp.where(ok, y[:6], 0.0)
    return jnp.where(jnp.isfinite(value), value, 0.0), lam, alpha, ok


@functools.partial(jax.custom_vjp, nondiff_argnums=(1, 2))
def _q_distance(W, U_key, max_iter):
    value, _, _, ok = _solve_keyed(W, U_key, max_iter)
    return value, ok


def _solve_keyed(W, U_key, max_iter):
    U, axes = _basis_from_key(*U_key)
    return solve(W, jnp.asarray(U), axes, max_iter)


@functools.lru_cache(maxsize=8)
def _basis_from_key(U_bytes: bytes, K: int):
    U = np.frombuffer(U_bytes, np.float64).reshape(6, K)
    return U, _axis_columns(U)


def _fwd(W, U_key, max_iter):
    value, lam, alpha, ok = _solve_keyed(W, U_key, max_iter)
    return (value, ok), (lam, alpha)


def _bwd(U_key, max_iter, res, cts):
    lam, alpha = res
    g_value, _ = cts
    return (g_value * lam[:, None] * alpha[None, :],)


_q_distance.defvjp(_fwd, _bwd)


def q_distance(W: Float[Array, "6 N"], U: np.ndarray, max_iter: int = MAX_ITER) -> tuple[Float[Array, ""],
                                                                                          Bool[Array, ""]]:
    """Q-distance E_g of primitive wrenches W (6, N) in the gauge of basis U (6, K), and a solve flag, in pure JAX.

    Same contract as `lp_host.q_distance`: differentiable wrt W (reverse mode, dE_g/dW = lam alpha^T); U is a host
    array fixed per configuration; vmap batches it (the pivots of a batch run in lockstep until all are done).
    """
    U = np.ascontiguousarray(U, np.float64)
    return _q_distance(W, (U.tobytes(), U.shape[1]), max_iter)
