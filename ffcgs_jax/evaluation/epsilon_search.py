"""The Ferrari-Canny epsilon of a wrench set on the device, by facet walks (see `search_epsilon`), and the rank test
that force closure asks for: `device_metrics`' quality figures take these, and bench/evaluation_parts.py times them.

The walks' LPs are 6-row simplex solves written for a batched device: one-hot selections, elementwise products and
sums instead of gathers, scatters and library factorisations (`_simplex` says why)."""

from typing import NamedTuple

import jax
import jax.numpy as jnp

from ffcgs_jax.kernels import simplex
from ffcgs_jax.core.types import Array, Float

EPS_STARTS = 256  # spread start directions of the epsilon search
EPS_KEEP = 12  # of which the lowest start a facet walk
EPS_WALK = 5  # steps of each walk (walks measured converged within 6)
_MAX_PIVOTS = 64  # per simplex phase; the 6-row LPs here take about 10
_PIVOTS_PER_REFRESH = 4
_EXACT = jax.lax.Precision.HIGHEST


def rank_tol(dtype) -> float:
    """Relative singular value under which a wrench set is flat: the reference's 1e-9 in float64 reads eigenvalues of
    the Gram matrix here, the squares, which rounding holds only down to ~1e-16 relative: 1e-7 there. Float32:
    1e-3 (sets between 1e-9 and this are nearly flat: their epsilon is ~0)."""
    return 1e-7 if jnp.dtype(dtype) == jnp.float64 else 1e-3


def eps_tol(dtype) -> tuple[float, float]:
    """(epsilon above which a hull holds the origin strictly, E_g at most which it holds it): the reference's 1e-12
    for epsilon in float64; the LP's value is exact at a vertex up to rounding."""
    return (1e-12, 1e-9) if jnp.dtype(dtype) == jnp.float64 else (1e-6, 1e-6)


def _simplex(W, s, d, phase: int, basis, Binv, max_iter: int, unroll: bool | None = None):
    """Pivots of the revised simplex on min c.x, [W | diag(s)] x = d, x >= 0 from a feasible `basis` with inverse
    `Binv`: phase 1 prices the 6 artificial columns diag(s) at 1 and the wrenches at 0, phase 2 the wrenches at 1,
    and there the artificials never enter; a basic one (left at level 0 by phase 1) leaves at the first pivot whose
    column has a non-zero entry in its row. The pivot rules are the package's shared ones (`kernels.simplex`: Dantzig's
    rule, Bland's after `simplex.BLAND_AFTER` degenerate pivots, Bland's ratio tie-break), the inverse refreshed every
    `_PIVOTS_PER_REFRESH` (`simplex.inverse`).

    Written with one-hot selections, elementwise products and sums instead of gathers, scatters, matrix products
    and library inverses: on a GPU XLA fuses these into a few kernels per pivot, where small batched matrix
    products and LU factorisations are each a library call (`kernels.simplex` says the same of the shared pivots)."""
    n = W.shape[1]
    dt = W.dtype
    tol = simplex.pivot_tol(dt)  # the Q-distance simplex's pivot tolerance: the same LPs' scale
    cols = jnp.arange(n + 6)
    cost = jnp.where(cols < n, 0.0 if phase == 1 else 1.0, 1.0 if phase == 1 else 0.0).astype(dt)
    enter_ok = jnp.ones(n + 6, bool) if phase == 1 else cols < n

    def column(j):
        """Column j of [W | diag(s)] (6,), by a one-hot sum rather than a gather."""
        hot = (cols == j).astype(dt)
        return jnp.sum(W * hot[None, :n], axis=1) + s * hot[n:]

    def matrix(basis):
        return _columns(W, s, basis)

    def pivot(state):
        basis, Binv, it, degenerate, done = state
        xB = jnp.maximum(jnp.sum(Binv * d[None, :], axis=1), 0.0)
        y = jnp.sum(Binv * jnp.sum(cost[None, :] * (basis[:, None] == cols[None, :]), axis=1)[:, None], axis=0)
        priced = jnp.concatenate([jnp.sum(W * y[:, None], axis=0), s * y])
        in_basis = jnp.any(basis[:, None] == cols[None, :], axis=0)
        r = jnp.where(in_basis | ~enter_ok, 0.0, cost - priced)
        enter, optimal = simplex.entering(r, degenerate, tol)
        u = jnp.sum(Binv * column(enter)[None, :], axis=1)
        stuck = (basis >= n) & (phase == 2) & (jnp.abs(u) > tol)
        leave, best = simplex.ratio_test(xB, u, basis, tol, forced=stuck)
        stop = done | optimal | ~jnp.isfinite(best)
        new_basis, new = simplex.exchange(basis, Binv, enter, leave, u)
        return (jnp.where(stop, basis, new_basis), jnp.where(stop, Binv, new), it + jnp.where(stop, 0, 1),
                simplex.degenerate_run(degenerate, best, tol), stop)

    def refresh(state):
        basis, Binv, it, degenerate, done = state
        fresh, smallest = simplex.inverse(matrix(basis))
        return basis, jnp.where(smallest > 0, fresh, Binv), it, degenerate, done

    state = (basis, Binv, jnp.zeros((), jnp.int32), jnp.zeros((), jnp.int32), jnp.zeros((), bool))
    basis, Binv, _, _, _ = _pivot_loop(pivot, refresh, state, max_iter, unroll)
    return basis, Binv


def _pivot_loop(pivot, refresh, state, max_iter: int, unroll: bool | None = None):
    """`simplex.pivot_loop` with this module's trips: `_PIVOTS_PER_REFRESH` pivots in a loop, or twice as many
    unrolled (`unroll`; None: on a GPU only, where each trip's end is a device-to-host sync)."""
    unroll = jax.default_backend() != "cpu" if unroll is None else unroll
    return simplex.pivot_loop(pivot, refresh, state, max_iter, (2 if unroll else 1) * _PIVOTS_PER_REFRESH, unroll)


def _columns(W, s, basis):
    """The basis matrix of [W | diag(s)] (6, 6), by one-hot sums (see `_simplex`)."""
    n = W.shape[1]
    cols = jnp.arange(n + 6)
    hot = (basis[None, :] == cols[:, None]).astype(W.dtype)  # (n + 6, 6)
    return jnp.sum(W[:, :, None] * hot[None, :n, :], axis=1) + s[:, None] * hot[n:, :]


def _dual_simplex(W, s, d, basis, Binv, max_iter: int, unroll: bool | None = None):
    """Dual simplex pivots on phase 2 of `ray_facet`'s LP (min 1.x, [W | diag(s)] x = d, x >= 0, artificials never
    entering) from a basis optimal for another right-hand side: its duals y = B^-T c_B do not depend on d, so it stays
    dual feasible, and only the basic values B^-1 d may have turned negative. Each pivot takes the most negative basic
    value out and lets in the wrench column of least reduced cost per unit of that row, which keeps every reduced
    cost >= 0. A basic artificial must end at 0: one above 0 has its column's sign flipped (its row of B^-1 negated),
    which makes its value negative and takes it out the same way. A walk's next ray leaves through the facet it came
    from or one near it, so a few pivots replace a cold two-phase solve (bench/RESULTS.md, "End-to-end speed")."""
    n = W.shape[1]
    dt = W.dtype
    tol = simplex.pivot_tol(dt)
    cols = jnp.arange(n + 6)
    six = jnp.arange(6)

    def values(basis, Binv, s):
        """B^-1 d, with basic artificials above 0 flipped to below it: (values, Binv, s)."""
        xB = jnp.sum(Binv * d[None, :], axis=1)
        flip = (basis >= n) & (xB > tol)
        which = jnp.sum(jnp.where(flip[:, None], (basis[:, None] - n) == six[None, :], False), axis=0) > 0
        sign = jnp.where(flip, -1.0, 1.0).astype(dt)
        return xB * sign, Binv * sign[:, None], jnp.where(which, -s, s)

    def pivot(state):
        basis, Binv, it, s, done = state
        xB, Binv, s = values(basis, Binv, s)
        leave = jnp.argmin(xB)
        stop = done | (jnp.min(xB) >= -tol)
        at = six == leave
        row = jnp.sum(jnp.where(at[:, None], Binv, 0.0), axis=0)  # e_leave^T B^-1
        alpha = jnp.concatenate([jnp.sum(W * row[:, None], axis=0), s * row])
        y = jnp.sum(Binv * (basis < n).astype(dt)[:, None], axis=0)
        reduced = jnp.maximum(1.0 - jnp.sum(W * y[:, None], axis=0), 0.0)  # >= 0 but for rounding
        in_basis = jnp.any(basis[:, None] == cols[None, :n], axis=0)
        ok = ~in_basis & (alpha[:n] < -tol)
        ratio = jnp.where(ok, reduced / jnp.where(ok, -alpha[:n], 1.0), jnp.inf)
        enter = jnp.argmin(ratio)
        stop = stop | ~jnp.any(ok)  # no column can take the row: d outside the cone (no force closure)
        hot = (cols[:n] == enter).astype(dt)
        u = jnp.sum(Binv * jnp.sum(W * hot[None, :], axis=1)[None, :], axis=1)
        new_basis, new = simplex.exchange(basis, Binv, enter, leave, u)
        return (jnp.where(stop, basis, new_basis), jnp.where(stop, Binv, new), it + jnp.where(stop, 0, 1), s, stop)

    def refresh(state):
        basis, Binv, it, s, done = state
        fresh, smallest = simplex.inverse(_columns(W, s, basis))
        return basis, jnp.where(smallest > 0, fresh, Binv), it, s, done

    state = (basis, Binv, jnp.zeros((), jnp.int32), s, jnp.zeros((), bool))
    basis, Binv, _, s, _ = _pivot_loop(pivot, refresh, state, max_iter, unroll)
    return basis, Binv, s


class RayBasis(NamedTuple):
    """The optimal basis of a `ray_facet` LP, for the next ray of a walk to start from (`_dual_simplex`)."""

    basis: Array  # (6,) column indices into [W | diag(s)]
    Binv: Array  # (6, 6)
    s: Array  # (6,) the artificial columns' signs


def ray_facet(W: Float[Array, "6 N"], d: Float[Array, " 6"], warm: RayBasis | None = None,
              unroll: bool | None = None) -> tuple[Float[Array, " 6"], RayBasis]:
    """Unit normal of the facet of conv(W) through which the ray from the origin along d leaves (the origin inside),
    and the LP's optimal basis.

    The ray leaves at d / g, g = min 1.lam s.t. W lam = d, lam >= 0 (the gauge of d); that LP's dual optimum y is
    the polar vertex of the facet (y . w <= 1 with equality on it), so the normal is y / |y| and the facet's distance
    1 / |y|. Cold: two-phase simplex on the 6 rows, phase 1 from the artificial columns sign(d_i) e_i. `warm`: the
    optimal basis of the same W for another d, finished by dual simplex pivots (`_dual_simplex`)."""
    n = W.shape[1]
    dt = W.dtype
    if warm is None:
        s = jnp.where(d >= 0, 1.0, -1.0).astype(dt)
        basis, Binv = jnp.arange(n, n + 6), jnp.diag(s)
        basis, Binv = _simplex(W, s, d, 1, basis, Binv, _MAX_PIVOTS, unroll)
        basis, Binv = _simplex(W, s, d, 2, basis, Binv, _MAX_PIVOTS, unroll)
    else:
        basis, Binv, s = _dual_simplex(W, warm.s, d, warm.basis, warm.Binv, _MAX_PIVOTS, unroll)
    y = jnp.sum(Binv * (basis < n).astype(dt)[:, None], axis=0)  # B^-T c_B, c_B = 1 on wrench columns
    size = jnp.sqrt(jnp.sum(y * y))
    return jnp.where(size > 0, y / jnp.where(size > 0, size, 1.0), d), RayBasis(basis, Binv, s)


def search_epsilon(W: Float[Array, "6 N"], starts: Float[Array, "M 6"], warm: bool = True,
                   unroll: bool | None = None) -> Float[Array, ""]:
    """min over searched unit directions u of h(u) = max_j u . w_j: an upper bound of the signed Ferrari-Canny
    epsilon, exact where the walk reaches the nearest facet (see the module docstring). Meaningful when the
    origin is inside the hull (force closure); otherwise only its sign is. `warm` False solves every ray of a walk
    cold (two phases), as before the warm starts: the same facets, kept for tests and bench/evaluation_parts.py.
    `unroll`: the simplex pivots of a loop trip unrolled, None for the backend's default (unrolled on a GPU);
    bench/first_compile.py compares compile seconds against the warm call."""
    # full float32 products: a GPU's default (TF32-like) precision errs by ~1e-3, a tenth of a typical epsilon
    h0 = jnp.max(jnp.matmul(starts, W, precision=_EXACT), axis=1)
    dirs = starts[jax.lax.top_k(-h0, EPS_KEEP)[1]]
    best = jnp.min(h0)

    def step(dirs, best, start):  # start: the rays' last bases (RayBasis), or None to solve them cold
        new, bases = jax.vmap(ray_facet, (None, 0, 0 if start is not None else None, None))(W, dirs, start, unroll)
        moved = jnp.any(jnp.abs(new - dirs) > 1e-6)
        h = jnp.max(jnp.matmul(new, W, precision=_EXACT), axis=1)
        return new, jnp.minimum(best, jnp.min(h)), moved, bases

    def walk(carry):
        i, dirs, best, _, bases = carry
        dirs, best, moved, bases = step(dirs, best, bases if warm else None)
        return i + 1, dirs, best, moved, bases

    # the first ray of each walk is solved cold, the next ones from the basis of the ray before (a few dual pivots);
    # a walk that returns the facet it started from has ended (the origin's foot point lies in that facet)
    dirs, best, moved, bases = step(dirs, best, None)
    carry = (jnp.ones((), jnp.int32), dirs, best, moved, bases)
    return jax.lax.while_loop(lambda c: (c[0] < EPS_WALK) & c[3], walk, carry)[2]


def full_rank(W: Float[Array, "6 N"]) -> Array:
    """Whether the centred wrenches span R^6 (`metrics.epsilon_q1`'s test: smallest singular value above
    `rank_tol`), from the Gram matrix G: its smallest eigenvalue lies within a factor of 6 of
    1 / trace(G^-1) and its largest of trace(G) / 6 .. trace(G), so the ratio is tested to that factor, by an
    elementwise Gauss-Jordan inverse instead of a library SVD (see `_simplex`)."""
    Wc = W - jnp.mean(W, axis=1, keepdims=True)
    G = jnp.sum(Wc[:, None, :] * Wc[None, :, :], axis=2)
    inv, smallest = simplex.inverse(G)
    tr, tr_inv = jnp.trace(G), jnp.trace(inv)
    ok = (smallest > 0) & jnp.isfinite(tr_inv) & (tr_inv > 0)
    return ok & (1.0 / jnp.where(ok, tr_inv, 1.0) > rank_tol(W.dtype)**2 * tr)
