"""MJX forward kinematics of the SVH (and a toy hand) against MuJoCo C, finite differences and reference tables."""

import json

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.hand import kinematics as K

from paths import DATA

FK_TOL = 1e-6  # m, MJX vs MuJoCo C in float64 (the bound; the observed error is ~1e-15)
TABLE_TOL = 1e-3  # m, vs the shared/svh README table
CAPSULE_SKIN = 1 - np.sqrt(15 / 16)  # fraction of a capsule's radius its spheres may leave uncovered
FINGERS = ("thumb", "index", "middle", "ring", "little")


@pytest.fixture(scope="module")
def toy():
    return K.load_hand(DATA / "toy_hand" / "toy.toml")


def random_poses(rng, n, spread=0.3):
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.random(n, random_state=rng).as_matrix()
    T[:, :3, 3] = rng.uniform(-spread, spread, (n, 3))
    return T


def random_q(rng, hand, n):
    lo, hi = np.asarray(hand.lower), np.asarray(hand.upper)
    return rng.uniform(lo, hi, (n, len(lo)))


def mujoco_c_fk(hand, T, q):
    """Reference: MuJoCo C with the root body moved to the wrist pose and qpos from the coupling."""
    m = hand.spec.mj_model()
    root = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, hand.spec.root_body)
    m.body_pos[root] = T[:3, 3]
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, T[:3, :3].ravel())
    m.body_quat[root] = quat
    d = mujoco.MjData(m)
    d.qpos[:] = np.asarray(hand.coupling) @ q
    mujoco.mj_kinematics(m, d)
    return d


def test_fk_matches_mujoco_c_on_100_random_configs(svh):
    rng = np.random.default_rng(0)
    T, q = random_poses(rng, 100), random_q(rng, svh, 100)
    fr = jax.jit(K.forward_kinematics_batch)(svh, jnp.asarray(T), jnp.asarray(q))
    site_ids = list(svh.contact_site_ids)
    worst = 0.0
    for i in range(100):
        d = mujoco_c_fk(svh, T[i], q[i])
        worst = max(worst, np.abs(np.asarray(fr.contacts[i]) - d.site_xpos[site_ids]).max(),
                    np.abs(np.asarray(fr.body_pos[i, 1:]) - d.xpos[1:]).max(),
                    np.abs(np.asarray(fr.geom_pos[i]) - d.geom_xpos).max())
        np.testing.assert_allclose(np.asarray(fr.body_rot[i, 1:]), d.xmat.reshape(-1, 3, 3)[1:], atol=1e-9)
        np.testing.assert_allclose(np.asarray(fr.geom_rot[i]), d.geom_xmat.reshape(-1, 3, 3), atol=1e-9)
        np.testing.assert_allclose(np.asarray(fr.palm_pos[i]), d.site_xpos[svh.palm_site_id], atol=FK_TOL)
    assert worst < FK_TOL, worst


@pytest.mark.parametrize("case", json.loads((DATA / "svh_reference_fk.json").read_text())["cases"],
                         ids=lambda c: c["name"])
def test_fingertips_match_reference_table(svh, case):
    q = jnp.array([case["channels"][n] for n in svh.spec.channel_names])
    tips = np.asarray(K.contact_points(svh, jnp.eye(4), q))
    ref = np.array([case["contact_points"][f] for f in FINGERS])
    if case["j5_fixed"]:  # the alternative model with the palm fold j5 held at 0
        qpos = np.asarray(svh.coupling) @ np.asarray(q)
        m = svh.spec.mj_model()
        qpos[m.jnt_qposadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, "j5")]] = 0
        d = mujoco.MjData(m)
        d.qpos[:] = qpos
        mujoco.mj_kinematics(m, d)
        tips = d.site_xpos[list(svh.contact_site_ids)]
    np.testing.assert_allclose(tips, ref, atol=TABLE_TOL)


def test_jacobian_matches_central_differences(svh):
    rng = np.random.default_rng(1)
    jac = jax.jit(K.contact_jacobian)
    pts = jax.jit(K.contact_points)
    for T, q in zip(random_poses(rng, 5), random_q(rng, svh, 5)):
        J = np.asarray(jac(svh, jnp.asarray(T), jnp.asarray(q)))
        eps = 1e-6
        fd = np.stack([
            (np.asarray(pts(svh, T, q + eps * e)) - np.asarray(pts(svh, T, q - eps * e))) / (2 * eps)
            for e in np.eye(len(q))
        ], -1)
        np.testing.assert_allclose(J, fd, atol=1e-8)
        assert np.abs(J).max() > 0.01  # the fingertips really move with q


def test_vmap_over_4096_equals_loop_of_single_calls(svh):
    rng = np.random.default_rng(2)
    T, q = jnp.asarray(random_poses(rng, 4096)), jnp.asarray(random_q(rng, svh, 4096))
    batched = np.asarray(jax.jit(K.forward_kinematics_batch)(svh, T, q).contacts)
    single = jax.jit(K.contact_points)
    loop = np.stack([np.asarray(single(svh, T[i], q[i])) for i in range(4096)])
    np.testing.assert_allclose(batched, loop, rtol=0, atol=1e-12)


def test_second_call_does_not_recompile(svh):
    f = jax.jit(K.contact_jacobian)
    f(svh, jnp.eye(4), jnp.zeros(9)).block_until_ready()
    T, q = jnp.asarray(random_poses(np.random.default_rng(9), 1)[0]), jnp.asarray(np.full(9, 0.1))
    with jax.log_compiles():
        with _count_compiles() as n:
            f(svh, T, q).block_until_ready()
    assert n[0] == 0


class _count_compiles:
    def __enter__(self):
        import logging

        self.count = [0]
        self.handler = logging.Handler()
        self.handler.emit = lambda rec: self.count.__setitem__(0, self.count[0] + ("Compiling" in rec.getMessage()))
        logging.getLogger("jax").addHandler(self.handler)
        return self.count

    def __exit__(self, *exc):
        import logging

        logging.getLogger("jax").removeHandler(self.handler)


def test_limits_means_and_ranges(svh):
    assert svh.n_channels == 9 and svh.n_contacts == 5
    np.testing.assert_allclose(svh.q_mean, (np.asarray(svh.lower) + np.asarray(svh.upper)) / 2)
    np.testing.assert_allclose(svh.q_range, np.asarray(svh.upper) - np.asarray(svh.lower))
    assert np.all(np.asarray(svh.q_range) > 0)
    np.testing.assert_allclose(K.clamp_q(svh, jnp.full(9, 5.0)), svh.upper)


def test_mjcf_couplings_and_limits_agree_with_spec(svh):
    """The MuJoCo equality constraints and joint ranges encode the same coupling the FK applies."""
    m = svh.spec.mj_model()
    A = np.asarray(svh.coupling)
    for e in range(m.neq):
        j1, j2 = m.eq_obj1id[e], m.eq_obj2id[e]
        a1, a2 = m.jnt_qposadr[j1], m.jnt_qposadr[j2]
        master_col = int(np.flatnonzero(A[a2])[0])
        assert A[a2, master_col] == 1.0
        np.testing.assert_allclose(m.eq_data[e, 1], A[a1, master_col])
    assert m.neq + m.nu == m.njnt
    for j in range(m.njnt):  # every joint's range is its multiplier times its channel's range
        col = int(np.flatnonzero(A[m.jnt_qposadr[j]])[0])
        np.testing.assert_allclose(m.jnt_range[j], A[m.jnt_qposadr[j], col] * np.array(
            [svh.lower[col], svh.upper[col]]), atol=1e-8)
    np.testing.assert_allclose(m.actuator_ctrlrange, np.stack([svh.lower, svh.upper], 1))


def test_collision_spheres_lie_inside_geoms_and_cover_capsules(svh):
    m = svh.spec.mj_model()
    T = random_poses(np.random.default_rng(3), 1)[0]
    q = jnp.asarray(random_q(np.random.default_rng(4), svh, 1)[0])
    centres, radii = map(np.asarray, K.collision_spheres(svh, jnp.asarray(T), q))
    d = mujoco_c_fk(svh, T, np.asarray(q))
    body = np.asarray(svh.sphere_body)
    covered_capsules = 0
    for g in range(m.ngeom):
        R, p, size = d.geom_xmat[g].reshape(3, 3), d.geom_xpos[g], m.geom_size[g]
        mine = np.flatnonzero(body == m.geom_bodyid[g])
        local = (centres[mine] - p) @ R
        if m.geom_type[g] == mujoco.mjtGeom.mjGEOM_CAPSULE:
            on_axis = (np.abs(local[:, :2]).max(1) < 1e-9) & (np.abs(local[:, 2]) <= size[1] + 1e-9)
            own = mine[on_axis & np.isclose(radii[mine], size[0])]
            assert len(own) >= 2
            rng = np.random.default_rng(g)
            u = rng.normal(size=(500, 3))
            u *= (size[0] * rng.uniform(0, 1, (500, 1)) ** (1 / 3)) / np.linalg.norm(u, axis=1, keepdims=True)
            u[:, 2] += rng.uniform(-size[1], size[1], 500)
            dist = np.linalg.norm((u @ R.T + p)[:, None] - centres[own][None], axis=-1) - radii[own][None]
            assert (dist.min(1) <= CAPSULE_SKIN * size[0]).all()
            covered_capsules += 1
        elif m.geom_type[g] == mujoco.mjtGeom.mjGEOM_BOX:
            inside = (np.abs(local) + radii[mine, None] <= size + 1e-9).all(1)
            assert inside.sum() >= 1
    assert covered_capsules == 15  # 3 phalanges x 5 fingers


def test_box_vertices_are_geom_box_corners_at_q0(svh):
    T = random_poses(np.random.default_rng(5), 1)[0]
    v = np.asarray(K.box_vertices(svh, jnp.asarray(T)))
    d = mujoco_c_fk(svh, T, np.zeros(9))
    m = svh.spec.mj_model()
    corners = []
    for g in range(m.ngeom):
        for s in np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1], indexing="ij")).reshape(3, -1).T:
            corners.append(d.geom_xmat[g].reshape(3, 3) @ (m.geom_aabb[g, :3] + s * m.geom_aabb[g, 3:])
                           + d.geom_xpos[g])
    np.testing.assert_allclose(v, np.array(corners), atol=1e-9)


def test_tetrahedron_is_rigid_with_palm_and_not_flat(svh):
    T = jnp.asarray(random_poses(np.random.default_rng(6), 1)[0])
    p = np.asarray(K.tetrahedron_points(svh, T))
    vol = abs(np.linalg.det(p[1:] - p[0])) / 6
    assert vol > 1e-6  # m^3: a 4 cm tetrahedron, far from flat
    pose_only = K.forward_kinematics(svh, T, jnp.asarray(svh.upper))
    np.testing.assert_allclose(np.asarray(pose_only.palm_normal), np.asarray(T[:3, :3]) @ [0, 1, 0], atol=1e-12)


def test_toy_hand_loads_and_matches_mujoco_c(toy):
    assert toy.spec.channel_names == ("a", "b") and toy.n_contacts == 2
    rng = np.random.default_rng(7)
    for T, q in zip(random_poses(rng, 10), random_q(rng, toy, 10)):
        got = np.asarray(K.contact_points(toy, jnp.asarray(T), jnp.asarray(q)))
        d = mujoco_c_fk(toy, T, q)
        np.testing.assert_allclose(got, d.site_xpos[list(toy.contact_site_ids)], atol=FK_TOL)
        m = toy.spec.mj_model()
        jb2 = m.jnt_qposadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, "jb2")]
        assert d.qpos[jb2] == pytest.approx(0.5 * q[1])


def test_toy_hand_root_pose_is_the_wrist_pose(toy):
    """The MJCF places the toy palm away from the origin; the wrist pose still maps the root frame to the world."""
    p = np.asarray(K.forward_kinematics(toy, jnp.eye(4), jnp.zeros(2)).palm_pos)
    np.testing.assert_allclose(p, [0, 0.01, 0], atol=1e-12)


def write_spec(tmp_path, **changes):
    import tomllib

    spec = tomllib.loads((DATA / "toy_hand" / "toy.toml").read_text())
    for k, v in changes.items():
        section, _, key = k.rpartition("__")
        (spec[section] if section else spec)[key] = v
    (tmp_path / "toy.xml").write_text((DATA / "toy_hand" / "toy.xml").read_text())

    def val(v):
        return json.dumps(v)

    lines = [f"{k} = {val(v)}" for k, v in spec.items() if not isinstance(v, dict)]
    for sec, tab in spec.items():
        if isinstance(tab, dict):
            lines += [f"[{sec}]"] + [f"{k} = {val(v)}" for k, v in tab.items()]
    path = tmp_path / "toy.toml"
    path.write_text("\n".join(lines))
    return path


@pytest.mark.parametrize("changes, message", [
    ({"contact_sites": ["tip_a", "tip_x"]}, r"contact_sites names unknown site\(s\) \['tip_x'\]"),
    ({"palm_site": "nope"}, r"palm_site names unknown site\(s\) \['nope'\]"),
    ({"coupling__joints": ["ja", "jb", "jzz"]}, r"unknown joint\(s\) \['jzz'\]"),
    ({"coupling__matrix": [[1, 0], [0, 1]]}, r"matrix must be 3x2"),
    ({"coupling__matrix": [[1, 0, 0], [0, 1, 0], [0, 0.5, 0]]}, r"matrix must be 3x2"),
    ({"coupling__joints": ["ja", "jb"], "coupling__matrix": [[1, 0], [0, 1]]}, r"\['jb2'\] are not in"),
    ({"tetrahedron_sites": ["t0", "t1", "t2"]}, r"exactly 4 sites"),
    ({"root_body": "fa"}, r"must be a child of the world with no joint"),
    ({"channels__upper": [1.2, -1.0]}, r"need lower < upper"),
    ({"palm_normal": [0, 0, 0]}, r"non-zero 3-vector"),
    ({"grip": 3}, r"unknown key\(s\) \['grip'\]"),
    ({"mjcf": "missing.xml"}, r"mjcf file not found"),
])
def test_bad_specs_name_the_problem(tmp_path, changes, message):
    with pytest.raises(FfcgsError, match=message):
        K.load_hand(write_spec(tmp_path, **changes))


def test_unknown_builtin_hand_lists_choices():
    with pytest.raises(FfcgsError, match="built-in hands: svh"):
        K.load_hand("shadow")


def test_input_checks(svh):
    with pytest.raises(FfcgsError, match=r"shape \(4, 4\) or \(B, 4, 4\)"):
        K.check_wrist_poses(np.eye(3))
    with pytest.raises(FfcgsError, match="NaN"):
        K.check_wrist_poses(np.full((4, 4), np.nan))
    with pytest.raises(FfcgsError, match="rigid"):
        K.check_wrist_poses(np.diag([2.0, 1, 1, 1]))
    with pytest.raises(FfcgsError, match=r"shape \(9,\)"):
        K.check_q(svh, np.zeros(7))
    assert K.check_wrist_poses(random_poses(np.random.default_rng(0), 3)).shape == (3, 4, 4)


@pytest.mark.parametrize("frac", [0.2, 0.5, 0.9])
def test_simulated_actuators_and_equalities_reproduce_the_coupling(svh, frac):
    """In MuJoCo physics (gravity off) the 9 position actuators plus the equality constraints settle the 20 joints
    at coupling @ ctrl: the MJCF expresses the same coupling that the kinematics apply."""
    m = svh.spec.mj_model()
    m.opt.gravity[:] = 0
    d = mujoco.MjData(m)
    ctrl = np.asarray(svh.lower) + frac * np.asarray(svh.q_range)
    d.ctrl[:] = ctrl
    for _ in range(3000):  # 6 s of simulated time
        mujoco.mj_step(m, d)
    np.testing.assert_allclose(d.qpos, np.asarray(svh.coupling) @ ctrl, atol=1e-6)


def test_check_wrist_poses_projects_float32_drift_and_refuses_real_errors():
    P = random_poses(np.random.default_rng(1), 4)
    drift = P.copy()
    drift[:, :3, :3] += 1.5e-4 * np.random.default_rng(2).standard_normal((4, 3, 3))  # float32 descent-like drift
    out = K.check_wrist_poses(drift)
    R = out[:, :3, :3]
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), (4, 3, 3)), atol=1e-12)
    assert np.abs(out - P).max() < 3e-3 and np.allclose(np.linalg.det(R), 1.0)
    with pytest.raises(FfcgsError, match="rigid transforms"):
        K.check_wrist_poses(P @ np.diag([1.01, 1.0, 1.0, 1.0]))
