"""One MuJoCo model for the worlds of many objects: a template scene with empty object slots, and each object's
rows of the model fields that differ between objects.

Why slots and per-world fields, not objects placed apart in one model: with objects side by side every world would
carry every object as a free body (nv and the constraint solver grow with the batch) and every object's geoms
(kinematics and broadphase grow with it), while a world needs one. MuJoCo Warp indexes its geom, body and dof
fields by world (`Model` fields whose shape starts with "*") and skips a mesh geom whose `geom_dataid` is -1 in a
world, so a world of object k is the template with object k's parts in its first slots and the rest switched off:
the same scene as object k's own (`scene.build`), and a world never sees another object.

- `template(spec, cfg, kind, slots)`: the scene `scene.build` makes, with an object of `slots` placeholder parts.
  Kind "ours" holds the table (on a mocap body: the second mocap, after the wrist's) and the hold weld (lift-shake
  and six-dir worlds share it: gravity, the table's height and the weld are set per world); kind "dexgraspbench" is DexGraspBench's scene (no table, no weld,
  its own contacts and no-slip solver), so the two never share a launch.
- `object_rows(scene)`: what object k's worlds need, read from its own compiled scene (`runner.scenes`): its
  meshes, its part geoms' frames and bounds, its body's mass and inertia and the weights MuJoCo derives from them.
- `MeshPool`: the meshes of every object so far, appended after the template's own (hand meshes and the
  placeholder), in MuJoCo's layout.

Left out, on purpose: `stat.meaninertia` (one number per model, which scales the solver's tolerance) stays the
template's; an object's own scene has its own. It moves the solver's stopping point, not the physics.
"""

import dataclasses

import mujoco
import numpy as np
import trimesh

from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.hand.spec import HandSpec
from ffcgs_jax.physics import protocols
from ffcgs_jax.physics import scene as physics_scene
from ffcgs_jax.physics.config import PhysicsConfig
from ffcgs_jax.physics.scene import PhysicsScene

KINDS = protocols.KINDS  # the scenes protocols run on
# mesh fields in MuJoCo's layout: per mesh (nmesh, ...) with the address fields that point into a flat array, and
# the flat arrays themselves; indices stored inside the flat arrays (faces, graph, polygon vertices and maps) are
# local to their mesh, so appending a mesh shifts only the addresses
PER_MESH = ("vertnum", "normalnum", "pos", "quat", "polynum")
ADDRESSES = {"vertadr": "vert", "faceadr": "face", "normaladr": "normal", "graphadr": "graph", "polyadr": "polynormal"}
PER_POLY = ("polynormal", "polyvertadr", "polyvertnum")
FLAT = ("vert", "face", "normal", "graph", "polyvert", "polymap")
PER_VERT = ("polymapadr", "polymapnum")


def _placeholder() -> tuple[trimesh.Trimesh, tuple[np.ndarray, np.ndarray]]:
    """A box off the origin and turned: its body's centre of mass is off the body frame and its principal axes are
    not the frame's, so MuJoCo compiles the object body as a general one (`body_simple` 0) whose free joint couples
    all six dofs in the mass matrix. A centred, aligned placeholder compiles as a "simple" body, and MuJoCo Warp
    would then drop the coupling terms every real object has (its sparsity pattern is fixed at `put_model`)."""
    box = trimesh.creation.box((0.01, 0.02, 0.03))
    box.apply_transform(trimesh.transformations.rotation_matrix(0.7, (1.0, 2.0, 3.0)))
    box.apply_translation((0.005, -0.004, 0.003))
    return box, (np.asarray(box.vertices, np.float32), np.asarray(box.faces, np.int32))


def template(spec: HandSpec, cfg: PhysicsConfig, kind: str, slots: int) -> PhysicsScene:
    """The scene of `kind` (`KINDS`) with an object of `slots` placeholder parts; `cfg` as the objects' scenes were
    built with (a protocol's `settings(cfg)`)."""
    if kind not in KINDS:
        raise FfcgsError(f"unknown world model kind {kind!r}; kinds: {', '.join(KINDS)}")
    box, part = _placeholder()
    if kind == "dexgraspbench":
        out = physics_scene.build(spec, box, [part] * slots, cfg, gravity=False, dexgraspbench=True)
    else:
        out = physics_scene.build(spec, box, [part] * slots, cfg, gravity=True, table_z=0.0, hold=True,
                                  table_mocap=True)
    if out.model.body_simple[out.obj_body] != 0:
        raise FfcgsError("the world model's object compiled as a simple body: its mass matrix would drop terms")
    return out


@dataclasses.dataclass(frozen=True)
class ObjectRows:
    """One object's part of the world model: `meshes` (MuJoCo's mesh fields of its parts, addresses relative to its
    own first mesh), per part (P, ...) geom rows, its body rows, the six free-joint dofs' invweight0, the table's
    height (NaN: its scenes have none) and its mass."""

    meshes: dict[str, np.ndarray]
    geom: dict[str, np.ndarray]
    body: dict[str, np.ndarray | float]  # mass and subtree mass are scalars
    dof_invweight0: np.ndarray
    table_z: float
    mass: float
    friction: np.ndarray  # (3,) the object's geoms' sliding, torsional and rolling friction

    @property
    def parts(self) -> int:
        return len(self.geom["dataid"])


def object_rows(scene: PhysicsScene) -> ObjectRows:
    """`ObjectRows` of the object of `scene` (a scene of `scene.build`)."""
    m = scene.model
    geoms = np.asarray(scene.obj_geoms)
    ids = m.geom_dataid[geoms]
    if (m.geom_type[geoms] != mujoco.mjtGeom.mjGEOM_MESH).any() or (ids < 0).any():
        raise FfcgsError("the world model needs every object part as a mesh geom")
    first, count = int(ids.min()), len(geoms)
    if not np.array_equal(np.sort(ids), np.arange(first, first + count)):
        raise FfcgsError("the object's meshes are not consecutive in its scene")
    meshes = _mesh_slice(m, first, count)
    geom = dict(dataid=(ids - first).astype(np.int32), pos=m.geom_pos[geoms], quat=m.geom_quat[geoms],
                size=m.geom_size[geoms], aabb=m.geom_aabb[geoms].reshape(-1, 2, 3), rbound=m.geom_rbound[geoms])
    b = scene.obj_body
    body = dict(mass=m.body_mass[b], ipos=m.body_ipos[b], iquat=m.body_iquat[b], inertia=m.body_inertia[b],
                invweight0=m.body_invweight0[b], subtreemass=m.body_subtreemass[b])
    dof = m.jnt_dofadr[m.body_jntadr[b]]
    table = float(m.geom_pos[scene.table_geom, 2]) if scene.table_geom >= 0 else float("nan")
    friction = m.geom_friction[geoms[0]].copy()  # every part's (`scene.build`), and the table's
    return ObjectRows(meshes, geom, body, m.dof_invweight0[dof: dof + 6].copy(), table, float(scene.mass), friction)


# what differs per world rather than per engine: an object's friction, mass and geometry (robust trials vary them)
PER_WORLD = ("sim_friction", "mass", "density", "collision", "voxel_cells", "voxel_tol", "coacd_threshold",
             "hull_vertices", "collision_budget", "robust")


def engine_config(cfg: PhysicsConfig) -> PhysicsConfig:
    """`cfg` with the per-world fields (`PER_WORLD`) at their defaults: what an engine is built and keyed by."""
    base = PhysicsConfig()
    return dataclasses.replace(cfg, **{f: getattr(base, f) for f in PER_WORLD})


def _mesh_slice(m: mujoco.MjModel, first: int, count: int) -> dict[str, np.ndarray]:
    """Meshes first .. first+count-1 of `m` as a stand-alone set: per-mesh and flat arrays, addresses from 0."""
    sel = slice(first, first + count)
    out = {f: np.array(getattr(m, f"mesh_{f}")[sel]) for f in PER_MESH}
    ends = {}
    for adr, flat in ADDRESSES.items():
        a = np.array(getattr(m, f"mesh_{adr}")[sel], np.int64)
        ends[flat] = _segment(np.asarray(getattr(m, f"mesh_{adr}"), np.int64), first, count,
                              len(getattr(m, f"mesh_{flat}")))
        out[adr] = np.where(a >= 0, a - ends[flat][0], -1)
    vstart, vstop = ends["vert"]
    pstart, pstop = ends["polynormal"]
    out["vert"] = np.array(m.mesh_vert[vstart:vstop])
    out["face"] = np.array(m.mesh_face[slice(*ends["face"])])
    out["normal"] = np.array(m.mesh_normal[slice(*ends["normal"])])
    out["graph"] = np.array(m.mesh_graph[slice(*ends["graph"])])
    for f in PER_POLY:
        out[f] = np.array(getattr(m, f"mesh_{f}")[pstart:pstop])
    for f in PER_VERT:
        out[f] = np.array(getattr(m, f"mesh_{f}")[vstart:vstop])
    # the polygon vertex and map lists: flat arrays addressed by polyvertadr and polymapadr
    pv0 = int(out["polyvertadr"].min()) if len(out["polyvertadr"]) else 0
    pv1 = int((out["polyvertadr"] + out["polyvertnum"]).max()) if len(out["polyvertadr"]) else 0
    out["polyvert"] = np.array(m.mesh_polyvert[pv0:pv1])
    out["polyvertadr"] = out["polyvertadr"] - pv0
    pm0 = int(out["polymapadr"].min()) if len(out["polymapadr"]) else 0
    pm1 = int((out["polymapadr"] + out["polymapnum"]).max()) if len(out["polymapadr"]) else 0
    out["polymap"] = np.array(m.mesh_polymap[pm0:pm1])
    out["polymapadr"] = out["polymapadr"] - pm0
    return out


def _segment(adr: np.ndarray, first: int, count: int, total: int) -> tuple[int, int]:
    """[start, stop) of the flat array that meshes first .. first+count-1 use, from the address field `adr`
    (-1: the mesh has no entry there): MuJoCo stores meshes' entries in mesh order, so a range of meshes owns
    everything from its first address to the next mesh's."""
    own = adr[first: first + count]
    after = adr[first + count:]
    start = int(own[own >= 0].min()) if (own >= 0).any() else 0
    stop = int(after[after >= 0].min()) if (after >= 0).any() else total
    return (start, stop) if (own >= 0).any() else (0, 0)


class MeshPool:
    """The meshes of a world model: the template's own, then each added object's, in MuJoCo's layout (`arrays`)."""

    def __init__(self, template_model: mujoco.MjModel):
        base = _mesh_slice(template_model, 0, template_model.nmesh) if template_model.nmesh else None
        self._parts: list[dict[str, np.ndarray]] = [base] if base is not None else []
        self.nmesh = int(template_model.nmesh)

    def add(self, meshes: dict[str, np.ndarray]) -> int:
        """Append an object's meshes (`ObjectRows.meshes`); returns the pool index of its first mesh."""
        first = self.nmesh
        self._parts.append(meshes)
        self.nmesh += len(meshes["vertnum"])
        return first

    def arrays(self) -> dict[str, np.ndarray]:
        """Every mesh field (`mesh_<name>` in MuJoCo) over the pool, addresses made absolute."""
        out: dict[str, list] = {f: [] for f in (*PER_MESH, *ADDRESSES, *PER_POLY, *FLAT, *PER_VERT)}
        off = dict.fromkeys(("vert", "face", "normal", "graph", "polynormal", "polyvert", "polymap"), 0)
        for p in self._parts:
            for f in PER_MESH:
                out[f].append(p[f])
            for adr, flat in ADDRESSES.items():
                out[adr].append(np.where(p[adr] >= 0, p[adr] + off[flat], -1))
            out["polynormal"].append(p["polynormal"])
            out["polyvertadr"].append(p["polyvertadr"] + off["polyvert"])
            out["polyvertnum"].append(p["polyvertnum"])
            out["polymapadr"].append(p["polymapadr"] + off["polymap"])
            out["polymapnum"].append(p["polymapnum"])
            for f in FLAT:
                out[f].append(p[f])
            for f in off:
                off[f] += len(p[f])
        return {f: np.concatenate(v) if v else np.zeros(0) for f, v in out.items()}


def check_same_hand(template_scene: PhysicsScene, scene: PhysicsScene) -> None:
    """Refuse an object scene whose hand, joints or options differ from the template's (one line)."""
    a, b = template_scene.model, scene.model
    ha, hb = template_scene.hand_geoms, scene.hand_geoms  # ids shift with the table, a world geom numbered first
    same = (a.nq == b.nq and a.nv == b.nv and a.nu == b.nu and len(ha) == len(hb)
            and np.array_equal(a.geom_type[ha], b.geom_type[hb]) and np.allclose(a.geom_size[ha], b.geom_size[hb])
            and a.opt.timestep == b.opt.timestep and a.opt.noslip_iterations == b.opt.noslip_iterations)
    if not same:
        raise FfcgsError("an object's physics scene differs from its world model's (hand, joints or solver): "
                         "objects of one GPU launch need one hand and one physics config")


def kind_of(scene: PhysicsScene) -> str:
    return "dexgraspbench" if scene.dexgraspbench else "ours"


def protocol_kind(protocol: str) -> str:
    return protocols.get(protocol).kind
