"""DexGraspBench's protocol (`physics/dexgraspbench.py`): the scene options read back from the compiled model, the
two versions, the pre-grasp / grasp / squeeze plan, sanity grasps that must pass or fail, branching = a fresh
reset, the GPU backends' refusal and `ffcgs eval --protocol dexgraspbench`."""

import mujoco
import numpy as np
import pytest

from ffcgs_jax.physics import backend_cpu
from ffcgs_jax.physics import dexgraspbench as dgb
from ffcgs_jax.physics import protocols as P
from ffcgs_jax.physics import runner as physics
from ffcgs_jax.physics.backend import pose_hand
from ffcgs_jax.physics.config import DEXGRASPBENCH, PhysicsConfig
from physics_trials import ONE_TRIAL
from ffcgs_jax.synthesis import grasp_io

from test_runner import BALL, SPEC, enveloping_ball_grasp, run  # noqa: F401 - run: the CLI helper

VERSIONS = {"dexgraspbench": (0.1, 5.0), "dexgraspbench-bodex": (0.03, 1.0)}  # mass kg, kp N m/rad


@pytest.fixture(scope="module")
def scenes():
    # friction, condim, mass and kp set here must not reach the benchmark's scene: it fixes its own
    mine = PhysicsConfig(sim_friction=1.0, condim=3, torsional=0.0, mass=0.5, kp=20.0, timestep=0.002, impratio=100.0)
    return physics.scenes(SPEC, BALL, mine, DEXGRASPBENCH)


@pytest.mark.parametrize("protocol", DEXGRASPBENCH)
def test_scene_options_read_back_from_the_compiled_model(scenes, protocol):
    sc = scenes[protocol]
    m = sc.model
    assert sc.dexgraspbench
    assert m.opt.timestep == 0.004 and m.opt.integrator == mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    assert m.opt.cone == mujoco.mjtCone.mjCONE_ELLIPTIC and m.opt.impratio == 10.0
    assert m.opt.noslip_iterations == 2 and not m.opt.gravity.any()
    geoms = np.concatenate([sc.hand_geoms, sc.obj_geoms])
    assert len(sc.hand_geoms) and len(sc.obj_geoms) and len(geoms) == m.ngeom  # no table
    assert (m.geom_condim[geoms] == 4).all()
    np.testing.assert_array_equal(m.geom_friction[geoms, :2], np.tile([0.6, 0.02], (len(geoms), 1)))
    assert (m.geom_priority[geoms] == 0).all()  # equal priority: MuJoCo mixes hand and object per contact
    np.testing.assert_array_equal(m.geom_solref[sc.hand_geoms], np.tile([0.005, 1.0], (len(sc.hand_geoms), 1)))
    np.testing.assert_array_equal(m.geom_solimp[sc.hand_geoms, :3], np.tile([0.5, 0.99, 0.0001],
                                                                            (len(sc.hand_geoms), 1)))
    np.testing.assert_array_equal(m.geom_solref[sc.obj_geoms], np.tile([0.02, 1.0], (len(sc.obj_geoms), 1)))
    weld = [i for i in range(m.neq) if m.eq_type[i] == mujoco.mjtEq.mjEQ_WELD]
    assert len(weld) == 1 and sc.hold_eq == -1  # the wrist's; the object is never held
    np.testing.assert_array_equal(m.eq_solref[weld[0]], [0.02, 1.0])
    np.testing.assert_array_equal(m.eq_data[weld[0], :3], 0.0)  # anchored at the root's origin


@pytest.mark.parametrize("protocol", DEXGRASPBENCH)
def test_the_two_versions_differ_in_mass_and_kp_only(scenes, protocol):
    mass, kp = VERSIONS[protocol]
    sc = scenes[protocol]
    m = sc.model
    assert m.body_mass[sc.obj_body] == pytest.approx(mass) and sc.mass == pytest.approx(mass)
    np.testing.assert_array_equal(m.actuator_gainprm[:, 0], kp)
    np.testing.assert_array_equal(m.actuator_biasprm[:, 1], -kp)
    assert (dgb.VERSIONS[protocol].mass, dgb.VERSIONS[protocol].kp) == (mass, kp)
    a, b = (P.get(p).settings(PhysicsConfig()) for p in DEXGRASPBENCH)
    assert {k for k in vars(a) if getattr(a, k) != getattr(b, k)} == {"mass", "kp"}


def test_the_wrist_weld_is_stiff(scenes):
    """1 N on the hand's root moves it well under a millimetre (MjSpec's default weld data would anchor the weld
    1 m away, letting the hand swing centimetres)."""
    sc = scenes["dexgraspbench"]
    m, d = sc.model, mujoco.MjData(sc.model)
    pos, quat = np.array([0.0, 0.0, 0.5]), np.array([1.0, 0.0, 0.0, 0.0])
    q_open = np.clip(0.0, sc.lower, sc.upper)
    pose_hand(sc, d, pos, quat, q_open)
    d.ctrl[:] = q_open
    d.xfrc_applied[sc.root_body, :3] = [1.0, 0.0, 0.0]
    moved = 0.0
    for _ in range(250):
        mujoco.mj_step(m, d)
        moved = max(moved, float(np.linalg.norm(d.xpos[sc.root_body] - pos)))
    assert moved < 1e-3


def test_plan_pregrasp_grasp_squeeze(scenes):
    sc = scenes["dexgraspbench"]
    T, q = enveloping_ball_grasp()
    cfg = P.get("dexgraspbench").settings(PhysicsConfig())
    direction = np.zeros((1, 9))
    direction[0, [1, 6, 8]] = [1.0, -0.5, 1.0]  # channel 8 is at its lower limit 0 at q: the pre-grasp clips there
    batch, depth, _ = physics.prepare(sc, BALL, T[None], q[None], cfg, squeeze_dir=direction)
    np.testing.assert_array_equal(batch.q_grasp, q[None])
    np.testing.assert_allclose(batch.q_start, np.clip(q - 0.2 * direction, sc.lower, sc.upper))
    np.testing.assert_allclose(batch.q_target, np.clip(q + 0.2 * direction, sc.lower, sc.upper))
    np.testing.assert_array_equal(batch.wrist_pos, T[None, :3, 3])
    assert depth.shape == (1,) and depth[0] >= 0  # at the pre-grasp: physics.evaluate checks it
    grasp, squeeze = P.grasp_and_squeeze(batch, cfg)
    assert grasp.n == squeeze.n == 100  # 0.4 s each at 4 ms
    ctrl = grasp.make(0, 100)[0][0]
    frac = (ctrl[:, 1] - batch.q_start[0, 1]) / (batch.q_grasp[0, 1] - batch.q_start[0, 1])
    np.testing.assert_allclose(frac, np.repeat(np.arange(1, 11) / 10, 10))  # 10 targets, 40 ms each
    np.testing.assert_allclose(squeeze.make(99, 100)[0][0, 0], batch.q_target[0])


def test_holding_grasp_passes_far_hand_is_lost_deep_hand_fails_at_once():
    T, q = enveloping_ball_grasp()
    far, _ = enveloping_ball_grasp(shift=0.05)
    deep, _ = enveloping_ball_grasp(shift=-0.03)
    r = physics.evaluate(SPEC, BALL, np.stack([T, far, deep]), np.stack([q, q, q]), PhysicsConfig(robust=ONE_TRIAL, backend="cpu"),
                         ("dexgraspbench",))
    assert r["dexgraspbench_success"].tolist() == [True, False, False], r
    reasons = [P.REASONS[i] for i in r["dexgraspbench_reason"]]
    assert reasons == ["ok", "lost", "penetration"]
    assert (r["dexgraspbench_move_dir"][0] < 0.05).all() and (r["dexgraspbench_rot_dir"][0] < 15).all()
    assert r["dexgraspbench_move"][1] >= 0.05  # pushed away at the first check
    assert r["dexgraspbench_pregrasp_penetration"][2] > 0.01 and np.isnan(r["dexgraspbench_move"][2])


def test_each_direction_from_the_squeezed_state_equals_a_fresh_reset():
    """The pushes start from the squeezed state simulated once; the benchmark re-simulates pre-grasp -> squeeze
    for each direction. Deterministic simulation: the same largest move and turn, bit for bit."""
    T, q = enveloping_ball_grasp()
    p = "dexgraspbench"
    cfg = P.get(p).settings(PhysicsConfig())
    sc = physics.scenes(SPEC, BALL, cfg, (p,))[p]
    batch, depth, _ = physics.prepare(sc, BALL, T[None], q[None], cfg)
    sim = backend_cpu.CpuSim(sc, 1)
    branched = P.run_protocol(sim, batch, depth, cfg, p)
    k = 5  # -z, the last direction: the branched run has pushed five others from the same state before
    state = sim.initial(batch)
    ref = sim.probe(state, batch)
    for seg in P.grasp_and_squeeze(batch, cfg):
        state = sim.run(state, batch, seg)
    move = rot = 0.0
    for piece in P.split_segment(P.bench_push(batch, cfg, P.DIRECTIONS[k], sc.mass), 50):
        state = sim.run(state, batch, piece)
        now = sim.probe(state, batch)
        move = max(move, float(np.linalg.norm(now["pos"][0] - ref["pos"][0])))
        rot = max(rot, float(P.rotation_angle(now["quat"], ref["quat"])[0]))
    assert branched["success"][0]
    assert branched["move_dir"][0, k] == move and branched["rot_dir"][0, k] == rot


def test_mjx_is_refused_in_one_line():
    """MJX has no no-slip solver; Warp has one (the GPU worlds run DexGraspBench's test there)."""
    T, q = enveloping_ball_grasp()
    with pytest.raises(physics.FfcgsError, match="runs on the CPU and Warp backends only"):
        physics.evaluate(SPEC, BALL, T[None], q[None], PhysicsConfig(backend="mjx"), ("dexgraspbench",))


def test_ffcgs_eval_protocol_dexgraspbench(capsys, tmp_path):
    T, q = enveloping_ball_grasp()
    far, _ = enveloping_ball_grasp(shift=0.05)
    path = tmp_path / "g.npz"
    np.savez(path, object_name=np.array("ball"), wrist_pose=np.stack([T, far]), q=np.stack([q, q]),
             valid=np.array([True, True]))
    code, out, err = run(capsys, "eval", path, "--protocol", "dexgraspbench", "--backend", "cpu", "--trials", "1")
    assert code == 0, err
    assert "dexgraspbench success (all)  1 / 2 = 50.0 %" in out and "lost 1" in out
    a = grasp_io.load_npz(path)
    assert a["dexgraspbench_success"].tolist() == [True, False]
    assert a["dexgraspbench_move_dir"].shape == (2, 6) and a["dexgraspbench_pregrasp_penetration"].shape == (2,)
    code, _, err = run(capsys, "eval", path, "--protocol", "dexgraspbench-bodx")
    assert code != 0 and "dexgraspbench, dexgraspbench-bodex" in err and len(err.strip().splitlines()) == 1



def test_video_plan_is_grasp_squeeze_then_six_pushes_from_the_squeeze(scenes):
    from ffcgs_jax.viz import physics_video as video

    sc = scenes["dexgraspbench-bodex"]
    T, q = enveloping_ball_grasp()
    batch, _, _ = physics.prepare(sc, BALL, T[None], q[None], P.get("dexgraspbench-bodex").settings(PhysicsConfig()))
    plan = video.phases(sc, batch, PhysicsConfig(timestep=0.002), "dexgraspbench-bodex")  # its own 4 ms
    assert [(label, seg.n, restart) for label, seg, restart in plan[:3]] == [
        ("grasp", 100, False), ("squeeze", 100, False), ("push +x", 500, True)]
    assert len(plan) == 8 and all(restart for _, _, restart in plan[2:])
    np.testing.assert_allclose(plan[2][1].force, [0.3, 0.0, 0.0])  # 10 x 30 g
