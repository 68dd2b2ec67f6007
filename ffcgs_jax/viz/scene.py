"""MuJoCo scenes (host side): the hand's MJCF plus an object mesh and the table, for pictures and physics.

The hand's root body is placed at the wrist pose and its joints set from the channels, so a scene shows exactly
what `hand.kinematics.forward_kinematics` computes.
"""

import mujoco
import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from ffcgs_jax.hand.spec import HandSpec
from ffcgs_jax.physics.scene import add_mesh_geom, add_table


def build_scene(
    spec: HandSpec,
    wrist_pose: np.ndarray,
    obj: trimesh.Trimesh | None = None,
    table_z: float | None = None,
) -> tuple[mujoco.MjModel, mujoco.MjData]:
    """Hand at `wrist_pose` (4x4, world <- root body), optional object mesh (world frame) and table plane z.

    Object and table get contype=1, conaffinity=2, so they collide with the hand (contype=2, conaffinity=1)
    but not with each other through that pair; physics scenes add their own settings later.
    """
    s = mujoco.MjSpec.from_file(spec.mjcf_path)
    root = s.body(spec.root_body)
    root.pos = wrist_pose[:3, 3]
    x, y, z, w = Rotation.from_matrix(wrist_pose[:3, :3]).as_quat()
    root.quat = [w, x, y, z]
    if obj is not None:
        add_mesh_geom(s, s.worldbody, "object", obj.vertices, obj.faces)
    if table_z is not None:
        add_table(s, table_z, conaffinity=2)
    m = s.compile()
    return m, mujoco.MjData(m)


def set_channels(m: mujoco.MjModel, d: mujoco.MjData, coupling: np.ndarray, q: np.ndarray) -> None:
    """Set the hand's joints from channel values (coupling: (nq_hand, Q) as in `Hand.coupling`) and run kinematics."""
    d.qpos[: coupling.shape[0]] = coupling @ q
    mujoco.mj_kinematics(m, d)


def default_wrist_pose(
    obj: trimesh.Trimesh, palm_center: np.ndarray, palm_normal: np.ndarray, standoff: float = 0.03
) -> np.ndarray:
    """A top-down pose for pictures: the palm faces down (-z) from `standoff` metres above the object's top.

    The hand is turned by the smallest rotation that takes its palm normal (root frame) to -z, then a quarter
    turn about z; the palm centre
    (root frame) is put above the centre of the object's bounding box. A viewing default, not a grasp sampler.
    """
    lo, hi = obj.bounds
    R, _ = Rotation.align_vectors([[0.0, 0.0, -1.0]], [palm_normal])
    T = np.eye(4)
    # then a quarter turn about z, so the default front camera (looking along +y) sees the hand side-on
    T[:3, :3] = Rotation.from_euler("z", -np.pi / 2).as_matrix() @ R.as_matrix()
    target = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, hi[2] + standoff])
    T[:3, 3] = target - T[:3, :3] @ palm_center
    return T
