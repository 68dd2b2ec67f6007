"""The Q-distance LP solved inside the compiled graph: a dense revised simplex with a fixed pivot budget.

Same LP and interface as `lp_host.py` (the ProxSuite reference path), in standard form:

    E_g = min c^T x   s.t.   A x = b,  x >= 0,    x = [rho (K), alpha (N)],   c = [1 (K), 0 (N)]
    A = [[U, -W], [0, 1^T]]  (7 x (K + N)),     b = [0 (6), 1]

Its dual is lp_host's: max t s.t. U^T lam <= 1, t <= w_i^T lam, with y = [lam, t] the simplex multipliers. So one
basis gives the value, lam (the separating direction) and alpha (the hull weights), and the backward pass is the
same envelope-theorem gradient dE_g/dW = lam alpha^T.

Why a simplex: the LP has 7 rows, so a basis is a 7 x 7 matrix. It ends at an exact vertex (values agree with HiGHS
to rounding), where a first-order method would need thousands of steps to reach 1e-6 on the degenerate instances
(origin inside the hull) that force closure produces.

Why an explicit basis inverse: a pivot is then a rank-one update of a 7 x 7 array, elementwise work that XLA fuses
into a few kernels, where LU factorisations and triangular solves are library calls that cannot fuse (on a GPU
they made each pivot a dozen tiny launches). The inverse is recomputed from scratch (Gauss-Jordan) every
few pivots, which also gives the returned solution, so rounding from the updates cannot build up.

Start without phase 1: U holds +-e_i (`quality.basis`), so {sign(w_0i) e_i for i < 6} plus alpha_0 is a feasible
basis: rho_i = |w_0i|, alpha_0 = 1. A warm start (`basis0`, the optimal basis of a nearby LP, e.g. the previous
descent step's) is used instead when it is still a primal-feasible basis of this LP; after a small move of the
wrenches it takes about a third of a cold start's pivots (`bench/lp_warm_pivots.py`, random walks of the contacts:
4.7 against 12.8 on average; the batch's worst LP, which sets a lockstep batch's pace, gains less: 20.9 against
22.6). Where it is not (degenerate vertices, common at force
closure where E_g = 0, turn slightly infeasible) the solve starts cold. Repairing such bases with dual simplex steps
was tried: fewer pivots on average, but a longer worst case, and a batch pivots in lockstep, so it measured slower
(H100, B = 8192: 24k against 42k grasps/s).

Pivoting: the package's shared simplex rules (`simplex.py`): Dantzig's rule (most negative reduced cost),
switching to Bland's rule (lowest index) after `simplex.BLAND_AFTER` consecutive degenerate pivots, which rules out
cycling. A solve that has not reached optimality
within `max_iter` pivots returns ok = False (callers mask it, as for the host path).
"""

import functools
import os
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.kernels import lp_pallas, simplex
from ffcgs_jax.core.types import Array, Bool, Float, Int

MAX_ITER = 100  # pivots; instances of this size took at most about 40 (tests/kernels/test_lp_jax.py)
# Pivots per while-loop trip (the inverse is refreshed after each trip). With XLA pivots on a GPU each trip cost a
# device-to-host check of the loop condition and a dozen launches: 8 measured 46 ms against 51 ms for 4 and 56 ms
# for 2 (H100, 32 grasps x 50 steps). On a CPU the pivots a finished batch still runs are wasted work, so fewer.
# The Pallas kernel uses the same counts, so both paths take the same pivots.
_PIVOTS_PER_TRIP_CPU = 4
_PIVOTS_PER_TRIP_GPU = 8


def _pivots_per_trip() -> int:
    return _PIVOTS_PER_TRIP_CPU if jax.default_backend() == "cpu" else _PIVOTS_PER_TRIP_GPU


def axis_columns(U: np.ndarray) -> np.ndarray:
    """Indices (2, 6) of the +e_i and -e_i columns of U."""
    out = np.zeros((2, 6), np.int32)
    for s, sign in enumerate((1.0, -1.0)):
        for i in range(6):
            hits = np.flatnonzero(np.all(np.isclose(U, sign * np.eye(6)[:, i:i + 1], atol=1e-12), axis=0))
            if not len(hits):
                raise ValueError("the LP basis U must contain +-e_i for a phase-1-free start")
            out[s, i] = hits[0]
    return out


def cold_basis(W: Float[Array, "6 N"], axes: np.ndarray, K: int) -> Int[Array, " 7"]:
    """The phase-1-free feasible start: sign(w_0i) e_i for the six wrench axes, then alpha_0."""
    return jnp.concatenate([jnp.where(W[:, 0] >= 0, axes[0], axes[1]), jnp.array([K], jnp.int32)])


class Solution(NamedTuple):
    value: Float[Array, ""]  # E_g
    lam: Float[Array, " 6"]  # the separating direction (dual)
    alpha: Float[Array, " N"]  # hull weights (primal)
    ok: Bool[Array, ""]  # optimal within the pivot budget
    basis: Int[Array, " 7"]  # the final basis: a warm start for a nearby LP
    pivots: Int[Array, ""]  # pivots taken


def kernel_for(backend: str) -> str:
    """Which implementation runs the pivots: "pallas" (one GPU program per LP, `lp_pallas.py`) on GPUs, "xla"
    elsewhere; the environment variable FFCGS_LP_KERNEL (xla, pallas, auto) overrides it. Read when a function is
    traced, so set it before the first call. "pallas" on a CPU runs Pallas's interpreter (tests only: it is slow)."""
    choice = os.environ.get("FFCGS_LP_KERNEL", "auto").strip().lower() or "auto"
    if choice not in ("auto", "xla", "pallas"):
        raise FfcgsError(f"FFCGS_LP_KERNEL must be auto, xla or pallas, got {choice!r}")
    if choice == "auto":
        return "pallas" if backend in ("gpu", "cuda", "rocm") else "xla"
    return choice


def solve(W: Float[Array, "6 N"], U: Float[Array, "6 K"], axes: np.ndarray, max_iter: int = MAX_ITER,
          basis0: Int[Array, " 7"] | None = None) -> Solution:
    """One LP; see the module docstring. vmap batches it.

    `basis0`, optional: a warm-start basis (column indices), used when it is a primal-feasible basis of this LP
    (7 distinct in-range columns, non-singular, B^-1 b >= 0), otherwise the cold start is; entries < 0 mean
    "none"."""
    dt = W.dtype
    K, N = U.shape[1], W.shape[1]
    tol = simplex.pivot_tol(dt)
    if kernel_for(jax.default_backend()) == "pallas":
        basis, Binv, ok, pivots = lp_pallas.solve_basis(
            W, U, axes, max_iter, jnp.full(7, -1, jnp.int32) if basis0 is None else basis0, tol,
            _pivots_per_trip(), simplex.BLAND_AFTER, interpret=jax.default_backend() == "cpu")
        return _solution(basis, Binv, ok, pivots, K, N)
    A = jnp.concatenate([jnp.concatenate([U.astype(dt), -W], 1),
                         jnp.concatenate([jnp.zeros((1, K), dt), jnp.ones((1, N), dt)], 1)], 0)
    c = jnp.concatenate([jnp.ones(K, dt), jnp.zeros(N, dt)])
    cols = jnp.arange(K + N)
    basis = cold_basis(W, axes, K)
    # the cold basis [[D, -w_0], [0, 1]] (D = diag(+-1)) has the inverse [[D, D w_0], [0, 1]]: no elimination
    sign = jnp.where(W[:, 0] >= 0, 1.0, -1.0).astype(dt)
    Binv = jnp.eye(7, dtype=dt).at[:6, :6].set(jnp.diag(sign)).at[:6, 6].set(sign * W[:, 0])
    if basis0 is not None:
        basis0 = jnp.asarray(basis0, jnp.int32)
        inv0, smallest = simplex.inverse(A[:, jnp.clip(basis0, 0, K + N - 1)])
        usable = (jnp.all(basis0 >= 0) & jnp.all(basis0 < K + N) & (smallest > tol)
                  & jnp.all(inv0[:, 6] >= -tol) & jnp.all(jnp.isfinite(inv0)))
        basis, Binv = jnp.where(usable, basis0, basis), jnp.where(usable, inv0, Binv)

    def reduced_costs(basis, Binv):
        return jnp.where(jnp.isin(cols, basis), 0.0, c - A.T @ (Binv.T @ c[basis]))

    def pivot(state):
        basis, Binv, it, degenerate, done, ok = state
        xB = jnp.maximum(Binv[:, 6], 0.0)  # B^-1 b with b = e_7
        enter, optimal = simplex.entering(reduced_costs(basis, Binv), degenerate, tol)
        u = Binv @ A[:, enter]
        leave, best = simplex.ratio_test(xB, u, basis, tol)
        stop = done | optimal | ~jnp.any(u > tol) | (it >= max_iter)  # no positive u: unbounded (cannot happen)
        # indexed, not one-hot: 7% faster on a CPU (B = 1024, float32); GPUs run the Pallas kernel by default
        new_basis, new_Binv = simplex.exchange(basis, Binv, enter, leave, u, one_hot=False)
        return (jnp.where(stop, basis, new_basis), jnp.where(stop, Binv, new_Binv), it + jnp.where(stop, 0, 1),
                jnp.where(stop, degenerate, simplex.degenerate_run(degenerate, best, tol)),
                stop, jnp.where(done, ok, optimal))

    def refresh(state):
        basis, Binv, it, degenerate, done, ok = state
        # a fresh inverse after every trip: no drift from the rank-one updates, and the returned one is exact.
        # Optimality seen through the updated inverse is confirmed with the fresh one (the same test as `pivot`'s,
        # so a trip that made no pivot always confirms), or the pivots go on; an unconfirmed trip counts against
        # the budget, so the loop ends whatever rounding does.
        Binv = simplex.inverse(A[:, basis])[0]
        confirmed = ~jnp.any(reduced_costs(basis, Binv) < -tol)
        redo = done & ~confirmed
        return basis, Binv, it + redo, degenerate, done & ~(redo & (it < max_iter)), ok & confirmed

    init = (basis, Binv, jnp.zeros((), jnp.int32), jnp.zeros((), jnp.int32), jnp.zeros((), bool),
            jnp.zeros((), bool))
    # a trip's pivots unrolled on every backend, as many as the Pallas kernel's trips (`_pivots_per_trip`)
    basis, Binv, pivots, _, _, ok = simplex.pivot_loop(pivot, refresh, init, max_iter, _pivots_per_trip(), True)
    return _solution(basis, Binv, ok, pivots, K, N)


def _solution(basis, Binv, ok, pivots, K: int, N: int) -> Solution:
    """Value, duals and hull weights read off an optimal basis and its inverse."""
    dt = Binv.dtype
    c = jnp.concatenate([jnp.ones(K, dt), jnp.zeros(N, dt)])
    xB = jnp.maximum(Binv[:, 6], 0.0)
    y = Binv.T @ c[basis]
    value = jnp.maximum(y[6], 0.0)
    alpha = jnp.zeros(K + N, dt).at[basis].set(xB)[K:]
    s = jnp.sum(alpha)
    ok = ok & jnp.isfinite(value) & (s > 0.5)
    alpha = jnp.where(ok, alpha / jnp.where(s > 0, s, 1.0), 0.0)
    lam = jnp.where(ok, y[:6], 0.0)
    return Solution(jnp.where(jnp.isfinite(value), value, 0.0), lam, alpha, ok, basis, pivots)


@functools.partial(jax.custom_vjp, nondiff_argnums=(2, 3))
def _q_distance(W, basis0, U_key, max_iter):
    sol = _solve_keyed(W, basis0, U_key, max_iter)
    return sol.value, sol.ok, sol.basis


def _solve_keyed(W, basis0, U_key, max_iter):
    U, axes = basis_from_key(*U_key)
    return solve(W, jnp.asarray(U), axes, max_iter, basis0)


@functools.lru_cache(maxsize=8)
def basis_from_key(U_bytes: bytes, K: int):
    U = np.frombuffer(U_bytes, np.float64).reshape(6, K)
    return U, axis_columns(U)


def _fwd(W, basis0, U_key, max_iter):
    sol = _solve_keyed(W, basis0, U_key, max_iter)
    return (sol.value, sol.ok, sol.basis), (sol.lam, sol.alpha)


def _bwd(U_key, max_iter, res, cts):
    lam, alpha = res
    g_value = cts[0]
    return g_value * lam[:, None] * alpha[None, :], None


_q_distance.defvjp(_fwd, _bwd)


def q_distance(W: Float[Array, "6 N"], U: np.ndarray, max_iter: int = MAX_ITER,
               basis0: Int[Array, " 7"] | None = None) -> tuple[Float[Array, ""], Bool[Array, ""], Int[Array, " 7"]]:
    """Q-distance E_g of primitive wrenches W (6, N) in the gauge of basis U (6, K), a solve flag and the final
    basis (pass it back as `basis0` to warm-start a nearby LP), in pure JAX.

    Same contract as `lp_host.q_distance` for the first two outputs: differentiable wrt W (reverse mode,
    dE_g/dW = lam alpha^T); U is a host array fixed per configuration; vmap batches it (with XLA pivots a batch
    runs in lockstep until all are done; the Pallas kernel, `kernel_for`, lets each LP stop on its own).
    """
    U = np.ascontiguousarray(U, np.float64)
    if basis0 is None:
        basis0 = jnp.full(7, -1, jnp.int32)
    return _q_distance(W, jnp.asarray(basis0, jnp.int32), (U.tobytes(), U.shape[1]), max_iter)
