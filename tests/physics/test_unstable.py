"""Physics that knows when it failed: a diverged simulation fails with reason "unstable" and never passes, on every
protocol; the summary counts it; MuJoCo's warnings reach neither the working folder (MUJOCO_LOG.TXT) nor stderr;
wrist poses the hand cannot reach the object from are refused in one line, through `fj.evaluate_physics` and
`ffcgs eval`; the grasps beside an unstable one keep their outcome."""

import hashlib

import mujoco
import numpy as np
import pytest

import ffcgs_jax as fj
from ffcgs_jax.cli import main as cli_main
from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.geometry import mesh_io
from ffcgs_jax.hand import spec as hand_spec
from ffcgs_jax.physics import backend, backend_cpu
from ffcgs_jax.physics import protocols as P
from ffcgs_jax.physics import runner as physics
from ffcgs_jax.physics.backend_warp import WarpSim, WarpState
from ffcgs_jax.synthesis import grasp_io

from test_runner import BALL, FAST, SPEC, ball_grasps, enveloping_ball_grasp

UNSTABLE = P.REASONS.index("unstable")


def far_grasps(offset=1e15):
    """The enveloping grasp, and the same grasp with its wrist `offset` m away along x."""
    T, q = enveloping_ball_grasp()
    far = T.copy()
    far[0, 3] += offset
    return np.stack([T, far]), np.stack([q, q])


# ---------------------------------------------------------------------------------------------------------------
# the reason and the check


def test_unstable_is_appended_so_old_reason_indices_read_the_same():
    assert P.REASONS[:4] == ("ok", "penetration", "lost", "slip") and P.REASONS[4] == "unstable"
    bad, lost, moved, unst = (np.array(v, bool) for v in ([1, 0, 0, 0, 0], [1, 1, 0, 1, 0], [1, 1, 1, 1, 0],
                                                          [1, 1, 1, 0, 0]))
    assert P.failure_reason(bad, lost, moved, unst).tolist() == [1, UNSTABLE, UNSTABLE, 2, 0]
    assert P.failure_reason(bad, lost, moved).tolist() == [1, 2, 3, 2, 0]  # callers without the flag


def test_diverged_flags_nan_inf_and_runaway_speeds_only():
    qpos, qvel = np.zeros((5, 3)), np.full((5, 2), 50.0)  # 50 m/s: fast, not absurd
    qpos[1, 0], qvel[2, 1], qvel[3, 0] = np.nan, np.inf, -2 * backend.MAX_SPEED
    qpos[4] = 1e3  # far is no divergence by itself: a mesh need not sit at the origin
    assert backend.diverged(qpos, qvel).tolist() == [False, True, True, True, False]


def test_gpu_backends_read_instability_from_the_state():
    """MJX and Warp cannot run here: their `unstable` on hand-made states (rows past n are Warp's padding)."""
    from ffcgs_jax.hand.mjx_import import mjx
    from ffcgs_jax.physics.backend_mjx import MjxSim

    qpos, qvel = np.zeros((4, 7)), np.zeros((4, 6))
    qpos[1, 2], qvel[3, 0] = np.nan, 1e6
    ball = mujoco.MjModel.from_xml_string("<mujoco><worldbody><body><freejoint/><geom size='0.1'/></body>"
                                          "</worldbody></mujoco>")
    state = mjx.make_data(mjx.put_model(ball, impl="jax")).replace(qpos=qpos, qvel=qvel)  # a batch of 4
    assert MjxSim.unstable(None, state).tolist() == [False, True, False, True]
    warp = WarpState({"qpos": qpos, "qvel": qvel}, 3, np.zeros(3, bool))
    assert WarpSim.unstable(None, warp).tolist() == [False, True, False]


# ---------------------------------------------------------------------------------------------------------------
# unstable trials on the CPU backend


class Injected(backend_cpu.CpuSim):
    """CPU MuJoCo with grasp 1 started with a NaN velocity (MuJoCo warns, resets and rollout stops the trial: the
    clock check sees it) and grasp 2 with its object flying at 1e5 m/s (finite, under MuJoCo's own 1e10 bound: on
    lift-shake's free object only the speed check sees it; six-dir's hold weld makes MuJoCo warn too). Only a start
    of three grasps is changed: the rows of the test's batch."""

    def initial(self, batch):
        out = super().initial(batch)
        m, sc = self.scene.model, self.scene
        dof = 1 + m.nq + m.jnt_dofadr[m.body_jntadr[sc.obj_body]]  # the object's x velocity in a FULLPHYSICS state
        if len(out) == 3:
            out[1, 1 + m.nq] = np.nan
            out[2, dof] = 1e5
        return out


@pytest.mark.parametrize("protocol", ["lift-shake", "six-dir", "dexgraspbench"])
def test_diverged_trials_fail_unstable_and_the_others_keep_their_outcome(protocol):
    cfg = P.get(protocol).settings(FAST)
    T, q = enveloping_ball_grasp()
    Ts, qs = np.stack([T] * 3), np.stack([q] * 3)
    sc = physics.scenes(SPEC, BALL, cfg, (protocol,))[protocol]
    batch, depth, _ = physics.prepare(sc, BALL, Ts, qs, cfg)
    r = P.run_protocol(Injected(sc, 2), batch, depth, cfg, protocol)
    alone = P.run_protocol(backend_cpu.CpuSim(sc, 1), batch.rows(slice(0, 1)), depth[:1], cfg, protocol)
    assert r["reason"][1:].tolist() == [UNSTABLE, UNSTABLE] and not r["success"][1:].any()
    assert np.isnan(r["move"][1:]).all() and np.isnan(r["rot"][1:]).all()
    for k in alone:  # the grasp beside them: the outcome it has alone, to the bit
        np.testing.assert_array_equal(r[k][:1], alone[k], err_msg=k)
    assert alone["success"][0]  # and that outcome is a pass: the injected two would have passed too


def test_unstable_scene_fails_counts_in_the_summary_and_writes_nothing(tmp_path, monkeypatch, capfd):
    """A 1 s timestep: MuJoCo warns about bad accelerations. Nothing in the working folder (MuJoCo's default handler
    appends to MUJOCO_LOG.TXT there), nothing on stderr, every protocol fails "unstable", the summary says so."""
    build = physics.scenes

    def unstable_scenes(*args, **kwargs):
        out = build(*args, **kwargs)
        for s in out.values():
            s.model.opt.timestep = 1.0
        return out

    monkeypatch.setattr(physics, "scenes", unstable_scenes)
    monkeypatch.chdir(tmp_path)
    old = mujoco.get_mju_user_warning()
    mujoco.set_mju_user_warning(None)  # as in a fresh process: MuJoCo's own handler
    try:
        Ts, qs = ball_grasps(2)
        r = fj.evaluate_physics(SPEC, BALL, {"wrist_pose": Ts, "q": qs}, FAST)
    finally:
        mujoco.set_mju_user_warning(old)
    out, err = capfd.readouterr()
    assert list(tmp_path.iterdir()) == [] and "WARNING" not in out + err, (out, err)
    for p in ("lift_shake", "six_dir"):
        assert r.as_arrays()[f"{p}_reason"].tolist() == [UNSTABLE] * 2 and not r.as_arrays()[f"{p}_success"].any()
    text = fj.summary(r)
    assert "lift-shake success (all)  0 / 2" in text and "unstable 2" in text, text


def test_a_callers_own_warning_handler_is_kept(monkeypatch):
    heard = []
    old = mujoco.get_mju_user_warning()
    mujoco.set_mju_user_warning(heard.append)
    try:
        T, q = enveloping_ball_grasp()
        sc = physics.scenes(SPEC, BALL, FAST, ("six-dir",))["six-dir"]
        batch, depth, _ = physics.prepare(sc, BALL, T[None], q[None], FAST)
        sim = backend_cpu.CpuSim(sc, 1)
        state = sim.initial(batch)
        state[0, 1 + sc.model.nq] = np.nan
        state = sim.run(state, batch, P.closing(batch, FAST)[0])
    finally:
        mujoco.set_mju_user_warning(old)
    assert sim.unstable(state).tolist() == [True]
    assert any("QVEL" in h for h in heard), heard


# ---------------------------------------------------------------------------------------------------------------
# poses out of reach


def test_wrist_1e15_m_away_is_refused_in_one_line():
    Ts, qs = far_grasps()
    with pytest.raises(FfcgsError) as e:
        fj.evaluate_physics("svh", BALL, {"wrist_pose": Ts, "q": qs})
    msg = str(e.value)
    assert "\n" not in msg and "1 of 2 grasps" in msg and "grasp 1 at 1e+15 m" in msg, msg
    # numbered as the caller's grasps when only some are tested
    with pytest.raises(FfcgsError, match="1 of 1 grasps .* the first grasp 1 at"):
        fj.evaluate_physics("svh", BALL, {"wrist_pose": Ts, "q": qs}, which=[1])


def test_poses_in_millimetres_are_refused_in_one_line():
    Ts, qs = far_grasps(0.0)
    Ts[:, :3, 3] *= 1000
    with pytest.raises(FfcgsError, match=r"2 of 2 grasps .* in metres"):
        physics.evaluate(SPEC, BALL, Ts, qs, FAST)


@pytest.mark.parametrize("hand", ["svh", "allegro"])
def test_hand_reach_bounds_every_geom_at_any_joint_angles(hand):
    spec = hand_spec.load_spec(hand)
    reach = physics.hand_reach(spec)
    m = spec.mj_model()
    d = mujoco.MjData(m)
    root = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, spec.root_body)
    below = np.zeros(m.nbody, bool)  # the root's subtree: what the wrist pose carries
    below[root] = True
    for i in range(root + 1, m.nbody):
        below[i] = below[m.body_parentid[i]]
    hand = below[m.geom_bodyid]
    lo, hi = m.jnt_range[:, 0], m.jnt_range[:, 1]
    widest = 0.0
    for u in np.random.default_rng(0).uniform(size=(200, m.njnt)):
        d.qpos[m.jnt_qposadr] = lo + u * (hi - lo)
        mujoco.mj_kinematics(m, d)
        far = np.linalg.norm(d.geom_xpos - d.xpos[root], axis=1) + m.geom_rbound
        widest = max(widest, float(far[hand].max()))
    assert widest <= reach < 1.5 * widest, (widest, reach)


def test_reach_limit_is_where_refusal_starts():
    T, _ = enveloping_ball_grasp()
    limit = physics.hand_reach(SPEC) + physics.REACH_MARGIN
    top = BALL.bounds[1, 2]
    near, beyond = T.copy(), T.copy()
    near[:3, 3] = [0.0, 0.0, top + limit - 0.01]
    beyond[:3, 3] = [0.0, 0.0, top + limit + 0.01]
    physics.check_reach(SPEC, BALL, near[None])
    with pytest.raises(FfcgsError, match="1 of 2 grasps"):
        physics.check_reach(SPEC, BALL, np.stack([near, beyond]))


def test_ffcgs_eval_of_a_far_pose_is_one_error_line(tmp_path, capsys):
    Ts, qs = far_grasps()
    path = tmp_path / "grasps.npz"
    grasp_io.save_arrays({"wrist_pose": Ts, "q": qs, "valid": np.ones(2, bool), "object_name": np.array("ball"),
                          **mesh_io.identity("ball", 1.0, BALL)}, path)
    before = hashlib.sha256(path.read_bytes()).hexdigest()
    code = cli_main.main(["eval", str(path), "--backend", "cpu"])
    out, err = capsys.readouterr()
    assert code == 2 and err.startswith("ffcgs: error: ") and len(err.strip().splitlines()) == 1, err
    assert "grasp 1 at 1e+15 m" in err and "Traceback" not in err
    assert hashlib.sha256(path.read_bytes()).hexdigest() == before
