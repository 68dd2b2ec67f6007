"""The simplex machinery that the package's LPs share: one place for the pivot rules they agree on.

Users: the Q-distance LP (`lp_jax.solve`, a 7-row revised simplex) and the epsilon search's ray LPs
(`evaluation.epsilon_search`: a two-phase primal simplex and a dual simplex on 6 rows). Each keeps what is its own
(its columns, costs and phases, how it prices, the dual ratio rule); the pieces here are those where the solvers
must not drift apart: the pivot tolerance, Dantzig's entering rule with the switch to Bland's after a run of
degenerate pivots (which rules out cycling), the ratio test with Bland's tie-break, the rank-one (eta) update of
the explicit basis inverse, the Gauss-Jordan refresh of that inverse, and the loop of pivot trips with a refresh
after each.

The inverse is explicit because a pivot is then a rank-one update of a small array, elementwise work that XLA
fuses into a few kernels, where batched LU factorisations and triangular solves are library calls that cannot fuse
(on a GPU each pivot became a dozen tiny launches). The update is written gather-free (one-hot selections, `where`
and sums) for the same reason. `lp_pallas` runs the Q-distance pivots as a Pallas kernel; it mirrors these rules
in its own code (its docstring says why) and tests/kernels/test_lp_jax.py holds the two to the same pivots.
"""

import jax
import jax.numpy as jnp

from ffcgs_jax.core.types import Array, Float, Int

BLAND_AFTER = 8  # consecutive degenerate pivots after which Bland's rule enters


def pivot_tol(dtype) -> float:
    """Optimality / pivot tolerance: a few hundred ulps of the O(1) entries."""
    return 1e-9 if jnp.finfo(dtype).bits == 64 else 1e-5


def inverse(M: Float[Array, "n n"]) -> tuple[Float[Array, "n n"], Float[Array, ""]]:
    """Gauss-Jordan inverse with partial pivoting, unrolled (n is 6 or 7 here), and the smallest pivot's magnitude:
    a singular M gives a zero pivot (and a non-finite inverse, which callers must not use)."""
    n = M.shape[0]
    rows = jnp.arange(n)
    A, inv = M, jnp.eye(n, dtype=M.dtype)
    smallest = jnp.asarray(jnp.inf, M.dtype)
    for k in range(n):
        p = jnp.argmax(jnp.where(rows >= k, jnp.abs(A[:, k]), -1.0))
        perm = jnp.where(rows == k, p, jnp.where(rows == p, k, rows))
        A, inv = A[perm], inv[perm]
        piv = A[k, k]
        smallest = jnp.fmin(smallest, jnp.abs(piv))  # fmin: NaNs after a zero pivot must not hide it
        piv = jnp.where(piv == 0, 1.0, piv)
        A_k, inv_k = A[k] / piv, inv[k] / piv
        f = jnp.where(rows == k, 0.0, A[:, k])
        A = (A - f[:, None] * A_k[None, :]).at[k].set(A_k)
        inv = (inv - f[:, None] * inv_k[None, :]).at[k].set(inv_k)
    return inv, smallest


def entering(reduced: Float[Array, " n"], degenerate: Int[Array, ""], tol: float
             ) -> tuple[Int[Array, ""], Array]:
    """The entering column and whether the basis is optimal (no reduced cost below -tol).

    Dantzig's rule (the most negative reduced cost) makes the fewest pivots on these LPs; after `BLAND_AFTER`
    consecutive degenerate pivots Bland's (the lowest index with a negative one), which cannot cycle. Callers give
    columns that must not enter a reduced cost of 0."""
    neg = reduced < -tol
    enter = jnp.where(degenerate >= BLAND_AFTER, jnp.argmax(neg), jnp.argmin(reduced))
    return enter, ~jnp.any(neg)


def degenerate_run(degenerate: Int[Array, ""], step: Float[Array, ""], tol: float) -> Int[Array, ""]:
    """The count of consecutive degenerate pivots (step length `step` <= tol) after one more pivot."""
    return jnp.where(step <= tol, degenerate + 1, 0)


def ratio_test(xB: Float[Array, " m"], u: Float[Array, " m"], basis: Int[Array, " m"], tol: float,
               forced: Array | None = None) -> tuple[Int[Array, ""], Float[Array, ""]]:
    """The leaving row and the step length (inf when no entry of u is above tol: unbounded along u).

    Rows with u > tol bound the step at xB / u; `forced` rows (a caller's basic artificials that must leave) at 0.
    Ties within tol go to the lowest basis index, Bland's tie-break, which together with `entering`'s switch rules
    out cycling on degenerate vertices."""
    pos = u > tol
    ratio = jnp.where(pos, xB / jnp.where(pos, u, 1.0), jnp.inf)
    if forced is not None:
        ratio = jnp.where(forced, 0.0, ratio)
    best = jnp.min(ratio)
    # non-tied rows take a sentinel above every column index, so callers need not pass their column count
    leave = jnp.argmin(jnp.where(ratio <= best + tol, basis, jnp.iinfo(basis.dtype).max))
    return leave, best


def exchange(basis: Int[Array, " m"], Binv: Float[Array, "m m"], enter: Int[Array, ""], leave: Int[Array, ""],
             u: Float[Array, " m"], one_hot: bool = True) -> tuple[Int[Array, " m"], Float[Array, "m m"]]:
    """The basis with column `enter` in row `leave`, and its inverse by the rank-one (eta) update of `Binv`, where
    u = B^-1 a_enter; a zero pivot entry (only in pivots the caller discards) divides by 1.

    `one_hot`: the leaving row selected by one-hot sums and `where`s, which XLA fuses with the rest of a pivot on a
    GPU, where gathers and scatters each cost a launch; False indexes it (a gather and a scatter), which measured
    faster for the Q-distance LP on a CPU. Both give the same bits."""
    if not one_hot:
        u_leave = u[leave]
        row = Binv[leave] / jnp.where(jnp.abs(u_leave) > 0, u_leave, 1.0)
        return basis.at[leave].set(enter.astype(basis.dtype)), (Binv - u[:, None] * row[None, :]).at[leave].set(row)
    at = jnp.arange(basis.shape[0]) == leave
    u_leave = jnp.sum(jnp.where(at, u, 0.0))
    row = jnp.sum(jnp.where(at[:, None], Binv, 0.0), axis=0) / jnp.where(jnp.abs(u_leave) > 0, u_leave, 1.0)
    new = jnp.where(at[:, None], row[None, :], Binv - u[:, None] * row[None, :])
    return jnp.where(at, enter.astype(basis.dtype), basis), new


def pivot_loop(pivot, refresh, state: tuple, max_iter: int, pivots: int, unroll: bool) -> tuple:
    """Trips of `pivots` pivots, each followed by `refresh`, until the state's done flag (state[4]) or `max_iter`
    pivots (state[2]); returns the final state.

    `pivot` and `refresh` map a state to a state. The refresh (a fresh inverse, in `lp_jax` also the check that
    an optimum seen through the updated inverse holds) bounds the rounding that rank-one updates build up. Each
    trip ends in a loop-condition check, a device-to-host sync on a GPU, so callers unroll more pivots per trip
    there. `unroll` False keeps one copy of the pivot in a `fori_loop`: on a CPU every kernel of an executable is
    its own memory mapping, and unrolled copies of a whole evaluation ran a long test process out of mappings
    (vm.max_map_count) after a few dozen executables."""

    def trip(state):
        if unroll:
            for _ in range(pivots):
                state = pivot(state)
        else:
            state = jax.lax.fori_loop(0, pivots, lambda _, st: pivot(st), state)
        return refresh(state)

    return jax.lax.while_loop(lambda st: ~st[4] & (st[2] < max_iter), trip, state)
