"""The physics test on MuJoCo MJX: `MjxSim`, the `backend.Simulator` interface on a batched
`mjx.Data`.

The grasps of a batch are one vmapped `mjx.Data`; each `CHUNK` of steps is one jitted loop, fed the
chunk's servo targets and wrist (mocap) positions as arrays.

What MJX (mujoco-mjx 3.17, its JAX implementation) supports of the scene `scene.build` makes, checked on
the SVH hand with the built-in ball, box and mug:
- collisions: every pair the scene collides has an MJX function: hand capsules and boxes against the object's
  convex mesh parts (separating-axis tests over the hull's faces and edges), and the hand and the object against
  the table plane. MJX refuses margin or gap on mesh geoms (the scene sets neither).
- elliptic (and pyramidal) cones, impratio, the Newton solver, the implicitfast integrator (without fluid drag),
  weld and joint equality constraints (the wrist weld, the MJCF's finger couplings, the six-dir hold switched
  through `eq_active`), gravcomp, mocap bodies, xfrc_applied: all supported.
- not supported: the no-slip solver (MJX ignores `noslip_iterations` silently, so `MjxSim` refuses it), the PGS
  solver, flex, fluid drag with implicitfast (`mjx.put_model` raises; `MjxSim` turns that into FfcgsError).

How it differs from CPU MuJoCo: MJX has its own collision code (a fixed contact slot count per geom pair, all
kept in the constraint arrays), so trajectories agree with `CpuSim` loosely, not to round-off (see
tests/physics/test_backend_mjx.py); it runs in JAX's precision (float32 unless jax_enable_x64 is set).

Cost: MJX compiles one collision routine per (geom type, mesh) pair and keeps a contact slot for every candidate
pair, so compile time, memory and step time grow with the object's convex parts. On a 2-core CPU: the ball
(1 part, 160 slots with the table) compiles its step in about 50 s; the mug (22 parts, 1716 slots, 5191
constraint rows without a table) in about 270 s. Each `MjxSim` therefore compiles its step loop once per batch
size, shared by all chunk lengths (a traced trip count over fixed-size buffers).
"""

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.hand.mjx_import import mjx
from ffcgs_jax.physics.backend import CHUNK, Batch, Segment, diverged, pose_hand, route_mujoco_warnings
from ffcgs_jax.physics.scene import PhysicsScene
from ffcgs_jax.runtime.fixed_shapes import pad_rows


def put_model(model: mujoco.MjModel) -> mjx.Model:
    """The MJX model of a physics scene, or FfcgsError naming what MJX cannot run."""
    if model.opt.noslip_iterations > 0:
        raise FfcgsError("MJX has no no-slip solver (noslip_iterations > 0); use the cpu physics backend")
    try:
        # impl="jax": the Warp implementation, picked by default where installed, is a different simulator
        return mjx.put_model(model, impl="jax")
    except NotImplementedError as e:
        raise FfcgsError(f"MJX cannot run this physics scene: {e}; use the cpu physics backend") from None


def _chunk(m: mjx.Model, d: mjx.Data, ctrl: jax.Array, mocap_pos: jax.Array, n: jax.Array) -> mjx.Data:
    """`n` steps of one grasp; ctrl (CHUNK, Q) and mocap_pos (CHUNK, 3) padded past n."""

    def step(i, d):
        return mjx.step(m, d.replace(ctrl=ctrl[i], mocap_pos=mocap_pos[i][None]))

    # a traced trip count: every chunk length shares one compiled loop, which takes minutes to compile
    return jax.lax.fori_loop(0, n, step, d)


def _probe(m: mjx.Model, d: mjx.Data, mocap_pos: jax.Array, obj_body: int, root_body: int, obj: jax.Array,
           hand: jax.Array, table: jax.Array) -> dict[str, jax.Array]:
    # positions and contacts need only kinematics and collision, not the solver (a much smaller program)
    d = mjx.collision(m, mjx.kinematics(m, d.replace(mocap_pos=mocap_pos[None])))
    c = d._impl.contact
    g1, g2 = c.geom[:, 0], c.geom[:, 1]
    on = c.dist < 0  # MJX keeps a slot for every candidate pair; only penetrating ones are contacts

    def pair(a, b):
        return jnp.any(on & ((a[g1] & b[g2]) | (a[g2] & b[g1])))

    pos = d.xpos[obj_body]
    rel = d.xmat[root_body].T @ (pos - d.xpos[root_body])
    return {"pos": pos, "quat": d.xquat[obj_body], "rel": rel, "table": pair(obj, table), "touch": pair(obj, hand)}


class MjxSim:
    """Runs segments for a batch on MuJoCo MJX. States are batched `mjx.Data` (leading axis: grasps)."""

    def __init__(self, scene: PhysicsScene):
        route_mujoco_warnings()  # `initial` poses the hands with CPU MuJoCo
        self.scene = scene
        self.model = put_model(scene.model)
        self._device = jax.devices()[0]  # where put_model puts the model
        self._data0 = mjx.make_data(self.model)
        self._dtype = self._data0.qpos.dtype
        ng = scene.model.ngeom
        masks = [np.isin(np.arange(ng), ids) for ids in (scene.obj_geoms, scene.hand_geoms, [scene.table_geom])]
        self._masks = [self._put(mk) for mk in masks]
        self._run = jax.jit(jax.vmap(_chunk, in_axes=(None, 0, 0, 0, None)))
        probe = jax.vmap(_probe, in_axes=(None, 0, 0, None, None, None, None, None))
        self._probe = jax.jit(probe, static_argnums=(3, 4))

    def _put(self, x, dtype=None) -> jax.Array:
        # committed to the device, as jit outputs are: jit compiles anew when an argument's commitment changes
        return jax.device_put(np.asarray(x, dtype), self._device)

    def _call(self, fn, *args):
        # MJX broadcasts across ranks internally; a caller's jax_numpy_rank_promotion="raise" must not apply
        with jax.numpy_rank_promotion("allow"):
            return fn(*args)

    def initial(self, batch: Batch) -> mjx.Data:
        sc = self.scene
        d = mujoco.MjData(sc.model)
        b = len(batch.q_start)
        qpos = np.zeros((b, sc.model.nq))
        for g in range(b):
            pose_hand(sc, d, batch.wrist_pos[g], batch.wrist_quat[g], batch.q_start[g])
            qpos[g] = d.qpos
        data = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (b, *x.shape)), self._data0)
        return data.replace(qpos=self._put(qpos, self._dtype),
                            mocap_pos=self._put(batch.wrist_pos[:, None], self._dtype),
                            mocap_quat=self._put(batch.wrist_quat[:, None], self._dtype))

    def run(self, state: mjx.Data, batch: Batch, seg: Segment, track=None) -> mjx.Data:
        """Advance `state` through `seg`; `track(state)` sees the state after each chunk. `batch` may hold fewer
        grasps than `state` (after `take`): the rows past it are padding."""
        sc, m = self.scene, self.scene.model
        b = len(state.qpos)
        xfrc = np.zeros((b, m.nbody, 6))
        if seg.force is not None:
            xfrc[:, sc.obj_body, :3] = seg.force
        active = np.tile(m.eq_active0.astype(bool), (b, 1))
        if sc.hold_eq >= 0:
            active[:, sc.hold_eq] = seg.hold
        state = state.replace(xfrc_applied=self._put(xfrc, self._dtype), eq_active=self._put(active))
        ctrl = np.zeros((b, CHUNK, m.nu))
        mocap = np.zeros((b, CHUNK, 3))
        wrist = pad_rows(batch.wrist_pos, b)
        for i0 in range(0, seg.n, CHUNK):
            i1 = min(seg.n, i0 + CHUNK)
            c, off = seg.make(i0, i1)
            ctrl[:, : i1 - i0] = pad_rows(np.broadcast_to(c, (len(batch.wrist_pos), *c.shape[1:])), b)
            mocap[:, : i1 - i0] = wrist[:, None] + off[None]
            state = self._call(self._run, self.model, state, self._put(ctrl, self._dtype),
                               self._put(mocap, self._dtype), self._put(i1 - i0, np.int32))
            if track is not None:
                track(state)
        return state

    def take(self, state: mjx.Data, idx: np.ndarray) -> mjx.Data:
        """The grasps at `idx` first, padded to the batch's size: a smaller batch would compile the step anew."""
        rows = pad_rows(np.asarray(idx), len(state.qpos))
        return jax.tree_util.tree_map(lambda x: x[rows], state)

    def flagged(self, state: mjx.Data) -> np.ndarray:
        return np.zeros(len(state.qpos), bool)  # fixed contact slots per pair: nothing to overflow

    def unstable(self, state: mjx.Data) -> np.ndarray:
        # MJX neither warns nor resets: a diverged grasp keeps its NaN or runaway state, so the last one shows it
        return diverged(np.asarray(state.qpos), np.asarray(state.qvel))

    def probe(self, state: mjx.Data, batch: Batch, offset=(0.0, 0.0, 0.0)) -> dict[str, np.ndarray]:
        """Object pose (world, and position in the hand's root frame), table and hand contact of each state, with
        the wrist target moved by `offset` (3,)."""
        n = len(batch.wrist_pos)
        mocap = self._put(pad_rows(batch.wrist_pos + np.asarray(offset), len(state.qpos)), self._dtype)
        out = self._call(self._probe, self.model, state, mocap, self.scene.obj_body, self.scene.root_body,
                         *self._masks)
        return {k: np.asarray(v, bool if k in ("table", "touch") else np.float64)[:n] for k, v in out.items()}

