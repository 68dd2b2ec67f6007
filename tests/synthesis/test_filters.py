"""Pose filters, fingertip-path filter and whole-hand penetration against constructed poses and closed forms."""


import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.geometry import mesh_io
from ffcgs_jax.geometry import sdf as S
from ffcgs_jax.hand import kinematics as K
from ffcgs_jax.synthesis import filters as F

from paths import DATA

TOY = DATA / "toy_hand" / "toy.toml"  # two fingers: MJX compiles (and differentiates) faster
BALL_R = 0.035  # m, the built-in ball (resting on z = 0)
BALL_C = np.array([0.0, 0.0, BALL_R])
DEPTH_TOL = 1e-3  # m: grid interpolation + the ball mesh's facets (the grid's voxel is ~3 mm)
FD_TOL = 1e-6  # relative: autodiff vs central differences where the SDF is exactly linear
FD_EPS = 1e-6  # rad
N_BATCH = 12  # poses in the batch-vs-loop test



def _depths(svh, sdf, T, q):
    """Every per-pose measure at once, so the tests compile MJX kinematics only a few times (seconds each)."""
    return (*F.hand_penetration(svh, sdf, T, q), *F.hand_table_penetration(svh, sdf, T, q),
            F.penetration_penalty(svh, sdf, T, q))


def _depths_batch(svh, sdf, Ts, qs):
    return (*F.hand_penetration_batch(svh, sdf, Ts, qs), *F.hand_table_penetration_batch(svh, sdf, Ts, qs),
            F.penetration_penalty_batch(svh, sdf, Ts, qs))


depths = jax.jit(_depths)  # -> depth, per-sphere depths, table depth, per-sphere table depths, penalty
depths_batch = jax.jit(_depths_batch)
penalty_grads = jax.jit(jax.grad(F.penetration_penalty, argnums=(2, 3)))  # d/dT, d/dq
# the energy's way: one forward-kinematics pass shared with the contacts, handed in
penalty_grads_shared = jax.jit(jax.grad(
    lambda h, s, T, q: F.penetration_penalty(h, s, T, q, K.forward_kinematics(h, T, q)), argnums=(2, 3)))
collides = jax.jit(F.pose_collides, static_argnums=3)
clearance = jax.jit(F.pose_clearance)


@pytest.fixture(scope="module")
def toy():
    return K.load_hand(TOY)


@pytest.fixture(scope="module")
def box():
    return S.build_sdf(mesh_io.load_mesh("box"))  # 5 x 8 x 14 cm, centred in x/y, z from 0 to 0.14


@pytest.fixture(scope="module")
def ball():
    return S.build_sdf(mesh_io.load_mesh("ball"))


@pytest.fixture(scope="module")
def plane():
    """The half-space y <= -0.015 as an exact (linear) grid: d = y + 0.015, gradient (0, 1, 0).

    The toy hand's fingers curl towards -y as they close, so their spheres enter it, its palm spheres stay out.
    Its Taylor-blended query is exact, so finite differences check the penalty's gradient without interpolation
    error.
    """
    res, h = 32, 0.02
    origin = np.full(3, -0.31)
    y = origin[1] + h * np.arange(res)
    grid = np.zeros((res, res, res, 4))
    grid[..., 0] = (y + 0.015)[None, :, None]
    grid[..., 2] = 1.0
    return S.GradientSDF(jnp.asarray(grid), jnp.asarray(origin), jnp.asarray(h), jnp.asarray(-1.0))


def pose(R=np.eye(3), t=(0.0, 0.0, 0.0)) -> jnp.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return jnp.asarray(T)


def rot_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


FINGERS_DOWN = rot_x(np.pi)  # root z (along the fingers) -> world -z


def palm_root(svh) -> np.ndarray:
    m = svh.spec.mj_model()
    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)
    return np.asarray(svh.root_inv)[:3, :3] @ d.site_xpos[svh.palm_site_id] + np.asarray(svh.root_inv)[:3, 3]


def c_spheres(svh, T, q) -> tuple[np.ndarray, np.ndarray]:
    """Reference sphere centres from MuJoCo C: the root body moved to the wrist pose, qpos from the coupling."""
    m = svh.spec.mj_model()
    root = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, svh.spec.root_body)
    T = np.asarray(T)
    m.body_pos[root] = T[:3, 3]
    mujoco.mju_mat2Quat(m.body_quat[root], T[:3, :3].ravel())
    d = mujoco.MjData(m)
    d.qpos[:] = np.asarray(svh.coupling) @ np.asarray(q)
    mujoco.mj_kinematics(m, d)
    b = np.asarray(svh.sphere_body)
    centres = np.einsum("sij,sj->si", d.xmat.reshape(-1, 3, 3)[b], np.asarray(svh.sphere_pos)) + d.xpos[b]
    return centres, np.asarray(svh.sphere_radius)


def test_config_check_rejects_out_of_range():
    F.FilterConfig().check()
    with pytest.raises(FfcgsError, match="palm_up_max"):
        F.FilterConfig(palm_up_max=1.5).check()
    with pytest.raises(FfcgsError, match="clearance"):
        F.FilterConfig(clearance=-0.01).check()
    with pytest.raises(FfcgsError, match="tip_table_margin"):
        F.FilterConfig(tip_table_margin=float("nan")).check()


def test_far_pose_is_collision_free(svh, box):
    assert not collides(svh, box, pose(t=(0.6, 0.4, 0.5)))
    assert float(clearance(svh, box, pose(t=(0.6, 0.4, 0.5)))) > 0.3


def test_palm_inside_object_collides(svh, box):
    # palm centre at the box's centre, hand pointing down so it stays above the table except where it is in the box
    T = pose(FINGERS_DOWN, np.array([0, 0, 0.07]) - FINGERS_DOWN @ palm_root(svh))
    assert collides(svh, box, T)
    assert float(clearance(svh, box, T)) < -0.01


def test_pose_below_table_collides_and_clearance_counts(svh, box):
    far = np.array([0.5, 0.0, 0.0])  # beside the object: only the table matters
    lowest = float(np.asarray(svh.box_vertices)[:, 2].min())  # identity rotation: box corners' lowest z
    assert collides(svh, box, pose(t=far + [0, 0, -0.05]))
    above = pose(t=far + [0, 0, 0.01 - lowest])  # lowest corner 1 cm above the table
    assert not collides(svh, box, above)
    assert collides(svh, box, above, F.FilterConfig(clearance=0.02))
    assert not collides(svh, box, above, F.FilterConfig(clearance=0.005))


def test_palm_up(svh):
    # The SVH palm faces +y in its root frame; rotating about x by a tilts it to (0, cos a, sin a).
    assert not F.palm_up(svh, pose())  # horizontal: z = 0 is not above 0
    assert F.palm_up(svh, pose(rot_x(np.pi / 2)))
    assert not F.palm_up(svh, pose(rot_x(-np.pi / 2)))
    tilted = pose(rot_x(0.1))  # palm 0.1 rad above the horizon, z = sin(0.1) ~ 0.0998
    assert F.palm_up(svh, tilted)
    assert not F.palm_up(svh, tilted, F.FilterConfig(palm_up_max=0.2))
    assert not F.palm_up(svh, pose(rot_x(np.pi / 2)), F.FilterConfig(palm_up_max=1.0))  # disabled


def test_tips_below_table(box):
    rng = np.random.default_rng(0)
    path = rng.uniform(-0.1, 0.1, (10, 5, 3))
    path[..., 2] = rng.uniform(0.01, 0.2, (10, 5))  # all at least 1 cm above the table (z = 0)
    assert not F.tips_below_table(box, jnp.asarray(path))
    assert F.tips_below_table(box, jnp.asarray(path), margin=0.2)
    dip = path.copy()
    dip[4, 2, 2] = -0.001  # one tip dips 1 mm below the table in the middle of the path
    assert F.tips_below_table(box, jnp.asarray(dip))
    assert not F.tips_below_table(box, jnp.asarray(dip), margin=-0.002)


def _pushed_into_ball(svh, depth: float) -> tuple[jnp.ndarray, int]:
    """Hand pointing down onto the ball with its lowest sphere (middle fingertip) `depth` metres inside it."""
    c, r = c_spheres(svh, np.eye(4), np.zeros(svh.n_channels))
    k = int(np.argmax(c[:, 2]))
    target = BALL_C + [0, 0, BALL_R + r[k] - depth]
    return pose(FINGERS_DOWN, target - FINGERS_DOWN @ c[k]), k


def test_hand_penetration_zero_when_far(svh, ball):
    q = 0.5 * (svh.lower + svh.upper)
    depth, per, tdepth, tper, pen = depths(svh, ball, pose(t=(0.3, 0.3, 0.3)), q)
    assert float(depth) == 0.0 and float(jnp.max(per)) == 0.0
    assert float(tdepth) == 0.0 and float(jnp.max(tper)) == 0.0
    assert float(pen) == 0.0


def test_hand_penetration_matches_a_sphere_pushed_into_the_ball(svh, ball):
    q = jnp.zeros(svh.n_channels)
    T, k = _pushed_into_ball(svh, 0.008)
    depth, per, tdepth, _, pen = depths(svh, ball, T, q)
    # reference: closed-form ball distance at every sphere centre (centres from MuJoCo C)
    c, r = c_spheres(svh, T, q)
    ref = np.maximum(r - (np.linalg.norm(c - BALL_C, axis=1) - BALL_R), 0.0)
    assert abs(float(depth) - 0.008) < DEPTH_TOL
    assert int(jnp.argmax(per)) == k
    np.testing.assert_allclose(np.asarray(per), ref, atol=DEPTH_TOL)
    clear = np.linalg.norm(c - BALL_C, axis=1) - BALL_R - r > DEPTH_TOL  # spheres well outside the ball
    assert clear.sum() > 100 and (np.asarray(per)[clear] == 0).all()
    # the penalty: the same depths beyond the contact tolerance, squared and summed, plus the q = 0 box corners'
    # squared depths in ball or table
    v = np.asarray(K.box_vertices(svh, T))
    corner = np.maximum(-np.minimum(np.linalg.norm(v - BALL_C, axis=1) - BALL_R, v[:, 2]), 0.0)
    beyond = np.maximum(ref - F.CONTACT_TOL, 0.0)
    assert float(pen) == pytest.approx(float(np.sum(beyond**2) + np.sum(corner**2)), rel=1e-2)  # SDF vs closed form
    assert float(tdepth) == 0.0  # the table is 7 cm below the fingertip


def test_hand_table_penetration(svh, ball):
    q = jnp.zeros(svh.n_channels)
    T, _ = _pushed_into_ball(svh, 0.0)
    T = T.at[:3, 3].add(jnp.array([0.5, 0.0, -0.075]))  # beside the ball, the fingertips 7.5 cm lower
    c, r = c_spheres(svh, T, q)
    ref = np.maximum(r - c[:, 2], 0.0)  # table at z = 0
    depth, _, tdepth, tper, _ = depths(svh, ball, T, q)
    assert ref.max() == pytest.approx(0.005, abs=1e-9)  # the lowest sphere is 5 mm into the table
    assert float(tdepth) == pytest.approx(ref.max(), abs=1e-12)
    np.testing.assert_allclose(np.asarray(tper), ref, atol=1e-12)
    assert float(depth) == 0.0  # the object is 50 cm away


@pytest.mark.e2e  # over 20 s on the 2-core CPU: kept out of plain `pytest` (README)
def test_penetration_penalty_gradient_matches_finite_differences(toy, plane):
    q0 = 0.5 * (toy.lower + toy.upper)
    _, per, *_, pen = depths(toy, plane, jnp.eye(4), q0)
    assert float(pen) > 0 and 0 < int((per > 0).sum()) < len(per)  # some spheres in the plane, some out
    fd = np.array([(float(depths(toy, plane, jnp.eye(4), q0 + FD_EPS * e)[-1])
                    - float(depths(toy, plane, jnp.eye(4), q0 - FD_EPS * e)[-1])) / (2 * FD_EPS)
                   for e in np.eye(toy.n_channels)])
    gT, g = penalty_grads(toy, plane, jnp.eye(4), q0)
    g = np.asarray(g)
    assert np.isfinite(g).all() and np.abs(g).min() > 0
    np.testing.assert_allclose(g, fd, rtol=FD_TOL, atol=FD_TOL * np.abs(fd).max())
    for a, b in zip(penalty_grads_shared(toy, plane, jnp.eye(4), q0), (gT, g)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-12, atol=1e-15)


def test_penetration_penalty_gradient_finite_on_the_ball(toy, ball):
    T = pose(t=BALL_C + [0.03, 0.0, 0.0])  # the palm straddles the ball's surface on its +x side
    for q in (jnp.zeros(toy.n_channels), toy.upper):  # at the joint limits
        gT, gq = penalty_grads(toy, ball, T, q)
        assert np.isfinite(np.asarray(gT)).all() and np.isfinite(np.asarray(gq)).all()
    gT, _ = penalty_grads(toy, ball, T, jnp.zeros(toy.n_channels))
    assert float(gT[0, 3]) < 0  # moving the hand out along +x lowers the penalty
    assert float(depths(toy, ball, T, jnp.zeros(toy.n_channels))[-1]) > 0


def test_batches_equal_loops(toy, ball):
    """vmap versions against loops of single calls (on the toy hand: the batching is hand-independent)."""
    rng = np.random.default_rng(1)
    Ts = [pose(t=BALL_C + [0.03, 0.0, 0.0]), pose(t=(0.3, 0, 0.3)), pose(rot_x(np.pi / 2), (0, -0.06, 0.0)),
          pose(rot_x(-0.3), (0.0, 0.0, 0.005))]
    for _ in range(N_BATCH - len(Ts)):  # random poses around the ball, some into it or the table
        R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
        Ts.append(pose(R * np.sign(np.linalg.det(R)), rng.uniform([-0.06, -0.06, 0.0], [0.06, 0.06, 0.1])))
    Tb = jnp.stack(Ts)
    qb = jnp.asarray(rng.uniform(np.asarray(toy.lower), np.asarray(toy.upper), (N_BATCH, toy.n_channels)))
    tips = jnp.asarray(rng.uniform(0.005, 0.5, (N_BATCH, 6, 5, 3)))  # below 0.01 m: 1 % of the points
    cfg = F.FilterConfig(palm_up_max=0.1, clearance=0.01)
    coll = jax.jit(F.pose_collides_batch, static_argnums=3)(toy, ball, Tb, cfg)
    np.testing.assert_array_equal(coll, [bool(collides(toy, ball, T, cfg)) for T in Ts])
    assert 0 < int(coll.sum()) < N_BATCH  # the cases are not all alike
    np.testing.assert_allclose(jax.jit(F.pose_clearance_batch)(toy, ball, Tb),
                               [float(clearance(toy, ball, T)) for T in Ts], atol=1e-12)
    up = jax.jit(F.palm_up_batch, static_argnums=2)(toy, Tb, cfg)
    np.testing.assert_array_equal(up, [bool(F.palm_up(toy, T, cfg)) for T in Ts])
    assert 0 < int(up.sum()) < N_BATCH
    below = jax.jit(F.tips_below_table_batch, static_argnums=2)(ball, tips, 0.01)
    np.testing.assert_array_equal(below, [bool(F.tips_below_table(ball, t, 0.01)) for t in tips])
    assert 0 < int(below.sum()) < N_BATCH
    batch = depths_batch(toy, ball, Tb, qb)
    assert int((batch[0] > 0).sum()) >= 2 and int((batch[2] > 0).sum()) >= 1  # object and table depths exercised
    for i in range(N_BATCH):
        for b, one in zip(batch, depths(toy, ball, Ts[i], qb[i])):
            np.testing.assert_allclose(b[i], one, atol=1e-12, rtol=1e-12)
