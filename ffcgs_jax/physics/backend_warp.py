"""The physics test on MuJoCo Warp: `WarpSim`, the `backend.Simulator` interface with the grasps of a batch as
the worlds of one `mujoco_warp.Data`.

The same scene (`scene.build`), protocols and success rules as the CPU backend. Each step's inputs (servo targets,
the wrist's mocap position) come from per-chunk buffers on the device, indexed by a step counter that also lives on
the device, so on a CUDA device one step (inputs, `mujoco_warp.step`, counter) is captured once as a CUDA graph and
replayed. A state is a device copy of what a step reads (qpos, qvel, act, warm start, time, mocap, ctrl), so the six
pushes of six-dir each start from the same closed state, as on the CPU.

Contact and constraint buffers are sized from the scene (`buffer_sizes`); MuJoCo Warp flags a world whose
contacts or constraint rows did not fit (`Data.overflow`). Such a world's result is not trusted: `WarpSim.flagged`
marks it and `runner.evaluate` runs those grasps again on the CPU. A world whose state is not finite or runs away
(`backend.diverged`, read after each chunk) is `WarpSim.unstable`: that grasp fails "unstable".

Needs `pip install -e ".[warp]"` (warp-lang, mujoco-warp). It runs on a CUDA device, or slowly on the CPU (what
the tests use); kernels compile on first use (about a minute) and are cached on disk by Warp.
"""

import ctypes.util
import dataclasses
import typing

import mujoco
import numpy as np

from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.physics.backend import CHUNK, Batch, Segment, diverged, pose_hand, route_mujoco_warnings
from ffcgs_jax.physics.scene import PhysicsScene
from ffcgs_jax.runtime.fixed_shapes import pad_rows

MAX_WORLDS = 8192  # grasps simulated at once: 8192 worlds of the mug scene fit an H100 with room to spare
MIN_WORLDS = 64  # the smallest batch of worlds survivors move to: below it a step costs about the same
_STATE_FIELDS = ("qpos", "qvel", "act", "qacc_warmstart", "time", "mocap_pos", "mocap_quat", "ctrl")


def unavailable() -> str | None:
    """Why the warp backend cannot run here, or None when it can."""
    try:
        import mujoco_warp  # noqa: F401
        import warp  # noqa: F401
    except ImportError as e:
        return f"the warp physics backend needs warp-lang and mujoco-warp (pip install -e \".[warp]\"): {e}"
    return None


def no_cuda() -> str | None:
    """Why warp would run on the CPU here (no CUDA device), or None when it has one."""
    if ctypes.util.find_library("cuda") is None:  # no driver: starting Warp would only print a warning about it
        return "no CUDA driver"
    try:
        import warp as wp
    except ImportError:
        return None  # a CUDA machine without warp-lang: `unavailable` says so

    wp.config.log_level = wp.LOG_WARNING  # no start-up banner on stdout: commands print their own results there
    return None if wp.get_cuda_device_count() > 0 else "Warp finds no CUDA device"


def put_model(m: mujoco.MjModel, **kw):
    """MuJoCo Warp's model of `m` (`kw`: `mujoco_warp.put_model`'s), its overflow printf off: a world that overflows
    is flagged (`untrusted_overflows`) and run again on the CPU, and the runner says so in one warning line, where
    the printf put 2 lines per world on the terminal, over 1,000 for an object that overflows in every trial."""
    import mujoco_warp as mjw

    model = mjw.put_model(m, **kw)
    model.opt.warn_overflow = 0
    return model


def untrusted_overflows() -> int:
    """The `Data.overflow` bits of a world whose simulation dropped contacts or constraint rows: never scored."""
    import mujoco_warp as mjw

    bits = mjw.OverflowType
    return int(bits.NEFC | bits.NJMAX_NNZ | bits.BROADPHASE | bits.NARROWPHASE | bits.CCD | bits.NVMAX
               | bits.EPA_HORIZON)


def buffer_sizes(scene: PhysicsScene) -> tuple[int, int]:
    """(contacts, constraint rows) to allocate per world. Every hand geom may touch the object (several points
    for a box or a mesh part) and the table; each contact takes condim rows (elliptic cones) or 2 (condim - 1)
    (pyramidal), the equality constraints 6 rows each. Generous: memory is cheap next to a wrong result, and
    `Data.overflow` catches the rest."""
    m = scene.model
    nhand, nobj = len(scene.hand_geoms), len(scene.obj_geoms)
    nconmax = int(8 * nhand + 4 * nobj + 32)
    condim = int(m.geom_condim.max())
    rows = condim if m.opt.cone == mujoco.mjtCone.mjCONE_ELLIPTIC else 2 * (condim - 1)
    return nconmax, int(rows * nconmax + 6 * m.neq + m.nv)


@typing.no_type_check  # Warp's annotations are array specs, not types: no runtime type checking here
def _kernels():
    import warp as wp

    @wp.kernel
    @typing.no_type_check
    def inputs(counter: wp.array(dtype=wp.int32), ctrl_buf: wp.array3d(dtype=wp.float32),
               pos_buf: wp.array2d(dtype=wp.vec3), ctrl: wp.array2d(dtype=wp.float32),
               mocap_pos: wp.array2d(dtype=wp.vec3)):
        w = wp.tid()
        j = counter[0]
        jc = wp.min(j, counter[1] - 1)  # a constant segment has one row of inputs
        for a in range(ctrl.shape[1]):
            ctrl[w, a] = ctrl_buf[w, jc, a]
        mocap_pos[w, 0] = pos_buf[w, wp.min(j, counter[2] - 1)]

    @wp.kernel
    @typing.no_type_check
    def advance(counter: wp.array(dtype=wp.int32)):
        counter[0] = counter[0] + 1

    return inputs, advance


@dataclasses.dataclass
class WarpState:
    """The per-world arrays a step reads, for `n` grasps: device arrays of one `_Worlds` (rows past n are
    padding), or host arrays of n rows after `WarpSim.take`. `overflow` (n,): a world's buffers overflowed at some
    step so far."""

    arrays: dict
    n: int
    overflow: np.ndarray


class _Worlds:
    """One `mujoco_warp.Data` of `nworld` worlds, its per-chunk input buffers and its captured step."""

    def __init__(self, sim: "WarpSim", nworld: int):
        wp, m = sim._wp, sim.scene.model
        self.nworld = nworld
        d0 = mujoco.MjData(m)  # no forward pass: its contacts would count against the buffers
        self.d = sim._mjw.put_data(m, d0, nworld=nworld, nconmax=sim.nconmax, njmax=sim.njmax)
        self.ctrl_buf = wp.zeros((nworld, CHUNK, m.nu), dtype=wp.float32)
        self.pos_buf = wp.zeros((nworld, CHUNK), dtype=wp.vec3)
        self.counter = wp.zeros(3, dtype=wp.int32)
        self.graph = None


class WarpSim:
    """Runs segments for a batch of up to `nworld` grasps on MuJoCo Warp. A batch runs on the smallest of
    nworld, nworld / 2, nworld / 4, ... (down to `MIN_WORLDS`) worlds that holds it, padded: as grasps whose failure
    is certain leave (`take`), the survivors move to fewer worlds and each step costs less."""

    def __init__(self, scene: PhysicsScene, nworld: int, device: str | None = None,
                 sizes: tuple[int, int] | None = None):
        reason = unavailable()
        if reason:
            raise FfcgsError(reason)
        route_mujoco_warnings()  # `initial` poses the hands with CPU MuJoCo
        import mujoco_warp as mjw
        import warp as wp

        m = scene.model
        if m.nmocap != 1:
            raise FfcgsError(f"the warp backend drives one mocap wrist, the scene has {m.nmocap}")
        self.scene, self.nworld = scene, int(nworld)
        self.nconmax, self.njmax = sizes or buffer_sizes(scene)
        self.device = wp.get_device(device)
        self._wp, self._mjw = wp, mjw
        self._inputs, self._advance = _kernels()
        self._bad = untrusted_overflows()
        with wp.ScopedDevice(self.device):
            self.m = put_model(m)
        self._worlds: dict[int, _Worlds] = {}

    def _size(self, n: int) -> int:
        if n > self.nworld:
            raise FfcgsError(f"a warp batch holds at most {self.nworld} grasps, got {n}")
        size = self.nworld
        while size // 2 >= max(n, MIN_WORLDS):
            size //= 2
        return size

    def _worlds_for(self, n: int) -> _Worlds:
        size = self._size(n)
        if size not in self._worlds:
            with self._wp.ScopedDevice(self.device):
                self._worlds[size] = _Worlds(self, size)
        return self._worlds[size]

    # ---------------------------------------------------------------------------------------------------------
    # state <-> Data

    def _pad(self, x: np.ndarray, size: int | None = None) -> np.ndarray:
        # not a padder of its own: it picks the world count (`_size` refuses a batch larger than the worlds)
        return pad_rows(x, size or self._size(len(x)))

    def _save(self, w: _Worlds, n: int, overflow: np.ndarray) -> WarpState:
        return WarpState({f: self._wp.clone(getattr(w.d, f)) for f in _STATE_FIELDS}, n, overflow)

    def _load(self, state: WarpState) -> _Worlds:
        w = self._worlds_for(state.n)
        for f in _STATE_FIELDS:
            a = state.arrays[f]
            if isinstance(a, np.ndarray):
                self._assign(w, f, self._pad(a, w.nworld))
            else:
                self._wp.copy(getattr(w.d, f), a)
        return w

    def _assign(self, w: _Worlds, field: str, values: np.ndarray) -> None:
        wp, arr = self._wp, getattr(w.d, field)
        scalar = wp.dtype_to_numpy(getattr(arr.dtype, "_wp_scalar_type_", arr.dtype))  # no device round trip
        arr.assign(wp.array(np.ascontiguousarray(values, dtype=scalar), dtype=arr.dtype, device=self.device))

    def take(self, state: WarpState, idx: np.ndarray) -> WarpState:
        """The grasps at `idx`, as host arrays (one download and gather; the next run uploads them to the
        smallest worlds that hold them)."""
        idx = np.asarray(idx)
        if len(idx) == state.n and (idx == np.arange(state.n)).all():
            return state
        arrays = {f: (a if isinstance(a, np.ndarray) else a.numpy())[idx] for f, a in state.arrays.items()}
        return WarpState(arrays, len(idx), state.overflow[idx])

    def flagged(self, state: WarpState) -> np.ndarray:
        return state.overflow

    def unstable(self, state: WarpState) -> np.ndarray:
        qpos, qvel = (a if isinstance(a, np.ndarray) else a.numpy() for a in map(state.arrays.get, ("qpos", "qvel")))
        return diverged(qpos[: state.n], qvel[: state.n])

    def initial(self, batch: Batch) -> WarpState:
        """Each grasp's start (hand at its wrist pose with the fingers at q_start, at rest), set on the CPU."""
        m, sc = self.scene.model, self.scene
        d = mujoco.MjData(m)
        b = len(batch.q_start)
        qpos = np.zeros((b, m.nq))
        for g in range(b):
            pose_hand(sc, d, batch.wrist_pos[g], batch.wrist_quat[g], batch.q_start[g])
            qpos[g] = d.qpos
        w = self._worlds_for(b)
        with self._wp.ScopedDevice(self.device):
            self._assign(w, "qpos", self._pad(qpos, w.nworld))
            for f in ("qvel", "act", "qacc_warmstart", "time", "xfrc_applied", "qfrc_applied"):
                getattr(w.d, f).zero_()
            self._assign(w, "mocap_pos", self._pad(batch.wrist_pos, w.nworld)[:, None])
            self._assign(w, "mocap_quat", self._pad(batch.wrist_quat, w.nworld)[:, None])
            self._assign(w, "ctrl", self._pad(batch.q_start, w.nworld))
            return self._save(w, b, np.zeros(b, bool))

    # ---------------------------------------------------------------------------------------------------------
    # stepping

    def _step(self, w: _Worlds) -> None:
        wp = self._wp
        wp.launch(self._inputs, dim=w.nworld, inputs=[w.counter, w.ctrl_buf, w.pos_buf],
                  outputs=[w.d.ctrl, w.d.mocap_pos], device=self.device)
        self._mjw.step(self.m, w.d)
        wp.launch(self._advance, dim=1, inputs=[w.counter], device=self.device)

    def _steps(self, w: _Worlds, k: int) -> None:
        wp = self._wp
        if not self.device.is_cuda:
            for _ in range(k):
                self._step(w)
            return
        if w.graph is None:  # buffers and counter stay put, so one captured step serves every chunk
            with wp.ScopedCapture(device=self.device) as capture:
                self._step(w)
            w.graph = capture.graph
            k -= 1  # the capture ran the step once
        for _ in range(k):
            wp.capture_launch(w.graph)

    def run(self, state: WarpState, batch: Batch, seg: Segment, track=None) -> WarpState:
        """Advance `state` through `seg`; `track(state)` sees the state after each `CHUNK` of steps."""
        wp, m, sc = self._wp, self.scene.model, self.scene
        n = state.n
        with wp.ScopedDevice(self.device):
            w = self._load(state)
            w.d.overflow.zero_()
            xfrc = np.zeros((w.nworld, m.nbody, 6))
            if seg.force is not None:
                xfrc[:, sc.obj_body, :3] = seg.force
            self._assign(w, "xfrc_applied", xfrc)
            if sc.hold_eq >= 0:
                active = np.ones((w.nworld, m.neq), bool)
                active[:, sc.hold_eq] = seg.hold
                self._assign(w, "eq_active", active)
            wrist = self._pad(batch.wrist_pos, w.nworld)
            for i0 in range(0, seg.n, CHUNK):
                i1 = min(seg.n, i0 + CHUNK)
                ctrl, off = seg.make(i0, i1)
                ctrl = self._pad(np.broadcast_to(ctrl, (n, *ctrl.shape[1:])), w.nworld)
                pos = wrist[:, None] + off[None]
                w.ctrl_buf[:, : ctrl.shape[1]].assign(wp.array(ctrl.astype(np.float32), dtype=wp.float32))
                w.pos_buf[:, : pos.shape[1]].assign(wp.array(pos.astype(np.float32), dtype=wp.vec3))
                w.counter.assign(wp.array([0, ctrl.shape[1], pos.shape[1]], dtype=wp.int32))
                self._steps(w, i1 - i0)
                if track is not None:  # a probe reloads this same state: stepping goes on from it
                    track(self._save(w, n, state.overflow))
            overflow = state.overflow | ((w.d.overflow.numpy()[:n] & self._bad) != 0)
            return self._save(w, n, overflow)

    # ---------------------------------------------------------------------------------------------------------
    # reading

    def probe(self, state: WarpState, batch: Batch, offset=(0.0, 0.0, 0.0)) -> dict[str, np.ndarray]:
        """Object pose (world, and position in the hand's root frame), table and hand contact of each state, with
        the wrist target moved by `offset` (3,)."""
        sc, b = self.scene, state.n
        with self._wp.ScopedDevice(self.device):
            w = self._load(state)
            self._assign(w, "mocap_pos", self._pad(batch.wrist_pos + np.asarray(offset), w.nworld)[:, None])
            self._assign(w, "mocap_quat", self._pad(batch.wrist_quat, w.nworld)[:, None])
            self._mjw.forward(self.m, w.d)
            xpos, xquat = w.d.xpos.numpy()[:b], w.d.xquat.numpy()[:b]
            xmat = w.d.xmat.numpy()[:b].reshape(b, -1, 3, 3)
            n = int(w.d.nacon.numpy()[0])
            geom = w.d.contact.geom.numpy()[:n]
            world = w.d.contact.worldid.numpy()[:n]
        pos, quat = xpos[:, sc.obj_body].astype(np.float64), xquat[:, sc.obj_body].astype(np.float64)
        root = xmat[:, sc.root_body].astype(np.float64)
        rel = np.einsum("bji,bj->bi", root, pos - xpos[:, sc.root_body])
        is_obj = np.isin(geom, sc.obj_geoms)
        obj_pair = is_obj.any(1)
        table = obj_pair & (geom == sc.table_geom).any(1)
        touch = obj_pair & np.isin(geom, sc.hand_geoms).any(1)
        keep = world < b
        table_w, touch_w = np.zeros(b, bool), np.zeros(b, bool)
        table_w[world[keep & table]] = True
        touch_w[world[keep & touch]] = True
        return dict(pos=pos, quat=quat, rel=rel, table=table_w, touch=touch_w)
