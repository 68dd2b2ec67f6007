"""Hand sites in the hand's root frame at q = 0, on the host: the palm centre that places sampled poses, and the
palm tetrahedron of the CVAE's pose loss."""

import mujoco
import numpy as np

from ffcgs_jax.hand.kinematics import Hand


def root_frame_sites(hand: Hand, site_ids) -> np.ndarray:
    """Positions of MuJoCo sites at q = 0 in the hand's root frame, host NumPy (len(site_ids), 3).

    Computed with MuJoCo C on the host: one call at sampler construction, where tracing MJX would cost seconds.
    """
    m = hand.spec.mj_model()
    d = mujoco.MjData(m)
    d.qpos[:] = 0.0  # q = 0, as the FK's qpos = coupling @ q
    mujoco.mj_kinematics(m, d)
    root_inv = np.asarray(hand.root_inv, np.float64)
    return d.site_xpos[np.asarray(site_ids)] @ root_inv[:3, :3].T + root_inv[:3, 3]


def palm_centre_root(hand: Hand) -> np.ndarray:
    """The palm centre (the palm site at q = 0) in the hand's root frame, host NumPy (3,)."""
    return root_frame_sites(hand, [hand.palm_site_id])[0]


def tetrahedron_root(hand: Hand) -> np.ndarray:
    """The 4 palm-tetrahedron sites (the sampler's pose loss) in the hand's root frame, host NumPy (4, 3)."""
    return root_frame_sites(hand, list(hand.tetrahedron_site_ids))
