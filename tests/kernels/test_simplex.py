"""The shared simplex rules (`kernels/simplex.py`) on small hand-made cases; the solvers that use them are tested
against HiGHS and Qhull in test_lp_jax.py and tests/evaluation/test_device_metrics.py."""

import jax
import jax.numpy as jnp
import numpy as np

from ffcgs_jax.kernels import simplex


def test_inverse_matches_numpy_and_flags_singular():
    rng = np.random.default_rng(7)
    for _ in range(5):
        M = rng.normal(size=(7, 7))
        inv, smallest = simplex.inverse(jnp.asarray(M))
        np.testing.assert_allclose(inv, np.linalg.inv(M), rtol=1e-9, atol=1e-9)
        assert float(smallest) > 1e-6
    M[:, 3] = M[:, 1]
    assert float(simplex.inverse(jnp.asarray(M))[1]) < 1e-12


def test_entering_is_dantzig_then_bland():
    r = jnp.array([0.0, -1.0, -3.0, 2.0, -2.0])
    tol = simplex.pivot_tol(r.dtype)
    assert [int(simplex.entering(r, jnp.int32(0), tol)[0]), bool(simplex.entering(r, jnp.int32(0), tol)[1])] == [2, 0]
    assert int(simplex.entering(r, jnp.int32(simplex.BLAND_AFTER), tol)[0]) == 1  # the lowest negative index
    assert bool(simplex.entering(jnp.array([0.0, -1e-12, 1.0]), jnp.int32(0), tol)[1])  # optimal within tol


def test_ratio_test_breaks_ties_by_lowest_basis_index():
    xB, u = jnp.array([2.0, 1.0, 1.0, 5.0]), jnp.array([1.0, 1.0, 1.0, -1.0])
    tol = simplex.pivot_tol(xB.dtype)
    leave, best = simplex.ratio_test(xB, u, jnp.array([3, 9, 4, 0]), tol)
    assert (int(leave), float(best)) == (2, 1.0)  # rows 1 and 2 tie at 1; row 2 holds the lower column, 4
    leave, best = simplex.ratio_test(xB, u, jnp.array([3, 9, 4, 0]), tol, forced=jnp.array([False] * 3 + [True]))
    assert (int(leave), float(best)) == (3, 0.0)
    assert not np.isfinite(float(simplex.ratio_test(xB, -jnp.abs(u), jnp.arange(4), tol)[1]))  # unbounded


def test_exchange_updates_the_inverse_the_same_in_both_forms():
    rng = np.random.default_rng(1)
    B, a = rng.normal(size=(6, 6)), rng.normal(size=6)
    Binv, basis = jnp.asarray(np.linalg.inv(B)), jnp.arange(10, 16)
    u = Binv @ jnp.asarray(a)
    one_hot = simplex.exchange(basis, Binv, jnp.asarray(3), jnp.asarray(2), u)
    indexed = simplex.exchange(basis, Binv, jnp.asarray(3), jnp.asarray(2), u, one_hot=False)
    np.testing.assert_array_equal(one_hot[0], indexed[0])
    np.testing.assert_array_equal(one_hot[1], indexed[1])
    B[:, 2] = a
    np.testing.assert_array_equal(one_hot[0], [10, 11, 3, 13, 14, 15])
    np.testing.assert_allclose(one_hot[1], np.linalg.inv(B), atol=1e-9)


def test_pivot_loop_stops_at_done_or_the_budget():
    def pivot(st):
        x, trips, it, _, done = st
        return x + 1, trips, it + jnp.where(done, 0, 1), 0, done | (x + 1 >= 6)

    def refresh(st):
        return st[0], st[1] + 1, st[2], st[3], st[4]

    for unroll in (False, True):
        state = (jnp.int32(0), jnp.int32(0), jnp.int32(0), 0, jnp.bool_(False))
        _, trips, it, _, _ = jax.jit(lambda s, u=unroll: simplex.pivot_loop(pivot, refresh, s, 100, 4, u))(state)
        assert (int(it), int(trips)) == (6, 2)
        _, trips, it, _, _ = simplex.pivot_loop(pivot, refresh, state, 3, 2, unroll)
        assert (int(it), int(trips)) == (4, 2)  # the budget is checked between trips
