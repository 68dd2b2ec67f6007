"""The physics protocols as open-loop segments, and the success rules that judge them.

`closing` (both protocols), `lift_shake` and `push` (six-dir) turn a `Batch` into `Segment`s; `run_protocol`
drives a backend (`backend.Simulator`) through them and applies the success rules described in `runner`.
"""

import math

import numpy as np

from ffcgs_jax.errors import FfcgsError
from ffcgs_jax.physics.backend import Batch, Segment, Simulator
from ffcgs_jax.physics.config import PROTOCOLS, PhysicsConfig

LIFT_HOLD = 0.25  # seconds of rest between the lift and the shaking


DIRECTIONS = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], np.float64)


REASONS = ("ok", "penetration", "lost", "slip")


def result_key(protocol: str, field: str) -> str:
    """The name of a per-grasp result of `runner.evaluate`, e.g. ("six-dir", "success") -> "six_dir_success"."""
    return f"{protocol.replace('-', '_')}_{field}"



def wilson(successes: int, n: int, z: float = 1.959963984540054) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion (95 % by default); (0, 1) when n = 0."""
    if n == 0:
        return 0.0, 1.0
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return max(0.0, centre - half), min(1.0, centre + half)



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



def _angle(q1: np.ndarray, q2: np.ndarray) -> np.ndarray:
    """Rotation angle (degrees) between unit quaternions, row by row."""
    c = np.clip(np.abs(np.sum(q1 * q2, axis=-1)), 0.0, 1.0)
    return np.degrees(2 * np.arccos(c))



def _reason(bad_start: np.ndarray, lost: np.ndarray, moved: np.ndarray) -> np.ndarray:
    return np.select([bad_start, lost, moved], [1, 2, 3], 0).astype(np.int8)



def run_protocol(sim: Simulator, batch: Batch, depth: np.ndarray, cfg: PhysicsConfig, protocol: str
                 ) -> dict[str, np.ndarray]:
    """Execute and test every grasp of `batch` on `sim` (a `backend_cpu.CpuSim` or `backend_mjx.MjxSim` for the
    protocol's scene). Returns per-grasp arrays: success, reason (index into REASONS), move (m), rot (deg) and, for
    six-dir, move_dir / rot_dir (B, 6)."""
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
