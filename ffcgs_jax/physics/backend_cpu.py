"""The CPU backend of the physics test: `CpuSim`, CPU MuJoCo through `mujoco.rollout` (threads across grasps, no
Python per step).

Instability: `mujoco.rollout` clears a trial's warning counters when it starts and stops stepping the trial at its
first warning (bad qpos, qvel or qacc, contact or constraint buffer full, ...), repeating that state to the end,
so such a trial's clock stops; MuJoCo's own checks also reset the data, clock included. A trial whose clock is
not where its steps put it, whose state is not finite or that moved faster than `backend.MAX_SPEED` at any step
diverged: `CpuSim` writes NaN into its state's time (which no step reads), so the mark goes wherever the row goes
(`take`) and `unstable` reads it back."""

import os
from collections.abc import Callable

import mujoco
import numpy as np
from mujoco import rollout

from ffcgs_jax.physics.backend import CHUNK, Batch, Segment, diverged, pose_hand, route_mujoco_warnings
from ffcgs_jax.physics.scene import PhysicsScene

GROUP_PER_THREAD = 4  # CPU grasps per thread per rollout group: keeps threads busy and the progress bar moving


_STATE = mujoco.mjtState.mjSTATE_FULLPHYSICS


_CTRL = mujoco.mjtState.mjSTATE_CTRL | mujoco.mjtState.mjSTATE_MOCAP_POS | mujoco.mjtState.mjSTATE_MOCAP_QUAT


class CpuSim:
    """Runs segments for a batch on CPU MuJoCo with `mujoco.rollout` threads. States are FULLPHYSICS vectors."""

    def __init__(self, scene: PhysicsScene, workers: int = 0):
        route_mujoco_warnings()
        self.scene = scene
        self.nthread = workers or os.cpu_count() or 1
        self.datas = [mujoco.MjData(scene.model) for _ in range(self.nthread)]
        self.size = mujoco.mj_stateSize(scene.model, _STATE)

    def initial(self, batch: Batch) -> np.ndarray:
        d = self.datas[0]
        out = np.zeros((len(batch.q_start), self.size))
        for g in range(len(out)):
            pose_hand(self.scene, d, batch.wrist_pos[g], batch.wrist_quat[g], batch.q_start[g])
            for w in d.warning:
                w.number = 0
            mujoco.mj_forward(self.scene.model, d)
            mujoco.mj_getState(self.scene.model, d, out[g], _STATE)
            if any(w.number for w in d.warning):
                out[g, 0] = np.nan
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
            bad = self._diverged(state[:, 0], states)
            state = np.ascontiguousarray(states[:, -1])
            state[bad, 0] = np.nan
            if track is not None:
                track(state)
        return state

    def take(self, state: np.ndarray, idx: np.ndarray) -> np.ndarray:
        return state[idx]

    def flagged(self, state: np.ndarray) -> np.ndarray:
        return np.zeros(len(state), bool)  # a full contact or constraint buffer is a warning here: `unstable`

    def unstable(self, state: np.ndarray) -> np.ndarray:
        return ~np.isfinite(state).all(axis=1)

    def _diverged(self, t0: np.ndarray, states: np.ndarray) -> np.ndarray:
        """Which trials of a rollout (B, k, nstate) from times t0 (B,) diverged (see the module's docstring)."""
        m = self.scene.model
        k, dt = states.shape[1], m.opt.timestep
        clock = np.abs(states[:, -1, 0] - (t0 + k * dt)) <= 0.5 * dt  # False for NaN: marked before
        flat = states.reshape(-1, states.shape[2])
        moved = diverged(flat[:, 1: 1 + m.nq], flat[:, 1 + m.nq: 1 + m.nq + m.nv]).reshape(len(states), k)
        return ~clock | moved.any(axis=1)

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
