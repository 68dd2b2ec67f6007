"""Messages of Foxglove's well-known schemas (`viz.foxglove_schemas`) for a grasp run: the object mesh, the table,
the hand's collision geoms, contact points and frame transforms, as JSON-ready dicts (host side, numpy + MuJoCo).

Every message carries every field of its schema (empty lists where there is nothing). Poses are 4x4 homogeneous
transforms in, `foxglove.Pose` (position + unit quaternion x, y, z, w) out; lengths in metres.

The hand is posed with MuJoCo's forward kinematics of the hand's own MJCF, its joints set from the channels through
the hand's coupling matrix and placed by its `root_inv`: exactly `hand.kinematics.forward_kinematics`, whose MJX
results tests/hand/test_kinematics.py checks against this MuJoCo path; here without compiling anything.
"""

import mujoco
import numpy as np
from scipy.spatial.transform import Rotation

from ffcgs_jax.physics.scene import OBJECT_RGBA, TABLE_RGBA

HAND_RGBA = (0.45, 0.6, 0.85, 1.0)  # a valid grasp's hand
INVALID_HAND_RGBA = (0.85, 0.45, 0.4, 1.0)
CONTACT_RGBA = (0.1, 0.75, 0.2, 1.0)
CONTACT_DIAMETER = 0.006  # m
TABLE_THICKNESS = 0.005  # m


def stamp(ns: int) -> dict:
    """A `time` {sec, nsec} from integer nanoseconds since the epoch."""
    ns = int(ns)
    return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


def vector(p) -> dict:
    x, y, z = (float(v) for v in p)
    return {"x": x, "y": y, "z": z}


def quaternion(R) -> dict:
    x, y, z, w = (float(v) for v in Rotation.from_matrix(np.asarray(R, np.float64)).as_quat())
    return {"x": x, "y": y, "z": z, "w": w}


def pose(T) -> dict:
    T = np.asarray(T, np.float64)
    return {"position": vector(T[:3, 3]), "orientation": quaternion(T[:3, :3])}


def color(rgba) -> dict:
    r, g, b, a = (float(v) for v in rgba)
    return {"r": r, "g": g, "b": b, "a": a}


def _translation(p) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = p
    return T


def cube(T, size, rgba) -> dict:
    return {"pose": pose(T), "size": vector(size), "color": color(rgba)}


def sphere(T, size, rgba) -> dict:
    return {"pose": pose(T), "size": vector(size), "color": color(rgba)}


def cylinder(T, size, rgba) -> dict:
    return {"pose": pose(T), "size": vector(size), "bottom_scale": 1.0, "top_scale": 1.0, "color": color(rgba)}


def triangles(vertices, faces, rgba, T=None) -> dict:
    """An indexed `TriangleListPrimitive` (vertices (V, 3), faces (F, 3) into them)."""
    v = np.asarray(vertices, np.float64).reshape(-1, 3)
    return {"pose": pose(np.eye(4) if T is None else T), "points": [vector(p) for p in v], "color": color(rgba),
            "colors": [], "indices": [int(i) for i in np.asarray(faces, np.int64).ravel()]}


def text(position, label: str, rgba=(0.1, 0.1, 0.1, 1.0), font_size: float = 14.0) -> dict:
    """A billboard label of `font_size` screen pixels."""
    return {"pose": pose(_translation(position)), "billboard": True, "font_size": float(font_size),
            "scale_invariant": True, "color": color(rgba), "text": label}


def entity(ns: int, frame_id: str, entity_id: str, *, frame_locked: bool = False, metadata: dict | None = None,
           **primitives: list) -> dict:
    """A `SceneEntity`; `primitives` by their field names (cubes=[...], spheres=[...], ...), the rest empty."""
    fields = ("arrows", "cubes", "spheres", "cylinders", "lines", "triangles", "texts", "models")
    unknown = set(primitives) - set(fields)
    if unknown:
        raise ValueError(f"unknown primitive field(s) {sorted(unknown)}; fields: {', '.join(fields)}")
    return {"timestamp": stamp(ns), "frame_id": frame_id, "id": entity_id, "lifetime": {"sec": 0, "nsec": 0},
            "frame_locked": frame_locked,
            "metadata": [{"key": str(k), "value": str(v)} for k, v in (metadata or {}).items()],
            **{f: list(primitives.get(f, ())) for f in fields}}


def scene_update(entities: list[dict]) -> dict:
    return {"deletions": [], "entities": list(entities)}


def frame_transform(ns: int, parent: str, child: str, T) -> dict:
    T = np.asarray(T, np.float64)
    return {"timestamp": stamp(ns), "parent_frame_id": parent, "child_frame_id": child,
            "translation": vector(T[:3, 3]), "rotation": quaternion(T[:3, :3])}


def object_entity(ns: int, mesh, frame_id: str = "object") -> dict:
    """The object's triangle mesh (a trimesh.Trimesh, in `frame_id`)."""
    return entity(ns, frame_id, "object", triangles=[triangles(mesh.vertices, mesh.faces, OBJECT_RGBA)],
                  metadata={"vertices": len(mesh.vertices), "faces": len(mesh.faces)})


def table_entity(ns: int, lo, hi, table_z: float, frame_id: str = "world") -> dict:
    """A thin slab whose top is the plane z = table_z, three times the xy extent of the box lo..hi."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    extent = 3 * max(float(np.max(hi[:2] - lo[:2])), 0.05)
    centre = [(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, table_z - TABLE_THICKNESS / 2]
    return entity(ns, frame_id, "table", cubes=[cube(_translation(centre), (extent, extent, TABLE_THICKNESS),
                                                     TABLE_RGBA)], metadata={"table_z": f"{table_z:.6f}"})


class HandGeometry:
    """The collision geoms of a hand (`hand.kinematics.Hand`) as Foxglove primitives, posed for channel values q
    in the hand's root (wrist) frame: put them in an entity whose frame is the wrist's.

    Boxes become cubes, spheres and ellipsoids spheres, cylinders cylinders, capsules a cylinder with a sphere on
    each end, mesh geoms triangle lists; the hand's collision geoms are the ones `hand.kinematics` uses (contype or
    conaffinity set, not on the world body)."""

    def __init__(self, hand):
        self.model = hand.spec.mj_model()
        self.data = mujoco.MjData(self.model)
        self.coupling = np.asarray(hand.coupling, np.float64)
        self.root_inv = np.asarray(hand.root_inv, np.float64)
        m = self.model
        self.geoms = [g for g in range(m.ngeom)
                      if m.geom_bodyid[g] != 0 and (m.geom_contype[g] or m.geom_conaffinity[g])]

    def _kinematics(self, q) -> None:
        self.data.qpos[:] = self.coupling @ np.asarray(q, np.float64)
        mujoco.mj_kinematics(self.model, self.data)

    def geom_poses(self, q) -> np.ndarray:
        """(G, 4, 4) poses of the collision geoms in the root frame."""
        self._kinematics(q)
        out = np.tile(np.eye(4), (len(self.geoms), 1, 1))
        out[:, :3, :3] = self.data.geom_xmat[self.geoms].reshape(-1, 3, 3)
        out[:, :3, 3] = self.data.geom_xpos[self.geoms]
        return self.root_inv @ out

    def site_positions(self, q, site_ids) -> np.ndarray:
        """(S, 3) positions of MuJoCo sites in the root frame (e.g. `Hand.contact_site_ids`)."""
        self._kinematics(q)
        p = self.data.site_xpos[list(site_ids)]
        return p @ self.root_inv[:3, :3].T + self.root_inv[:3, 3]

    def primitives(self, q, rgba=HAND_RGBA) -> dict[str, list]:
        """{"cubes", "spheres", "cylinders", "triangles"} of the hand at q, in the root frame."""
        m, T_all = self.model, self.geom_poses(q)
        out: dict[str, list] = {"cubes": [], "spheres": [], "cylinders": [], "triangles": []}
        for g, T in zip(self.geoms, T_all):
            kind, s = mujoco.mjtGeom(int(m.geom_type[g])), np.asarray(m.geom_size[g], np.float64)
            if kind == mujoco.mjtGeom.mjGEOM_BOX:
                out["cubes"].append(cube(T, 2 * s, rgba))
            elif kind == mujoco.mjtGeom.mjGEOM_SPHERE:
                out["spheres"].append(sphere(T, [2 * s[0]] * 3, rgba))
            elif kind == mujoco.mjtGeom.mjGEOM_ELLIPSOID:
                out["spheres"].append(sphere(T, 2 * s, rgba))
            elif kind == mujoco.mjtGeom.mjGEOM_CYLINDER:
                out["cylinders"].append(cylinder(T, (2 * s[0], 2 * s[0], 2 * s[1]), rgba))
            elif kind == mujoco.mjtGeom.mjGEOM_CAPSULE:
                out["cylinders"].append(cylinder(T, (2 * s[0], 2 * s[0], 2 * s[1]), rgba))
                for end in (-1, 1):
                    out["spheres"].append(sphere(T @ _translation([0, 0, end * s[1]]), [2 * s[0]] * 3, rgba))
            elif kind == mujoco.mjtGeom.mjGEOM_MESH and m.geom_dataid[g] >= 0:
                k = m.geom_dataid[g]
                va, vn, fa, fn = m.mesh_vertadr[k], m.mesh_vertnum[k], m.mesh_faceadr[k], m.mesh_facenum[k]
                out["triangles"].append(triangles(m.mesh_vert[va:va + vn], m.mesh_face[fa:fa + fn], rgba, T))
        return out


def contact_spheres(points, rgba=CONTACT_RGBA, diameter: float = CONTACT_DIAMETER) -> list[dict]:
    return [sphere(_translation(p), [diameter] * 3, rgba) for p in np.asarray(points, np.float64).reshape(-1, 3)]
