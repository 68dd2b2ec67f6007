"""Early exit in `protocols.run_protocol`: grasps whose failure is certain leave the batch, and nothing else
changes. Checked against a plain run of every grasp through every segment (the protocol as written before early
exit), on grasps that pass, slip in some push direction, are dropped, or start in penetration."""

import dataclasses

import numpy as np
import pytest

from ffcgs_jax.physics import backend_cpu
from ffcgs_jax.physics import protocols as P
from ffcgs_jax.physics import runner as physics
from ffcgs_jax.physics.config import PhysicsConfig
from physics_trials import ONE_TRIAL

from test_runner import BALL, FAST, SPEC, ball_grasps, enveloping_ball_grasp

# pushes strong enough that the weaker grasps slip out within the short pushes
# (one slips in the first push, +x, and is not pushed further; one in the last, -z)
CFG = dataclasses.replace(FAST, sim_friction=0.6, accel=25.0, push_time=0.3)


def mixed():
    Ts, qs = ball_grasps(4)
    far, q = enveloping_ball_grasp(shift=0.05)  # touches nothing: dropped at once
    deep, _ = enveloping_ball_grasp(shift=-0.03)  # starts 3 cm inside: penetration
    return np.concatenate([Ts, far[None], deep[None]]), np.concatenate([qs, q[None], q[None]])


def full_run(sim, batch, depth, cfg, protocol):
    """Every grasp through every segment, judged at the end (lift-shake) or over the whole push (six-dir)."""
    state = sim.initial(batch)
    for seg in P.closing(batch, cfg):
        state = sim.run(state, batch, seg)
    ref = sim.probe(state, batch)
    bad = depth > cfg.max_initial_penetration
    if protocol == "lift-shake":
        for seg in P.lift_shake(batch, cfg):
            state = sim.run(state, batch, seg)
        end = sim.probe(state, batch, np.array([0.0, 0.0, cfg.lift_height]))
        move = np.linalg.norm(end["rel"] - ref["rel"], axis=1)
        lost, moved = ~end["touch"], (move >= cfg.max_slip) | end["table"]
        return dict(success=~(bad | lost | moved), reason=P.failure_reason(bad, lost, moved), move=move)
    move_dir, rot_dir = np.zeros((len(depth), 6)), np.zeros((len(depth), 6))
    for k, direction in enumerate(P.DIRECTIONS):
        def track(s, k=k):
            p = sim.probe(s, batch)
            move_dir[:, k] = np.maximum(move_dir[:, k], np.linalg.norm(p["pos"] - ref["pos"], axis=1))
            rot_dir[:, k] = np.maximum(rot_dir[:, k], P.rotation_angle(p["quat"], ref["quat"]))
        sim.run(state, batch, P.push(batch, cfg, direction, sim.scene.mass), track)
    lost = ~ref["touch"]
    moved = (move_dir.max(1) >= cfg.max_move) | (rot_dir.max(1) >= cfg.max_rot_deg)
    return dict(success=~(bad | lost | moved), reason=P.failure_reason(bad, lost, moved), move_dir=move_dir,
                rot_dir=rot_dir)


@pytest.fixture(scope="module")
def setup():
    Ts, qs = mixed()
    scenes = physics.scenes(SPEC, BALL, CFG, ("lift-shake", "six-dir"))
    batch, depth, _ = physics.prepare(scenes["six-dir"], BALL, Ts, qs, CFG)
    return scenes, batch, depth


@pytest.mark.parametrize("protocol", ["lift-shake", "six-dir"])
def test_early_exit_gives_the_full_runs_outcomes(setup, protocol):
    scenes, batch, depth = setup
    sim = backend_cpu.CpuSim(scenes[protocol], 1)
    full = full_run(sim, batch, depth, CFG, protocol)
    fast = P.run_protocol(sim, batch, depth, CFG, protocol)
    np.testing.assert_array_equal(fast["success"], full["success"])
    np.testing.assert_array_equal(fast["reason"], full["reason"])
    reasons = set(full["reason"].tolist())
    assert np.isnan(fast["move"][depth > CFG.max_initial_penetration]).all()  # never simulated
    if protocol == "six-dir":
        assert {1, 2, 3} <= reasons, reasons  # penetration, drops and slips are all covered
        tried = ~np.isnan(fast["move_dir"])
        failed = (full["move_dir"] >= CFG.max_move) | (full["rot_dir"] >= CFG.max_rot_deg)
        for g in np.flatnonzero(tried.any(1)):
            first = np.flatnonzero(failed[g])
            last = first[0] if len(first) else 5  # pushes stop after the first direction that fails
            assert tried[g].tolist() == [k <= last for k in range(6)], g
            same = np.arange(6) < (last if len(first) else 6)  # directions run to the end: identical values
            np.testing.assert_array_equal(fast["move_dir"][g, same], full["move_dir"][g, same])
            if len(first):  # the failing one stopped once past a bound
                k = first[0]
                assert fast["move_dir"][g, k] >= CFG.max_move or fast["rot_dir"][g, k] >= CFG.max_rot_deg
                assert fast["move_dir"][g, k] <= full["move_dir"][g, k]
        assert (tried.any(1) & ~tried.all(1)).any()  # some grasp skipped directions
    else:
        assert {0, 1, 2} <= reasons, reasons  # passes, penetration and drops
        ok = full["success"]
        np.testing.assert_array_equal(fast["move"][ok], full["move"][ok])


def test_auto_backend_needs_warp_a_cuda_device_and_the_lower_cost(monkeypatch, tmp_path):
    """`auto` weighs the CPU's core-seconds against Warp's steps and start-up (`cost`, the default figures here: no
    record): a 32-grasp check stays on 16 cores' CPU but goes to the GPU on 2 cores; a labelled build's thousands of
    grasps go to Warp."""
    from ffcgs_jax.physics import backend_warp, cost, worlds

    monkeypatch.setattr(backend_warp, "unavailable", lambda: None)
    monkeypatch.setattr(backend_warp, "no_cuda", lambda: None)
    monkeypatch.setattr(cost, "record_path", lambda: tmp_path / "cost.json")
    monkeypatch.setattr(worlds, "warm", lambda: False)
    monkeypatch.setattr(physics.os, "cpu_count", lambda: 16)
    backend, note = physics.resolve_backend("auto", 32)
    assert backend == "cpu" and "32 grasps take about" in note and "on 16 cores" in note
    assert physics.resolve_backend("auto", 4096) == ("warp", None)
    monkeypatch.setattr(physics.os, "cpu_count", lambda: 2)
    assert physics.resolve_backend("auto", 32) == ("warp", None)
    monkeypatch.setattr(physics.os, "cpu_count", lambda: 16)
    assert physics.resolve_backend("cpu", 10_000) == ("cpu", None)  # asked for: never second-guessed
    monkeypatch.setattr(backend_warp, "no_cuda", lambda: "no CUDA")
    backend, note = physics.resolve_backend("auto", 10_000)
    assert backend == "cpu" and "no CUDA device" in note
    monkeypatch.setattr(backend_warp, "no_cuda", lambda: None)
    monkeypatch.setattr(backend_warp, "unavailable", lambda: "missing")
    assert "not installed" in physics.resolve_backend("auto")[1]
    with pytest.raises(physics.FfcgsError, match="unknown physics backend 'gpu'"):
        physics.resolve_backend("gpu")


# --- protocols as registered objects ----------------------------------------------------------------------------


def test_the_protocol_names_come_from_the_registry():
    from ffcgs_jax.physics import config as physics_config

    assert physics_config.ALL_PROTOCOLS == P.names() == (
        "lift-shake", "six-dir", "dexgraspbench", "dexgraspbench-bodex")
    assert physics_config.PROTOCOLS == P.names(default=True) == ("lift-shake", "six-dir")
    assert physics_config.DEXGRASPBENCH == ("dexgraspbench", "dexgraspbench-bodex")
    six = P.get("six-dir")
    assert (six.kind, six.gravity, six.table, six.hold, six.directions) == ("ours", False, False, True, True)
    assert [label for label, _, _ in six.phases(*one_grasp(), 0.1)][:3] == ["closing", "settle", "push +x"]
    with pytest.raises(physics.FfcgsError, match="^unknown protocol 'drop'; protocols: lift-shake, six-dir, "
                                                 "dexgraspbench, dexgraspbench-bodex$"):
        P.get("drop")
    with pytest.raises(physics.FfcgsError, match="'six-dir' is registered already"):
        P.register(six)
    with pytest.raises(physics.FfcgsError, match="fixes gain, which PhysicsConfig does not have"):
        P.register(dataclasses.replace(six, name="six-dir-gain", fixed={"gain": 5.0}))


def one_grasp():
    z = np.zeros((1, 9))
    return P.Batch(np.zeros((1, 3)), np.array([[1.0, 0, 0, 0]]), z, z, z), CFG


def test_fixed_settings_apply_in_one_place_and_an_override_is_said_in_one_line():
    """DexGraspBench fixes its own friction (and mass, gain, solver, bounds): a value the user set otherwise is
    replaced, and one warning line names the protocol, the setting, the user's value and the one used; a default
    the user did not touch, or our protocols, say nothing."""
    import warnings

    import ffcgs_jax as fj

    bench = P.get("dexgraspbench")
    mine = PhysicsConfig(sim_friction=0.9, kp=3.0, backend="cpu", robust=ONE_TRIAL)
    used = bench.settings(mine)
    assert (used.sim_friction, used.kp, used.mass, used.condim) == (0.6, 5.0, 0.1, 4)
    assert used.squeeze == mine.squeeze and used.backend == "cpu"  # what the benchmark leaves to the user
    assert P.get("six-dir").settings(mine) is mine
    T, q = enveloping_ball_grasp()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        r = fj.evaluate_physics(SPEC, BALL, {"wrist_pose": T[None], "q": q[None]}, mine,
                                protocols=["dexgraspbench", "six-dir"])
    said = [str(w.message) for w in caught if "fixes" in str(w.message)]
    assert said == ["physics: protocol dexgraspbench fixes sim_friction = 0.6 (you set 0.9), kp = 5.0 (you set 3.0): "
                    "the protocol's values are used"], said
    assert r.protocols["dexgraspbench"].success.tolist() == [True]  # the grasp ran under the benchmark's friction
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        P.say_overrides(PhysicsConfig(), P.names())  # defaults (kp 0, condim 3, ...) are no choice of the user's
        P.say_overrides(mine, ("lift-shake", "six-dir"))
    assert caught == []
