"""The MuJoCo model of the physics test: the hand on a driven wrist, the object as a free body, the table.

- The hand's root body has a free joint welded (stiffly: `WELD_TIMECONST`) to a mocap body that carries the
  commanded wrist pose, with its weight compensated as an arm would; the channel servos (`PhysicsConfig.kp`)
  with the MJCF's coupling constraints (the SVH's 11, none on the Allegro) move the fingers.
- The object is a free body made of the convex parts of `convex.decompose`, with the mesh's centre of mass and
  inertia scaled to `mass` (or density x volume). Its frame is the mesh frame, so at qpos = identity it sits exactly
  where the grasps were planned.
- The table is the plane z = table_z (the mesh's lowest point by default, as in the Gradient-SDF).

Collision bits: hand geoms contype 2 / conaffinity 1 (no self-collision, as in the MJCF), object contype 1 /
conaffinity 2, table contype 1 / conaffinity 3, so hand-object, hand-table and object-table pairs collide.
Object and table geoms carry `friction`, `condim` and priority 1, so their values rule every contact they are in.

`dexgraspbench=True` builds DexGraspBench's scene instead (`dexgraspbench`): no-slip solver, every hand geom with
the benchmark's friction, condim and stiffer contacts, the object's geoms at priority 0 (MuJoCo mixes the two per
contact, as the benchmark's scene does) and the wrist weld at MuJoCo's default softness.
"""

import dataclasses

import mujoco
import numpy as np
import trimesh

from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.hand.spec import HandSpec
from ffcgs_jax.physics import dexgraspbench as dgb
from ffcgs_jax.physics.config import PhysicsConfig

ROLLING = 1e-4  # rolling friction (condim 6 only), MuJoCo's default
WELD_TIMECONST = 0.01  # s: how fast the wrist weld pulls the hand to its target (>= 2 timesteps for stability)
OBJECT_RGBA = (0.85, 0.55, 0.25, 1.0)
TABLE_RGBA = (0.72, 0.74, 0.78, 1.0)


def add_mesh_geom(s: mujoco.MjSpec, body, name: str, vertices: np.ndarray, faces: np.ndarray):
    """Add mesh `name` (float32 vertices, int32 faces) to spec `s` and a geom of it to `body`, coloured as the object,
    colliding with the hand (contype 1, conaffinity 2). The one place scenes (physics and pictures) add the object."""
    m = s.add_mesh()
    m.name = name
    m.uservert = np.asarray(vertices, np.float32).ravel()
    m.userface = np.asarray(faces, np.int32).ravel()
    g = body.add_geom()
    g.name, g.type, g.meshname = name, mujoco.mjtGeom.mjGEOM_MESH, name
    g.rgba, g.contype, g.conaffinity = OBJECT_RGBA, 1, 2
    return m, g


def add_table(s: mujoco.MjSpec, table_z: float, conaffinity: int, mocap: bool = False):
    """Add the table: the plane z = table_z, contype 1 (the hand and, with conaffinity 3, the object touch it).
    `mocap`: on a mocap body "table_mount" instead of the world body, so its height can differ per world and run
    (MuJoCo Warp computes the poses of world-body geoms once, when it makes its Data)."""
    parent = s.worldbody
    if mocap:
        parent = s.worldbody.add_body()
        parent.name, parent.mocap = "table_mount", True
    g = parent.add_geom()
    g.name, g.type, g.size, g.pos = "table", mujoco.mjtGeom.mjGEOM_PLANE, [0, 0, 0.01], [0, 0, table_z]
    g.rgba, g.contype, g.conaffinity = TABLE_RGBA, 1, conaffinity
    return g


@dataclasses.dataclass(frozen=True, eq=False)
class PhysicsScene:
    """A compiled physics model and the indices the protocols need.

    Attributes:
        model: the MjModel.
        coupling: (nq_hand, Q) channel-to-joint matrix, rows at `hand_qpos`.
        hand_qpos: (nq_hand,) qpos addresses of the coupled hand joints.
        obj_body, obj_qpos: the object's body id and its free joint's qpos address.
        root_body, root_qpos: the hand's root body id and its (welded) free joint's qpos address.
        obj_geoms, hand_geoms, palm_geoms: geom ids (palm: those of the root body).
        table_geom: the plane's geom id, or -1 when the scene has no table.
        hold_eq: id of the weld holding the object in place, or -1 when the scene has none.
        tip_sites: site ids of the fingertip contact points.
        lower, upper: (Q,) channel limits.
        mass: the object's mass, kg.
        dexgraspbench: DexGraspBench's scene (`build(..., dexgraspbench=True)`): `runner.prepare` then plans the
            benchmark's pre-grasp, grasp and squeeze.
    """

    model: mujoco.MjModel
    coupling: np.ndarray
    hand_qpos: np.ndarray
    obj_body: int
    obj_qpos: int
    root_body: int
    root_qpos: int
    obj_geoms: np.ndarray
    hand_geoms: np.ndarray
    palm_geoms: np.ndarray
    table_geom: int
    hold_eq: int
    tip_sites: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    mass: float
    dexgraspbench: bool = False


def build(spec: HandSpec, mesh: trimesh.Trimesh, parts: list[tuple[np.ndarray, np.ndarray]],
          cfg: PhysicsConfig = PhysicsConfig(), *, gravity: bool = True, table_z: float | None = None,
          hold: bool = False, dexgraspbench: bool = False, table_mocap: bool = False) -> PhysicsScene:
    """Compile the scene. `parts`: convex pieces from `convex.decompose(mesh)`; table_z None = no table;
    hold: add a weld of the object to the world (`hold_eq`) that the protocol switches on and off;
    dexgraspbench: DexGraspBench's contacts and solver (with the protocol's `settings(cfg)`, no gravity);
    table_mocap: the table on a mocap body (`add_table`), for the GPU worlds' model (`world_model`)."""
    s = mujoco.MjSpec.from_file(spec.mjcf_path)
    s.option.timestep = cfg.timestep
    s.option.cone = mujoco.mjtCone.mjCONE_ELLIPTIC if cfg.cone == "elliptic" else mujoco.mjtCone.mjCONE_PYRAMIDAL
    s.option.impratio = cfg.impratio
    s.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    s.option.gravity = [0.0, 0.0, -9.81 if gravity else 0.0]
    if dexgraspbench:
        s.option.noslip_iterations = dgb.NOSLIP_ITERATIONS
        for g in s.geoms:  # the hand's, before the object and table are added
            g.friction[:2] = [cfg.sim_friction, cfg.torsional]
            g.condim = cfg.condim
            g.solref[:2] = dgb.HAND_SOLREF
            g.solimp[:3] = dgb.HAND_SOLIMP
    root = s.body(spec.root_body)
    if root is None:
        raise FfcgsError(f"hand MJCF has no root body {spec.root_body!r}")
    actuators = tuple(a.name for a in s.actuators)
    if actuators != spec.channel_names:  # ctrl rows are channel vectors q
        raise FfcgsError(f"the physics test needs one actuator per channel of hand {spec.name!r}, named and ordered "
                         f"as its [channels] names {list(spec.channel_names)}; its MJCF has {list(actuators)}")
    # The wrist: a free joint welded to a mocap target. Moving a mocap body directly teleports the hand with zero
    # velocity, and MuJoCo's friction, which acts on velocities, then lets the object slide out frictionlessly.
    root.add_freejoint().name = "wrist"
    target = s.worldbody.add_body()
    target.name, target.mocap = "wrist_target", True
    # The weld keeps the root's pose relative to the target as it is in the compiled model: the target starts on the
    # root, so that relative pose is the identity (the SVH's root is the MJCF's origin; the Allegro's palm is turned
    # 90 degrees there, and a target at the origin would twist the hand away from every grasp).
    target.pos, target.quat = root.pos, root.quat
    weld = s.add_equality()
    weld.type, weld.objtype = mujoco.mjtEq.mjEQ_WELD, mujoco.mjtObj.mjOBJ_BODY
    weld.name1, weld.name2 = spec.root_body, "wrist_target"
    weld.solref = list(dgb.WELD_SOLREF) if dexgraspbench else [WELD_TIMECONST, 1.0]
    if dexgraspbench:  # anchor at the root's origin, relative pose from the compiled model, torquescale 1
        weld.data = [0.0] * 10 + [1.0] + [0.0] * (len(weld.data) - 11)
    _gravcomp(root)
    for a in s.actuators if cfg.kp > 0 else ():  # position servo: force = kp (ctrl - q)
        a.gainprm[0] = cfg.kp
        a.biasprm[1] = -cfg.kp

    body = s.worldbody.add_body()
    body.name = "object"
    body.add_freejoint()
    mass, com, inertia = _inertia(mesh, parts, cfg)
    body.explicitinertial = True
    body.mass, body.ipos, body.fullinertia = mass, com, inertia
    for i, (v, f) in enumerate(parts):
        m, g = add_mesh_geom(s, body, f"object_{i}", v, f)
        m.inertia = mujoco.mjtMeshInertia.mjMESH_INERTIA_SHELL  # the body's inertia is explicit; thin parts are fine
        _contact(g, cfg, priority=0 if dexgraspbench else 1)
    if hold:
        eq = s.add_equality()
        eq.type, eq.objtype, eq.name, eq.name1 = mujoco.mjtEq.mjEQ_WELD, mujoco.mjtObj.mjOBJ_BODY, "hold", "object"
        eq.solref = [WELD_TIMECONST, 1.0]  # as stiff as the wrist: at MuJoCo's 0.02 s closing fingers shove it 1-2 cm
    if table_z is not None:
        _contact(add_table(s, table_z, conaffinity=3, mocap=table_mocap), cfg)
    try:
        model = s.compile()
    except ValueError as e:
        raise FfcgsError(f"physics scene does not compile: {e}") from None

    def ids(kind, names):
        return np.array([mujoco.mj_name2id(model, kind, n) for n in names], np.int64)

    root_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, spec.root_body)
    obj_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "object")
    geom_body = model.geom_bodyid
    hand_bodies = _subtree(model, root_id)
    return PhysicsScene(
        model=model,
        coupling=np.asarray(spec.coupling, np.float64),
        hand_qpos=model.jnt_qposadr[ids(mujoco.mjtObj.mjOBJ_JOINT, spec.coupling_joints)],
        obj_body=obj_id,
        obj_qpos=int(model.jnt_qposadr[model.body_jntadr[obj_id]]),
        root_body=root_id,
        root_qpos=int(model.jnt_qposadr[model.body_jntadr[root_id]]),
        obj_geoms=np.flatnonzero(geom_body == obj_id),
        hand_geoms=np.flatnonzero(np.isin(geom_body, hand_bodies)),
        palm_geoms=np.flatnonzero(geom_body == root_id),
        table_geom=-1 if table_z is None else mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "table"),
        hold_eq=mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_EQUALITY, "hold") if hold else -1,
        tip_sites=ids(mujoco.mjtObj.mjOBJ_SITE, spec.contact_sites),
        lower=np.asarray(spec.lower, np.float64),
        upper=np.asarray(spec.upper, np.float64),
        mass=mass,
        dexgraspbench=dexgraspbench,
    )


def _gravcomp(body) -> None:
    """The arm carries the hand's weight, so the weld only answers to contacts."""
    body.gravcomp = 1.0
    for child in body.bodies:
        _gravcomp(child)


def _contact(g, cfg: PhysicsConfig, priority: int = 1) -> None:
    g.friction = [cfg.sim_friction, cfg.torsional, ROLLING]
    g.condim = cfg.condim
    g.priority = priority


def _subtree(model: mujoco.MjModel, root: int) -> np.ndarray:
    inside = np.zeros(model.nbody, bool)
    inside[root] = True
    for b in range(root + 1, model.nbody):  # MuJoCo numbers bodies depth-first, parents first
        inside[b] = inside[model.body_parentid[b]]
    return np.flatnonzero(inside)


def _inertia(mesh: trimesh.Trimesh, parts, cfg: PhysicsConfig) -> tuple[float, np.ndarray, np.ndarray]:
    """Mass, centre of mass and full inertia [xx, yy, zz, xy, xz, yz] about it, from the mesh if it is a closed
    volume, else from the union of the convex parts' hulls (overlaps counted twice: a small error for an inertia)."""
    solids = [mesh] if mesh.is_volume and mesh.volume > 0 else [trimesh.Trimesh(v, f).convex_hull for v, f in parts]
    volume = sum(float(m.volume) for m in solids)
    if not volume > 0:
        raise FfcgsError("the object has no volume: cannot give it a mass and inertia")
    mass = cfg.density * volume if cfg.density > 0 else cfg.mass
    com = sum(float(m.volume) * np.asarray(m.center_mass) for m in solids) / volume
    inertia = np.zeros((3, 3))
    for m in solids:  # parallel-axis shift of each solid's inertia (unit density) to the common centre
        r = np.asarray(m.center_mass) - com
        inertia += np.asarray(m.moment_inertia) + float(m.volume) * (r @ r * np.eye(3) - np.outer(r, r))
    inertia *= mass / volume
    return mass, com, np.array([inertia[0, 0], inertia[1, 1], inertia[2, 2], inertia[0, 1], inertia[0, 2],
                                inertia[1, 2]])
