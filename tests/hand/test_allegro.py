"""The built-in Allegro hand (right): names, MJX against MuJoCo C, the Menagerie reference FK table, where its
contact and palm sites sit, its servos in the physics scene, and that data/make_allegro_mjcf.py wrote the files."""

import filecmp
import json
import subprocess
import sys

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
import trimesh

from ffcgs_jax.hand import kinematics as K
from ffcgs_jax.physics import scene as physics_scene
from ffcgs_jax.physics.config import PhysicsConfig

from paths import DATA, REPO, SHARED
from test_kinematics import FK_TOL, mujoco_c_fk, random_poses, random_q

ASSETS = REPO / "ffcgs_jax" / "hand" / "assets" / "allegro"
NUMBERS = SHARED / "hands" / "allegro"
REFERENCE = json.loads((DATA / "allegro_reference_fk.json").read_text())
REF_TOL = 1e-4  # m: the numbers file's bound on its reference_fk table
FINGERS = ("th", "ff", "mf", "rf")  # the spec's contact-site order
JOINTS = tuple(f"{f}j{k}" for f in ("ff", "mf", "rf", "th") for k in range(4))
BODIES = ("palm",) + tuple(f"{f}_{link}" for f in ("ff", "mf", "rf", "th")
                           for link in ("base", "proximal", "medial", "distal", "tip"))
SKIN_DEPTH, SKIN_TOL = 0.001, 0.0002  # m: contact sites 1 mm (+- 0.2 mm) under the fingertip capsule's skin
CAPSULE, BOX = mujoco.mjtGeom.mjGEOM_CAPSULE, mujoco.mjtGeom.mjGEOM_BOX

_fk = jax.jit(K.forward_kinematics)
_fk_batch = jax.jit(K.forward_kinematics_batch)


@pytest.fixture(scope="module")
def allegro():
    return K.load_hand("allegro")


@pytest.fixture(scope="module")
def model(allegro):
    return allegro.spec.mj_model()


def _names(m, kind, n):
    return tuple(mujoco.mj_id2name(m, kind, i) for i in range(n))


def _tip_capsule(m, site):
    """The capsule geom on the body of contact site `site`."""
    (g,) = [g for g in range(m.ngeom) if m.geom_bodyid[g] == m.site_bodyid[site] and m.geom_type[g] == CAPSULE]
    return g


def _geom_local(m, g, p_body):
    """Body-frame points p_body in the frame of geom g."""
    R = np.zeros(9)
    mujoco.mju_quat2Mat(R, m.geom_quat[g])
    return (np.asarray(p_body) - m.geom_pos[g]) @ R.reshape(3, 3)


def test_loads_with_the_numbers_file_names(allegro, model):
    m = model
    assert allegro.n_channels == 16 and allegro.n_contacts == 4
    assert allegro.spec.channel_names == JOINTS and allegro.spec.coupling_joints == JOINTS
    assert _names(m, mujoco.mjtObj.mjOBJ_BODY, m.nbody)[1:] == BODIES
    assert _names(m, mujoco.mjtObj.mjOBJ_JOINT, m.njnt) == JOINTS
    assert all(m.jnt_type == mujoco.mjtJoint.mjJNT_HINGE)
    assert allegro.spec.contact_sites == tuple(f"{f}_tip_site" for f in FINGERS)
    assert [_names(m, mujoco.mjtObj.mjOBJ_BODY, m.nbody)[m.site_bodyid[s]] for s in allegro.contact_site_ids] == [
        f"{f}_tip" for f in FINGERS]
    np.testing.assert_array_equal(allegro.coupling, np.eye(16))
    np.testing.assert_allclose(np.stack([allegro.lower, allegro.upper], 1), m.jnt_range)
    # Only boxes and capsules, one capsule per fingertip; palm-root body straight under the world.
    assert set(m.geom_type.tolist()) == {int(BOX), int(CAPSULE)} and (m.geom_type == CAPSULE).sum() == 4
    assert m.body_parentid[1] == 0 and m.body_jntnum[1] == 0
    np.testing.assert_allclose(m.body_quat[1], [0, np.sqrt(0.5), 0, np.sqrt(0.5)], atol=1e-9)


def test_one_servo_per_joint_in_channel_order(allegro, model):
    m = model
    assert m.nu == 16
    assert _names(m, mujoco.mjtObj.mjOBJ_ACTUATOR, m.nu) == JOINTS
    assert [_names(m, mujoco.mjtObj.mjOBJ_JOINT, m.njnt)[j] for j in m.actuator_trnid[:, 0]] == list(JOINTS)
    np.testing.assert_allclose(m.actuator_gainprm[:, 0], 10.0)
    np.testing.assert_allclose(m.actuator_biasprm[:, :2], np.tile([0.0, -10.0], (16, 1)))
    np.testing.assert_allclose(m.actuator_ctrlrange, np.stack([allegro.lower, allegro.upper], 1))
    np.testing.assert_allclose(m.dof_damping, 1.0)
    assert m.neq == 0 and m.nexclude == 5


@pytest.mark.parametrize("frac", [0.2, 0.8])
def test_servos_settle_at_their_channel(allegro, frac):
    """MuJoCo physics, gravity off: the 16 servos hold every joint at its channel's target."""
    m = allegro.spec.mj_model()
    m.opt.gravity[:] = 0
    d = mujoco.MjData(m)
    ctrl = np.asarray(allegro.lower) + frac * np.asarray(allegro.q_range)
    d.ctrl[:] = ctrl
    for _ in range(1500):  # 3 s: 30 time constants of damping / kp
        mujoco.mj_step(m, d)
    np.testing.assert_allclose(d.qpos, np.asarray(allegro.coupling) @ ctrl, atol=1e-6)


def test_hand_never_collides_with_itself_but_with_objects_and_table(allegro):
    box = trimesh.creation.box([0.05, 0.05, 0.05])
    sc = physics_scene.build(allegro.spec, box, [(box.vertices, box.faces)], PhysicsConfig(), table_z=-0.025)
    m = sc.model
    ct, ca = m.geom_contype, m.geom_conaffinity
    hand = sc.hand_geoms
    assert len(hand) == 21 and len(sc.palm_geoms) == 1
    pair = lambda a, b: bool((ct[a] & ca[b]) | (ct[b] & ca[a]))  # noqa: E731
    assert not any(pair(a, b) for a in hand for b in hand)
    assert all(pair(a, b) for a in hand for b in (*sc.obj_geoms, sc.table_geom))
    # The scene writes channel q into ctrl: actuator i must drive the joint channel i drives.
    for i in range(m.nu):
        assert m.jnt_qposadr[m.actuator_trnid[i, 0]] == sc.hand_qpos[np.flatnonzero(sc.coupling[:, i])[0]]
    assert (m.actuator_gainprm[:, 0] > 0).all()  # still position servos, whatever gain the scene gave them
    np.testing.assert_allclose(m.actuator_biasprm[:, 1], -m.actuator_gainprm[:, 0])


def test_mjx_fk_matches_mujoco_c_on_random_configs(allegro):
    rng = np.random.default_rng(0)
    n = 40
    T, q = random_poses(rng, n), random_q(rng, allegro, n)
    fr = _fk_batch(allegro, jnp.asarray(T), jnp.asarray(q))
    worst = 0.0
    for i in range(n):
        d = mujoco_c_fk(allegro, T[i], q[i])
        worst = max(worst, np.abs(np.asarray(fr.contacts[i]) - d.site_xpos[list(allegro.contact_site_ids)]).max(),
                    np.abs(np.asarray(fr.body_pos[i, 1:]) - d.xpos[1:]).max(),
                    np.abs(np.asarray(fr.geom_pos[i]) - d.geom_xpos).max(),
                    np.abs(np.asarray(fr.palm_pos[i]) - d.site_xpos[allegro.palm_site_id]).max())
        np.testing.assert_allclose(np.asarray(fr.body_rot[i, 1:]), d.xmat.reshape(-1, 3, 3)[1:], atol=1e-9)
        np.testing.assert_allclose(np.asarray(fr.geom_rot[i]), d.geom_xmat.reshape(-1, 3, 3), atol=1e-9)
    assert worst < FK_TOL, worst
    assert np.ptp(np.asarray(fr.contacts), axis=0).min() > 0.1  # the poses and q really vary


def _capsule_ends(m, pos, rot):
    """Centres of the outer end of the fingertip capsules, per finger, from geom frames."""
    out = {}
    for f in FINGERS:
        g = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, f"{f}_tip")
        out[f] = pos[g] + rot[g][:, 2] * m.geom_size[g, 1]
    return out


@pytest.mark.parametrize("case", REFERENCE["cases"], ids=[f"case{i}" for i in range(len(REFERENCE["cases"]))])
def test_fingertips_match_reference_table(allegro, model, case):
    m = model
    assert REFERENCE["joint_order"] == list(allegro.spec.channel_names)
    ref = case["tip_capsule_end_centres_palm_frame"]
    q = np.asarray(case["qpos"])
    # MuJoCo C, the model's own qpos; results taken into the palm body's frame.
    d = mujoco.MjData(m)
    d.qpos[:] = np.asarray(allegro.coupling) @ q
    mujoco.mj_kinematics(m, d)
    R, p = d.xmat[1].reshape(3, 3), d.xpos[1]
    ends = _capsule_ends(m, d.geom_xpos, d.geom_xmat.reshape(-1, 3, 3))
    for f in FINGERS:
        np.testing.assert_allclose((ends[f] - p) @ R, ref[f], atol=REF_TOL, err_msg=f"MuJoCo C, {f}")
    # The package's MJX FK: with the identity wrist pose its frames are the palm (root) frame.
    fr = _fk(allegro, jnp.eye(4), jnp.asarray(q))
    ends = _capsule_ends(m, np.asarray(fr.geom_pos), np.asarray(fr.geom_rot))
    for f in FINGERS:
        np.testing.assert_allclose(ends[f], ref[f], atol=REF_TOL, err_msg=f"MJX, {f}")


def _flexion_velocity(m, d, site, joints, q, eps=1e-6):
    """How contact site `site` moves (in its capsule's frame) when `joints` turn together, by forward differences."""
    def at(qq):
        d.qpos[:] = qq
        mujoco.mj_kinematics(m, d)
        return d.site_xpos[site].copy(), d.xmat[m.site_bodyid[site]].reshape(3, 3).copy()

    p0, R = at(q)
    dq = np.zeros(m.nq)
    dq[[m.jnt_qposadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, j)] for j in joints]] = eps
    p1, _ = at(q + dq)
    v_body = R.T @ (p1 - p0) / eps
    g = _tip_capsule(m, site)
    return _geom_local(m, g, v_body + m.geom_pos[g])  # rotation only


def test_contact_sites_sit_1mm_under_the_fingertip_pads(allegro, model):
    m = model
    d = mujoco.MjData(m)
    qs = np.concatenate([[np.asarray(allegro.q_mean)], random_q(np.random.default_rng(3), allegro, 25)])
    for f, s in zip(FINGERS, allegro.contact_site_ids):
        g = _tip_capsule(m, s)
        r, h = m.geom_size[g, :2]
        local = _geom_local(m, g, m.site_pos[s])
        radial = local * [1, 1, 0]
        depth = r - np.linalg.norm(local - [0, 0, np.clip(local[2], -h, h)])
        assert abs(depth - SKIN_DEPTH) <= SKIN_TOL, (f, depth)
        assert 0 < local[2] <= h, (f, local)  # the distal half of the capsule's straight part
        for q in qs:  # the pad side: where the flexion joints j1..j3 move the tip
            v = _flexion_velocity(m, d, s, [f"{f}j{k}" for k in (1, 2, 3)], q) * [1, 1, 0]
            assert radial @ v > 0.9 * np.linalg.norm(radial) * np.linalg.norm(v), (f, q)


def test_thumb_pad_faces_the_other_fingertips(allegro, model):
    m = model
    d = mujoco.MjData(m)
    d.qpos[:] = np.asarray(allegro.coupling) @ np.asarray(allegro.q_mean)
    mujoco.mj_kinematics(m, d)
    s = allegro.contact_site_ids[0]
    b, g = m.site_bodyid[s], _tip_capsule(m, s)
    others = d.site_xpos[list(allegro.contact_site_ids[1:])].mean(0)
    to_others = _geom_local(m, g, d.xmat[b].reshape(3, 3).T @ (others - d.xpos[b]))
    radial = _geom_local(m, g, m.site_pos[s]) * [1, 1, 0]
    cos = radial @ (to_others * [1, 1, 0]) / np.linalg.norm(radial) / np.linalg.norm(to_others * [1, 1, 0])
    assert cos > 0.99, cos


def test_palm_site_normal_and_tetrahedron(allegro, model):
    m = model
    (g,) = [g for g in range(m.ngeom) if m.geom_bodyid[g] == 1]
    assert m.geom_type[g] == BOX and m.site_bodyid[allegro.palm_site_id] == 1
    n = np.asarray(allegro.palm_normal)
    n_box = _geom_local(m, g, n + m.geom_pos[g])
    k = int(np.argmax(np.abs(n_box)))
    np.testing.assert_allclose(np.abs(n_box), np.eye(3)[k], atol=1e-12)  # normal to a face of the palm box
    np.testing.assert_allclose(_geom_local(m, g, m.site_pos[allegro.palm_site_id]), m.geom_size[g] * n_box,
                               atol=1e-9)  # at the centre of that face
    # The face the fingers close over: tips at mid-range in front of it, and flexing moves them towards +n.
    q_open = np.clip(0.0, np.asarray(allegro.lower), np.asarray(allegro.upper))
    q_mid = np.asarray(allegro.q_mean)
    mid, opened = (_fk(allegro, jnp.eye(4), jnp.asarray(q)) for q in (q_mid, q_open))
    ahead = (np.asarray(mid.contacts) - np.asarray(mid.palm_pos)) @ n
    assert (ahead > 0.01).all(), ahead
    assert ((np.asarray(mid.contacts) - np.asarray(opened.contacts))[1:] @ n > 0.02).all()
    assert all(m.site_bodyid[s] == 1 for s in allegro.tetrahedron_site_ids)
    tet = m.site_pos[list(allegro.tetrahedron_site_ids)]  # on the palm (root) body: in the FK's root frame
    assert abs(np.linalg.det(tet[1:] - tet[0])) / 6 > 1e-6  # m^3: a 4 cm tetrahedron, far from flat
    np.testing.assert_allclose((tet[0] - np.asarray(mid.palm_pos)) @ n, 0.04, atol=1e-9)


@pytest.mark.skipif(not (NUMBERS / "kinematics.json").is_file(), reason="../shared/hands/allegro not present")
def test_generator_reproduces_the_shipped_files(tmp_path):
    subprocess.run([sys.executable, str(REPO / "data" / "make_allegro_mjcf.py"), "--allegro", str(NUMBERS),
                    "--out", str(tmp_path)], check=True, capture_output=True, cwd=REPO)
    for name, shipped in [("allegro.xml", ASSETS), ("allegro.toml", ASSETS), ("NOTICE", ASSETS),
                          ("allegro_reference_fk.json", DATA)]:
        assert filecmp.cmp(tmp_path / name, shipped / name, shallow=False), f"{name} differs from the generator's"


def test_notice_carries_the_simlab_license():
    text = (ASSETS / "NOTICE").read_text()
    assert "BSD 2-Clause" in text and "Copyright (c) 2016, SimLab" in text and "wonik_allegro" in text
    assert "BSD-2-Clause" in (ASSETS / "allegro.xml").read_text().splitlines()[0]
    assert "SimLab" in REFERENCE["license"]
