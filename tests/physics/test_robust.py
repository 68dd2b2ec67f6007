"""The robust verdict (`physics.robust`): the perturbation distribution reproducible and applied as stated, rates and
intervals, a robust grasp against a marginal one, `validate` ranking by it, and files without rates."""

import dataclasses

import numpy as np
import pytest
import scipy.stats

import ffcgs_jax as fj
from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.evaluation.ranking import ranked
from ffcgs_jax.physics import protocols as physics_protocols
from ffcgs_jax.physics import robust, runner
from ffcgs_jax.physics.config import PhysicsConfig, RobustConfig
from physics_trials import ONE_TRIAL

from test_runner import BALL, FAST, SPEC, enveloping_ball_grasp

ROBUST = dataclasses.replace(FAST, robust=RobustConfig())  # the default distribution, K = 8
BOTH = ("lift-shake", "six-dir")


def _grasps(shifts):
    pairs = [enveloping_ball_grasp(s) for s in shifts]
    return np.stack([t for t, _ in pairs]), np.stack([q for _, q in pairs])


def _angle_deg(Ra, Rb):
    c = (np.trace(Ra.T @ Rb) - 1) / 2
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


def test_the_trials_conditions_follow_the_stated_distribution_from_the_seed():
    cfg = PhysicsConfig(sim_friction=0.6, mass=0.1)
    plan = robust.trials(cfg)
    assert plan == robust.trials(cfg) and plan != robust.trials(dataclasses.replace(
        cfg, robust=RobustConfig(trial_seed=1)))
    f = np.array([t.settings["sim_friction"] for t in plan])
    m = np.array([t.settings["mass"] for t in plan])
    # the ranges at the default nominal values, each of the 8 equal bins drawn once
    assert f.min() >= 0.4 - 1e-12 and f.max() <= 0.8 + 1e-12 and m.min() >= 0.05 - 1e-12 and m.max() <= 0.3 + 1e-12
    assert sorted(np.floor((f - 0.4) / 0.05).astype(int)) == list(range(8))
    assert sorted(np.floor((m - 0.05) / 0.03125).astype(int)) == list(range(8))
    assert [t.settings["voxel_cells"] for t in plan] == [64, 48] * 4
    # a density-defined object scales its density, not a mass it does not have
    dense = robust.trials(dataclasses.replace(cfg, density=500.0))
    assert all("mass" not in t.settings and 250.0 <= t.settings["density"] <= 1500.0 for t in dense)


def test_a_perturbed_pose_stays_within_its_bounds_of_the_nominal_one():
    cfg = RobustConfig()
    T, q = _grasps(np.linspace(0.0, 0.01, 16))
    shifts, turns = [], []
    for k in range(cfg.trials):
        Tk, qk = robust.perturb(cfg, k, T, q)
        shift = np.linalg.norm(Tk[:, :3, 3] - T[:, :3, 3], axis=1)
        turn = np.array([_angle_deg(a[:3, :3], b[:3, :3]) for a, b in zip(T, Tk)])
        assert shift.max() <= 2e-3 + 1e-12 and turn.max() <= 2.0 + 1e-9
        assert np.abs(qk - q).max() <= 0.02 and not np.array_equal(qk, q)
        np.testing.assert_allclose(np.einsum("bij,bkj->bik", Tk[:, :3, :3], Tk[:, :3, :3]),
                                   np.broadcast_to(np.eye(3), (16, 3, 3)), atol=1e-12)  # still rotations
        shifts.append(shift)
        turns.append(turn)
    # spread over the balls, not a fixed offset
    assert np.median(shifts) > 0.8e-3 and np.median(turns) > 0.8
    # a grasp's draws are its own: the same alone as in a batch, and the same from the same seed
    Ta, qa = robust.perturb(cfg, 3, T[5:6], q[5:6])
    Tb, qb = robust.perturb(cfg, 3, T, q)
    np.testing.assert_array_equal(Ta[0], Tb[5])
    np.testing.assert_array_equal(qa[0], qb[5])
    Tc, _ = robust.perturb(RobustConfig(trial_seed=9), 3, T, q)
    assert not np.allclose(Tc, Tb)


def test_wilson_matches_scipy():
    for n in (1, 5, 8, 32):
        for k in range(n + 1):
            lo, hi = physics_protocols.wilson(np.array([k]), n, 0.9)
            ci = scipy.stats.binomtest(k, n).proportion_ci(confidence_level=0.9, method="wilson")
            assert lo[0] == pytest.approx(max(0.0, ci.low), abs=1e-12)
            assert hi[0] == pytest.approx(min(1.0, ci.high), abs=1e-12)
    # what "holds" means at the default K = 8: 7 or 8 passes
    holds = robust.rates(np.arange(8)[:, None] > np.arange(8)[None, :] - 1, RobustConfig())["holds"]
    assert np.flatnonzero(holds).tolist() == [6, 7]


def test_a_trials_settings_reach_its_simulation():
    """The same grasp in two items, one at friction 1, one at 0.05: the second drops the ball."""
    T, q = enveloping_ball_grasp()
    cfg = dataclasses.replace(FAST, robust=ONE_TRIAL)
    items = [runner.Item(BALL, T[None], q[None], settings={"sim_friction": s}) for s in (1.0, 0.05)]
    hi, lo = runner.evaluate_many(SPEC, items, cfg, ("lift-shake",), backend="cpu")
    assert hi["lift_shake_success"][0] and not lo["lift_shake_success"][0]


def test_a_robust_grasp_holds_and_a_marginal_one_straddles_the_threshold():
    """The enveloping grasp holds (7-8 of 8 trials); 4 mm further out it still passes its nominal trial, but under
    the perturbations its interval straddles the threshold."""
    T, q = _grasps([0.0, 0.004])
    nominal = runner.evaluate(SPEC, BALL, T, q, dataclasses.replace(FAST, robust=ONE_TRIAL), BOTH, backend="cpu")
    assert nominal["lift_shake_success"].all() and nominal["six_dir_success"].all()
    r = runner.evaluate(SPEC, BALL, T, q, ROBUST, BOTH, backend="cpu")
    for p in ("lift_shake", "six_dir"):
        assert r[f"{p}_trials"].shape == (2, 8)
        np.testing.assert_array_equal(r[f"{p}_rate"], r[f"{p}_trials"].mean(axis=1))
        assert r[f"{p}_rate"][0] >= 7 / 8 and r[f"{p}_success"][0] and r[f"{p}_reason"][0] == 0
        assert r[f"{p}_rate_low"][1] < 0.5 < r[f"{p}_rate_high"][1] and not r[f"{p}_success"][1]
        assert r[f"{p}_reason"][1] > 0  # the most frequent failure of its trials
    # the same grasp alone gets the same trials: its draws do not depend on the grasps beside it
    alone = runner.evaluate(SPEC, BALL, T[1:], q[1:], ROBUST, ("six-dir",), backend="cpu")
    np.testing.assert_array_equal(alone["six_dir_trials"][0], r["six_dir_trials"][1])


def _ball_set(shifts, E):
    from ffcgs_jax.synthesis.config import GraspConfig

    T, q = _grasps(shifts)
    n = len(shifts)
    arrays = {"wrist_pose": T, "q": q, "valid": np.ones(n, bool), "E": np.asarray(E, float),
              "channel_names": np.array(SPEC.channel_names), "synthesis_s": np.array(1.0)}
    return fj.GraspSet(arrays, {"E": np.zeros((2, n))}, GraspConfig(), "ball")


def test_validate_puts_robust_passers_before_marginal_ones(tmp_path):
    # the marginal grasp has the better E: one nominal trial (both pass) keeps it first, robust trials do not
    gs = _ball_set([0.004, 0.0], E=[0.1, 0.2])
    once = fj.validate(SPEC, BALL, gs, dataclasses.replace(FAST, robust=ONE_TRIAL, backend="cpu"), protocols=BOTH)
    assert once["physics_passed"].tolist() == [True, True] and once.order().tolist() == [0, 1]
    assert "physics_rate_low" not in once.arrays
    sure = fj.validate(SPEC, BALL, gs, dataclasses.replace(ROBUST, backend="cpu"), protocols=BOTH)
    assert sure["physics_passed"].tolist() == [False, True] and sure.order().tolist() == [1, 0]
    both = sure["lift_shake_trials"] & sure["six_dir_trials"]
    np.testing.assert_array_equal(sure["physics_rate"], both.mean(axis=1))
    assert sure["physics_rate_low"][1] >= 0.5 > sure["physics_rate_low"][0] and int(sure["physics_trials"]) == 8
    # the rates travel with the file, and the file ranks the same when read back
    path = tmp_path / "g.npz"
    fj.save_grasps(sure, path)
    back = fj.load_grasps(path)
    np.testing.assert_array_equal(back["six_dir_trials"], sure["six_dir_trials"])
    assert back.order().tolist() == [1, 0]


def test_files_without_rates_rank_as_before():
    arrays = {"q": np.zeros((4, 9)), "valid": np.array([True, True, False, True]), "E": np.array([0.3, 0.1, 0.0, 0.2]),
              "physics_passed": np.array([False, False, False, True])}
    assert ranked(arrays).tolist() == [3, 1, 0, 2]
    # an older file read through the loader: no rates, the order of its E and validity
    old = fj.load_grasps("tests/data/grasps_ae66fbd_toy_box.npz")
    assert "physics_rate_low" not in old.arrays
    assert old.order().tolist() == np.lexsort((np.arange(len(old["E"])), old["E"], ~old["valid"])).tolist()


def test_bad_robust_settings_get_one_line():
    with pytest.raises(FfcgsError, match="physics.robust.geometries: 'voxel-hulls@2' is no geometry"):
        PhysicsConfig(robust=RobustConfig(geometries=("voxel-hulls@2",))).check()
    with pytest.raises(FfcgsError, match="physics.robust.trials"):
        RobustConfig(trials=0).check()
    with pytest.raises(FfcgsError, match="physics.robust.trials 2 can never show a grasp holds.* or >= 3"):
        RobustConfig(trials=2).check()
    RobustConfig(trials=3).check()  # 3 of 3: the lower bound 3 / (3 + 1.645^2) = 0.526 clears 0.5
    with pytest.raises(FfcgsError, match=r"physics.robust.mass_factors\[1\]"):
        RobustConfig(mass_factors=(2.0, 1.0)).check()
