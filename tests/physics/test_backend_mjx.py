"""The MJX physics backend against CPU MuJoCo (`backend_cpu.CpuSim`) on the built-in ball, in float32 as on a GPU.

MJX compiles slowly on CPU (about 10 s for the probe, 40-50 s more for the step loop), so the default suite checks
the start states and the probe (~12 s); the simulated comparisons (~50-60 s each) are marked slow.
"""

import jax
import mujoco
import numpy as np
import pytest

from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.geometry import mesh_io
from ffcgs_jax.hand import spec as hand_spec
from ffcgs_jax.physics import backend_cpu
from ffcgs_jax.physics import protocols as physics_protocols
from ffcgs_jax.physics import runner as physics
from ffcgs_jax.physics.backend_mjx import MjxSim, put_model
from ffcgs_jax.physics.config import PhysicsConfig
from physics_trials import ONE_TRIAL
from ffcgs_jax.viz import scene

pytestmark = pytest.mark.e2e  # MJX physics compiled beside CPU MuJoCo

CFG = PhysicsConfig(robust=ONE_TRIAL, close_time=0.1, settle_time=0.05, push_time=0.1)
# MJX's collision code differs from MuJoCo C's, so trajectories agree loosely. Observed on the grasps below: after
# the short closing (75 steps) the ball's position differs by up to 0.4 mm and its orientation by up to 3.4 deg
# (the polyhedral ball rolls a little under the fingers; float64 gives the same: collision code, not precision);
# after a 0.1 s push that moves it 5-10 cm, the position by up to 1.7 mm.
POS_TOL = 3e-3  # m
ROT_TOL = 5.0  # degrees
STATE_TOL = 1e-5  # m: the same kinematics at the start, float32 round-off only


def grasps(mesh, spec, dz):
    """The top-down viewing pose (palm 3 cm above the ball) moved up by each of `dz` (m), q at mid-range."""
    m, d = scene.build_scene(spec, np.eye(4))
    scene.set_channels(m, d, np.asarray(spec.coupling), np.zeros(len(spec.lower)))
    palm = d.site_xpos[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, spec.palm_site)].copy()
    T = scene.default_wrist_pose(mesh, palm, np.asarray(spec.palm_normal))
    poses = np.stack([T] * len(dz))
    poses[:, 2, 3] += dz
    q = 0.5 * (np.asarray(spec.lower) + np.asarray(spec.upper))
    return poses, np.tile(q, (len(dz), 1))


@pytest.fixture(scope="module")
def ball():
    return hand_spec.load_spec("svh"), mesh_io.load_mesh("ball")


def sims(spec, mesh, poses, q, protocol):
    sc = physics.scenes(spec, mesh, CFG, (protocol,))[protocol]
    batch, _, _ = physics.prepare(sc, mesh, poses, q, CFG)
    return backend_cpu.CpuSim(sc, 2), MjxSim(sc), batch


def rotation_deg(q1, q2):
    return np.degrees(2 * np.arccos(np.clip(np.abs(np.sum(q1 * q2, axis=-1)), 0, 1)))


def assert_same_probe(a, b, pos_tol, rot_tol):
    np.testing.assert_allclose(a["pos"], b["pos"], atol=pos_tol)
    np.testing.assert_allclose(a["rel"], b["rel"], atol=pos_tol)
    assert rotation_deg(a["quat"], b["quat"]).max() < rot_tol
    np.testing.assert_array_equal(a["table"], b["table"])
    np.testing.assert_array_equal(a["touch"], b["touch"])


def test_unsupported_options_are_named():
    spec, mesh = hand_spec.load_spec("svh"), mesh_io.load_mesh("box")
    sc = physics.scenes(spec, mesh, CFG, ("six-dir",))["six-dir"]
    m = sc.model
    m.opt.noslip_iterations = 3
    with pytest.raises(FfcgsError, match="no-slip"):
        put_model(m)
    m.opt.noslip_iterations = 0
    m.opt.solver = mujoco.mjtSolver.mjSOL_PGS
    with pytest.raises(FfcgsError, match="MJX cannot run"):
        put_model(m)


def test_start_states_and_probe_match_cpu(ball):
    spec, mesh = ball
    poses, q = grasps(mesh, spec, [0.0, -0.02, 0.2])  # the palm 1 cm into the ball in the second
    with jax.enable_x64(False):
        cpu, mjx_sim, batch = sims(spec, mesh, poses, q, "lift-shake")
        sc = cpu.scene
        c, g = cpu.initial(batch), mjx_sim.initial(batch)
        np.testing.assert_allclose(np.asarray(g.qpos), c[:, 1: 1 + sc.model.nq], atol=STATE_TOL)  # after time
        # move the ball per grasp: 3 mm into the table, 1 cm up, unchanged
        dz = np.array([-0.003, 0.01, 0.0])
        c[:, 1 + sc.obj_qpos + 2] += dz
        g = g.replace(qpos=g.qpos.at[:, sc.obj_qpos + 2].add(dz.astype(np.float32)))
        offset = (0.0, 0.0, 0.05)
        a, b = cpu.probe(c, batch, offset), mjx_sim.probe(g, batch, offset)
    assert_same_probe(a, b, STATE_TOL, 0.01)
    np.testing.assert_array_equal(a["table"], [True, False, False])
    np.testing.assert_array_equal(a["touch"], [False, True, False])


def simulate(sim, batch, protocol):
    """Probes after closing and, for six-dir, after every chunk of a push along -z."""
    s = sim.initial(batch)
    for seg in physics_protocols.closing(batch, CFG):
        s = sim.run(s, batch, seg)
    probes = [sim.probe(s, batch)]
    if protocol == "six-dir":
        push = physics_protocols.push(batch, CFG, physics_protocols.DIRECTIONS[5], sim.scene.mass)
        sim.run(s, batch, push, lambda st: probes.append(sim.probe(st, batch)))
    return probes


@pytest.mark.slow
@pytest.mark.parametrize("protocol", ["lift-shake", "six-dir"])
def test_closing_and_push_match_cpu(ball, protocol):
    """Closing (lift-shake: on the table; six-dir: the ball held by its weld), then six-dir pushes it along -z."""
    spec, mesh = ball
    poses, q = grasps(mesh, spec, [0.0, -0.005, 0.2])
    with jax.enable_x64(False):
        cpu, mjx_sim, batch = sims(spec, mesh, poses, q, protocol)
        ref, out = simulate(cpu, batch, protocol), simulate(mjx_sim, batch, protocol)
    assert len(ref) == len(out)
    for a, b in zip(ref, out):
        assert_same_probe(a, b, POS_TOL, ROT_TOL)
    if protocol == "lift-shake":
        np.testing.assert_array_equal(ref[0]["touch"], [True, True, False])
        assert ref[0]["table"].all()
    else:  # the push moves every ball, the free one (no finger near it) by accel t^2 / 2 = 5 cm
        assert (np.abs(ref[-1]["pos"][:, 2] - ref[0]["pos"][:, 2]) > 0.01).all()
