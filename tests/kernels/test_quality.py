"""The Q-distance: batched ProxSuite path vs qpsolvers and HiGHS, its custom VJP vs finite differences, and what it
measures on spheres (convex hull of the primitive wrenches, sum alpha = 1)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import qpsolvers
from scipy.optimize import linprog

from ffcgs_jax.evaluation.metrics import q_distance_reference
from ffcgs_jax.kernels import lp_host, quality

REF_TOL = 1e-6  # the bound between the batched path and the references
GRAD_TOL = 1e-4  # relative, custom VJP vs central differences of the LP value (solver accuracy 1e-7)
R = 0.05  # sphere radius (m)
U = quality.basis(64)


def sphere_contacts(theta, n=5, phase=0.0):
    """n contacts on a ring at polar angle theta around +z on a sphere of radius R, outward normals."""
    phi = phase + 2 * np.pi * np.arange(n) / n
    nrm = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.full(n, np.cos(theta))], 1)
    return R * nrm, nrm


def e_g(contacts, normals, **kw):
    v, ok = quality.q_distance(jnp.asarray(contacts), jnp.asarray(normals), jnp.zeros(3), R, **kw)
    assert bool(ok)
    return float(v)


def random_wrenches(rng, n_inst, shift):
    return rng.normal(size=(n_inst, 6, 40)) * 0.5 + shift * np.array([1.0, 0.3, 0, 0, 0, 0])[None, :, None]


def primal_matrices(W, U):
    K, N = U.shape[1], W.shape[1]
    A = np.zeros((7, K + N))
    A[:6, :K], A[:6, K:], A[6, K:] = U, -W, 1.0
    b = np.zeros(7)
    b[6] = 1.0
    c = np.concatenate([np.ones(K), np.zeros(N)])
    return c, A, b


def qpsolvers_dual(W, U):
    """qpsolvers' proxqp on the dual LP (min -t s.t. U^T lam <= 1, t <= w_i^T lam); None when it gives up."""
    K, N = U.shape[1], W.shape[1]
    G = np.zeros((K + N, 7))
    G[:K, :6], G[K:, :6], G[K:, 6] = U.T, -W.T, 1.0
    h = np.concatenate([np.ones(K), np.zeros(N)])
    c = np.zeros(7)
    c[6] = -1.0
    x = qpsolvers.solve_qp(np.zeros((7, 7)), c, G, h, solver="proxqp", eps_abs=1e-9, eps_rel=0.0)
    return None if x is None else x[6]


@pytest.mark.parametrize("shift", [0.0, 0.5, 1.0, 3.0])
def test_batched_path_agrees_with_qpsolvers_and_highs(shift):
    W = random_wrenches(np.random.default_rng(int(shift * 10)), 12, shift)
    value, lam, alpha, ok = lp_host.solve_batch(W, U)
    assert ok.all()
    answered = 0
    for b in range(len(W)):
        c, A, bb = primal_matrices(W[b], U)
        highs = linprog(c, A_eq=A, b_eq=bb, bounds=(0, None), method="highs").fun
        assert abs(value[b] - highs) < REF_TOL
        ref = qpsolvers_dual(W[b], U)
        if ref is not None:  # see test_proxsuite_defaults_raise_false_infeasibility_alarms
            assert abs(value[b] - ref) < REF_TOL
            answered += 1
        np.testing.assert_allclose(alpha[b].sum(), 1.0, atol=1e-6)
        np.testing.assert_allclose(W[b] @ alpha[b] @ lam[b], value[b], atol=1e-5)  # primal-dual consistency
    assert answered >= len(W) // 3
    if shift == 3.0:
        assert value.min() > 0.1  # all wrenches on one side: the origin is outside the hull


def test_proxsuite_defaults_raise_false_infeasibility_alarms():
    """Why lp_host switches ProxSuite's infeasibility tests off: with defaults (as qpsolvers calls it) some of these
    always-feasible LPs come back as infeasible (None), while the batched path solves every one."""
    none = 0
    for shift in (0.0, 0.5, 1.0):
        W = random_wrenches(np.random.default_rng(int(shift * 10)), 12, shift)
        none += sum(qpsolvers_dual(w, U) is None for w in W)
        assert lp_host.solve_batch(W, U)[3].all()
    assert none > 0


def test_jax_path_batches_into_one_call_and_equals_single_calls():
    W = jnp.asarray(random_wrenches(np.random.default_rng(3), 8, 1.0))
    batched = jax.jit(jax.vmap(lambda w: lp_host.q_distance(w, U)))(W)
    for b in range(8):
        single = lp_host.q_distance(W[b], U)
        np.testing.assert_allclose(float(batched[0][b]), float(single[0]), atol=1e-12)
        assert bool(batched[1][b])


@pytest.mark.parametrize("seed", range(4))
def test_custom_vjp_matches_central_differences(seed):
    rng = np.random.default_rng(seed)
    W = random_wrenches(rng, 1, 1.0)[0]
    v, ok = lp_host.q_distance(jnp.asarray(W), U)
    assert bool(ok) and float(v) > 0.05  # non-degenerate: a unique separating direction
    G = np.asarray(jax.grad(lambda w: lp_host.q_distance(w, U)[0])(jnp.asarray(W)))
    for _ in range(3):
        E = rng.normal(size=W.shape)
        eps = 1e-5
        fd = (q_distance_reference((W + eps * E).T, U) - q_distance_reference((W - eps * E).T, U)) / (2 * eps)
        assert abs(np.sum(G * E) - fd) <= GRAD_TOL * max(1.0, abs(fd)), (np.sum(G * E), fd)


def test_gradient_wrt_contacts_and_normals_matches_finite_differences():
    c, n = sphere_contacts(np.deg2rad(50))
    c = c + np.random.default_rng(0).normal(scale=0.003, size=c.shape)

    @jax.jit
    def f(cc, nn):
        return quality.q_distance(cc, nn, jnp.zeros(3), R)[0]

    gc, gn = jax.jit(jax.grad(f, argnums=(0, 1)))(jnp.asarray(c), jnp.asarray(n))
    rng = np.random.default_rng(1)
    for arg, g in ((0, gc), (1, gn)):
        E = rng.normal(size=c.shape)
        eps = 1e-6
        plus = [jnp.asarray(c), jnp.asarray(n)]
        minus = [jnp.asarray(c), jnp.asarray(n)]
        plus[arg] = plus[arg] + eps * E
        minus[arg] = minus[arg] - eps * E
        fd = (float(f(*plus)) - float(f(*minus))) / (2 * eps)
        assert abs(float(jnp.sum(g * E)) - fd) < 1e-3 * max(1.0, abs(fd)), (arg, float(jnp.sum(g * E)), fd)


def test_gradients_stay_finite_on_degenerate_grasps():
    c, n = sphere_contacts(np.deg2rad(60))
    coincident = np.repeat(c[:1], 5, 0), np.repeat(n[:1], 5, 0)
    zero_normals = c, np.zeros_like(n)
    value = jax.jit(lambda a, b: quality.q_distance(a, b, jnp.zeros(3), R))
    grad = jax.jit(jax.grad(lambda a, b: value(a, b)[0], argnums=(0, 1)))
    for cc, nn in (coincident, zero_normals):
        v, ok = value(jnp.asarray(cc), jnp.asarray(nn))
        gc, gn = grad(jnp.asarray(cc), jnp.asarray(nn))
        assert np.isfinite(float(v)) and np.isfinite(np.asarray(gc)).all() and np.isfinite(np.asarray(gn)).all()
    assert not bool(value(jnp.asarray(c), jnp.zeros_like(jnp.asarray(n)))[1])


def test_one_sided_contacts_are_not_force_closure():
    assert e_g(*sphere_contacts(np.deg2rad(20))) > 0.5


def test_well_spread_five_finger_grasp_is_force_closure():
    # a triangular bipyramid: 3 contacts on the equator, 2 at the poles
    phi = 2 * np.pi * np.arange(3) / 3
    n = np.concatenate([np.stack([np.cos(phi), np.sin(phi), 0 * phi], 1), [[0, 0, 1.0], [0, 0, -1.0]]])
    assert e_g(R * n, n) < 1e-6


def test_e_g_drops_as_contacts_spread():
    values = [e_g(*sphere_contacts(np.deg2rad(t))) for t in (10, 30, 50, 70, 85)]
    assert all(a > b for a, b in zip(values, values[1:])), values
    assert values[-1] < 1e-6  # a ring below 90 - atan(mu) = 78.7 degrees holds the sphere


def test_sum_alpha_le_1_would_always_give_zero():
    """The literal eq. 8 (sum alpha <= 1) contains the origin for any contacts: it cannot rank grasps."""
    c, n = sphere_contacts(np.deg2rad(20))
    W = np.asarray(quality.primitive_wrenches(jnp.asarray(c), jnp.asarray(n), jnp.zeros(3), R, 0.2, 8))
    cost, A, b = primal_matrices(W, U)
    le = linprog(cost, A_eq=A[:6], b_eq=b[:6], A_ub=A[6:], b_ub=b[6:], bounds=(0, None), method="highs").fun
    assert le == pytest.approx(0.0, abs=1e-12)
    assert e_g(c, n) > 0.5  # while the convex-hull reading (sum alpha = 1) tells the one-sided grasp apart


def test_e_g_does_not_depend_on_object_size():
    c, n = sphere_contacts(np.deg2rad(45))
    small = float(quality.q_distance(jnp.asarray(c), jnp.asarray(n), jnp.zeros(3), R)[0])
    big = float(quality.q_distance(jnp.asarray(10 * c), jnp.asarray(n), jnp.zeros(3), 10 * R)[0])
    assert small == pytest.approx(big, abs=1e-6)


def test_matches_the_independent_numpy_reference():
    c, n = sphere_contacts(np.deg2rad(40), phase=0.3)
    from ffcgs_jax.evaluation.metrics import primitive_wrenches

    W = primitive_wrenches(c, n, np.zeros(3), R, 0.2, 8)  # NumPy, (N, 6), its own tangent frames
    assert e_g(c, n) == pytest.approx(q_distance_reference(W, U), abs=2e-3)  # pyramids may turn differently


def test_cone_edges_lie_on_the_friction_cone():
    n = jnp.asarray([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    f = np.asarray(quality.cone_edges(n, 0.2, 8))
    np.testing.assert_allclose(np.linalg.norm(f, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(f @ np.asarray(n), -1 / np.sqrt(1.04), atol=1e-12)  # half-angle atan(0.2), inward
