"""A toy training set for the CVAE tests: a few small procedural objects at res 8, grasps with the palm on a ring
around each object facing its centre (so the pose is a learnable function of the shape plus a 1-D latent)."""

import numpy as np

from ffcgs_jax.dataset import mcap_io as dio
from ffcgs_jax.dataset import schema

RES = 8


def sphere_grid(radius: float, centre: np.ndarray, res: int) -> tuple[np.ndarray, np.ndarray, float]:
    """Closed-form Gradient-SDF of a sphere on a cube of side 4 * radius: (grid, origin, voxel size)."""
    h = 4 * radius / res
    origin = centre - h * (res - 1) / 2
    ijk = np.stack(np.meshgrid(*(np.arange(res),) * 3, indexing="ij"), -1)
    d = origin + h * ijk - centre
    r = np.linalg.norm(d, axis=-1, keepdims=True)
    return np.concatenate([r - radius, d / np.maximum(r, 1e-9)], -1).astype(np.float32), origin, h


def toy_pose(size: float, angle: float) -> np.ndarray:
    """Root origin at distance 1.5 * size on a horizontal ring around the sphere's centre, z axis pointing at it."""
    p = np.array([np.cos(angle), np.sin(angle), 0.0]) * 1.5 * size + np.array([0, 0, size])
    z = -p / np.linalg.norm(p)
    x = np.cross([0.0, 0.0, 1.0], z)
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    T[:3, 3] = p
    return T


def make_toy_dataset(path, n_objects: int = 5, grasps: int = 8, seed: int = 0, res: int = RES, hand: str | None = None,
                     channels: int = 9):
    rng = np.random.default_rng(seed)
    w = dio.DatasetWriter(path, {"toy": True, "seed": seed, **({"hand": hand} if hand else {})})
    for i in range(n_objects):
        size = 0.03 + 0.01 * i
        grid, origin, h = sphere_grid(size, np.array([0.0, 0.0, size]), res)
        poses = np.stack([toy_pose(size, a) for a in rng.uniform(0, 2 * np.pi, grasps)])
        noisy = poses.copy()
        noisy[:, :3, 3] += rng.normal(0, 0.002, (grasps, 3))
        z = np.zeros(grasps)
        w.add(schema.Record.create(object_name=f"toy{i}", mesh_sha256="0" * 64, rotation_index=0, rotation=np.eye(3),
                                split="train", grid=grid, origin=origin, voxel_size=h,
                                table_z=0.0, wrist_pose=poses, q=np.zeros((grasps, channels)), epsilon=z, E=z,
                                E_g=z, E_c=z, wrist_pose_noisy=noisy))
    return w.finish()
