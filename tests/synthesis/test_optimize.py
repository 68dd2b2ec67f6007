"""Algorithm 1 (`optimize`), its Adam (`optim`) and the wrist twist, on the two-finger toy hand around the ball."""

import logging

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ffcgs_jax.geometry import mesh_io
from ffcgs_jax.geometry import sdf as sdf_mod
from ffcgs_jax.geometry.config import SDFConfig
from ffcgs_jax.hand import kinematics as K
from ffcgs_jax.synthesis import energy as En
from ffcgs_jax.synthesis.config import EnergyConfig, OptimConfig
from ffcgs_jax.kernels.adam import adam_init, adam_update
from ffcgs_jax.synthesis.optimize import optimize, twist_pose

TOY = "tests/data/toy_hand/toy.toml"
TOY_LOWER, TOY_UPPER = np.array([0.0, 0.0]), np.array([1.2, 1.0])  # from toy.toml
ECFG = EnergyConfig(a_pen=0.0, a_m=0.0)  # penalty and margin are energy's business (test_energy, test_margin)
# the descent alone: the final projection (`synthesis.project`, tests/synthesis/test_project.py) trades E for
# overlap, and 6 steps of gd on the toy hand leave links inside the object
GD = OptimConfig(iters=6, method="gd", step=0.01, step_end=0.002, wrist=False, project_steps=0)
# adam + wrist (defaults); every pose converged at t = 0; no projection, which would move the open hands that
# sit in the object
STOP = OptimConfig(iters=4, eps_g=10.0, eps_c=1.0, project_steps=0)
RTOL_ADAM = 1e-4  # see test_adam_bias_correction_in_float64: the bias correction is computed in float32
ATOL_BATCH = 1e-9  # one pose alone vs in a batch of 4: same math, differently fused


def _pose(rotvec, t):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


POSES = np.stack([_pose([0, 0, 0], [0, 0, 0]), _pose([0, 0, 0.5], [0.003, 0, 0]),
                  _pose([0.2, 0, 0], [0, -0.01, 0.005]), _pose([0, 0.3, 0], [0, 0, -0.005])])


@pytest.fixture(scope="module")
def toy():
    hand = K.load_hand(TOY)
    target = En.make_target(sdf_mod.build_sdf(mesh_io.load_mesh("ball"), SDFConfig(res=16)))
    return hand, target, jnp.asarray(POSES)


def run(hand, target, poses, ocfg, ecfg=ECFG):
    return jax.block_until_ready(optimize(hand, target, poses, ecfg, ocfg))


@pytest.fixture(scope="module")
def gd_result(toy):
    return run(*toy, GD)


class count_compiles:
    """Counts XLA compilations logged by JAX inside the block (as tests/hand/test_kinematics.py)."""

    def __enter__(self):
        self.n = 0
        self.handler = logging.Handler()
        self.handler.emit = lambda rec: setattr(self, "n", self.n + ("Compiling" in rec.getMessage()))
        logging.getLogger("jax").addHandler(self.handler)
        self.ctx = jax.log_compiles()
        self.ctx.__enter__()
        return self

    def __exit__(self, *exc):
        self.ctx.__exit__(*exc)
        logging.getLogger("jax").removeHandler(self.handler)


# ---------------------------------------------------------------------------------------------------------------
# Adam
# ---------------------------------------------------------------------------------------------------------------


def _numpy_adam(params, grads_seq, lr, b1=0.9, b2=0.999, eps=1e-8):
    p = {k: np.array(v, np.float64) for k, v in params.items()}
    m = {k: np.zeros_like(v) for k, v in p.items()}
    v = {k: np.zeros_like(x) for k, x in p.items()}
    out = []
    for t, g in enumerate(grads_seq, start=1):
        for k in p:
            m[k] = b1 * m[k] + (1 - b1) * g[k]
            v[k] = b2 * v[k] + (1 - b2) * g[k] ** 2
            p[k] = p[k] - lr * (m[k] / (1 - b1**t)) / (np.sqrt(v[k] / (1 - b2**t)) + eps)
        out.append({k: x.copy() for k, x in p.items()})
    return out


def _adam_steps(params, grads_seq, lr):
    state = adam_init(params)
    p, out = params, []
    for g in grads_seq:
        upd, state = adam_update(g, state, lr)
        p = jax.tree.map(lambda a, u: a + u, p, upd)
        out.append(p)
    return out, state


def _problem():
    rng = np.random.default_rng(3)
    params = {"a": rng.normal(size=3), "b": rng.normal(size=(2, 2))}
    grads = [{"a": rng.normal(size=3) * s, "b": rng.normal(size=(2, 2)) * s} for s in (1.0, 0.1, 3.0, 1e-3, 0.5)]
    return params, grads


def test_adam_matches_numpy_reference():
    params, grads = _problem()
    ref = _numpy_adam(params, grads, lr=0.1)
    got, state = _adam_steps({k: jnp.asarray(v) for k, v in params.items()},
                             [{k: jnp.asarray(v) for k, v in g.items()} for g in grads], 0.1)
    for r, g in zip(ref, got):
        for k in r:
            np.testing.assert_allclose(np.asarray(g[k]), r[k], rtol=RTOL_ADAM)
    assert int(state.count) == len(grads)
    # the first step moves every coordinate by lr against the sign of its gradient (m / sqrt(v) = sign(g))
    np.testing.assert_allclose(np.asarray(got[0]["a"]) - params["a"], -0.1 * np.sign(grads[0]["a"]), rtol=1e-4)


def test_adam_state_starts_at_zero_and_keeps_dtype():
    params = {"a": jnp.ones(3), "b": jnp.ones((2, 2))}
    s = adam_init(params)
    assert int(s.count) == 0
    assert all(float(jnp.abs(x).max()) == 0 for x in jax.tree.leaves((s.mu, s.nu)))
    upd, _ = adam_update(params, s, 0.1)
    assert all(u.dtype == jnp.float64 for u in jax.tree.leaves(upd))


def test_adam_bias_correction_in_float64():
    params, grads = _problem()
    ref = _numpy_adam(params, grads, lr=0.1)
    got, _ = _adam_steps({k: jnp.asarray(v) for k, v in params.items()},
                         [{k: jnp.asarray(v) for k, v in g.items()} for g in grads], 0.1)
    np.testing.assert_allclose(np.asarray(got[0]["a"]), ref[0]["a"], rtol=1e-10)


# ---------------------------------------------------------------------------------------------------------------
# twist_pose
# ---------------------------------------------------------------------------------------------------------------


H0 = _pose([0.4, -0.2, 0.9], [0.1, -0.05, 0.2])


def test_twist_zero_is_identity():
    np.testing.assert_allclose(np.asarray(twist_pose(jnp.asarray(H0), jnp.zeros(6))), H0, atol=1e-15)


@pytest.mark.parametrize("w", [[0.3, -0.5, 0.2], [1e-7, 2e-7, -1e-7], [0.0, 0.0, np.pi - 1e-3]])
def test_twist_matches_scipy_rotvec(w):
    t = np.array([0.01, 0.02, -0.03])
    D = np.eye(4)
    D[:3, :3] = Rotation.from_rotvec(w).as_matrix()
    D[:3, 3] = t
    got = np.asarray(twist_pose(jnp.asarray(H0), jnp.asarray(np.concatenate([w, t]))))
    np.testing.assert_allclose(got, H0 @ D, atol=1e-12)


def test_twist_derivative_at_zero_is_the_hat_map():
    """d(H D(xi))/dxi at 0: H [e_k]x in the rotation block for k < 3, H e_k in the translation column for k >= 3."""
    H = jnp.asarray(H0)
    for jac in (jax.jacfwd, jax.jacrev):
        J = np.asarray(jax.jit(jac(lambda xi: twist_pose(H, xi)))(jnp.zeros(6)))  # (4, 4, 6)
        assert np.isfinite(J).all()
        for k in range(6):
            dD = np.zeros((4, 4))
            if k < 3:
                dD[:3, :3] = np.stack([np.cross(np.eye(3)[k], np.eye(3)[j]) for j in range(3)], 1)  # [e_k]x
            else:
                dD[k - 3, 3] = 1.0
            np.testing.assert_allclose(J[..., k], H0 @ dD, atol=1e-12)


# ---------------------------------------------------------------------------------------------------------------
# optimize
# ---------------------------------------------------------------------------------------------------------------


@pytest.mark.slow  # CI margin: the default suite reached 15.3 min on the 2-core machine
def test_optimize_traces_under_rank_promotion_raise(toy):
    hand, target, poses = toy
    optimize(hand, target, poses, ECFG, GD)


def test_channels_stay_within_the_joint_limits(gd_result):
    q = np.asarray(gd_result.q)
    assert q.shape == (4, 2)
    assert (q >= TOY_LOWER - 1e-12).all() and (q <= TOY_UPPER + 1e-12).all()
    assert (np.abs(q) > 1e-3).any()  # and q moved


@pytest.mark.e2e  # over 20 s on the 2-core CPU: kept out of plain `pytest` (README)
def test_steps_past_the_limits_are_clipped(toy):
    big = run(*toy, OptimConfig(iters=2, method="gd", step=50.0, step_end=50.0, wrist=False))
    q = np.asarray(big.q)
    assert (q >= TOY_LOWER - 1e-12).all() and (q <= TOY_UPPER + 1e-12).all()
    assert np.isclose(q, TOY_UPPER).any() or np.isclose(q, TOY_LOWER).any()  # the clip was needed


def test_energy_decreases_for_most_poses(gd_result):
    E = np.asarray(gd_result.trace.E)
    assert (E[-1] <= E[0] + 1e-12).sum() >= 3
    assert (E[-1] < E[0] - 1e-3).any()


def test_trace_shapes_and_final_terms(toy, gd_result):
    T, B, C = GD.iters, 4, 2
    tr = gd_result.trace
    assert tr.E.shape == tr.E_g.shape == tr.E_c.shape == (T + 1, B)
    assert tr.tips.shape == (T + 1, B, C, 3)
    r = gd_result
    assert r.final.E.shape == (B,) and r.final.contacts.shape == (B, C, 3)
    assert r.iters.shape == r.converged.shape == r.lp_ok.shape == (B,)
    np.testing.assert_allclose(np.asarray(tr.E[-1]), np.asarray(r.final.E), rtol=0)
    assert (np.asarray(r.iters) == T).all() and not np.asarray(r.converged).any()
    # the recorded start is q = 0 (clamped) at the given poses, the end the returned q
    hand, target, poses = toy
    fk = jax.jit(jax.vmap(lambda H, q: En.fingertip_contacts(hand, target.sdf, K.forward_kinematics(hand, H, q))[0]))
    np.testing.assert_allclose(np.asarray(tr.tips[0]), np.asarray(fk(poses, jnp.zeros((B, 2)))), atol=1e-12)
    np.testing.assert_allclose(np.asarray(tr.tips[-1]), np.asarray(fk(poses, r.q)), atol=1e-12)


def test_fixed_wrist_returns_the_input_poses(toy, gd_result):
    np.testing.assert_array_equal(np.asarray(gd_result.wrist_pose), POSES)


@pytest.mark.e2e  # over 20 s on the 2-core CPU: kept out of plain `pytest` (README)
def test_batch_members_are_independent(toy, gd_result):
    """Each pose alone (B = 1) gives what it gets in the batch of 4."""
    hand, target, poses = toy
    for i in (0, 2):
        one = run(hand, target, poses[i:i + 1], GD)
        np.testing.assert_allclose(np.asarray(one.q[0]), np.asarray(gd_result.q[i]), atol=ATOL_BATCH)
        np.testing.assert_allclose(np.asarray(one.trace.E[:, 0]), np.asarray(gd_result.trace.E[:, i]),
                                   rtol=1e-9)
        assert int(one.iters[0]) == int(gd_result.iters[i])


def test_second_call_does_not_recompile(toy, gd_result):
    hand, target, poses = toy
    shifted = poses.at[:, 2, 3].add(0.002)  # new values, same shapes and configs
    with count_compiles() as c:
        r = run(hand, target, shifted, GD)
    assert c.n == 0
    assert not np.allclose(np.asarray(r.q), np.asarray(gd_result.q))  # it did run on the new poses


@pytest.mark.e2e  # over 20 s on the 2-core CPU: kept out of plain `pytest` (README)
def test_early_stop_at_iteration_zero(toy):
    """With eps_g and eps_c huge every pose has converged before the first step: nothing moves (wrist included)."""
    hand, target, poses = toy
    r = run(hand, target, poses, STOP)
    assert (np.asarray(r.iters) == 0).all()
    assert np.asarray(r.converged).all()
    np.testing.assert_array_equal(np.asarray(r.q), np.zeros((4, 2)))  # q = clip(0) = lower for the toy
    np.testing.assert_allclose(np.asarray(r.wrist_pose), POSES, atol=1e-15)
    E = np.asarray(r.trace.E)
    assert E.shape == (STOP.iters + 1, 4)
    np.testing.assert_allclose(E, np.broadcast_to(E[0], E.shape), rtol=1e-12)
