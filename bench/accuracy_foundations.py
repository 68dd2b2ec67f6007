"""Accuracy of the foundations, in float64: MJX FK vs MuJoCo C, fingertips vs the SVH table, SDF vs trimesh.

    python bench/accuracy_foundations.py [--ycb ../shared/objects/ycb] [--configs 1000] [--points 2000]

The SDF part uses the YCB test split (sorted files at index % 5 == 4) and reports, per object and resolution, the
error of `geometry.sdf.query` against trimesh's exact signed distance at points within 2 cm of the surface, in voxels.
"""

import argparse
import json
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402
import trimesh  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from ffcgs_jax.geometry import sdf  # noqa: E402
from ffcgs_jax.geometry.config import SDFConfig  # noqa: E402
from ffcgs_jax.hand import kinematics as K  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def fk_error(n: int) -> float:
    hand = K.load_hand("svh")
    rng = np.random.default_rng(0)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.random(n, random_state=rng).as_matrix()
    T[:, :3, 3] = rng.uniform(-0.5, 0.5, (n, 3))
    q = rng.uniform(hand.lower, hand.upper, (n, 9))
    fr = jax.jit(K.forward_kinematics_batch)(hand, jnp.asarray(T), jnp.asarray(q))
    m = hand.spec.mj_model()
    d = mujoco.MjData(m)
    worst = 0.0
    for i in range(n):
        m.body_pos[1] = T[i, :3, 3]
        quat = np.zeros(4)
        mujoco.mju_mat2Quat(quat, T[i, :3, :3].ravel())
        m.body_quat[1] = quat
        d.qpos[:] = np.asarray(hand.coupling) @ q[i]
        mujoco.mj_kinematics(m, d)
        worst = max(worst, np.abs(np.asarray(fr.contacts[i]) - d.site_xpos[list(hand.contact_site_ids)]).max(),
                    np.abs(np.asarray(fr.geom_pos[i]) - d.geom_xpos).max())
    return worst


def table_error() -> dict[str, float]:
    hand = K.load_hand("svh")
    cases = json.loads((REPO / "tests" / "data" / "svh_reference_fk.json").read_text())["cases"]
    out = {}
    for c in cases:
        if c["j5_fixed"]:
            continue
        q = jnp.array([c["channels"][n] for n in hand.spec.channel_names])
        tips = np.asarray(jax.jit(K.contact_points)(hand, jnp.eye(4), q))
        ref = np.array([c["contact_points"][f] for f in ("thumb", "index", "middle", "ring", "little")])
        out[c["name"]] = float(np.abs(tips - ref).max())
    return out


def sdf_errors(ycb: Path, n_points: int, resolutions=(32, 64)):
    files = sorted(ycb.glob("*.stl"))
    test = [f for i, f in enumerate(files) if i % 5 == 4]
    q = jax.jit(sdf.query)
    rows = []
    for f in test:
        mesh = trimesh.load(f)
        rng = np.random.default_rng(0)
        pts, face = trimesh.sample.sample_surface(mesh, n_points, seed=1)
        pts = pts + mesh.face_normals[face] * rng.uniform(-0.02, 0.02, (n_points, 1))
        ref = -trimesh.proximity.signed_distance(mesh, pts)
        for r in resolutions:
            s = sdf.build_sdf(mesh, SDFConfig(res=r))
            h = float(s.voxel_size)
            err = np.abs(np.asarray(q(s, jnp.asarray(pts))[0]) - ref)
            rows.append((f.stem, r, h * 1000, err.mean() * 1000, np.quantile(err, 0.99) / h, err.max() / h,
                         np.mean(err < 0.5 * h)))
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ycb", default=str(REPO.parent / "shared" / "objects" / "ycb"))
    ap.add_argument("--configs", type=int, default=1000)
    ap.add_argument("--points", type=int, default=2000)
    args = ap.parse_args()
    print(f"MJX FK vs MuJoCo C (float64), {args.configs} random wrist poses and configurations: "
          f"max |error| = {fk_error(args.configs):.2e} m")
    for name, e in table_error().items():
        print(f"fingertips vs shared/svh table, case {name}: max |error| = {e * 1000:.4f} mm")
    print()
    print("| object | res | voxel (mm) | mean err (mm) | p99 err (voxel) | max err (voxel) | < 0.5 voxel |")
    print("|---|---|---|---|---|---|---|")
    for name, r, h, mean, p99, mx, frac in sdf_errors(Path(args.ycb), args.points):
        print(f"| {name} | {r} | {h:.2f} | {mean:.3f} | {p99:.3f} | {mx:.3f} | {frac:.2%} |")


if __name__ == "__main__":
    main()
