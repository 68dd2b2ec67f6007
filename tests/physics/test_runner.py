"""The physics test (`runner.py`): sanity grasps that must pass or fail, determinism, batch = loop, Wilson
intervals against SciPy, the convex decomposition and its cache, the object's inertia, and `ffcgs eval`."""

import dataclasses
import json

import mujoco
import numpy as np
import pytest
import scipy.stats
import trimesh

from ffcgs_jax.cli import commands as cli
from ffcgs_jax.cli import main as cli_main
from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.evaluation.ranking import ranked
from ffcgs_jax.geometry import mesh_io
from ffcgs_jax.hand import spec as hand_spec
from ffcgs_jax.physics import backend_cpu, convex, evaluate_physics
from ffcgs_jax.physics import config as physics_config
from ffcgs_jax.physics import protocols as physics_protocols
from ffcgs_jax.physics import runner as physics
from ffcgs_jax.physics import validate as physics_validate
from ffcgs_jax.physics.config import PhysicsConfig
from physics_trials import ONE_TRIAL
from ffcgs_jax.physics.results import PhysicsResult
from ffcgs_jax.synthesis import grasp_io
from ffcgs_jax.viz import scene

SPEC = hand_spec.load_spec("svh")
BALL = mesh_io.load_mesh("ball")
FAST = PhysicsConfig(robust=ONE_TRIAL, close_time=0.2, settle_time=0.1, lift_height=0.03, shake_cycles=1, shake_amplitude=0.02,
                     push_time=0.2)


def _palm_frame():
    m = SPEC.mj_model()
    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)
    return d.site_xpos[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, SPEC.palm_site)].copy()


def enveloping_ball_grasp(shift: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Palm down over the 7 cm ball, its centre 11 cm out along the fingers and 4.5 cm in front of the palm (root
    frame), fingers closed by hand to touch it (found by closing each finger until contact). `shift` moves the
    hand along its palm normal: + away from the ball."""
    R = scene.default_wrist_pose(BALL, _palm_frame(), np.array(SPEC.palm_normal))[:3, :3]
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = BALL.bounds.mean(0) - R @ np.array([-0.006, 0.045 + shift, 0.11])
    q = np.array([0.24, 0.59, 1.33, 0.23, 1.33, 0.17, 0.51, 0.41, 0.0])
    return T, q


def evaluate(wrist, q, cfg=PhysicsConfig(robust=ONE_TRIAL, sim_friction=1.0), protocols=physics_config.PROTOCOLS):
    return physics.evaluate(SPEC, BALL, np.asarray(wrist).reshape(-1, 4, 4), np.asarray(q).reshape(-1, 9), cfg,
                            protocols)


def test_enveloping_ball_grasp_with_high_friction_passes_both_protocols():
    T, q = enveloping_ball_grasp()
    r = evaluate(T, q)
    assert r["initial_penetration"][0] < 0.002
    assert r["lift_shake_success"][0] and r["six_dir_success"][0], r
    assert r["lift_shake_move"][0] < 0.02 and r["six_dir_move"][0] < 0.05 and r["six_dir_rot"][0] < 15


def test_hand_5cm_away_fails_and_deep_penetration_fails():
    far, q = enveloping_ball_grasp(shift=0.05)
    deep, _ = enveloping_ball_grasp(shift=-0.03)
    r = evaluate(np.stack([far, deep]), np.stack([q, q]))
    assert not r["lift_shake_success"].any() and not r["six_dir_success"].any()
    lost, pen = physics_protocols.REASONS.index("lost"), physics_protocols.REASONS.index("penetration")
    assert r["lift_shake_reason"].tolist() == [lost, pen] and r["six_dir_reason"].tolist() == [lost, pen]
    assert r["initial_penetration"][0] == 0 and r["initial_penetration"][1] > 0.01


def ball_grasps(k: int = 3):
    T, q = enveloping_ball_grasp()
    shifts = np.linspace(-0.004, 0.008, k)
    Ts = np.stack([enveloping_ball_grasp(s)[0] for s in shifts])
    qs = np.stack([q * (1 - 0.1 * i) for i in range(k)])
    return Ts, qs


def test_deterministic_and_batch_equals_loop():
    Ts, qs = ball_grasps()
    a = evaluate(Ts, qs, FAST)
    b = evaluate(Ts, qs, FAST)
    one = [evaluate(Ts[i], qs[i], FAST) for i in range(len(qs))]
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)
        np.testing.assert_array_equal(a[k], np.concatenate([o[k] for o in one]), err_msg=k)


@pytest.mark.parametrize("k,n", [(0, 10), (3, 10), (10, 10), (37, 50), (1, 1)])
def test_wilson_interval_matches_scipy(k, n):
    ref = scipy.stats.binomtest(k, n).proportion_ci(confidence_level=0.95, method="wilson")
    np.testing.assert_allclose(physics_protocols.wilson(k, n), (ref.low, ref.high), atol=1e-12)


def test_convex_parts_cover_the_mug_and_are_cached(tmp_path, monkeypatch):
    monkeypatch.setenv("FFCGS_CACHE_DIR", str(tmp_path))
    mug = mesh_io.load_mesh("mug")
    cfg = PhysicsConfig(robust=ONE_TRIAL)
    parts = convex.decompose(mug, cfg)
    assert len(parts) > 1 and all(len(v) <= cfg.hull_vertices for v, _ in parts)
    pts = trimesh.sample.volume_mesh(mug, 2000)
    hulls = [trimesh.Trimesh(v, f).convex_hull for v, f in parts]
    covered = np.logical_or.reduce([h.contains(pts) for h in hulls])
    assert covered.mean() > 0.95
    monkeypatch.setattr(convex, "compute_parts", lambda *a: pytest.fail("cache not used"))
    again = convex.decompose(mug, cfg)
    assert all(np.array_equal(v, w) and np.array_equal(f, g) for (v, f), (w, g) in zip(parts, again))
    assert len(list((tmp_path / "convex").glob("*.npz"))) == 1


def test_convex_object_is_its_own_hull():
    box = mesh_io.load_mesh("box")
    (v, f), = convex.decompose(box, use_cache=False)
    assert np.isclose(trimesh.Trimesh(v, f).volume, box.volume)


@pytest.mark.parametrize("density", [0.0, 500.0])
def test_object_mass_and_inertia_of_the_box(density):
    box = mesh_io.load_mesh("box")
    cfg = PhysicsConfig(robust=ONE_TRIAL, density=density)
    sc = physics.scenes(SPEC, box, cfg, ("lift-shake",))["lift-shake"]
    m = sc.model
    mass = density * box.volume if density else cfg.mass
    a, b, c = box.extents
    expect = mass / 12 * np.array([b * b + c * c, a * a + c * c, a * a + b * b])
    assert np.isclose(m.body_mass[sc.obj_body], mass)
    np.testing.assert_allclose(np.sort(m.body_inertia[sc.obj_body]), np.sort(expect), rtol=1e-6)
    np.testing.assert_allclose(m.body_ipos[sc.obj_body], box.bounds.mean(0), atol=1e-9)


def test_object_rests_on_the_table_and_an_open_hand_far_away_touches_nothing():
    T, q = enveloping_ball_grasp(shift=0.05)
    sc = physics.scenes(SPEC, BALL, PhysicsConfig(), ("lift-shake",))["lift-shake"]
    batch, depth, palm = physics.prepare(sc, BALL, T[None], q[None] * 0, PhysicsConfig())
    sim = backend_cpu.CpuSim(sc, 1)
    state = sim.initial(batch)
    for seg in physics_protocols.closing(batch, FAST):
        state = sim.run(state, batch, seg)
    p = sim.probe(state, batch)
    assert p["table"][0] and not p["touch"][0] and not palm[0]
    # resting where it was planned (body frame = mesh frame): nothing pushed it; the 64-vertex hull of the sphere
    # lies up to about 1 mm inside it, so it settles by that much
    assert np.linalg.norm(p["pos"][0]) < 2e-3


def test_bad_inputs_are_refused():
    T, q = enveloping_ball_grasp()
    with pytest.raises(physics.FfcgsError, match="q must have shape"):
        physics.evaluate(SPEC, BALL, T[None], q[None, :5])
    with pytest.raises(physics.FfcgsError, match="NaN"):
        evaluate(T, np.full(9, np.nan))
    with pytest.raises(physics.FfcgsError, match="unknown protocol"):
        evaluate(T, q, protocols=("drop",))
    with pytest.raises(physics.FfcgsError, match="friction"):
        evaluate(T, q, dataclasses.replace(PhysicsConfig(), sim_friction=-1.0))


# --- the command line -----------------------------------------------------------------------------------------


@pytest.fixture
def ball_npz(tmp_path):
    Ts, qs = ball_grasps(2)
    path = tmp_path / "g.npz"
    np.savez(path, object_name=np.array("ball"), wrist_pose=Ts, q=qs, valid=np.array([True, False]))
    return path


def run(capsys, *argv):
    code = cli_main.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


SHORT = ["--close-time", "0.2", "--settle-time", "0.1", "--push-time", "0.2"]


def test_eval_prints_rates_and_adds_results_to_the_npz(capsys, ball_npz):
    code, out, err = run(capsys, "eval", ball_npz, "--protocol", "six-dir", "--sim-friction", "1.0", *SHORT)
    assert code == 0, err
    a = grasp_io.load_npz(ball_npz)
    assert a["physics_tested"].tolist() == [True, False]  # only valid grasps by default
    ok = bool(a["six_dir_success"][0])
    # the robust verdict by default: the grasp holds or not, and the share of its 8 perturbed trials passed
    passed = int(a["six_dir_trials"][0].sum())
    assert f"six-dir holds (all)    {int(ok)} / 1 = " in out and "95 % CI" in out
    assert f"six-dir trials passed  {passed} / 8 = " in out and ok == (passed >= 7)
    assert a["six_dir_reason"][1] == -1 and np.isnan(a["six_dir_move"][1])
    assert '"sim_friction": 1.0' in str(a["physics_config_json"])


def test_eval_all_writes_out_and_keeps_the_input(capsys, ball_npz, tmp_path):
    out_path = tmp_path / "o.npz"
    code, out, err = run(capsys, "eval", ball_npz, "--all", "--protocol", "six-dir", "--out", out_path, *SHORT)
    assert code == 0, err
    assert grasp_io.load_npz(out_path)["physics_tested"].all()
    assert "six_dir_success" not in grasp_io.load_npz(ball_npz)


@pytest.mark.parametrize("args,message", [
    (["missing.npz"], "grasp file not found"),
    (["{npz}", "--protocol", "drop"], "unknown protocol"),
    (["{npz}", "--video", "x.avi"], "so the name must end in .gif or .mp4"),
    (["{npz}", "--backend", "tpu"], "invalid choice 'tpu' for argument '--backend'"),
    (["{bare}"], "no wrist_pose or q"),
    (["{anon}"], "pass --object"),
])
def test_eval_bad_input_one_line(capsys, ball_npz, tmp_path, args, message):
    bare = tmp_path / "bare.npz"
    np.savez(bare, x=np.zeros(3))
    anon = tmp_path / "anon.npz"
    np.savez(anon, wrist_pose=np.eye(4)[None], q=np.zeros((1, 9)))
    argv = [a.format(npz=ball_npz, bare=bare, anon=anon) for a in args]
    code, out, err = run(capsys, "eval", *argv)
    assert code == 2 and message in err and "Traceback" not in err and len(err.strip().splitlines()) == 1, err


def test_validate_puts_the_grasps_that_pass_first(monkeypatch):
    """Known outcomes: the enveloping grasp holds, the same grasp 5 cm off does not. The analytic order (valid,
    then E) offers the failing one first; the physics-checked order the one that holds, and keeps every grasp."""
    import ffcgs_jax as fj
    from ffcgs_jax.synthesis.config import GraspConfig

    good, q = enveloping_ball_grasp()
    far, _ = enveloping_ball_grasp(shift=0.05)
    arrays = {"wrist_pose": np.stack([far, good, good]), "q": np.stack([q, q, q]),
              "valid": np.array([True, True, False]), "E": np.array([0.1, 0.2, 0.3]),
              "channel_names": np.array(SPEC.channel_names), "synthesis_s": np.array(1.0)}
    gs = fj.GraspSet(arrays, {"E": np.zeros((2, 3))}, GraspConfig(), "ball")
    assert gs.order().tolist() == [0, 1, 2]
    checked = fj.validate(SPEC, BALL, gs, PhysicsConfig(robust=ONE_TRIAL, sim_friction=1.0, backend="cpu"), protocols=["six-dir"])
    assert checked.order().tolist() == [1, 0, 2] and gs.order().tolist() == [0, 1, 2]  # the input is unchanged
    assert checked["physics_passed"].tolist() == [False, True, False]
    assert checked["physics_tested"].tolist() == [True, True, False]  # the invalid grasp is not simulated
    assert checked["six_dir_success"].tolist() == [False, True, False] and checked["six_dir_reason"][2] == -1
    assert json.loads(str(checked["physics_protocols"])) == ["six-dir"] and str(checked["physics_backend"]) == "cpu"
    assert json.loads(str(checked["physics_config_json"]))["sim_friction"] == 1.0
    every = fj.validate(SPEC, BALL, gs, PhysicsConfig(robust=ONE_TRIAL, sim_friction=1.0, backend="cpu"), protocols=["six-dir"],
                         candidates="all")
    assert every["physics_passed"].tolist() == [False, True, True] and every.order().tolist() == [1, 2, 0]
    # stopping once one passes: a chunk of one grasp at a time, in the analytic order; six-dir first, so the
    # failing grasp never runs lift-shake, and the third is never simulated
    arrays3 = dict(arrays, valid=np.array([True, True, True]))
    three = fj.GraspSet(arrays3, {"E": np.zeros((2, 3))}, GraspConfig(), "ball")
    monkeypatch.setattr(physics_validate, "chunk_size", lambda: 1)
    early = fj.validate(SPEC, BALL, three, PhysicsConfig(robust=ONE_TRIAL, sim_friction=1.0, backend="cpu"),
                        protocols=["lift-shake", "six-dir"], need=1)
    assert early["physics_tested"].tolist() == [True, True, False] and early.order()[0] == 1
    assert early["physics_passed"].tolist() == [False, True, False]
    assert early["six_dir_reason"][0] > 0 and early["lift_shake_reason"][0] == -1  # not run after six-dir failed
    assert bool(early["lift_shake_success"][1]) and early["six_dir_reason"][2] == -1
    # ranked by the success predictor, the grasp it believes in is simulated first: one simulation suffices
    believed = fj.GraspSet(dict(arrays3, pred_success=np.array([0.2, 0.9, 0.5]), rank_by=np.array("predicted")),
                           {"E": np.zeros((2, 3))}, GraspConfig(), "ball")
    assert believed.order().tolist() == [1, 2, 0]
    quick = fj.validate(SPEC, BALL, believed, PhysicsConfig(robust=ONE_TRIAL, sim_friction=1.0, backend="cpu"), protocols=["six-dir"],
                        need=1)
    assert quick["physics_tested"].tolist() == [False, True, False] and quick.order()[0] == 1
    rows = dict(physics_validate.summary_rows(checked, ["six-dir"]))
    assert rows["physics-checked"].startswith("1 of 2 tested grasps pass six-dir") and \
        rows["physics-checked"].endswith("the first grasp passes")
    with pytest.raises(FfcgsError, match="unknown protocol 'jump'; protocols: lift-shake, six-dir, dexgraspbench"):
        fj.validate(SPEC, BALL, gs, protocols=["jump"])
    # the order before hand, object, grasps, cfg: `validate(hand, mesh, gs, ["six-dir"])` meets this check (called
    # directly: the suite's type-check hook would refuse the list at the annotation first, which a user has not)
    with pytest.raises(FfcgsError, match="cfg must be a PhysicsConfig, got list: .* protocols as a keyword"):
        evaluate_physics.check_cfg(["six-dir"], "validate")


@pytest.mark.slow  # 60-70 s on two cores, mostly compiling; test_validate_puts_the_grasps_that_pass_first covers it
def test_grasp_validate_end_to_end(capsys, tmp_path):
    path = tmp_path / "v.npz"
    code, out, err = run(capsys, "grasp", "box", "--n", "4", "--iters", "5", "--res", "16", "--validate",
                         "--protocol", "six-dir", *SHORT, "--out", path)
    assert code == 0, err
    line = next(l for l in out.splitlines() if l.startswith("physics-checked"))
    passed = int(line.split()[1])
    a = grasp_io.load_npz(path)
    assert a["physics_passed"].sum() == passed and len(a["q"]) == 4  # every grasp kept, ranked
    first = ranked(a)[0]
    assert bool(a["physics_passed"][first]) == (passed > 0)


@pytest.mark.parametrize("hand", ["svh", "allegro"])
def test_the_wrist_weld_holds_the_hand_where_it_is_put(hand):
    """Away from the object, the hand stays on its commanded wrist pose: the weld's rest pose is the identity for
    any root body frame (the Allegro's palm is turned 90 degrees in its MJCF; a weld that kept that turn threw the
    hand off every grasp)."""
    from ffcgs_jax.physics import backend, scene as physics_scene

    spec = hand_spec.load_spec(hand)
    s = physics_scene.build(spec, BALL, convex.decompose(BALL, PhysicsConfig()), PhysicsConfig(),
                            table_z=float(BALL.bounds[0, 2]))
    m, d = s.model, mujoco.MjData(s.model)
    quat = np.array([0.9, 0.3, -0.2, 0.25]) / np.linalg.norm([0.9, 0.3, -0.2, 0.25])
    pos = np.array([0.05, -0.1, 0.6])  # far above the ball
    q_open = np.clip(0.0, s.lower, s.upper)
    backend.pose_hand(s, d, pos, quat, q_open)
    d.ctrl[:] = q_open
    mujoco.mj_step(m, d, 100)
    got = d.qpos[s.root_qpos: s.root_qpos + 7]
    assert np.linalg.norm(got[:3] - pos) < 1e-3
    assert 2 * np.degrees(np.arccos(min(1.0, abs(float(got[3:] @ quat))))) < 0.5


# --- fj.evaluate_physics: evaluate in synthesize's order --------------------------------------------------------


def test_evaluate_physics_is_evaluate_on_a_grasp_set():
    import ffcgs_jax as fj
    from ffcgs_jax.synthesis.grasp import GraspSet

    Ts, qs = ball_grasps(3)
    squeeze = np.tile(np.linspace(0.2, 1.0, 9), (3, 1)) / 2
    gs = GraspSet({"wrist_pose": Ts, "q": qs, "squeeze_dir": squeeze}, {}, fj.GraspConfig(), "ball")
    old = physics.evaluate(SPEC, BALL, Ts[[2, 0]], qs[[2, 0]], FAST, ("six-dir",), "cpu",
                           squeeze_dir=squeeze[[2, 0]])
    new = fj.evaluate_physics(fj.load_hand("svh"), BALL, gs, FAST, protocols="six-dir", which=[2, 0], backend="cpu")
    by_name = fj.evaluate_physics("svh", BALL, {"wrist_pose": Ts, "q": qs, "squeeze_dir": squeeze}, FAST,
                                  protocols=["six-dir"], which=np.array([True, False, True]), backend="cpu")  # 0, 2
    assert set(new.as_arrays()) == set(old) and list(new.protocols) == ["six-dir"]
    for k in old:
        np.testing.assert_array_equal(new.as_arrays()[k], old[k], err_msg=k)
        np.testing.assert_array_equal(by_name.as_arrays()[k], old[k][::-1], err_msg=k)
    six = new.protocols["six-dir"]
    assert new.six_dir is six and six.move_dir.shape == (2, 6) and six.pregrasp_penetration is None
    np.testing.assert_array_equal(six.success, old["six_dir_success"])
    assert new.index.tolist() == [2, 0] and by_name.index.tolist() == [0, 2]
    assert six.reasons.tolist() == [physics_protocols.REASONS[r] for r in old["six_dir_reason"]]
    np.testing.assert_array_equal(new.passed, old["six_dir_success"])
    again = PhysicsResult.from_arrays(new.as_arrays())  # a file's arrays read back
    assert list(again.protocols) == ["six-dir"] and set(again.as_arrays()) == set(old)
    with pytest.raises(fj.FfcgsError, match=r"no dict of arrays: .*as_arrays\(\)\['six_dir_success'\]"):
        new["six_dir_success"]
    table = fj.summary(new).splitlines()  # what `ffcgs eval` prints, of the protocols the results hold
    assert [line.split("  ")[0] for line in table] == ["six-dir success (all)", "six-dir failures"], table
    with pytest.raises(fj.FfcgsError, match="no lift-shake outcome"):
        fj.summary(new, ["lift-shake"])


@pytest.mark.parametrize("call,message", [
    (lambda T, q: {"hand": 3}, "hand must be a Hand"),
    (lambda T, q: {"mesh": "ball"}, "mesh must be a trimesh.Trimesh"),
    (lambda T, q: {"grasps": [T, q]}, "grasps must be a GraspSet or a dict"),
    (lambda T, q: {"grasps": {"q": q}}, "grasps have no wrist_pose"),
    (lambda T, q: {"grasps": {"wrist_pose": T[0], "q": q}}, r"wrist_pose must have shape \(B, 4, 4\)"),
    (lambda T, q: {"grasps": {"wrist_pose": T, "q": q[:, :5]}}, r"q must have shape \(2, 9\)"),
    (lambda T, q: {"grasps": {"wrist_pose": T, "q": q.astype(str)}}, "q must hold real numbers"),
    (lambda T, q: {"cfg": {"friction": 1.0}}, "cfg must be a PhysicsConfig"),
    (lambda T, q: {"cfg": ("six-dir",)}, "cfg must be a PhysicsConfig, got tuple: .* protocols as a keyword"),
    (lambda T, q: {"which": [5]}, "out of range for 2 grasps"),
    (lambda T, q: {"which": [0.5]}, "which must be grasp indices"),
    (lambda T, q: {"which": [True]}, r"which as a mask must have shape \(2,\)"),
    (lambda T, q: {"which": []}, "no grasps to test"),
    (lambda T, q: {"protocols": "drop"}, "unknown protocol 'drop'"),
])
def test_evaluate_physics_bad_input_one_line(call, message):
    import ffcgs_jax as fj

    Ts, qs = ball_grasps(2)
    args = {"hand": SPEC, "mesh": BALL, "grasps": {"wrist_pose": Ts, "q": qs}, "cfg": FAST} | call(Ts, qs)
    with pytest.raises(fj.FfcgsError, match=message) as e:
        fj.evaluate_physics(**args)
    assert "\n" not in str(e.value)
