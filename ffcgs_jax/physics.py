"""The physics test: do the synthesised grasps hold the object in MuJoCo?

Execution of one grasp (all grasps of a batch in parallel):

1. The hand is put at the grasp's wrist pose with the fingers at (1 - open_fraction) q, on the straight channel
   path from the open hand (q = 0, which the synthesis filters checked against the object and the table) to q.
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
     `CHUNK` steps and at its end).

Failure modes are recorded per grasp (`reason`): penetration; lost (no hand contact left: dropped or pushed out
while closing); slip (still touched but moved past the bound).

The simulator is CPU MuJoCo through `mujoco.rollout` (threads across grasps, no Python per step); the scene and
the protocol are plain arrays, so `physics_mjx` runs the same plan on a GPU.
"""

import dataclasses
import math
import os
from collections.abc import Callable

import mujoco
import numpy as np
import trimesh
from mujoco import rollout

from ffcgs_jax import convex, physics_scene
from ffcgs_jax.config import PROTOCOLS, PhysicsConfig
from ffcgs_jax.errors import FfcgsError
from ffcgs_jax.hand_spec import HandSpec
from ffcgs_jax.physics_scene import PhysicsScene

CHUNK = 250  # steps per rollout call: bounds the state buffer (B x CHUNK x nstate) and samples the six-dir motion
LIFT_HOLD = 0.25  # seconds of rest between the lift and the shaking
DIRECTIONS = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], np.float64)
REASONS = ("ok", "penetration", "lost", "slip")
BACKENDS = ("cpu", "mjx")
GROUP_PER_THREAD = 4  # CPU grasps per thread per rollout group: keeps threads busy and the progress bar moving
_STATE = mujoco.mjtState.mjSTATE_FULLPHYSICS
_CTRL = mujoco.mjtState.mjSTATE_CTRL | mujoco.mjtState.mjSTATE_MOCAP_POS | mujoco.mjtState.mjSTATE_MOCAP_QUAT


@dataclasses.dataclass(frozen=True)
class Segment:
    """`n` steps of open-loop control: `make(i0, i1)` gives (ctrl (B, k, Q), wrist offset (k, 3)) for steps
    [i0, i1) of the segment, k = i1 - i0 or 1 when constant; `force` (3,) world force on the object or None;
    `hold`: the object is welded in place (six-dir closes on a floating object, which the table holds in
    lift-shake)."""

    n: int
    make: Callable[[int, int], tuple[np.ndarray, np.ndarray]]
    force: np.ndarray | None = None
    hold: bool = False


@dataclasses.dataclass
class Batch:
    """Per-grasp inputs of a run: wrist pose parts, start and target servo positions."""

    wrist_pos: np.ndarray  # (B, 3)
    wrist_quat: np.ndarray  # (B, 4) w x y z
    q_start: np.ndarray  # (B, Q)
    q_target: np.ndarray  # (B, Q)

    def rows(self, sel) -> "Batch":
        """The grasps at `sel` (a slice or indices), as a Batch."""
        return Batch(*(np.asarray(getattr(self, f.name))[sel] for f in dataclasses.fields(self)))


def result_key(protocol: str, field: str) -> str:
    """The name of a per-grasp result of `evaluate`, e.g. ("six-dir", "success") -> "six_dir_success"."""
    return f"{protocol.replace('-', '_')}_{field}"


def wilson(successes: int, n: int, z: float = 1.959963984540054) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion (95 % by default); (0, 1) when n = 0."""
    if n == 0:
        return 0.0, 1.0
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return max(0.0, centre - half), min(1.0, centre + half)


# ------------------------------------------------------------------------------------------------------------
# Scene and inputs
# ------------------------------------------------------------------------------------------------------------


def scenes(spec: HandSpec, mesh: trimesh.Trimesh, cfg: PhysicsConfig, protocols, table_z: float | None = None
           ) -> dict[str, PhysicsScene]:
    """One compiled scene per protocol (lift-shake: gravity and table; six-dir: neither)."""
    parts = convex.decompose(mesh, cfg)
    tz = float(mesh.bounds[0, 2]) if table_z is None else table_z
    out = {}
    for p in protocols:
        lift = p == "lift-shake"
        out[p] = physics_scene.build(spec, mesh, parts, cfg, gravity=lift, table_z=tz if lift else None,
                                     hold=not lift)
    return out


def check_inputs(scene: PhysicsScene, wrist_pose, q) -> tuple[np.ndarray, np.ndarray]:
    from ffcgs_jax.kinematics import check_wrist_poses

    T = check_wrist_poses(wrist_pose, "wrist_pose").reshape(-1, 4, 4)
    qq = np.asarray(q, np.float64)
    nq = len(scene.lower)
    if qq.ndim != 2 or qq.shape != (len(T), nq):
        raise FfcgsError(f"q must have shape ({len(T)}, {nq}) to match {len(T)} wrist poses, got {qq.shape}")
    if not np.isfinite(qq).all():
        raise FfcgsError("q contains NaN or inf")
    return T, np.clip(qq, scene.lower, scene.upper)


def prepare(scene: PhysicsScene, mesh: trimesh.Trimesh, wrist_pose, q, cfg: PhysicsConfig
            ) -> tuple[Batch, np.ndarray, np.ndarray]:
    """Servo start/target per grasp, the initial hand-object penetration depth (B,) at q (MuJoCo contact depth,
    metres, >= 0) and whether the palm touches the object at q (B,)."""
    from ffcgs_jax.metrics import mesh_contacts

    T, qq = check_inputs(scene, wrist_pose, q)
    m = scene.model
    d = mujoco.MjData(m)
    b = len(T)
    quat = np.array([_quat(t[:3, :3]) for t in T])
    depth, palm = np.zeros(b), np.zeros(b, bool)
    jac = np.zeros((b, len(scene.tip_sites), 3, qq.shape[1]))
    tips = np.zeros((b, len(scene.tip_sites), 3))
    jp = np.zeros((3, m.nv))
    dof = m.jnt_dofadr[np.searchsorted(m.jnt_qposadr, scene.hand_qpos)]
    for g in range(b):
        _pose_hand(scene, d, T[g, :3, 3], quat[g], qq[g])
        mujoco.mj_forward(m, d)
        depth[g], palm[g] = _contact_state(scene, d)
        for k, s in enumerate(scene.tip_sites):
            mujoco.mj_jacSite(m, d, jp, None, int(s))
            jac[g, k] = jp[:, dof] @ scene.coupling
            tips[g, k] = d.site_xpos[s]
    _, normals, signed = mesh_contacts(mesh, tips)
    near = (np.abs(signed) <= cfg.contact_band)[..., None]
    direction = np.einsum("bkiq,bki->bq", jac, -normals * near)
    scale = np.abs(direction).max(axis=1, keepdims=True)
    direction = np.where(scale > 1e-12, direction / np.maximum(scale, 1e-12), 0.0)
    target = np.clip(qq + cfg.squeeze * direction, scene.lower, scene.upper)
    start = (1.0 - cfg.open_fraction) * qq
    return Batch(T[:, :3, 3].copy(), quat, start, target), depth, palm


def _quat(R: np.ndarray) -> np.ndarray:
    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(R, np.float64).ravel())
    return q


def _pose_hand(scene: PhysicsScene, d: mujoco.MjData, pos, quat, q) -> None:
    d.mocap_pos[0], d.mocap_quat[0] = pos, quat
    d.qpos[:] = scene.model.qpos0
    d.qpos[scene.root_qpos: scene.root_qpos + 7] = np.concatenate([pos, quat])
    d.qpos[scene.hand_qpos] = scene.coupling @ q
    d.qvel[:] = 0


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


# ------------------------------------------------------------------------------------------------------------
# The protocols as open-loop segments
# ------------------------------------------------------------------------------------------------------------


def _steps(seconds: float, dt: float) -> int:
    return max(1, int(round(seconds / dt)))


def closing(batch: Batch, cfg: PhysicsConfig) -> list[Segment]:
    n = _steps(cfg.close_time, cfg.timestep)
    zero = np.zeros((1, 3))

    def ramp(i0, i1):
        s = (np.arange(i0, i1) + 1.0) / n
        return batch.q_start[:, None] + s[None, :, None] * (batch.q_target - batch.q_start)[:, None], zero

    settle = Segment(_steps(cfg.settle_time, cfg.timestep), lambda i0, i1: (batch.q_target[:, None], zero), hold=True)
    return [Segment(n, ramp, hold=True), settle]


def lift_shake(batch: Batch, cfg: PhysicsConfig) -> list[Segment]:
    dt = cfg.timestep
    hold = batch.q_target[:, None]
    n_lift = _steps(cfg.lift_height / cfg.lift_speed, dt)
    period = 4 * cfg.shake_amplitude / cfg.shake_speed
    n_shake = _steps(cfg.shake_cycles * period, dt) if cfg.shake_cycles else 0

    def lift(i0, i1):
        u = (np.arange(i0, i1) + 1.0) / n_lift
        off = np.zeros((i1 - i0, 3))
        off[:, 2] = cfg.lift_height * (1 - np.cos(np.pi * u)) / 2
        return hold, off

    def shake(i0, i1):
        t = (np.arange(i0, i1) + 1.0) * dt
        # a quarter period of smooth ramp in and out, so the wrist never jumps in velocity
        env = np.clip(np.minimum(t, n_shake * dt - t) / (period / 4), 0.0, 1.0)
        env = env * env * (3 - 2 * env)
        off = np.zeros((i1 - i0, 3))
        off[:, 0] = cfg.shake_amplitude * np.sin(2 * np.pi * t / period) * env
        off[:, 2] = cfg.lift_height
        return hold, off

    up = np.array([[0.0, 0.0, cfg.lift_height]])
    segs = [Segment(n_lift, lift), Segment(_steps(LIFT_HOLD, dt), lambda i0, i1: (hold, up))]
    return segs + ([Segment(n_shake, shake)] if n_shake else [])


def push(batch: Batch, cfg: PhysicsConfig, direction: np.ndarray, mass: float) -> Segment:
    zero = np.zeros((1, 3))
    return Segment(_steps(cfg.push_time, cfg.timestep), lambda i0, i1: (batch.q_target[:, None], zero),
                   force=cfg.accel * mass * direction)


# ------------------------------------------------------------------------------------------------------------
# CPU simulator
# ------------------------------------------------------------------------------------------------------------


class CpuSim:
    """Runs segments for a batch on CPU MuJoCo with `mujoco.rollout` threads. States are FULLPHYSICS vectors."""

    def __init__(self, scene: PhysicsScene, workers: int = 0):
        self.scene = scene
        self.nthread = workers or os.cpu_count() or 1
        self.datas = [mujoco.MjData(scene.model) for _ in range(self.nthread)]
        self.size = mujoco.mj_stateSize(scene.model, _STATE)

    def initial(self, batch: Batch) -> np.ndarray:
        d = self.datas[0]
        out = np.zeros((len(batch.q_start), self.size))
        for g in range(len(out)):
            _pose_hand(self.scene, d, batch.wrist_pos[g], batch.wrist_quat[g], batch.q_start[g])
            mujoco.mj_forward(self.scene.model, d)
            mujoco.mj_getState(self.scene.model, d, out[g], _STATE)
        return out

    def run(self, state: np.ndarray, batch: Batch, seg: Segment, track: Callable | None = None) -> np.ndarray:
        """Advance `state` (B, nstate) through `seg`; `track(states)` sees each chunk's last states."""
        m, sc = self.scene.model, self.scene
        b = len(state)
        spec = _CTRL
        if seg.force is not None:
            spec |= mujoco.mjtState.mjSTATE_XFRC_APPLIED
        if sc.hold_eq >= 0:
            spec |= mujoco.mjtState.mjSTATE_EQ_ACTIVE
        for i0 in range(0, seg.n, CHUNK):
            i1 = min(seg.n, i0 + CHUNK)
            ctrl, off = seg.make(i0, i1)
            k = max(ctrl.shape[1], off.shape[0])
            parts = [np.broadcast_to(ctrl, (b, k, ctrl.shape[2]))]  # in mjtState bit order, as mj_setState reads
            if seg.force is not None:
                xfrc = np.zeros((b, k, m.nbody, 6))
                xfrc[:, :, sc.obj_body, :3] = seg.force
                parts.append(xfrc.reshape(b, k, -1))
            if sc.hold_eq >= 0:
                active = np.ones((b, k, m.neq))
                active[:, :, sc.hold_eq] = float(seg.hold)
                parts.append(active)
            parts += [np.broadcast_to(batch.wrist_pos[:, None] + off[None], (b, k, 3)),
                      np.broadcast_to(batch.wrist_quat[:, None], (b, k, 4))]
            control = np.ascontiguousarray(np.concatenate(parts, axis=2))
            states, _ = rollout.rollout(m, self.datas, state, control, control_spec=spec, nstep=i1 - i0,
                                        persistent_pool=True)
            state = np.ascontiguousarray(states[:, -1])
            if track is not None:
                track(state)
        return state

    def probe(self, state: np.ndarray, batch: Batch, offset=(0.0, 0.0, 0.0)) -> dict[str, np.ndarray]:
        """Object pose (world, and position in the hand's root frame), table and hand contact of each state, with
        the wrist target moved by `offset` (3,)."""
        m, d, sc = self.scene.model, self.datas[0], self.scene
        b = len(state)
        pos, quat, rel = np.zeros((b, 3)), np.zeros((b, 4)), np.zeros((b, 3))
        table, touch = np.zeros(b, bool), np.zeros(b, bool)
        obj, hand = set(sc.obj_geoms.tolist()), set(sc.hand_geoms.tolist())
        for g in range(b):
            mujoco.mj_setState(m, d, state[g], _STATE)
            d.mocap_pos[0], d.mocap_quat[0] = batch.wrist_pos[g] + offset, batch.wrist_quat[g]
            mujoco.mj_forward(m, d)
            pos[g], quat[g] = d.xpos[sc.obj_body], d.xquat[sc.obj_body]
            rel[g] = d.xmat[sc.root_body].reshape(3, 3).T @ (pos[g] - d.xpos[sc.root_body])
            for c in d.contact[: d.ncon]:
                pair = {int(c.geom1), int(c.geom2)}
                if pair & obj and sc.table_geom in pair:
                    table[g] = True
                if pair & obj and pair & hand:
                    touch[g] = True
        return dict(pos=pos, quat=quat, rel=rel, table=table, touch=touch)


# ------------------------------------------------------------------------------------------------------------
# Running the protocols
# ------------------------------------------------------------------------------------------------------------


def _angle(q1: np.ndarray, q2: np.ndarray) -> np.ndarray:
    """Rotation angle (degrees) between unit quaternions, row by row."""
    c = np.clip(np.abs(np.sum(q1 * q2, axis=-1)), 0.0, 1.0)
    return np.degrees(2 * np.arccos(c))


def _reason(bad_start: np.ndarray, lost: np.ndarray, moved: np.ndarray) -> np.ndarray:
    return np.select([bad_start, lost, moved], [1, 2, 3], 0).astype(np.int8)


def run_protocol(sim, batch: Batch, depth: np.ndarray, cfg: PhysicsConfig, protocol: str) -> dict[str, np.ndarray]:
    """Execute and test every grasp of `batch` on `sim` (a `CpuSim` or `physics_mjx.MjxSim` for the protocol's
    scene). Returns per-grasp arrays: success, reason (index into REASONS), move (m), rot (deg) and, for six-dir,
    move_dir / rot_dir (B, 6)."""
    if protocol not in PROTOCOLS:
        raise FfcgsError(f"unknown protocol {protocol!r}; protocols: {', '.join(PROTOCOLS)}")
    bad_start = depth > cfg.max_initial_penetration
    state = sim.initial(batch)
    for seg in closing(batch, cfg):
        state = sim.run(state, batch, seg)
    ref = sim.probe(state, batch)
    if protocol == "lift-shake":
        for seg in lift_shake(batch, cfg):
            state = sim.run(state, batch, seg)
        up = np.array([0.0, 0.0, cfg.lift_height])
        end = sim.probe(state, batch, up)
        move = np.linalg.norm(end["rel"] - ref["rel"], axis=1)
        rot = _angle(end["quat"], ref["quat"])
        lost = ~end["touch"]
        moved = (move >= cfg.max_slip) | end["table"]
        return dict(success=~(bad_start | lost | moved), reason=_reason(bad_start, lost, moved), move=move, rot=rot)
    b = len(depth)
    move_dir, rot_dir = np.zeros((b, 6)), np.zeros((b, 6))
    for k, direction in enumerate(DIRECTIONS):
        def track(s, k=k):
            p = sim.probe(s, batch)
            move_dir[:, k] = np.maximum(move_dir[:, k], np.linalg.norm(p["pos"] - ref["pos"], axis=1))
            rot_dir[:, k] = np.maximum(rot_dir[:, k], _angle(p["quat"], ref["quat"]))
        sim.run(state, batch, push(batch, cfg, direction, sim.scene.mass), track)
    move, rot = move_dir.max(axis=1), rot_dir.max(axis=1)
    lost = ~ref["touch"]
    moved = (move >= cfg.max_move) | (rot >= cfg.max_rot_deg)
    return dict(success=~(bad_start | lost | moved), reason=_reason(bad_start, lost, moved), move=move, rot=rot,
                move_dir=move_dir, rot_dir=rot_dir)


def evaluate(spec: HandSpec, mesh: trimesh.Trimesh, wrist_pose, q, cfg: PhysicsConfig = PhysicsConfig(),
             protocols=PROTOCOLS, backend: str = "cpu", table_z: float | None = None,
             progress: Callable[[int], None] | None = None) -> dict[str, np.ndarray]:
    """Run the physics test on grasps (wrist_pose (B, 4, 4) object frame, q (B, Q) channels).

    CPU runs the grasps in groups of `GROUP_PER_THREAD` x threads, so `progress(k)` (k grasps done) ticks often;
    MJX runs them as one batch. Returns flat per-grasp arrays for an npz: initial_penetration, palm_contact and,
    per protocol p (with '-' written '_'), p_success, p_reason (index into REASONS), p_move (m), p_rot (degrees)
    and for six-dir six_dir_move_dir, six_dir_rot_dir (B, 6)."""
    cfg.check()
    protocols = tuple(protocols)
    for p in protocols:
        if p not in PROTOCOLS:
            raise FfcgsError(f"unknown protocol {p!r}; protocols: {', '.join(PROTOCOLS)}")
    if backend not in BACKENDS:
        raise FfcgsError(f"unknown physics backend {backend!r}; backends: {', '.join(BACKENDS)}")
    if len(np.asarray(q).reshape(-1)) == 0:
        raise FfcgsError("no grasps to test")
    tick = progress or (lambda n: None)
    built = scenes(spec, mesh, cfg, protocols, table_z)
    # the scenes differ only in gravity, table and the hold weld, none of which the hand-object contacts, the
    # fingertip Jacobians or the squeeze target depend on: prepare once
    batch, depth, palm = prepare(built[protocols[0]], mesh, wrist_pose, q, cfg)
    out: dict[str, np.ndarray] = {"initial_penetration": depth, "palm_contact": palm}
    for p, scene in built.items():
        if backend == "cpu":
            sim = CpuSim(scene, cfg.workers)
            group = GROUP_PER_THREAD * sim.nthread
        else:
            from ffcgs_jax.physics_mjx import MjxSim

            sim, group = MjxSim(scene), len(depth)
        parts = []
        for i in range(0, len(depth), group):
            rows = slice(i, i + group)
            parts.append(run_protocol(sim, batch.rows(rows), depth[rows], cfg, p))
            tick(len(depth[rows]))
        for k in parts[0]:
            out[result_key(p, k)] = np.concatenate([r[k] for r in parts])
    return out


def summary_rows(results: dict[str, np.ndarray], protocols) -> list[tuple[str, str]]:
    """Success rates over all tested grasps with 95 % Wilson intervals, and failure reasons."""
    rows = []
    for p in protocols:
        ok, reason = results[result_key(p, "success")], results[result_key(p, "reason")]
        k, n = int(ok.sum()), len(ok)
        lo, hi = wilson(k, n)
        rate = f"{100 * k / n:.1f} %" if n else "-"
        rows.append((f"{p} success (all)", f"{k} / {n} = {rate}  (95 % CI {100 * lo:.1f}-{100 * hi:.1f} %)"))
        counts = ", ".join(f"{r} {int((reason == i).sum())}" for i, r in enumerate(REASONS) if i)
        rows.append((f"{p} failures", counts))
    return rows
