"""The MuJoCo Warp backend against the CPU backend on the same grasps: same outcomes, same failure reasons, moves
within a millimetre; a world whose contact buffers overflow is run again on the CPU, never scored from the
overflowed simulation. Warp runs on the CPU here (slowly; its kernels compile once, about a minute, and are cached
on disk), so these tests need `pip install -e ".[warp]"` and are skipped without it."""

import ctypes

import numpy as np
import pytest

from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.physics import backend_warp
from ffcgs_jax.physics import runner as physics
from ffcgs_jax.physics.config import PhysicsConfig
from physics_trials import ONE_TRIAL

from test_runner import BALL, SPEC, ball_grasps, enveloping_ball_grasp

pytestmark = pytest.mark.skipif(backend_warp.unavailable() is not None, reason="warp-lang / mujoco-warp missing")

FAST = PhysicsConfig(robust=ONE_TRIAL, sim_friction=1.0, close_time=0.2, settle_time=0.1, lift_height=0.03, shake_cycles=1,
                     shake_amplitude=0.02, push_time=0.2)


def _four():
    Ts, qs = ball_grasps(3)
    far, q = enveloping_ball_grasp(shift=0.05)  # touches nothing: fails as "lost" on both
    return np.concatenate([Ts, far[None]]), np.concatenate([qs, q[None]])


def test_warp_gives_the_cpu_outcomes():
    Ts, qs = _four()
    cpu = physics.evaluate(SPEC, BALL, Ts, qs, FAST, backend="cpu")
    warp = physics.evaluate(SPEC, BALL, Ts, qs, FAST, backend="warp")
    for p in ("lift_shake", "six_dir"):
        np.testing.assert_array_equal(warp[f"{p}_success"], cpu[f"{p}_success"], err_msg=p)
        np.testing.assert_array_equal(warp[f"{p}_reason"], cpu[f"{p}_reason"], err_msg=p)
        ok = cpu[f"{p}_success"]
        np.testing.assert_allclose(warp[f"{p}_move"][ok], cpu[f"{p}_move"][ok], atol=1e-3, err_msg=p)
    assert cpu["lift_shake_success"].tolist() == [True, True, False, False]  # the comparison covers both outcomes
    assert not warp["physics_rerun_cpu"].any()


def test_overflowed_worlds_are_rerun_on_the_cpu(monkeypatch, capfd):
    """Buffers of 2 contacts cannot hold a grasp: every world overflows, and the results are the CPU's. The
    warning says so once; MuJoCo Warp's printf per world stays off."""
    Ts, qs = _four()
    from ffcgs_jax.physics import worlds

    worlds.clear()  # engines keep the buffers they were built with
    monkeypatch.setattr(worlds, "buffer_sizes", lambda scene: (2, 60))
    with pytest.warns(UserWarning, match="overflowed"):
        warp = physics.evaluate(SPEC, BALL, Ts[:2], qs[:2], FAST, protocols=("six-dir",), backend="warp")
    worlds.clear()
    cpu = physics.evaluate(SPEC, BALL, Ts[:2], qs[:2], FAST, protocols=("six-dir",), backend="cpu")
    assert warp["physics_rerun_cpu"].all()
    for k in ("six_dir_success", "six_dir_reason", "six_dir_move", "six_dir_move_dir"):
        np.testing.assert_array_equal(warp[k], cpu[k], err_msg=k)
    ctypes.CDLL(None).fflush(None)  # the kernels' printf goes through the C library's buffered stdout
    printed = capfd.readouterr()
    assert "overflow" not in printed.out + printed.err


def test_buffer_sizes_grow_with_the_scene():
    small = physics.scenes(SPEC, BALL, FAST, ("six-dir",))["six-dir"]
    ncon, njmax = backend_warp.buffer_sizes(small)
    assert ncon >= 8 * len(small.hand_geoms) and njmax >= 3 * ncon


def test_a_batch_larger_than_the_worlds_is_refused():
    scene = physics.scenes(SPEC, BALL, FAST, ("six-dir",))["six-dir"]
    sim = backend_warp.WarpSim(scene, 2)
    with pytest.raises(FfcgsError, match="at most 2 grasps"):
        sim._pad(np.zeros((3, 3)))


def test_survivors_move_to_fewer_worlds(monkeypatch):
    """As grasps fail for certain they leave; the rest run on fewer worlds, with the CPU's outcomes."""
    from ffcgs_jax.physics import backend_cpu
    from ffcgs_jax.physics import protocols as P

    from test_protocols import CFG, mixed

    monkeypatch.setattr(backend_warp, "MIN_WORLDS", 1)
    Ts, qs = mixed()
    scene = physics.scenes(SPEC, BALL, CFG, ("six-dir",))["six-dir"]
    batch, depth, _ = physics.prepare(scene, BALL, Ts, qs, CFG)
    sim = backend_warp.WarpSim(scene, 8)
    warp = P.run_protocol(sim, batch, depth, CFG, "six-dir")
    cpu = P.run_protocol(backend_cpu.CpuSim(scene, 1), batch, depth, CFG, "six-dir")
    np.testing.assert_array_equal(warp["success"], cpu["success"])
    np.testing.assert_array_equal(warp["reason"], cpu["reason"])
    np.testing.assert_array_equal(np.isnan(warp["move_dir"]), np.isnan(cpu["move_dir"]))
    assert len(sim._worlds) >= 3 and min(sim._worlds) < 4, sorted(sim._worlds)  # 8 worlds, then fewer
    assert not warp["flagged"].any()


def test_eval_backend_warp_with_a_video(tmp_path, capsys):
    """`ffcgs eval --backend warp --video`: the batch on warp, the video a CPU replay of the chosen grasp."""
    from ffcgs_jax.cli import main as cli_main
    from ffcgs_jax.synthesis import grasp_io

    Ts, qs = _four()
    path = tmp_path / "g.npz"
    np.savez(path, object_name=np.array("ball"), wrist_pose=Ts[:2], q=qs[:2], valid=np.ones(2, bool))
    code = cli_main.main(["eval", str(path), "--backend", "warp", "--protocol", "six-dir", "--sim-friction", "1.0",
                          "--close-time", "0.2", "--settle-time", "0.1", "--push-time", "0.2",
                          "--video", str(tmp_path / "v.gif")])
    out, err = capsys.readouterr()
    assert code == 0, err
    assert "backend warp" in out and (tmp_path / "v.gif").stat().st_size > 1000
    assert grasp_io.load_npz(path)["physics_tested"].all()
