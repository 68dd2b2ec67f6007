"""The physics protocols as the worlds of MuJoCo Warp launches: every grasp, protocol, push direction and object of
a batch at once (`run_jobs`).

The unit of GPU work is a world, one program of `world_kernels`:
- lift-shake: one world per grasp (close, lift, shake);
- six-dir: one world per grasp closes; from its closed state (kept on the device at exactly the step the CPU
  backend's pushes start from) six push worlds start, one per direction, so no world runs six pushes in turn;
- DexGraspBench's test: one world per grasp from the pre-grasp to the squeeze, then six push worlds likewise,
  with MuJoCo Warp's no-slip solver (`dexgraspbench.NOSLIP_ITERATIONS`, as on the CPU).

Objects: each engine holds one model (`world_model`): the hand and an object of `slots` empty mesh slots; a world
shows its own object through per-world model fields, so the worlds of any objects share one launch, and a world's
hand meets only its object. Lift-shake and six-dir worlds share the engine of kind "ours" (gravity, table and hold
weld are set per world); DexGraspBench's worlds have their own engine (its solver and contacts differ).

Scheduling: `nworld` worlds step together, captured as one CUDA graph per world count (`MIN_WORLDS`, 2 x, ... up
to `nworld`) with buffers allocated once per engine. Every `SYNC` steps the host reads each world's status:
finished worlds give their results, closed worlds their pushes, and free worlds are refilled from the queue (new
grasps, new objects, pushes). When the queue is dry and at most half of the worlds run, the survivors move to the
smallest world count that holds them. The checks themselves run on the device (`world_kernels.events`), at the
steps where the CPU backend checks (`Schedule`), so the outcomes are the CPU protocols' on the same scene up to
float32 and MuJoCo Warp's collision code (bench/RESULTS.md gives the measured agreement).

Worlds whose contact or constraint buffers overflowed are marked `flagged` and run again on the CPU by the caller;
a world whose state diverges fails "unstable", as on the CPU.
"""

import dataclasses
import os
import queue
import threading
import time
import warnings
from collections.abc import Callable, Iterable

import mujoco
import numpy as np

from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.hand.spec import HandSpec
from ffcgs_jax.runtime import compiled
from ffcgs_jax.physics import protocols as P
from ffcgs_jax.physics import world_kernels as K
from ffcgs_jax.physics import world_model
from ffcgs_jax.physics.backend import MAX_SPEED, Batch, route_mujoco_warnings
from ffcgs_jax.physics.backend_warp import put_model, unavailable, untrusted_overflows
from ffcgs_jax.physics.config import PhysicsConfig
from ffcgs_jax.physics.scene import PhysicsScene
from ffcgs_jax.physics.world_programs import Block, JobState, Layout, Schedule, Stats

MAX_WORLDS = 8192  # worlds stepped together: 8192 of the SVH's scene fit an H100 with room to spare
MIN_WORLDS = 64  # the fewest worlds on a GPU: below it a step costs about the same
MIN_WORLDS_CPU = 8  # Warp on the CPU (tests): a world costs its share there
COMPACT = True  # survivors move to fewer worlds at the tail (off: the tests' uncompacted reference)
SYNC = 50  # steps between looks at the worlds' status (a refill waits at most this long)
# Buffers: contacts are one pool over all worlds (a world may take more than its share), constraint rows are a
# hard limit per world. Grasps of complex objects reach about 21 contacts and 81 rows at most (CPU MuJoCo, the SVH);
# MuJoCo Warp's kernels launch over these sizes, so room to spare costs every step. A world that overflows is run
# again on the CPU (`flagged`), so a rare tight case costs time, never a wrong label.
CONTACTS_PER_WORLD = 48
ROWS_PER_WORLD = 256
GRAVITY = -9.81  # m/s^2, `scene.build`'s
# model fields that differ per world (`gather`): an object's parts, mass and inertia; the table's height
BATCHED = ("geom_dataid", "geom_pos", "geom_quat", "geom_size", "geom_aabb", "geom_rbound", "geom_friction",
           "body_mass", "body_ipos", "body_iquat", "body_inertia", "body_invweight0", "body_subtreemass",
           "dof_invweight0")
MESH_FIELDS = ("vertadr", "vertnum", "faceadr", "normaladr", "normalnum", "graphadr", "vert", "normal", "face",
               "graph", "pos", "quat", "polynum", "polyadr", "polynormal", "polyvertadr", "polyvertnum", "polyvert",
               "polymapadr", "polymapnum", "polymap")


@dataclasses.dataclass(frozen=True)
class Job:
    """One protocol over one object's grasps, as `protocols.run_protocol` takes it: `scene` (the object's scene
    for `protocol`, from `runner.scenes`), `batch` and `depth` (`runner.prepare`), `cfg` (for DexGraspBench's
    protocols their `settings(cfg)`). `object_key`: jobs with the same key share the object's
    meshes on the device (default: one copy per job)."""

    scene: PhysicsScene
    batch: Batch
    depth: np.ndarray
    cfg: PhysicsConfig
    protocol: str
    object_key: object = None


def buffer_sizes(scene: PhysicsScene) -> tuple[int, int]:
    """(contacts per world on average, constraint rows per world at most) of the worlds of `scene`: the equality
    constraints' rows and the dofs on top of `ROWS_PER_WORLD` for contacts."""
    m = scene.model
    return CONTACTS_PER_WORLD, int(ROWS_PER_WORLD + 6 * m.neq + m.nv)


class Engine:
    """The worlds of one model kind ("ours": lift-shake and six-dir; "dexgraspbench": DexGraspBench's test) for
    one hand and config, on one device. Reused across calls (`engine`): its model, buffers and graphs stay."""

    def __init__(self, spec: HandSpec, cfg: PhysicsConfig, kind: str, slots: int, nworld: int = MAX_WORLDS,
                 device: str | None = None):
        reason = unavailable()
        if reason:
            raise FfcgsError(reason)
        route_mujoco_warnings()
        import mujoco_warp as mjw
        import warp as wp

        t0 = time.perf_counter()
        self.wp, self.mjw, self.kind, self.cfg = wp, mjw, kind, cfg
        self.scene = world_model.template(spec, cfg, kind, slots)
        m = self.scene.model
        if m.nmocap != (2 if self.scene.table_geom >= 0 else 1):  # the wrist's target and the table's mount
            raise FfcgsError(f"the GPU worlds drive a mocap wrist and table, the hand's model has more mocap bodies")
        if m.na:
            raise FfcgsError("the GPU worlds hold no actuator activations: this hand's actuators have state")
        self.nworld, self.slots = int(nworld), int(slots)
        self.lay, self.sched = Layout(m.nu), Schedule(cfg, m.nu)
        self.nconmax, self.njmax = buffer_sizes(self.scene)
        self.device = wp.get_device(device)
        self.k = K.build(float(MAX_SPEED))
        self.bad_overflow = untrusted_overflows()
        gclass = np.zeros(m.ngeom, np.int32)
        gclass[self.scene.hand_geoms] = K.HAND
        gclass[self.scene.obj_geoms] = K.OBJECT
        if self.scene.table_geom >= 0:
            gclass[self.scene.table_geom] = K.TABLE
        obj = self.scene.obj_body
        self.obj_dof = int(m.jnt_dofadr[m.body_jntadr[obj]])
        self.qpos0 = np.array(m.qpos0)
        with wp.ScopedDevice(self.device):
            self.m = put_model(m, batch_sizes=dict.fromkeys(BATCHED, self.nworld))
            self.m.opt.gravity = wp.zeros(self.nworld, dtype=wp.vec3)
            for item in filter(None, os.environ.get("FFCGS_WARP_SOLVER", "").split(",")):  # bench experiments
                k, _, v = item.partition("=")
                if k == "tolerance":
                    self.m.opt.tolerance = wp.array([float(v)], dtype=wp.float32)
                else:
                    setattr(self.m.opt, k, int(v))
            arr = lambda x, dt=wp.int32: wp.array(np.ascontiguousarray(x), dtype=dt)  # noqa: E731
            self.col, self.gclass = arr(self.lay.col), arr(gclass)
            self.slot_geoms = arr(self.scene.obj_geoms.astype(np.int32))
            self.ev_t, self.ev_code = arr(self.sched.ev_t), arr(self.sched.ev_code)
            self.sched_i, self.sched_f = arr(self.sched.ints), arr(self.sched.floats, wp.float32)
            self.bounds = arr(self.sched.bounds, wp.float32)
            self.ip = wp.zeros((self.nworld, self.lay.ni), dtype=wp.int32)
            self.fp = wp.zeros((self.nworld, self.lay.nf), dtype=wp.float32)
            self.snap = [wp.zeros((self.nworld, n), dtype=wp.float32) for n in (m.nq, m.nv, m.nv)]
            self.touch, self.table = (wp.zeros(self.nworld, dtype=wp.int32) for _ in range(2))
        self._mesh_cap: dict[str, int] = {}
        self._data: dict[int, tuple] = {}
        # host view of the worlds: which job, grasp and direction each runs (-1: free)
        self.tag = np.full((self.nworld, 3), -1, np.int64)
        self.stats = Stats()
        self.start_run()
        self.stats.setup_s = time.perf_counter() - t0

    def start_run(self) -> None:
        """A new run (`run_jobs`): fresh worlds, no objects (keys name one run's objects: `runner` numbers them 0, 1,
        ... in every call), and figures of its own (the engine's start counts in the run that built it)."""
        self.pool = world_model.MeshPool(self.scene.model)
        self._objects: dict[object, int] = {}
        self._rows: list[world_model.ObjectRows] = []
        self._first: list[int] = []
        self._dirty = True  # the mesh pool and object rows go to the device before the next placement
        self.size = 0
        self.timing: dict[int, tuple[float, int]] = {}  # world count -> (seconds, step calls) of stepping
        self.stats = Stats(setup_s=0.0 if self.stats.steps else self.stats.setup_s)

    # -------------------------------------------------------------------------------------------------------
    # objects

    def add_object(self, key, scene: PhysicsScene) -> int:
        """The engine's index of the object of `scene` (added on first sight of `key`)."""
        if key in self._objects:
            return self._objects[key]
        world_model.check_same_hand(self.scene, scene)
        rows = world_model.object_rows(scene)
        if rows.parts > self.slots:
            raise FfcgsError(f"an object of {rows.parts} convex parts does not fit the {self.slots} slots of the "
                             f"GPU worlds (physics.max_hulls)")
        self._objects[key] = len(self._rows)
        self._rows.append(rows)
        self._first.append(self.pool.add(rows.meshes))
        self.stats.objects += 1
        self._dirty = True
        return self._objects[key]

    def _upload_pool(self) -> None:
        """The mesh pool into the model's mesh arrays; arrays that must grow are reallocated (at twice the size,
        so this is rare) and the captured graphs, which point at them, are dropped."""
        wp = self.wp
        host = self.pool.arrays()
        with wp.ScopedDevice(self.device):
            for f in MESH_FIELDS:
                old = getattr(self.m, f"mesh_{f}")
                a = np.ascontiguousarray(host[f]).astype(wp.dtype_to_numpy(
                    getattr(old.dtype, "_wp_scalar_type_", old.dtype)))
                a = a.reshape(len(host[f]), -1) if a.ndim > 1 else a
                n = len(a)
                if f not in self._mesh_cap or n > self._mesh_cap[f]:
                    cap = max(1, 2 * n)
                    new = wp.zeros(cap, dtype=old.dtype)
                    setattr(self.m, f"mesh_{f}", new)
                    self._mesh_cap[f] = cap
                    for d in getattr(self, "_data", {}).values():
                        d[1] = None
                if n:
                    wp.copy(getattr(self.m, f"mesh_{f}"), wp.array(a, dtype=old.dtype), count=n)
            self.m.nmesh = self.pool.nmesh
        self._dirty = False
        self._upload_objects()

    def _upload_objects(self) -> None:
        wp, rows = self.wp, self._rows
        with wp.ScopedDevice(self.device):
            if not rows:
                self._obj = None
                return
            cat = lambda f: np.concatenate([r.geom[f] for r in rows])  # noqa: E731
            body = lambda f: np.stack([np.asarray(r.body[f], np.float64) for r in rows])  # noqa: E731
            nparts = np.array([r.parts for r in rows], np.int32)
            a = lambda x, dt: wp.array(np.ascontiguousarray(x, np.float32 if dt != wp.int32 else np.int32),  # noqa
                                       dtype=dt)
            self._obj = [a(nparts, wp.int32), a(np.concatenate([[0], np.cumsum(nparts)[:-1]]), wp.int32),
                         a(np.array(self._first), wp.int32), a(cat("dataid"), wp.int32), a(cat("pos"), wp.vec3),
                         a(cat("quat"), wp.quat), a(cat("size"), wp.vec3), a(cat("aabb"), wp.vec3),
                         a(cat("rbound"), wp.float32), a(body("mass").reshape(-1), wp.float32),
                         a(body("ipos"), wp.vec3), a(body("iquat"), wp.quat), a(body("inertia"), wp.vec3),
                         a(body("invweight0"), wp.vec2), a(body("subtreemass").reshape(-1), wp.float32),
                         a(np.stack([r.dof_invweight0 for r in rows]), wp.float32),
                         a(np.stack([r.friction for r in rows]), wp.vec3)]

    # -------------------------------------------------------------------------------------------------------
    # tasks

    def fresh(self, job_id: int, job: Job, obj: int, rows: np.ndarray) -> Block:
        """The first programs of grasps `rows` of `job` (lift-shake; six-dir's or DexGraspBench's closing)."""
        L, sc, b = self.lay, self.scene, job.batch
        kind = {"lift-shake": K.LIFT, "six-dir": K.SIX_CLOSE}.get(job.protocol, K.BENCH_SQUEEZE)
        n, m = len(rows), sc.model
        ip = np.zeros((n, L.ni), np.int32)
        ip[:, L.KIND], ip[:, L.EVP] = kind, self.sched.adr[kind]
        ip[:, L.EVE], ip[:, L.OBJ] = self.sched.adr[kind] + self.sched.num[kind], obj
        fp = np.zeros((n, L.nf), np.float32)
        q = m.nu
        fp[:, L.QS: L.QS + q], fp[:, L.QT: L.QT + q] = b.q_start[rows], b.q_target[rows]
        if b.q_grasp is not None:
            fp[:, L.QG: L.QG + q] = b.q_grasp[rows]
        fp[:, L.WP: L.WP + 3], fp[:, L.WQ: L.WQ + 4] = b.wrist_pos[rows], b.wrist_quat[rows]
        fp[:, L.RQ] = 1.0
        fp[:, L.TZ] = self._rows[obj].table_z
        qpos = np.tile(self.qpos0, (n, 1))
        qpos[:, sc.root_qpos: sc.root_qpos + 3], qpos[:, sc.root_qpos + 3: sc.root_qpos + 7] = \
            b.wrist_pos[rows], b.wrist_quat[rows]
        qpos[:, sc.hand_qpos] = b.q_start[rows] @ sc.coupling.T
        zeros = np.zeros((n, m.nv))
        tag = np.stack([np.full(n, job_id), rows, np.full(n, -1)], axis=1)
        return Block(ip, fp, qpos, zeros, zeros.copy(), tag)

    def pushes(self, ip: np.ndarray, fp: np.ndarray, snaps: list[np.ndarray], tag: np.ndarray,
               accel: float) -> Block:
        """Six push programs for each closed world (its rows `ip`, `fp`, its kept state `snaps`)."""
        L = self.lay
        kind = K.SIX_PUSH if self.kind == "ours" else K.BENCH_PUSH
        n = len(ip)
        ip6, fp6 = np.repeat(ip, 6, axis=0), np.repeat(fp, 6, axis=0)
        ip6[:, L.KIND], ip6[:, L.T], ip6[:, L.ST] = kind, 0, K.RUNNING
        ip6[:, L.EVP], ip6[:, L.EVE] = self.sched.adr[kind], self.sched.adr[kind] + self.sched.num[kind]
        ip6[:, [L.UNST, L.FLAG, L.TOUCH, L.LOST, L.TABLE]] = 0
        mass = np.array([self._rows[o].mass for o in ip[:, L.OBJ]])
        fp6[:, L.F: L.F + 3] = (accel * np.repeat(mass, 6)[:, None]) * np.tile(P.DIRECTIONS, (n, 1))
        fp6[:, L.MOVE], fp6[:, L.ROT] = 0.0, 0.0
        tag6 = np.repeat(tag, 6, axis=0)
        tag6[:, 2] = np.tile(np.arange(6), n)
        return Block(ip6, fp6, *(np.repeat(s, 6, axis=0) for s in snaps), tag6)

    # -------------------------------------------------------------------------------------------------------
    # worlds

    def _world_count(self, n: int) -> int:
        size, least = self.nworld, MIN_WORLDS if self.device.is_cuda else MIN_WORLDS_CPU
        while size // 2 >= max(n, least):
            size //= 2
        return size

    def _data_for(self, size: int):
        if size not in self._data:
            wp, m = self.wp, self.scene.model
            with wp.ScopedDevice(self.device):
                d = self.mjw.put_data(m, mujoco.MjData(m), nworld=size, nconmax=self.nconmax, njmax=self.njmax)
            self._data[size] = [d, None]
        return self._data[size]

    def resize(self, size: int) -> None:
        """Step `size` worlds from now on, all of them free."""
        self.size = size
        self._data_for(size)
        self.tag[:] = -1
        self.vacate(np.arange(size))

    def vacate(self, idx: np.ndarray) -> None:
        """Empty worlds `idx`: no program, no object, no table (a free world costs a step but solves nothing)."""
        if len(idx) == 0:
            return
        wp, m = self.wp, self.m
        with wp.ScopedDevice(self.device):
            wp.launch(self.k["vacate"], dim=len(idx), inputs=[wp.array(np.asarray(idx, np.int32), dtype=wp.int32),
                                                              self.slot_geoms, self.ip, m.geom_dataid,
                                                              m.opt.gravity])
        self.tag[idx] = -1

    def place(self, block: Block) -> Block:
        """Put as many tasks of `block` as there are free worlds; returns the rest."""
        free = np.flatnonzero(self.tag[: self.size, 0] < 0)
        n = min(len(free), len(block.ip))
        if n == 0:
            return block
        wp = self.wp
        now, rest = block.split(n)
        idx = free[:n]
        d = self._data[self.size][0]
        with wp.ScopedDevice(self.device):
            a = lambda x, dt=wp.float32: wp.array(np.ascontiguousarray(x, np.float32 if dt == wp.float32 else  # noqa
                                                                       np.int32), dtype=dt)
            widx = a(idx, wp.int32)
            wp.launch(self.k["place"], dim=n, inputs=[widx, a(now.ip, wp.int32), a(now.fp), a(now.qpos),
                                                      a(now.qvel), a(now.warm), self.ip, self.fp, d.qpos, d.qvel,
                                                      d.qacc_warmstart, d.overflow])
            o, m = self._obj, self.m
            wp.launch(self.k["gather"], dim=n, inputs=[
                widx, self.ip, self.fp, self.col, self.slot_geoms, int(self.scene.obj_body), self.obj_dof, *o, int(self.scene.table_geom), m.geom_friction, m.geom_dataid, m.geom_pos, m.geom_quat, m.geom_size,
                m.geom_aabb, m.geom_rbound, m.body_mass, m.body_ipos, m.body_iquat, m.body_inertia,
                m.body_invweight0, m.body_subtreemass, m.dof_invweight0, m.opt.gravity, GRAVITY])
        self.tag[idx] = now.tag
        return rest

    def _one_step(self, d) -> None:
        wp, k, s = self.wp, self.k, self.size
        wp.launch(k["control"], dim=s, inputs=[self.ip, self.fp, self.col, self.sched_i, self.sched_f, self.ev_t,
                                              self.ev_code, int(self.scene.obj_body), int(self.scene.hold_eq),
                                              d.qpos, d.qvel, d.qacc_warmstart, d.ctrl, d.mocap_pos, d.mocap_quat,
                                              d.eq_active, d.xfrc_applied, *self.snap])
        self.mjw.step(self.m, d)
        wp.launch(k["clear_flags"], dim=s, inputs=[self.touch, self.table])
        wp.launch(k["contact_flags"], dim=d.contact.worldid.shape[0],
                  inputs=[d.nacon, d.contact.geom, d.contact.worldid, self.gclass, self.touch, self.table])
        wp.launch(k["events"], dim=s, inputs=[self.ip, self.fp, self.col, self.ev_t, self.ev_code, self.bounds,
                                             int(self.scene.obj_body), int(self.scene.root_body), self.bad_overflow,
                                             d.overflow, d.qpos, d.qvel, d.xpos, d.xquat, d.xmat, self.touch,
                                             self.table])

    def advance(self, n: int) -> bool:
        """`n` step calls of the current worlds (a captured graph on CUDA); True when this call captured the graph
        (the first at this world count: Warp's kernels load or compile then)."""
        wp = self.wp
        entry = self._data[self.size]
        d = entry[0]
        with wp.ScopedDevice(self.device):
            if not self.device.is_cuda:
                first = not entry[1]
                for _ in range(n):
                    self._one_step(d)
                entry[1] = True  # no graph on the CPU: marks that this world count has stepped
                return first
            captured = entry[1] is None
            if captured:
                with wp.ScopedCapture(device=self.device) as capture:
                    self._one_step(d)
                entry[1] = capture.graph
                n -= 1
            for _ in range(n):
                wp.capture_launch(entry[1])
        return captured

    def status(self) -> tuple[np.ndarray, np.ndarray]:
        """The int and float rows of the current worlds (host copies)."""
        return self.ip.numpy()[: self.size], self.fp.numpy()[: self.size]

    def snapshots(self, idx: np.ndarray) -> list[np.ndarray]:
        return [s.numpy()[idx] for s in self.snap]

    def evacuate(self) -> Block:
        """Every running world as tasks (state included), the worlds then free: survivors moving to fewer worlds."""
        ip, fp = self.status()
        busy = np.flatnonzero((self.tag[: self.size, 0] >= 0) & (ip[:, self.lay.ST] == K.RUNNING))
        d = self._data[self.size][0]
        return Block(ip[busy], fp[busy], d.qpos.numpy()[busy], d.qvel.numpy()[busy],
                      d.qacc_warmstart.numpy()[busy], self.tag[busy].copy())


_ENGINES: dict[tuple, Engine] = {}  # one per kind (`engine`): bounded by the kinds
compiled.register("physics.worlds engines", _ENGINES)


def engine(spec: HandSpec, cfg: PhysicsConfig, kind: str, slots: int, nworld: int = MAX_WORLDS,
           device: str | None = None) -> Engine:
    """The process's engine for (hand, config, kind, slots, worlds, device): built once, its graphs kept."""
    key = (spec.name, spec.mjcf_path, cfg, kind, slots, nworld, device)
    if key not in _ENGINES:
        for old in [k for k in _ENGINES if k[3] == kind]:  # one per kind: each holds buffers for `nworld` worlds
            del _ENGINES[old]
        _ENGINES[key] = Engine(spec, cfg, kind, slots, nworld, device)
    return _ENGINES[key]


def warm() -> bool:
    """Whether an engine is built in this process (a run then pays no start-up)."""
    return bool(_ENGINES)


def clear() -> None:
    """Drop the engines (their device buffers and graphs)."""
    _ENGINES.clear()


def run_jobs(spec: HandSpec, jobs: Iterable[Job], nworld: int = MAX_WORLDS, device: str | None = None,
             slots: int | None = None, progress: Callable[[int], None] | None = None, stats: dict | None = None,
             record: bool = False) -> list[dict[str, np.ndarray] | None]:
    """Run every job (one protocol over one object's grasps) as worlds; returns `run_protocol`'s arrays per job,
    in order, None for a job whose object could not become worlds (too many parts for the slots, a model MuJoCo
    Warp refuses; a warning says why: the caller runs it on the CPU). `jobs` may be a generator that prepares objects as it goes (`runner.evaluate_many`): it runs on a
    thread, so the next objects' geometry is built while the GPU simulates. `progress(k)`: k more grasps have all
    their worlds done (grasps that start in penetration count at once). `stats` (a dict): filled with each
    engine's `Stats` by kind. `record`: remember this run's seconds per step and start-up for `auto` (`cost`)."""
    feed: queue.Queue = queue.Queue(maxsize=64)
    END = object()

    def produce():
        try:
            for j in jobs:
                feed.put(j)
        except BaseException as e:  # noqa: BLE001 - handed to the caller's thread
            feed.put(e)
        feed.put(END)

    threading.Thread(target=produce, daemon=True, name="ffcgs-physics-feed").start()
    states: list[JobState] = []
    engines: dict[str, Engine] = {}
    pending: dict[str, list[Block]] = {}
    fed = False
    while True:
        while not fed:  # take what the feeder has ready; block only when nothing is left to simulate
            idle = all(not pending.get(k) and not (e.tag[: e.size, 0] >= 0).any() for k, e in engines.items())
            try:
                item = feed.get(block=idle)
            except queue.Empty:
                break
            if item is END:
                fed = True
                break
            if isinstance(item, BaseException):
                raise item
            _add(spec, item, states, engines, pending, nworld, device, slots, progress)
        if fed and all(not pending.get(k) and not (e.tag[: e.size, 0] >= 0).any() for k, e in engines.items()):
            break
        for kind, e in engines.items():
            _round(e, pending[kind], states, progress, fed)
    if stats is not None:
        stats.update({k: e.stats for k, e in engines.items()})
    if record:
        _remember(engines)
    for s in states:
        if s.cpu is not None:
            warnings.warn(f"physics: {s.job.protocol} of an object runs on the CPU: {s.cpu}", stacklevel=2)
    return [s.result() for s in states]


def _remember(engines: dict[str, "Engine"]) -> None:
    from ffcgs_jax.physics import cost

    for e in engines.values():
        if not e.device.is_cuda:
            continue  # Warp on the CPU is a test path, not a choice `auto` makes
        for size, (seconds, steps) in e.timing.items():
            if steps >= 4 * SYNC:
                cost.remember_warp(size, seconds / steps)
        if e.stats.setup_s > 0:
            cost.remember_setup(e.stats.setup_s)


def _add(spec, job: Job, states, engines, pending, nworld, device, slots, progress) -> None:
    kind = world_model.kind_of(job.scene)
    if kind not in engines:
        n = slots or job.cfg.max_hulls
        engines[kind] = engine(spec, world_model.engine_config(job.cfg), kind, n, nworld, device)
        engines[kind].start_run()
        pending[kind] = []
    e = engines[kind]
    if world_model.engine_config(job.cfg) != e.cfg:
        raise FfcgsError("the jobs of one GPU run need one physics config per protocol kind (but for the object's "
                         "friction, mass and geometry, which are per world)")
    key = ("job", len(states)) if job.object_key is None else job.object_key
    st = JobState(job)
    states.append(st)
    try:
        obj = e.add_object(key, job.scene)
    except FfcgsError as err:  # this object cannot become worlds: its grasps go to the CPU (`JobState.cpu`)
        st.cpu = str(err)
        return
    rows = np.flatnonzero(~st.bad_start)
    if progress is not None and len(rows) < st.b:
        progress(st.b - len(rows))
    if len(rows):
        pending[kind].append(e.fresh(len(states) - 1, job, obj, rows))
        st.open += len(rows)


def _round(e: Engine, pending: list[Block], states: list[JobState], progress, fed: bool) -> None:
    L = e.lay
    t0 = time.perf_counter()
    if e._dirty:
        e._upload_pool()
    queued = sum(len(b.ip) for b in pending)
    busy = int((e.tag[: e.size, 0] >= 0).sum()) if e.size else 0
    want = e._world_count(queued + busy)
    if e.size == 0:
        e.resize(want)
    elif COMPACT and fed and want < e.size and queued == 0:  # the tail: survivors move to fewer worlds
        pending.insert(0, e.evacuate())
        e.resize(want)
    elif want > e.size:  # more work arrived than the worlds hold: grow (the running worlds move along)
        pending.insert(0, e.evacuate())
        e.resize(want)
    while pending:
        rest = e.place(pending[0])
        if len(rest.ip):
            pending[0] = rest
            break
        pending.pop(0)
    t1 = time.perf_counter()
    running = int((e.tag[: e.size, 0] >= 0).sum())
    if running == 0:
        e.stats.place_s += t1 - t0
        return
    captured = e.advance(SYNC)
    ip, fp = e.status()
    t2 = time.perf_counter()
    if captured:  # kernels compiled or loaded and the graph captured: start-up, not a measure of stepping
        e.stats.setup_s += t2 - t1
    else:
        sec, n = e.timing.get(e.size, (0.0, 0))
        e.timing[e.size] = (sec + t2 - t1, n + SYNC)
        e.stats.steps += SYNC
        e.stats.world_steps += SYNC * e.size
        e.stats.busy_steps += SYNC * running
        e.stats.step_s += t2 - t1
    ended = np.flatnonzero((e.tag[: e.size, 0] >= 0) & (ip[:, L.ST] != K.RUNNING))
    done_grasps = 0
    if len(ended):
        spawn = []
        for w in ended:
            j, g, k = e.tag[w]
            st = states[j]
            r, f = ip[w], fp[w]
            kind = r[L.KIND]
            st.flagged[g] |= bool(r[L.FLAG])
            if kind == K.LIFT:
                st.move[g], st.rot[g] = f[L.MOVE], f[L.ROT]
                st.lost[g], st.table[g], st.unstable[g] = bool(r[L.LOST]), bool(r[L.TABLE]), bool(r[L.UNST])
                st.open -= 1
                done_grasps += 1
            elif kind in (K.SIX_CLOSE, K.BENCH_SQUEEZE):
                st.unstable[g] |= bool(r[L.UNST])
                st.lost[g] = r[L.ST] == K.BRANCHED and not r[L.TOUCH]
                push = r[L.ST] == K.BRANCHED and (kind == K.BENCH_SQUEEZE or r[L.TOUCH])
                if push:
                    spawn.append(w)
                    st.open += 5  # six pushes replace the closing world
                else:
                    st.open -= 1
                    done_grasps += 1
            else:
                st.move_dir[g, k], st.rot_dir[g, k] = f[L.MOVE], f[L.ROT]
                st.unstable_dir[g, k], st.pushed[g, k] = bool(r[L.UNST]), True
                st.open -= 1
                if st.pushed[g].all():
                    done_grasps += 1
        if spawn:
            spawn = np.array(spawn)
            snaps = e.snapshots(spawn)
            accel = states[e.tag[spawn[0], 0]].job.cfg.accel
            pending.insert(0, e.pushes(ip[spawn], fp[spawn], snaps, e.tag[spawn].copy(), accel))
        e.vacate(ended)
    e.stats.place_s += t1 - t0
    e.stats.read_s += time.perf_counter() - t2
    if progress is not None and done_grasps:
        progress(done_grasps)
