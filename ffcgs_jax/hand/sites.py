"""Hand sites in the hand's root frame of the open hand, on the host: the palm centre that places sampled poses,
the palm tetrahedron of the CVAE's pose loss, and the geometric sampler's standoff derived from the hand."""

import math

import cachetools
import mujoco
import numpy as np

from ffcgs_jax.hand.kinematics import Hand, open_qpos
from ffcgs_jax.runtime import compiled


def root_frame_sites(hand: Hand, site_ids) -> np.ndarray:
    """Positions of MuJoCo sites of the open hand (`kinematics.open_qpos`) in the hand's root frame, host NumPy
    (len(site_ids), 3).

    Computed with MuJoCo C on the host: one call at sampler construction, where tracing MJX would cost seconds.
    """
    m = hand.spec.mj_model()
    d = mujoco.MjData(m)
    d.qpos[:] = open_qpos(np.asarray(hand.coupling), hand.spec)
    mujoco.mj_kinematics(m, d)
    root_inv = np.asarray(hand.root_inv, np.float64)
    return d.site_xpos[np.asarray(site_ids)] @ root_inv[:3, :3].T + root_inv[:3, 3]


def palm_centre_root(hand: Hand) -> np.ndarray:
    """The palm centre (the palm site at q = 0) in the hand's root frame, host NumPy (3,)."""
    return root_frame_sites(hand, [hand.palm_site_id])[0]


def tetrahedron_root(hand: Hand) -> np.ndarray:
    """The 4 palm-tetrahedron sites (the sampler's pose loss) in the hand's root frame, host NumPy (4, 3)."""
    return root_frame_sites(hand, list(hand.tetrahedron_site_ids))


STANDOFF_STEP = 0.005  # m: standoffs are whole multiples of this


def open_hand_reach(hand: Hand) -> float:
    """How far in front of the palm centre, along the palm normal, the open hand's collision geometry reaches: its
    farthest collision-box corner (metres; `Hand.box_vertices`, the pose filter's points)."""
    n = np.asarray(hand.palm_normal, np.float64)
    return float(((np.asarray(hand.box_vertices, np.float64) - palm_centre_root(hand)) @ n).max())


_STANDOFFS = cachetools.LRUCache(8)  # per HandSpec: finding the reach compiles the MJCF; a few hands a process
compiled.register("hand.sites standoffs", _STANDOFFS)


def default_standoff(hand: Hand) -> float:
    """The geometric sampler's standoff for `hand`: `open_hand_reach` rounded up to the next 5 mm (5 mm at least),
    so the open hand clears a flat face it is placed over. The SVH: its thumb's proximal link reaches 4.51 cm, so 5 cm (the
    value chosen on the built-in box before it was derived: candidates passing the box-corner filter rose from
    26 % at 4-4.5 cm to 34 % at 5 cm and stayed there)."""
    if hand.spec not in _STANDOFFS:
        steps = max(1, math.ceil(open_hand_reach(hand) / STANDOFF_STEP - 1e-9))  # a flat hand still keeps 5 mm
        _STANDOFFS[hand.spec] = STANDOFF_STEP * steps
    return _STANDOFFS[hand.spec]
