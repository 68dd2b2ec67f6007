"""The interface both physics backends implement, and what they share.

A backend is a simulator over one compiled `PhysicsScene`: `initial(batch)` gives the states of a batch of grasps,
`run(state, batch, segment, track)` advances them through a `Segment` of open-loop control (calling
`track(state)` after each `CHUNK` of steps), `probe(state, batch, offset)` reads the object's pose and the
contacts the success rules need, `take(state, idx)` keeps the grasps at `idx` (grasps whose failure is certain
leave the batch), `flagged(state)` says which grasps' simulation the backend cannot vouch for (`runner` runs them
again on the CPU) and `unstable(state)` which diverged (a non-finite or absurd state, or MuJoCo warned and stopped
it: such a grasp fails with reason "unstable").
`protocols.run_protocol` drives any backend through a protocol; `backend_cpu.CpuSim` (CPU MuJoCo),
`backend_mjx.MjxSim` (MJX) and `backend_warp.WarpSim` (MuJoCo Warp) implement it and import only this module,
never each other.
"""

import dataclasses
import logging
from collections.abc import Callable
from typing import Any, Protocol, runtime_checkable

import mujoco
import numpy as np

from ffcgs_jax.physics.scene import PhysicsScene

CHUNK = 250  # steps per rollout call: bounds the state buffer (B x CHUNK x nstate) and samples the six-dir motion
# m/s or rad/s: no part of a hand or a grasped object moves this fast; a simulation that does has diverged (MuJoCo's
# own check, mjMAXVAL, is 1e10)
MAX_SPEED = 1e4

LOG = logging.getLogger("ffcgs_jax.physics")


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
    """Per-grasp inputs of a run: wrist pose parts, start and target servo positions, and for DexGraspBench's
    protocol the grasp's own q, the waypoint between its pre-grasp (q_start) and squeeze (q_target)."""

    wrist_pos: np.ndarray  # (B, 3)
    wrist_quat: np.ndarray  # (B, 4) w x y z
    q_start: np.ndarray  # (B, Q)
    q_target: np.ndarray  # (B, Q)
    q_grasp: np.ndarray | None = None  # (B, Q), DexGraspBench only

    def rows(self, sel) -> "Batch":
        """The grasps at `sel` (a slice or indices), as a Batch."""
        return Batch(*(None if getattr(self, f.name) is None else np.asarray(getattr(self, f.name))[sel]
                       for f in dataclasses.fields(self)))


@runtime_checkable
class Simulator(Protocol):
    """What `protocols.run_protocol` needs of a backend; states are whatever the backend keeps per grasp."""

    scene: PhysicsScene

    def initial(self, batch: Batch) -> Any: ...

    def run(self, state: Any, batch: Batch, seg: Segment, track: Callable | None = None) -> Any: ...

    def probe(self, state: Any, batch: Batch, offset=(0.0, 0.0, 0.0)) -> dict[str, np.ndarray]: ...

    def take(self, state: Any, idx: np.ndarray) -> Any: ...

    def flagged(self, state: Any) -> np.ndarray: ...

    def unstable(self, state: Any) -> np.ndarray: ...


def diverged(qpos: np.ndarray, qvel: np.ndarray) -> np.ndarray:
    """Per row of qpos (B, nq) and qvel (B, nv): the state is not finite or moves faster than `MAX_SPEED`."""
    qpos, qvel = np.asarray(qpos, np.float64), np.asarray(qvel, np.float64)
    finite = np.isfinite(qpos).all(axis=1) & np.isfinite(qvel).all(axis=1)
    return ~finite | (np.abs(np.nan_to_num(qvel)).max(axis=1, initial=0.0) > MAX_SPEED)


def _log_warning(message: str) -> None:
    LOG.debug("MuJoCo: %s", message)


def route_mujoco_warnings() -> None:
    """Send MuJoCo's warnings to the logger `LOG` (debug level) instead of MuJoCo's default: stderr and a
    MUJOCO_LOG.TXT it appends to in the current working folder. The backends read instability from each trial's
    state, so the text is only a diagnostic. A handler the caller installed (`mujoco.set_mju_user_warning`) is
    kept. Process-wide, as MuJoCo's handler is; called by each backend when it starts, not at import."""
    if mujoco.get_mju_user_warning() is None:
        mujoco.set_mju_user_warning(_log_warning)


def mat_to_quat(R: np.ndarray) -> np.ndarray:
    """The unit quaternion (w x y z) of rotation matrix R (3, 3)."""
    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(R, np.float64).ravel())
    return q


def pose_hand(scene: PhysicsScene, d: mujoco.MjData, pos, quat, q) -> None:
    """Put the hand of `d` at wrist (pos, quat) with channels q, at rest (the mocap target on the wrist)."""
    d.mocap_pos[0], d.mocap_quat[0] = pos, quat
    d.qpos[:] = scene.model.qpos0
    d.qpos[scene.root_qpos: scene.root_qpos + 7] = np.concatenate([pos, quat])
    d.qpos[scene.hand_qpos] = scene.coupling @ q
    d.qvel[:] = 0
