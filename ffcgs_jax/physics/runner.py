"""The physics test: do the synthesised grasps hold the object in MuJoCo?

Execution of one grasp (all grasps of a batch in parallel):

1. The hand is put at the grasp's wrist pose with the fingers at q_open + (1 - open_fraction) (q - q_open), on the
   straight channel path from the open hand (q_open: q = 0 clamped into the limits, which the synthesis filters
   checked against the object and the table) to q.
   If the hand then reaches deeper than `max_initial_penetration` into the object at q, the grasp fails
   ("penetration") without simulating.
2. Close (six-dir: with the floating object welded in place, as the table holds it in lift-shake, so the first
   finger to arrive does not push it away; the weld is released when the test starts): the servo targets ramp
   linearly, over `close_time`, to q plus a squeeze: `squeeze` radians along
   sum_i J_i^T (-n_i) over the fingertips within `contact_band` of the surface (J_i the tip's channel Jacobian,
   n_i the mesh's outward normal there). The servos end up pressing with about kp x squeeze. Then `settle_time`.
3. Test, by protocol:
   - `lift-shake` (the paper's real-robot test, Table III): gravity on, object on the table. The wrist rises
     `lift_height` with a cosine velocity profile at mean `lift_speed`, then moves +-`shake_amplitude` along world
     x for `shake_cycles` sine cycles at mean `shake_speed`. Success: the object's position in the palm frame
     moved less than `max_slip` from the end of closing, and it does not touch the table.
   - `six-dir` (DexGraspBench): gravity off, no table. From the closed state, a force `accel` x mass along +x, -x,
     +y, -y, +z, -z (world) in turn, each for `push_time` from the same closed state. Success: in every direction
     the object moves less than `max_move` and turns less than `max_rot_deg` (largest over the push, sampled every
     `backend.CHUNK` steps and at its end).

DexGraspBench's MuJoCo test (`dexgraspbench`, `dexgraspbench-bodex`; `dexgraspbench` describes it and how it
differs from the benchmark's code) has its own scene and execution: gravity off, the hand from a pre-grasp through
the grasp to a squeeze, then 10 x mass along each of the six directions for 2 s; < 5 cm and < 15 degrees.

Failure modes are recorded per grasp (`reason`, an index into `protocols.REASONS`): penetration; lost (no hand
contact left: dropped or pushed out while closing); slip (still touched but moved past the bound); unstable (the
simulation diverged: MuJoCo warned and stopped the trial (bad qpos, qvel or qacc, contact or constraint buffer
full), or its state turned non-finite or ran away (`backend.diverged`); its move and rot are NaN, and it never
passes). MuJoCo's warning text goes to the logger "ffcgs_jax.physics" at debug level, not to stderr or a
MUJOCO_LOG.TXT in the working folder (`backend.route_mujoco_warnings`). A grasp stops being simulated as soon as its
failure is certain (`protocols.run_protocol`: penetration at the start, dropped during lift-shake, past a bound in
a six-dir push); the outcomes are those of simulating every grasp to the end (tested, and identical on 271 grasps).

Poses the hand cannot reach the object from are refused before anything is simulated (`check_reach`): a wrist
farther from the mesh's bounding box than the hand's reach (`hand_reach`) plus `REACH_MARGIN`. Such a pose is a
wrong input (millimetres for metres, another frame), never a grasp to score, so the whole call is refused with one
line naming how many there are and the first.

The simulator (`PhysicsConfig.backend`, `resolve_backend`) is CPU MuJoCo through `mujoco.rollout` (threads across
grasps, no Python per step) or MuJoCo Warp (`worlds`: every grasp, protocol, push direction and object of a call
as the worlds of the same launches on a CUDA GPU); MJX
(`backend_mjx`) runs the same plan, slowly. The protocols and success
rules are in `protocols`, the backends' interface in `backend`.
"""

import collections
import dataclasses
import os
import time
import warnings
from collections.abc import Callable, Iterable

import mujoco
import numpy as np
import trimesh

from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.hand.spec import HandSpec
from ffcgs_jax.physics import convex
from ffcgs_jax.physics import protocols as physics_protocols
from ffcgs_jax.physics import robust
from ffcgs_jax.physics import scene as physics_scene
from ffcgs_jax.physics.backend import Batch, mat_to_quat, pose_hand
from ffcgs_jax.physics.backend_cpu import GROUP_PER_THREAD, CpuSim
from ffcgs_jax.physics.config import BACKENDS, PROTOCOLS, PhysicsConfig
from ffcgs_jax.physics.protocols import result_key, run_protocol
from ffcgs_jax.physics.scene import PhysicsScene

# m beyond the hand's reach before a wrist pose is refused: hull parts may bulge past the mesh a little, and a grasp
# just out of reach is a legitimate failure ("lost") rather than a wrong input
REACH_MARGIN = 0.1
MEASURED_BATCH = 8  # grasps from which a CPU run's time is recorded for `auto` (fewer: mostly start-up noise)


def resolve_backend(name: str, n: int | None = None, protocols=PROTOCOLS, cfg: PhysicsConfig | None = None
                    ) -> tuple[str, str | None]:
    """The backend `name` ("auto" or one of `config.BACKENDS`) runs `n` grasps under `protocols` on here, and for
    "auto" falling back to the CPU, why (one line). "auto" is MuJoCo Warp when it is installed, a CUDA device is
    present and it is the faster here for this batch by the costs measured on this machine (`cost.choose`: the
    CPU's core-seconds per grasp against Warp's seconds per step and start-up), else CPU MuJoCo. Without `n`, Warp
    wherever it can run."""
    if name not in BACKENDS:
        raise FfcgsError(f"unknown physics backend {name!r}; backends: {', '.join(BACKENDS)}")
    if name != "auto":
        return name, None
    from ffcgs_jax.physics import backend_warp, cost, worlds

    if backend_warp.no_cuda():  # first: it starts nothing where there is no driver
        return "cpu", "physics on the CPU: no CUDA device for MuJoCo Warp"
    if backend_warp.unavailable():
        return "cpu", 'physics on the CPU: MuJoCo Warp is not installed (pip install -e ".[warp]" on a CUDA machine)'
    if n is None:
        return "warp", None
    cfg = cfg or PhysicsConfig()
    return cost.choose(int(n), tuple(protocols), cfg, cfg.workers or os.cpu_count() or 1, worlds.warm())


def scenes(spec: HandSpec, mesh: trimesh.Trimesh, cfg: PhysicsConfig, protocols, table_z: float | None = None,
           parts=None) -> dict[str, PhysicsScene]:
    """One compiled scene per protocol, as the protocol asks (`registry.Protocol`: lift-shake gravity and table;
    six-dir neither, the object held while closing; DexGraspBench's its own contacts and solver, under its fixed
    settings). `parts`: the object's convex parts; default `convex.decompose(mesh, cfg)`."""
    parts = convex.decompose(mesh, cfg) if parts is None else parts
    tz = float(mesh.bounds[0, 2]) if table_z is None else table_z
    out = {}
    for p in protocols:
        pr = physics_protocols.get(p)
        out[p] = physics_scene.build(spec, mesh, parts, pr.settings(cfg), gravity=pr.gravity,
                                     table_z=tz if pr.table else None, hold=pr.hold,
                                     dexgraspbench=pr.kind == "dexgraspbench")
    return out



def hand_reach(spec: HandSpec) -> float:
    """An upper bound (m) on how far any geom of the hand reaches from its root body's origin at any joint angles:
    along the chain from the root to the geom's body, each body's offset, plus twice its hinge or ball joints'
    offsets from its origin (turning about such a joint moves the origin by at most that) and its slides' travel;
    then the geom's offset and bounding radius."""
    m = spec.mj_model()
    root = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, spec.root_body)
    far = np.full(m.nbody, np.nan)  # NaN: not below the root
    far[root] = 0.0
    for b in range(root + 1, m.nbody):  # MuJoCo numbers a body after its parent
        parent = m.body_parentid[b]
        if np.isnan(far[parent]):
            continue
        joints = range(m.body_jntadr[b], m.body_jntadr[b] + m.body_jntnum[b])
        slide = [j for j in joints if m.jnt_type[j] == mujoco.mjtJoint.mjJNT_SLIDE]
        turn = [j for j in joints if j not in slide]
        far[b] = (far[parent] + np.linalg.norm(m.body_pos[b])
                  + 2 * sum(np.linalg.norm(m.jnt_pos[j]) for j in turn)
                  + sum(np.abs(m.jnt_range[j]).max() for j in slide))
    hand = ~np.isnan(far[m.geom_bodyid])
    reach = far[m.geom_bodyid] + np.linalg.norm(m.geom_pos, axis=1) + m.geom_rbound
    return float(reach[hand].max(initial=0.0))


def check_reach(spec: HandSpec, mesh: trimesh.Trimesh, wrist_pose, index=None) -> None:
    """Refuse, in one line (FfcgsError), wrist poses (B, 4, 4) whose origin lies farther from the mesh's bounding box
    than the hand can reach (`hand_reach` + `REACH_MARGIN`): no finger could touch the object, and the simulation of
    a hand metres or kilometres away from its target is no test of anything. `index` (B,): the grasps' numbers for
    the message (default 0..B-1)."""
    from ffcgs_jax.hand.kinematics import check_wrist_poses

    pos = check_wrist_poses(wrist_pose, "wrist_pose").reshape(-1, 4, 4)[:, :3, 3]
    lo, hi = np.asarray(mesh.bounds, np.float64)
    dist = np.linalg.norm(pos - np.clip(pos, lo, hi), axis=1)
    limit = hand_reach(spec) + REACH_MARGIN
    far = np.flatnonzero(dist > limit)
    if len(far):
        first = int(far[0] if index is None else np.asarray(index)[far[0]])
        raise FfcgsError(f"{len(far)} of {len(pos)} grasps have the wrist farther from the object than hand "
                         f"{spec.name} can reach ({limit:.2f} m from the mesh's bounding box), the first grasp "
                         f"{first} at {dist[far[0]]:.3g} m: are the poses in metres and in the object's frame?")


def check_inputs(scene: PhysicsScene, wrist_pose, q) -> tuple[np.ndarray, np.ndarray]:
    from ffcgs_jax.hand.kinematics import check_wrist_poses

    T = check_wrist_poses(wrist_pose, "wrist_pose").reshape(-1, 4, 4)
    qq = np.asarray(q, np.float64)
    nq = len(scene.lower)
    if qq.ndim != 2 or qq.shape != (len(T), nq):
        raise FfcgsError(f"q must have shape ({len(T)}, {nq}) to match {len(T)} wrist poses, got {qq.shape}")
    if not np.isfinite(qq).all():
        raise FfcgsError("q contains NaN or inf")
    return T, np.clip(qq, scene.lower, scene.upper)



@dataclasses.dataclass(frozen=True)
class _Grasps:
    """The grasps as `_grasps` reads them: wrist (B, 3) and (B, 4), q (B, Q) within the limits, the squeeze direction
    (B, Q), and at q the penetration depth (B,) and palm contact (B,)."""

    pos: np.ndarray
    quat: np.ndarray
    q: np.ndarray
    direction: np.ndarray
    depth: np.ndarray
    palm: np.ndarray


def prepare(scene: PhysicsScene, mesh: trimesh.Trimesh, wrist_pose, q, cfg: PhysicsConfig, squeeze_dir=None
            ) -> tuple[Batch, np.ndarray, np.ndarray]:
    """Servo start/target per grasp, the initial hand-object penetration depth (B,) at q (MuJoCo contact depth,
    metres, >= 0) and whether the palm touches the object at q (B,). `squeeze_dir` (B, Q), e.g. a grasp file's,
    replaces the squeeze direction computed here from the fingertips within `cfg.contact_band`.

    On DexGraspBench's scene (`scene.dexgraspbench`) the batch is the benchmark's plan (`_plan`: start at the
    pre-grasp, q_grasp, target at the squeeze) and the depth is the one at the pre-grasp, which the benchmark checks."""
    grasps = _grasps(scene, mesh, wrist_pose, q, cfg, squeeze_dir)
    batch, depth = _plan(scene, grasps, cfg)
    return batch, depth, grasps.palm


def _grasps(scene: PhysicsScene, mesh: trimesh.Trimesh, wrist_pose, q, cfg: PhysicsConfig, squeeze_dir=None
            ) -> _Grasps:
    from ffcgs_jax.evaluation.metrics import mesh_contacts, squeeze_direction

    T, qq = check_inputs(scene, wrist_pose, q)
    if squeeze_dir is not None:
        squeeze_dir = np.asarray(squeeze_dir, np.float64)
        if squeeze_dir.shape != qq.shape or not np.isfinite(squeeze_dir).all():
            raise FfcgsError(f"squeeze_dir must be finite with shape {qq.shape} (one row per grasp), got "
                             f"{squeeze_dir.shape}")
    m = scene.model
    d = mujoco.MjData(m)
    b = len(T)
    quat = np.array([mat_to_quat(t[:3, :3]) for t in T])
    depth, palm = np.zeros(b), np.zeros(b, bool)
    jac = np.zeros((b, len(scene.tip_sites), 3, qq.shape[1]))
    tips = np.zeros((b, len(scene.tip_sites), 3))
    jp = np.zeros((3, m.nv))
    dof = m.jnt_dofadr[np.searchsorted(m.jnt_qposadr, scene.hand_qpos)]
    for g in range(b):
        pose_hand(scene, d, T[g, :3, 3], quat[g], qq[g])
        mujoco.mj_forward(m, d)
        depth[g], palm[g] = _contact_state(scene, d)
        for k, s in enumerate(scene.tip_sites if squeeze_dir is None else ()):  # Jacobians only to derive it
            mujoco.mj_jacSite(m, d, jp, None, int(s))
            jac[g, k] = jp[:, dof] @ scene.coupling
            tips[g, k] = d.site_xpos[s]
    if squeeze_dir is None:
        _, normals, signed = mesh_contacts(mesh, tips)
        direction = squeeze_direction(jac, normals, np.abs(signed) <= cfg.contact_band)
    else:
        direction = squeeze_dir
    return _Grasps(T[:, :3, 3].copy(), quat, qq, direction, depth, palm)


def _plan(scene: PhysicsScene, grasps: _Grasps, cfg: PhysicsConfig) -> tuple[Batch, np.ndarray]:
    """The servo plan of every grasp on `scene` and the penetration depth (B,) its protocol checks at the start.

    Ours: from the open hand (`open_fraction`) to q + squeeze x direction; depth at q. DexGraspBench's: from the
    pre-grasp q - squeeze x direction through q to the squeeze q + squeeze x direction (`dexgraspbench`), the wrist
    at the grasp's pose throughout; depth at the pre-grasp."""
    g = grasps
    target = np.clip(g.q + cfg.squeeze * g.direction, scene.lower, scene.upper)
    if scene.dexgraspbench:
        pre = np.clip(g.q - cfg.squeeze * g.direction, scene.lower, scene.upper)
        return Batch(g.pos, g.quat, pre, target, g.q), _depths(scene, g.pos, g.quat, pre)
    q_open = np.clip(0.0, scene.lower, scene.upper)  # where the synthesis starts: q = 0 within the limits
    start = q_open + (1.0 - cfg.open_fraction) * (g.q - q_open)
    return Batch(g.pos, g.quat, start, target), g.depth


def _depths(scene: PhysicsScene, pos: np.ndarray, quat: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Deepest hand-object penetration (m, >= 0) of each grasp with the hand at (pos, quat, q)."""
    d = mujoco.MjData(scene.model)
    out = np.zeros(len(q))
    for g in range(len(q)):
        pose_hand(scene, d, pos[g], quat[g], q[g])
        mujoco.mj_forward(scene.model, d)
        out[g] = _contact_state(scene, d)[0]
    return out



def _contact_state(scene: PhysicsScene, d: mujoco.MjData) -> tuple[float, bool]:
    """Deepest hand-object penetration (m, >= 0) and whether a palm geom touches the object."""
    depth, palm = 0.0, False
    obj = set(scene.obj_geoms.tolist())
    hand = set(scene.hand_geoms.tolist())
    palm_geoms = set(scene.palm_geoms.tolist())
    for c in d.contact[: d.ncon]:
        g1, g2 = int(c.geom1), int(c.geom2)
        if (g1 in obj and g2 in hand) or (g2 in obj and g1 in hand):
            depth = max(depth, -float(c.dist))
            palm |= (g1 in palm_geoms or g2 in palm_geoms) and float(c.dist) < 0
    return depth, palm



def evaluate(spec: HandSpec, mesh: trimesh.Trimesh, wrist_pose, q, cfg: PhysicsConfig = PhysicsConfig(),
             protocols=PROTOCOLS, backend: str | None = None, table_z: float | None = None,
             progress: Callable[[int], None] | None = None, squeeze_dir=None, parts=None) -> dict[str, np.ndarray]:
    """Run the physics test on grasps (wrist_pose (B, 4, 4) object frame, q (B, Q) channels) on `backend`
    (default `cfg.backend`; "auto" is resolved by `resolve_backend`). `squeeze_dir` (B, Q): the grasps' own squeeze
    directions (a grasp file's `squeeze_dir`); default: computed from the fingertips near the mesh (`prepare`).
    `parts`: the object's collision geometry as convex (vertices, faces) pairs; default `convex.decompose(mesh, cfg)`.

    CPU runs the grasps in groups of `GROUP_PER_THREAD` x threads, so `progress(k)` (k grasps done) ticks often;
    MJX runs them as one batch; warp runs every grasp, protocol and push direction as a world of the same launches
    (`worlds`); grasps whose warp contacts or constraints overflowed their buffers are run again on the CPU
    (`physics_rerun_cpu` marks them).
    Returns flat per-grasp arrays for an npz: initial_penetration, palm_contact and, per protocol p (with '-'
    written '_'), p_success, p_reason (index into protocols.REASONS), p_move (m), p_rot (degrees) and for six-dir
    and DexGraspBench's protocols p_move_dir, p_rot_dir (B, 6); for DexGraspBench's also p_pregrasp_penetration (m,
    the depth its penetration rule reads). A grasp whose simulation diverged fails with reason "unstable"; wrist
    poses out of the hand's reach of the object are refused before anything is simulated (`check_reach`).

    On "warp" every protocol (DexGraspBench's too, with MuJoCo Warp's no-slip solver) runs as the worlds of one
    launch (`worlds`): each grasp, protocol and push direction a world."""
    return evaluate_many(spec, [Item(mesh, wrist_pose, q, squeeze_dir, table_z, parts)], cfg, protocols, backend,
                         progress)[0]


@dataclasses.dataclass(frozen=True)
class Item:
    """One object's grasps for `evaluate_many`: as `evaluate`'s arguments of the same names."""

    mesh: trimesh.Trimesh
    wrist_pose: np.ndarray
    q: np.ndarray
    squeeze_dir: np.ndarray | None = None
    table_z: float | None = None
    parts: list | None = None
    settings: dict | None = None  # `PhysicsConfig` fields of this item alone (a robust trial's friction, mass, ...)


def evaluate_many(spec: HandSpec, items: Iterable[Item], cfg: PhysicsConfig = PhysicsConfig(), protocols=PROTOCOLS,
                  backend: str | None = None, progress: Callable[[int], None] | None = None,
                  threads: int | None = None, stats: dict | None = None) -> list[dict[str, np.ndarray]]:
    """`evaluate` for many objects at once: one result dict per item, in order. On MuJoCo Warp the grasps of every
    object are worlds of the same launches (`worlds.run_jobs`), and each object's collision geometry, scenes and
    grasp plan are built on `threads` CPU threads (default: the cores, at most 8) while the GPU simulates the
    objects before it. On the CPU the objects run one after another.

    `items` may be a generator (a labelled build's, which synthesises each object's candidates as it is asked for
    the next): it is then read on a thread while the GPU simulates, and "auto" takes Warp wherever it can run
    (the batch's size is not known in advance). `stats` (a dict): gets "backend", "geometry_s" (CPU seconds
    building collision geometry, scenes and plans, summed over threads) and on Warp each engine's `worlds.Stats`
    by kind ("ours", "dexgraspbench")."""
    cfg.check()
    protocols = tuple(protocols)
    for p in protocols:
        physics_protocols.get(p)  # an unknown name: one line listing the registered ones
    listed = isinstance(items, (list, tuple))
    k = cfg.robust.trials
    if k > 1:  # each object's grasps as K perturbed trials (`robust`), folded back below
        items = robust.expand(items, cfg)
        items = list(items) if listed else items
    if listed:
        for it in items:
            _check_item(spec, it)
    asked = cfg.backend if backend is None else backend
    n = sum(int(np.shape(it.q)[0]) for it in items) if listed else None
    backend, _ = resolve_backend(asked, n, protocols, cfg)
    bench = [p for p in protocols if physics_protocols.get(p).kind == "dexgraspbench"]
    if bench and backend == "mjx":
        raise FfcgsError(f"protocol {bench[0]} runs on the CPU and Warp backends only (MuJoCo's no-slip solver, "
                         f"which MJX lacks): use --backend cpu, warp or auto")
    physics_protocols.say_overrides(cfg, protocols)
    tick = progress or (lambda n: None)
    stats = {} if stats is None else stats
    stats.update(backend=backend, geometry_s=0.0)
    if backend == "warp":
        out = _on_worlds(spec, items, cfg, protocols, tick, threads, stats)
    else:
        out = []
        for it in items:
            if not listed:
                _check_item(spec, it)
            out.append(_on_simulator(spec, it, cfg, protocols, backend, tick, stats))
    if k > 1:
        out = [robust.combine(out[i: i + k], protocols, cfg.robust) for i in range(0, len(out), k)]
    return out


def _check_item(spec: HandSpec, it: Item) -> None:
    if len(np.asarray(it.q).reshape(-1)) == 0:
        raise FfcgsError("no grasps to test")
    check_reach(spec, it.mesh, it.wrist_pose)


def _prepared(spec: HandSpec, it: Item, cfg: PhysicsConfig, protocols, stats: dict | None = None
              ) -> tuple[dict, dict]:
    """An object's scenes, its result arrays so far (penetration, palm contact) and per protocol (batch, depth,
    protocol config)."""
    t0 = time.perf_counter()
    cfg = dataclasses.replace(cfg, **it.settings) if it.settings else cfg
    built = scenes(spec, it.mesh, cfg, protocols, it.table_z, it.parts)
    # the scenes differ only in gravity, table, the hold weld and contact softness and friction, none of which the
    # hand-object contacts, the fingertip Jacobians or the squeeze direction depend on: read the grasps once
    grasps = _grasps(built[protocols[0]], it.mesh, it.wrist_pose, it.q, cfg, it.squeeze_dir)
    out: dict[str, np.ndarray] = {"initial_penetration": grasps.depth, "palm_contact": grasps.palm}
    plans = {}
    for p, scene in built.items():
        pcfg = physics_protocols.get(p).settings(cfg)
        batch, depth = _plan(scene, grasps, pcfg)
        if scene.dexgraspbench:
            out[result_key(p, "pregrasp_penetration")] = depth
        plans[p] = (scene, batch, depth, pcfg)
    if stats is not None:
        stats["geometry_s"] = stats.get("geometry_s", 0.0) + time.perf_counter() - t0
    return out, plans


def _on_simulator(spec: HandSpec, it: Item, cfg: PhysicsConfig, protocols, backend: str, tick,
                  stats: dict | None = None) -> dict:
    from ffcgs_jax.physics import cost

    out, plans = _prepared(spec, it, cfg, protocols, stats)
    for p, (scene, batch, depth, pcfg) in plans.items():
        t0 = time.perf_counter()
        if backend == "cpu":
            sim = CpuSim(scene, cfg.workers)
            group = GROUP_PER_THREAD * sim.nthread
        else:
            from ffcgs_jax.physics.backend_mjx import MjxSim

            sim, group = MjxSim(scene), len(depth)
        parts = []
        for i in range(0, len(depth), group):
            rows = slice(i, i + group)
            part = run_protocol(sim, batch.rows(rows), depth[rows], pcfg, p)
            part.pop("flagged")
            parts.append(part)
            tick(len(depth[rows]))
        for k in parts[0]:
            out[result_key(p, k)] = np.concatenate([r[k] for r in parts])
        if backend == "cpu" and len(depth) >= MEASURED_BATCH:  # what `auto` weighs the next batch by
            cost.remember_cpu(p, (time.perf_counter() - t0) * sim.nthread / len(depth))
    return out


def _on_worlds(spec: HandSpec, items: Iterable[Item], cfg: PhysicsConfig, protocols, tick, threads, stats: dict
               ) -> list[dict]:
    """Every object, protocol and grasp of `items` as worlds of MuJoCo Warp launches; the CPU prepares the
    objects in order on a thread pool while the GPU runs the ones before; grasps whose worlds overflowed their
    buffers run again on the CPU (`physics_rerun_cpu`)."""
    import concurrent.futures

    from ffcgs_jax.physics import worlds

    outs: list[dict] = []
    plans: list[dict] = []
    order: list[tuple[int, str]] = []
    n = threads or min(8, os.cpu_count() or 1)

    def prepare(it: Item):
        _check_item(spec, it)
        return _prepared(spec, it, cfg, protocols, stats)

    window: collections.deque = collections.deque()
    source = iter(items)

    def jobs():
        # a window of objects in preparation, taken in order: the GPU starts on the first while the rest are built
        with concurrent.futures.ThreadPoolExecutor(n, thread_name_prefix="ffcgs-geometry") as pool:
            while True:
                # not past a ready head: a generator that synthesises each item as it is read (`label.label_many`)
                # would otherwise hold the GPU back for a whole window of objects
                while len(window) < 2 * n and not (window and window[0].done()):
                    it = next(source, None)
                    if it is None:
                        break
                    window.append(pool.submit(prepare, it))
                if not window:
                    return
                i = len(outs)
                out, plan = window.popleft().result()
                outs.append(out)
                plans.append(plan)
                for p, (scene, batch, depth, pcfg) in plan.items():
                    order.append((i, p))
                    yield worlds.Job(scene, batch, depth, pcfg, p, object_key=i)

    try:
        results = worlds.run_jobs(spec, jobs(), progress=tick, record=True, stats=stats)
    except FfcgsError:
        raise
    except Exception as e:  # noqa: BLE001 - the GPU (out of memory, a driver error): the CPU still answers
        worlds.clear()
        first = str(e).splitlines()[0] if str(e) else ""
        warnings.warn(f"physics: MuJoCo Warp failed ({type(e).__name__}: {first}); these grasps run on the CPU",
                      stacklevel=3)
        for f in list(window):  # objects prepared or in preparation, then the rest
            out, plan = f.result()
            outs.append(out)
            plans.append(plan)
        for out, plan in zip(outs, plans):
            for p, (scene, batch, depth, pcfg) in plan.items():
                part = run_protocol(CpuSim(scene, cfg.workers), batch, depth, pcfg, p)
                part.pop("flagged")
                out.update({result_key(p, k): v for k, v in part.items()})
                tick(len(depth))
        stats["backend"] = "cpu"
        return outs + [_on_simulator(spec, it, cfg, protocols, "cpu", tick, stats) for it in source]
    rerun = 0
    for (i, p), part in zip(order, results):
        out = outs[i]
        out.setdefault("physics_rerun_cpu", np.zeros(len(out["initial_penetration"]), bool))
        scene, batch, depth, pcfg = plans[i][p]
        if part is None:  # the object could not become worlds (`worlds.run_jobs` said why)
            part = run_protocol(CpuSim(scene, cfg.workers), batch, depth, pcfg, p)
            flagged = np.ones(len(depth), bool)
            part.pop("flagged")
        else:
            flagged = part.pop("flagged")
            if flagged.any():
                part = _rerun_on_cpu(scene, pcfg, p, batch, depth, part, flagged)
                rerun += int(flagged.sum())
        out["physics_rerun_cpu"] |= flagged
        for k, v in part.items():
            out[result_key(p, k)] = v
    if rerun:
        warnings.warn(f"physics: {rerun} grasp trials overflowed the GPU worlds' contact or constraint buffers and "
                      f"ran again on the CPU (physics_rerun_cpu marks them)", stacklevel=3)
    return outs


def _rerun_on_cpu(scene: PhysicsScene, cfg: PhysicsConfig, protocol: str, batch: Batch, depth: np.ndarray,
                  part: dict[str, np.ndarray], flagged: np.ndarray) -> dict[str, np.ndarray]:
    """The results of the grasps whose warp buffers overflowed, replaced by the CPU backend's: never scored from
    a simulation that dropped contacts or constraints."""
    idx = np.flatnonzero(flagged)
    redo = run_protocol(CpuSim(scene, cfg.workers), batch.rows(idx), depth[idx], cfg, protocol)
    redo.pop("flagged")
    for k, v in redo.items():
        part[k][idx] = v
    return part
