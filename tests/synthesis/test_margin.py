"""The force-closure margin E_m (`quality.support_margin`, `quality.refine_directions`) against float64 NumPy and
Qhull's epsilon, and its gradient against central differences."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ffcgs_jax.evaluation import metrics
from ffcgs_jax.geometry import mesh_io
from ffcgs_jax.geometry import sdf as sdf_mod
from ffcgs_jax.geometry.config import SDFConfig
from ffcgs_jax.hand import kinematics as K
from ffcgs_jax.kernels import quality
from ffcgs_jax.synthesis import energy as En
from ffcgs_jax.synthesis.config import EnergyConfig

MU, M_EDGES, R = 0.2, 8, 0.05
FD_STEP = 1e-6


def _grasp(seed: int, k: int = 4):
    """k contacts on a sphere of radius R about the origin, outward normals."""
    c = np.random.default_rng(seed).standard_normal((k, 3))
    n = c / np.linalg.norm(c, axis=1, keepdims=True)
    return R * n, n


def _wrenches(c, n):
    return quality.primitive_wrenches(jnp.asarray(c), jnp.asarray(n), jnp.zeros(3), R, MU, M_EDGES)


def test_support_margin_is_the_formula():
    c, n = _grasp(0)
    W = np.asarray(_wrenches(c, n))
    dirs = np.random.default_rng(1).standard_normal((16, 6))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    for delta in (0.0, 0.05, 0.5):
        E_m, h_min = quality.support_margin(jnp.asarray(W), jnp.asarray(dirs), delta)
        h = (dirs @ W).max(axis=1)
        np.testing.assert_allclose(float(E_m), np.maximum(delta - h, 0).mean(), rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(float(h_min), h.min(), rtol=1e-12)
    # the wrenches are the metrics module's (the mesh evaluation's) too
    np.testing.assert_allclose(W.T, metrics.primitive_wrenches(c, n, np.zeros(3), R, MU, M_EDGES), atol=1e-12)


@pytest.mark.parametrize("seed", [0, 1, 2, 4])
def test_searched_support_bounds_epsilon_from_above_and_closes_in(seed):
    """min_m h(u_m) >= Qhull's epsilon for any unit directions (epsilon is the minimum over all of them), and the
    search brings it from the start's value to within a factor 1.6 of epsilon (+0.005) on random grasps."""
    c, n = _grasp(seed)
    W = _wrenches(c, n)
    eps = metrics.epsilon_q1(np.asarray(W).T)
    start = jnp.asarray(quality.margin_start(16))
    h0 = float(quality.support_margin(W, start, 0.0)[1])
    dirs = jax.jit(quality.refine_directions, static_argnums=2)(W, start, 400)
    np.testing.assert_allclose(np.linalg.norm(np.asarray(dirs), axis=1), 1.0, rtol=1e-12)
    h = float(quality.support_margin(W, dirs, 0.0)[1])
    if eps > 0:
        assert eps - 1e-9 <= h <= 1.6 * eps + 0.005, (eps, h, h0)
        assert h < h0
    else:  # not in force closure: some direction has negative support, and the search finds one
        assert h < 0


def test_margin_gradient_matches_central_differences():
    """d E_m / d contacts and d E_m / d normals at fixed directions: a max of linear functions, smooth away from
    ties; delta above every support so each direction contributes."""
    c, n = _grasp(2)
    dirs = jnp.asarray(quality.margin_start(16))
    f = jax.jit(lambda cc, nn: quality.support_margin(
        quality.primitive_wrenches(cc, nn, jnp.zeros(3), R, MU, M_EDGES), dirs, 2.0)[0])
    gc, gn = jax.jit(jax.grad(f, argnums=(0, 1)))(jnp.asarray(c), jnp.asarray(n))
    for x, g, which in ((c, gc, 0), (n, gn, 1)):
        fd = np.zeros_like(x)
        for idx in np.ndindex(x.shape):
            e = np.zeros_like(x)
            e[idx] = FD_STEP
            args_p = [jnp.asarray(c), jnp.asarray(n)]
            args_m = [jnp.asarray(c), jnp.asarray(n)]
            args_p[which] = jnp.asarray(x + e)
            args_m[which] = jnp.asarray(x - e)
            fd[idx] = (float(f(*args_p)) - float(f(*args_m))) / (2 * FD_STEP)
        assert np.abs(fd).max() > 1e-3
        np.testing.assert_allclose(np.asarray(g), fd, rtol=1e-5, atol=1e-9)


@pytest.mark.e2e  # over 20 s on the 2-core CPU: kept out of plain `pytest` (README)
def test_energy_with_margin_adds_a_m_E_m_and_its_gradient_in_q():
    """In energy(): E = ... + a_m E_m; with the direction search off (margin_steps 0) E is a plain function of q,
    and its q-gradient (through the toy hand's kinematics) matches central differences."""
    hand = K.load_hand("tests/data/toy_hand/toy.toml")
    target = En.make_target(sdf_mod.build_sdf(mesh_io.load_mesh("ball"), SDFConfig(res=16)))
    H, q = jnp.eye(4), np.array([0.3, 0.4])
    on = EnergyConfig(a_c=0.0, a_q=0.0, a_pen=0.0, a_m=2.0, closure_margin=1.5, margin_steps=0)
    off = EnergyConfig(a_c=0.0, a_q=0.0, a_pen=0.0, a_m=0.0)
    vg = jax.jit(jax.value_and_grad(En.energy, argnums=3, has_aux=True), static_argnums=4)
    (E1, t1), g1 = vg(hand, target, H, jnp.asarray(q), on)
    (E0, t0), g0 = vg(hand, target, H, jnp.asarray(q), off)
    assert float(t1.E_m) > 0.1
    np.testing.assert_allclose(float(E1), float(E0) + 2.0 * float(t1.E_m), rtol=1e-12)
    f = lambda x: float(vg(hand, target, H, jnp.asarray(x), on)[0][0])  # noqa: E731
    fd = np.array([(f(q + 1e-5 * e) - f(q - 1e-5 * e)) / 2e-5 for e in np.eye(2)])
    np.testing.assert_allclose(np.asarray(g1), fd, rtol=1e-4)
    assert np.abs(np.asarray(g1) - np.asarray(g0)).max() > 1e-3
