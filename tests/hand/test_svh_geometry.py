"""The SVH collision primitives against the (GPL-derived, not shipped) link meshes in shared/svh/meshes."""


import mujoco
import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from ffcgs_jax.hand.spec import load_spec

from paths import SHARED

MESHES = SHARED / "svh" / "meshes"
# Links merged into their parent body (behind fixed joints), with their pose there (shared/svh joint table).
FOLDED = {
    "e1": (np.eye(3), np.array([0.0, -0.01313, 0.0])),
    "virtual_k": (Rotation.from_euler("xyz", [0.0, -1.5707, 1.5707]).as_matrix(), np.array([0.0, -0.01313, 0.11])),
}
# Capsules round off the corners of the box-like middle phalanges, so a few vertices there lie 2-5 mm outside.
COVER_TOL = 0.003  # m: a mesh vertex this close to a primitive counts as covered
MIN_COVERED = 0.93  # fraction of each link's mesh vertices within COVER_TOL
ALL_COVER_TOL = 0.005  # m: every mesh vertex lies this close to a primitive
MAX_PROUD = 0.006  # m: how far a primitive may stand out beyond its link's mesh bounding box


def _dist_to_geom(m, g, p):
    """Distance from points p (body frame) to geom g (<= 0 inside)."""
    R = np.zeros(9)
    mujoco.mju_quat2Mat(R, m.geom_quat[g])
    local = (p - m.geom_pos[g]) @ R.reshape(3, 3)
    size = m.geom_size[g]
    if m.geom_type[g] == mujoco.mjtGeom.mjGEOM_BOX:
        q = np.abs(local) - size
        return np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(1), 0)
    z = np.clip(local[:, 2], -size[1], size[1])
    return np.linalg.norm(local - np.stack([0 * z, 0 * z, z], 1), axis=1) - size[0]


@pytest.mark.skipif(not MESHES.is_dir(), reason="shared/svh/meshes not present")
def test_primitives_cover_link_meshes():
    m = load_spec("svh").mj_model()
    names = [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, g) for g in range(m.ngeom)]
    checked = 0
    for stl in sorted(MESHES.glob("*.stl")):
        link = stl.stem
        geoms = [g for g, n in enumerate(names) if n == link or (n or "").startswith(link + "_")]
        assert geoms, f"no collision geom for link {link}"
        R, t = FOLDED.get(link, (np.eye(3), np.zeros(3)))
        v = trimesh.load(stl).vertices @ R.T + t
        d = np.min([_dist_to_geom(m, g, v) for g in geoms], axis=0)
        covered = (d <= COVER_TOL).mean()
        assert covered >= MIN_COVERED, f"{link}: only {covered:.1%} of mesh vertices covered"
        assert d.max() <= ALL_COVER_TOL, f"{link}: a vertex lies {d.max() * 1000:.1f} mm outside the primitives"
        lo, hi = v.min(0), v.max(0)
        for g in geoms:  # no primitive sticks far out of its link's mesh box
            aabb_c, aabb_h = m.geom_aabb[g, :3], m.geom_aabb[g, 3:]
            R = np.zeros(9)
            mujoco.mju_quat2Mat(R, m.geom_quat[g])
            corners = (aabb_c + aabb_h * np.array(np.meshgrid(*[[-1, 1]] * 3)).reshape(3, -1).T) @ R.reshape(3, 3).T
            corners += m.geom_pos[g]
            proud = np.maximum(corners - hi, lo - corners).max()
            assert proud <= MAX_PROUD, f"{names[g]} stands {proud * 1000:.1f} mm outside its mesh"
        checked += 1
    assert checked == 23
