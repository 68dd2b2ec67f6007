"""The grasp pipeline on hands other than the SVH: the Allegro (16 channels, 4 fingertips, no couplings) and the
two-finger toy hand. Nothing may assume five fingers, nine channels or SVH distances (tests/synthesis/test_grasp.py
covers the SVH in depth; this module checks shapes, hand-derived defaults and the saved FK on the others)."""

import mujoco
import numpy as np
import pytest

from ffcgs_jax.geometry import mesh_io
from ffcgs_jax.geometry.config import SDFConfig
from ffcgs_jax.hand import kinematics as K
from ffcgs_jax.hand import sites
from ffcgs_jax.synthesis import grasp as G
from ffcgs_jax.synthesis.config import OptimConfig
from ffcgs_jax.viz import scene
from paths import DATA

pytestmark = pytest.mark.e2e  # the whole pipeline compiled for each hand

CFG = G.GraspConfig(n=4, sdf=SDFConfig(res=16), optim=OptimConfig(iters=5))
HANDS = {"allegro": "allegro", "toy": str(DATA / "toy_hand" / "toy.toml")}


@pytest.fixture(scope="module", params=sorted(HANDS))
def run(request):
    hand = K.load_hand(HANDS[request.param])
    return hand, G.synthesize(hand, mesh_io.load_mesh("box"), CFG, "box")


def test_fields_follow_the_hand(run):
    hand, gs = run
    g, c, q = CFG.n, hand.n_contacts, hand.n_channels
    assert gs["q"].shape == (g, q) and gs["squeeze_dir"].shape == (g, q) and gs["q_squeeze"].shape == (g, q)
    assert gs["contacts"].shape == (g, c, 3) and gs["contact_dist"].shape == (g, c)
    assert gs["joint_pos"].shape == (g, len(gs["joint_names"]))
    assert tuple(gs["channel_names"]) == hand.spec.channel_names
    for k in ("E", "E_g", "E_c", "E_q", "penetration"):
        assert np.isfinite(gs[k]).all(), k
    assert ((gs["q"] >= np.asarray(hand.lower) - 1e-6) & (gs["q"] <= np.asarray(hand.upper) + 1e-6)).all()


def test_no_shipped_weights_means_the_geometric_sampler_at_the_hands_standoff(run):
    hand, gs = run
    assert gs.config.sampler == "geometric"  # "auto": no cvae weights ship for these hands
    reach = sites.open_hand_reach(hand)
    assert gs.config.sampling.standoff == sites.default_standoff(hand)
    assert reach <= gs.config.sampling.standoff < max(reach, 0.0) + sites.STANDOFF_STEP + 1e-12


def test_saved_contacts_are_mujoco_c_fk_of_the_saved_pose(run):
    """With MuJoCo C, the hand at the saved wrist pose and channels: each contact lies on the skin of one of its
    fingertip's candidate spheres (as tests/synthesis/test_grasp.py checks for the SVH)."""
    hand, gs = run
    pos, rad, body = np.asarray(hand.tip_pos), np.asarray(hand.tip_radius), np.asarray(hand.tip_body)
    names = [mujoco.mj_id2name(hand.spec.mj_model(), mujoco.mjtObj.mjOBJ_BODY, int(b)) for b in body]
    for i in range(CFG.n):
        m, d = scene.build_scene(hand.spec, gs["wrist_pose"][i])
        scene.set_channels(m, d, np.asarray(hand.coupling), gs["q"][i])
        ids = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, n) for n in names]
        centres = np.einsum("cij,ctj->cti", d.xmat[ids].reshape(-1, 3, 3), pos) + d.xpos[ids][:, None]
        off_skin = np.abs(np.linalg.norm(gs["contacts"][i][:, None] - centres, axis=-1) - rad).min(axis=1)
        assert off_skin.max() <= 1e-9


def test_svh_standoff_is_the_former_constant():
    assert sites.default_standoff(K.load_hand("svh")) == pytest.approx(0.05, abs=1e-12)
