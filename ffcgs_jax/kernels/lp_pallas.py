"""The Q-distance simplex of `lp_jax.py` as one Pallas kernel: a whole solve per GPU program.

Why: XLA runs each pivot as about ten tiny kernels, and a batch pivots in lockstep until its slowest LP is done, so
at 32 grasps the LP was 18k of the 27k kernel launches of a 50-step descent on an H100 (profiler trace, 2026-11-22).
Here each LP runs all its pivots in one program, with its own stopping point; a descent step makes one launch.

Same algorithm, pivot for pivot, as `lp_jax.solve` (Dantzig's rule, Bland's after degenerate runs, the warm start
check, a Gauss-Jordan refresh of the inverse after every `lp_jax` trip of pivots, optimality confirmed on it).
Triton wants power-of-two blocks, so the 7 x (K + N) problem is padded to 8 x 128: row 7 and the last column form
a unit block that stays in the basis (no real column has a nonzero in row 7, so it never leaves), and the padding
columns have zero cost and zero entries, so they never price out. Dynamic indexing (a column of A, a row of the
inverse) is written as masked sums, which Triton lowers; the kernel only uses elementwise ops and reductions.

The kernel mirrors `kernels.simplex` rather than calling it: the shared helpers use argmin/argmax, boolean `any`,
gathers (`inverse`'s row swaps) and integer-limit sentinels, which this kernel spells as masked sums and
min-over-iota reductions for Triton, and Triton's lowering of the shared forms could not be checked without a GPU
build of JAX; test_pallas_kernel_takes_the_xla_pivots (tests/kernels/test_lp_jax.py) holds it to `lp_jax.solve`'s
pivots and bases.

`interpret=True` runs the same kernel through Pallas's interpreter on any backend: the tests use it on CPUs.
"""

import functools

import jax
import jax.numpy as jnp
from jax import lax
from jax.experimental import pallas as pl

from ffcgs_jax.core.types import Array, Bool, Float, Int

_ROWS, _COLS = 8, 128
_UNIT = _COLS - 1  # the padding unit column, always basic in row 7


def _masked_col(M, cols, j):
    """M[:, j] for a traced j."""
    return jnp.sum(jnp.where(cols[None, :] == j, M, 0), axis=1)


def _masked_row(M, rows, i):
    """M[i, :] for a traced i."""
    return jnp.sum(jnp.where(rows[:, None] == i, M, 0), axis=0)


def _entry(v, idx, i):
    return jnp.sum(jnp.where(idx == i, v, 0))


# Reductions of booleans and NaN tests written with the comparisons and int reductions every backend lowers
def _any(x):
    return jnp.max(x.astype(jnp.int32)) > 0


def _all(x):
    return jnp.min(x.astype(jnp.int32)) > 0


def _inverse(M, rows):
    """Gauss-Jordan with partial pivoting on an 8 x 8 block, and the smallest pivot's magnitude (`simplex.inverse`)."""
    dt = M.dtype
    inv = jnp.where(rows[:, None] == rows[None, :], 1.0, 0.0).astype(dt)
    smallest = jnp.asarray(jnp.inf, dt)
    for k in range(_ROWS):
        mag = jnp.where(rows >= k, jnp.abs(_masked_col(M, rows, k)), -1.0)
        p = jnp.min(jnp.where(mag == jnp.max(mag), rows, _ROWS))
        swap = lambda X: jnp.where(rows[:, None] == k, _masked_row(X, rows, p)[None, :],  # noqa: E731
                                   jnp.where(rows[:, None] == p, _masked_row(X, rows, k)[None, :], X))
        M, inv = swap(M), swap(inv)
        col = _masked_col(M, rows, k)
        piv = _entry(col, rows, k)
        smallest = jnp.where(piv != piv, 0.0, jnp.minimum(smallest, jnp.abs(piv)))
        piv = jnp.where(piv == 0, 1.0, piv)
        M_k, inv_k = _masked_row(M, rows, k) / piv, _masked_row(inv, rows, k) / piv
        f = jnp.where(rows == k, 0.0, col)
        M = jnp.where(rows[:, None] == k, M_k[None, :], M - f[:, None] * M_k[None, :])
        inv = jnp.where(rows[:, None] == k, inv_k[None, :], inv - f[:, None] * inv_k[None, :])
    return inv, smallest


def _kernel(A_ref, b0_ref, axes_ref, basis_ref, binv_ref, info_ref, *, K: int, n_cols: int, max_iter: int,
            tol: float, per_trip: int, bland_after: int):
    A = A_ref[...]
    dt = A.dtype
    rows = lax.broadcasted_iota(jnp.int32, (_ROWS,), 0)
    cols = lax.broadcasted_iota(jnp.int32, (_COLS,), 0)
    real = cols < n_cols
    c = jnp.where(cols < K, 1.0, 0.0).astype(dt)

    def basis_matrix(basis):
        out = jnp.zeros((_ROWS, _ROWS), dt)
        for j in range(_ROWS):
            out = jnp.where(rows[None, :] == j, _masked_col(A, cols, _entry(basis, rows, j))[:, None], out)
        return out

    # cold start: sign(w_0i) e_i for the six wrench axes, alpha_0, the unit column (closed-form inverse)
    w0 = -_masked_col(A, cols, K)
    first = rows < 6
    sign = jnp.where(first, jnp.where(w0 >= 0, 1.0, -1.0), 1.0).astype(dt)
    basis = jnp.where(first, jnp.where(w0 >= 0, axes_ref[0, :], axes_ref[1, :]),
                      jnp.where(rows == 6, jnp.int32(K), jnp.int32(_UNIT)))
    Binv = (jnp.where(rows[:, None] == rows[None, :], sign[:, None], 0.0)
            + jnp.where(first[:, None] & (rows[None, :] == 6), (sign * w0)[:, None], 0.0)).astype(dt)
    # warm start, when it is a primal-feasible basis of this LP
    b0 = b0_ref[...]
    in_range = _all((b0 >= 0) & ((b0 < n_cols) | (rows == _ROWS - 1)))
    inv0, smallest = _inverse(basis_matrix(jnp.clip(b0, 0, _COLS - 1)), rows)
    usable = (in_range & (smallest > tol) & _all(_masked_col(inv0, rows, 6) >= -tol)
              & _all(jnp.max(jnp.abs(inv0), axis=1) < jnp.inf))  # finite: NaN and inf fail the comparison
    basis, Binv = jnp.where(usable, b0, basis), jnp.where(usable, inv0, Binv)

    def reduced_costs(basis, Binv):
        y = jnp.sum(Binv * jnp.where(basis < K, 1.0, 0.0).astype(dt)[:, None], axis=0)  # B^-T c_B
        d = c - jnp.sum(A * y[:, None], axis=0)
        basic = jnp.max((cols[None, :] == basis[:, None]).astype(jnp.int32), axis=0) > 0
        return jnp.where(basic | ~real, 0.0, d)

    def pivot(state):
        basis, Binv, it, degenerate, done, ok = state
        xB = jnp.maximum(_masked_col(Binv, rows, 6), 0.0)
        d = reduced_costs(basis, Binv)
        neg = d < -tol
        optimal = ~_any(neg)
        dantzig = jnp.min(jnp.where(d == jnp.min(d), cols, _COLS))
        bland = jnp.min(jnp.where(neg, cols, _COLS))
        enter = jnp.where(degenerate >= bland_after, bland, dantzig)
        u = jnp.sum(Binv * _masked_col(A, cols, enter)[None, :], axis=1)
        pos = u > tol
        ratio = jnp.where(pos, xB / jnp.where(pos, u, 1.0), jnp.inf)
        best = jnp.min(ratio)
        tie = ratio <= best + tol
        lowest = jnp.min(jnp.where(tie, basis, _COLS))
        leave = jnp.min(jnp.where(tie & (basis == lowest), rows, _ROWS))
        stop = done | optimal | ~_any(pos) | (it >= max_iter)
        u_l = _entry(u, rows, leave)
        row = _masked_row(Binv, rows, leave) / jnp.where(u_l > tol, u_l, 1.0)
        new_Binv = jnp.where(rows[:, None] == leave, row[None, :], Binv - u[:, None] * row[None, :])
        return (jnp.where(stop, basis, jnp.where(rows == leave, enter, basis)),
                jnp.where(stop, Binv, new_Binv), it + (~stop).astype(jnp.int32),
                jnp.where(stop, degenerate, (degenerate + 1) * (best <= tol).astype(jnp.int32)),
                stop, jnp.where(done, ok, optimal))

    def trip(state):
        # a trip's pivots end at the first stop: the ones after it would change nothing (as in the XLA loop, which
        # must run them in lockstep), and each costs a few microseconds of reductions
        _, state = lax.while_loop(lambda ks: (ks[0] < per_trip) & ~ks[1][4],
                                  lambda ks: (ks[0] + 1, pivot(ks[1])), (jnp.zeros((), jnp.int32), state))
        basis, Binv, it, degenerate, done, ok = state
        Binv = _inverse(basis_matrix(basis), rows)[0]
        confirmed = ~_any(reduced_costs(basis, Binv) < -tol)
        redo = done & ~confirmed
        return basis, Binv, it + redo.astype(jnp.int32), degenerate, done & ~(redo & (it < max_iter)), ok & confirmed

    def cond(state):
        _, _, it, _, done, _ = state
        return ~done & (it < max_iter)

    zero = jnp.zeros((), jnp.int32)
    state = (basis, Binv, zero, zero, jnp.zeros((), bool), jnp.zeros((), bool))
    basis, Binv, it, _, _, ok = lax.while_loop(cond, trip, state)
    basis_ref[...] = basis
    binv_ref[...] = Binv
    info_ref[...] = (rows == 0).astype(jnp.int32) * ok.astype(jnp.int32) + (rows == 1).astype(jnp.int32) * it


def solve_basis(W: Float[Array, "6 N"], U: Float[Array, "6 K"], axes, max_iter: int, basis0: Int[Array, " 7"],
                tol: float, per_trip: int, bland_after: int, interpret: bool = False
                ) -> tuple[Int[Array, " 7"], Float[Array, "7 7"], Bool[Array, ""], Int[Array, ""]]:
    """The optimal basis, its inverse, whether it is optimal within `max_iter` pivots, and the pivots taken."""
    dt = W.dtype
    K, N = U.shape[1], W.shape[1]
    if K + N > _UNIT:
        raise ValueError(f"the Pallas LP kernel holds at most {_UNIT} columns, got K + N = {K + N}")
    A = jnp.zeros((_ROWS, _COLS), dt)
    A = A.at[:6, :K].set(U.astype(dt)).at[:6, K:K + N].set(-W).at[6, K:K + N].set(1.0).at[7, _UNIT].set(1.0)
    b0 = jnp.concatenate([jnp.asarray(basis0, jnp.int32), jnp.array([_UNIT], jnp.int32)])
    ax = jnp.zeros((2, _ROWS), jnp.int32).at[:, :6].set(jnp.asarray(axes, jnp.int32))
    kernel = functools.partial(_kernel, K=K, n_cols=K + N, max_iter=max_iter, tol=tol, per_trip=per_trip,
                               bland_after=bland_after)
    basis, Binv, info = pl.pallas_call(
        kernel, interpret=interpret,
        out_shape=(jax.ShapeDtypeStruct((_ROWS,), jnp.int32), jax.ShapeDtypeStruct((_ROWS, _ROWS), dt),
                   jax.ShapeDtypeStruct((_ROWS,), jnp.int32)),
    )(A, b0, ax)
    return basis[:7], Binv[:7, :7], info[0] > 0, info[1]
