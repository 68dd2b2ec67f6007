"""Annotation planner: annealing lowers the cheap energy, determinism, per-candidate independence, q limits,
the Metropolis rule, config errors."""

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ffcgs_jax.dataset import planner as PL
from ffcgs_jax.dataset.config import PlannerConfig
from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.geometry import mesh_io
from ffcgs_jax.geometry import sdf as S
from ffcgs_jax.geometry.config import SDFConfig
from ffcgs_jax.synthesis import energy
from ffcgs_jax.synthesis.config import FilterConfig

pytestmark = pytest.mark.e2e  # the planner's annealing compiled on the SVH

# One small config for every test, so the two executables (start, anneal_from) compile once.
CFG = PlannerConfig(population=8, steps=30, refine=8)
KEY = jax.random.PRNGKey(3)


@pytest.fixture(scope="module")
def target():
    return energy.make_target(S.build_sdf(mesh_io.load_mesh("box"), SDFConfig(res=16)))


@pytest.fixture(scope="module")
def run(svh, target):
    return PL.anneal(svh, target, CFG, KEY)


@pytest.mark.slow  # CI margin: ~50 s with its fixture on the 2-core machine
def test_annealing_lowers_the_energy(svh, target, run):
    s = PL.start_jit(svh, target, CFG, KEY)
    before = np.asarray(PL.cheap_energy_batch(svh, target, s.poses, s.q, CFG, FilterConfig()))
    poses, q, E = (np.asarray(a) for a in run)
    assert np.all(E <= before)  # the best state seen includes the start
    assert np.mean(E) < 0.9 * np.mean(before)
    # the returned energy is that of the returned state
    np.testing.assert_allclose(PL.cheap_energy_batch(svh, target, jnp.asarray(poses), jnp.asarray(q), CFG, FilterConfig()), E,
                               rtol=1e-9)


def test_deterministic_for_a_seed(svh, target, run):
    again = PL.anneal(svh, target, CFG, KEY)
    for a, b in zip(run, again):
        np.testing.assert_array_equal(a, b)
    other = PL.anneal(svh, target, CFG, jax.random.PRNGKey(4))
    assert not np.allclose(run[2], other[2])


@pytest.mark.slow  # CI margin: the default suite reached 15.3 min on the 2-core machine
def test_candidates_are_independent(svh, target):
    s = PL.start_jit(svh, target, CFG, KEY)
    k = 3
    # replace the other candidates' starts and keys: the first k must not notice
    perm = np.r_[np.arange(k), np.arange(CFG.population - 1, k - 1, -1)]
    keys2 = s.keys.at[k:].set(jax.vmap(jax.random.fold_in, (None, 0))(KEY, jnp.arange(CFG.population - k) + 99))
    a = PL.anneal_from_jit(svh, target, CFG, s.poses, s.q, s.keys)
    b = PL.anneal_from_jit(svh, target, CFG, s.poses[perm], s.q[perm], keys2)
    for x, y in zip(a, b):
        np.testing.assert_allclose(np.asarray(x)[:k], np.asarray(y)[:k], rtol=1e-12, atol=1e-12)
    assert not np.allclose(np.asarray(a[2])[k:], np.asarray(b[2])[k:])


def test_q_within_limits_and_poses_rigid(svh, run):
    poses, q, _ = (np.asarray(a) for a in run)
    assert q.shape == (CFG.population, svh.n_channels)
    assert np.all(q >= np.asarray(svh.lower)) and np.all(q <= np.asarray(svh.upper))
    R = poses[:, :3, :3]
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-9)
    np.testing.assert_array_equal(poses[:, 3], np.broadcast_to([0.0, 0.0, 0.0, 1.0], (CFG.population, 4)))


def test_metropolis_rule():
    acc = lambda *a: bool(PL.metropolis_accept(*(jnp.asarray(x) for x in a)))
    # uphill by 0.1 at T = 0.1: accepted with probability exp(-1) = 0.3679
    assert acc(1.0, 1.1, 0.1, math.exp(-1) - 1e-6)
    assert not acc(1.0, 1.1, 0.1, math.exp(-1) + 1e-6)
    assert acc(1.0, 0.5, 0.1, 0.999999)  # downhill: always
    assert acc(1.0, 1.0, 0.1, 0.999999)  # level: always
    assert not acc(1.0, float("nan"), 0.1, 1e-9)  # a NaN proposal: never


def test_temperatures_cool_geometrically():
    T = np.asarray(PL.temperatures(CFG))
    assert T[0] == pytest.approx(CFG.t0) and T[-1] == pytest.approx(CFG.t_end)
    np.testing.assert_allclose(T[1:] / T[:-1], (CFG.t_end / CFG.t0) ** (1 / (CFG.steps - 1)))


@pytest.mark.parametrize("change", [
    {"population": 0}, {"steps": 0}, {"t0": 0.0}, {"t_end": -1.0}, {"t0": 0.01, "t_end": 0.1}, {"step_q": -0.1},
    {"a_pen": float("nan")}, {"refine": 0}, {"refine": 9},
])
def test_config_errors(change):
    with pytest.raises(FfcgsError):
        dataclasses.replace(CFG, **change).check()
    CFG.check()


def test_rank_puts_valid_first_then_epsilon():
    from ffcgs_jax.synthesis.config import GraspConfig
    from ffcgs_jax.synthesis.grasp import GraspSet

    gs = GraspSet(dict(valid=np.array([False, True, True, True, False]), epsilon=np.array([0.9, 0.0, 0.2, 0.2, 0.1]),
                       E=np.array([0.0, 0.1, 0.3, 0.2, 0.0])), {}, GraspConfig(), "toy")
    assert PL.rank(gs).tolist() == [3, 2, 1, 0, 4]


def test_dedupe_drops_near_duplicates_only():
    from scipy.spatial.transform import Rotation

    base = np.eye(4)
    near = np.eye(4)
    near[:3, :3] = Rotation.from_rotvec([0.05, 0, 0]).as_matrix()
    near[:3, 3] = [0.003, 0, 0]
    far_t = np.eye(4)
    far_t[:3, 3] = [0.02, 0, 0]  # same rotation, 2 cm away: kept
    far_r = np.eye(4)
    far_r[:3, :3] = Rotation.from_rotvec([0, 0.5, 0]).as_matrix()  # same place, 0.5 rad: kept
    poses = np.stack([base, near, far_t, far_r, near])
    assert PL.dedupe(poses, 0.005, 0.1).tolist() == [0, 2, 3]
    assert PL.dedupe(poses, 0.0, 0.0).tolist() == [0, 1, 2, 3, 4]
    # a loop over pairs as the reference
    rng = np.random.default_rng(0)
    P = np.tile(np.eye(4), (40, 1, 1))
    P[:, :3, :3] = Rotation.random(40, random_state=1).as_matrix()
    P[:, :3, 3] = rng.uniform(-0.01, 0.01, (40, 3))
    kept = []
    for i in range(40):
        if not any(np.linalg.norm(P[i, :3, 3] - P[k, :3, 3]) < 0.008
                   and Rotation.from_matrix(P[i, :3, :3].T @ P[k, :3, :3]).magnitude() < 2.0 for k in kept):
            kept.append(i)
    assert PL.dedupe(P, 0.008, 2.0).tolist() == kept
