"""The physics protocols as open-loop segments, and the success rules that judge them.

`closing` (both protocols), `lift_shake` and `push` (six-dir) turn a `Batch` into `Segment`s; `run_protocol`
drives a backend (`backend.Simulator`) through them and applies the success rules described in `runner`.
DexGraspBench's protocols (`dexgraspbench`, described there): `grasp_and_squeeze` and `bench_push`.
"""

from collections.abc import Callable
from typing import Any

import numpy as np
import scipy.stats

from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.physics import dexgraspbench as dgb
from ffcgs_jax.physics.backend import CHUNK, Batch, Segment, Simulator
from ffcgs_jax.physics.config import ALL_PROTOCOLS, PhysicsConfig

LIFT_HOLD = 0.25  # seconds of rest between the lift and the shaking


DIRECTIONS = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], np.float64)


# a grasp's `reason` is its index here: new reasons go at the end, so files written before them read the same
REASONS = ("ok", "penetration", "lost", "slip", "unstable")
UNSTABLE = REASONS.index("unstable")


def result_key(protocol: str, field: str) -> str:
    """The name of a per-grasp result of `runner.evaluate`, e.g. ("six-dir", "success") -> "six_dir_success"."""
    return f"{protocol.replace('-', '_')}_{field}"



def wilson(successes: int, n: int, confidence: float = 0.95) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion (SciPy's `binomtest(...).proportion_ci`); (0, 1) when n = 0."""
    if n == 0:
        return 0.0, 1.0
    ci = scipy.stats.binomtest(int(successes), int(n)).proportion_ci(confidence_level=confidence, method="wilson")
    return max(0.0, float(ci.low)), min(1.0, float(ci.high))



def steps(seconds: float, dt: float) -> int:
    """Simulation steps of `seconds` at timestep dt (at least one)."""
    return max(1, int(round(seconds / dt)))



def closing(batch: Batch, cfg: PhysicsConfig) -> list[Segment]:
    n = steps(cfg.close_time, cfg.timestep)
    zero = np.zeros((1, 3))

    def ramp(i0, i1):
        s = (np.arange(i0, i1) + 1.0) / n
        return batch.q_start[:, None] + s[None, :, None] * (batch.q_target - batch.q_start)[:, None], zero

    settle = Segment(steps(cfg.settle_time, cfg.timestep), lambda i0, i1: (batch.q_target[:, None], zero), hold=True)
    return [Segment(n, ramp, hold=True), settle]



def lift_shake(batch: Batch, cfg: PhysicsConfig) -> list[Segment]:
    dt = cfg.timestep
    hold = batch.q_target[:, None]
    n_lift = steps(cfg.lift_height / cfg.lift_speed, dt)
    period = 4 * cfg.shake_amplitude / cfg.shake_speed
    n_shake = steps(cfg.shake_cycles * period, dt) if cfg.shake_cycles else 0

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
    segs = [Segment(n_lift, lift), Segment(steps(LIFT_HOLD, dt), lambda i0, i1: (hold, up))]
    return segs + ([Segment(n_shake, shake)] if n_shake else [])



def push(batch: Batch, cfg: PhysicsConfig, direction: np.ndarray, mass: float) -> Segment:
    zero = np.zeros((1, 3))
    return Segment(steps(cfg.push_time, cfg.timestep), lambda i0, i1: (batch.q_target[:, None], zero),
                   force=cfg.accel * mass * direction)



def rotation_angle(q1: np.ndarray, q2: np.ndarray) -> np.ndarray:
    """Rotation angle (degrees) between unit quaternions, row by row."""
    c = np.clip(np.abs(np.sum(q1 * q2, axis=-1)), 0.0, 1.0)
    return np.degrees(2 * np.arccos(c))



def failure_reason(bad_start: np.ndarray, lost: np.ndarray, moved: np.ndarray, unstable: np.ndarray | None = None
                   ) -> np.ndarray:
    """Per grasp, its index into REASONS: the first of a bad start, unstable (the simulation diverged: whatever it
    showed after that is not evidence), lost, moved that holds, else ok (0)."""
    unstable = np.zeros(len(bad_start), bool) if unstable is None else unstable
    return np.select([bad_start, unstable, lost, moved], [1, UNSTABLE, 2, 3], 0).astype(np.int8)



def _drive(sim: Simulator, state: Any, batch: Batch, rows: np.ndarray, segs: list[Segment], flagged: np.ndarray,
           unstable: np.ndarray, check: Callable[[Any, np.ndarray], np.ndarray] | None = None
           ) -> tuple[Any, np.ndarray]:
    """Run `segs` for the grasps `rows` of `batch` (their states: `state`) in pieces of `CHUNK` steps. After each
    piece `check(state, rows)` says which grasps go on; the others leave the batch (`sim.take`), so a grasp whose
    failure is already certain costs no more simulation. `flagged[rows]` collects the backend's untrusted worlds,
    `unstable[rows]` its diverged ones, which leave the batch too. Returns the final states and their grasps."""
    for seg in segs:
        for i0 in range(0, seg.n, CHUNK):
            if len(rows) == 0:
                return state, rows
            i1 = min(seg.n, i0 + CHUNK)

            def make(a, b, seg=seg, i0=i0, rows=rows):
                ctrl, off = seg.make(i0 + a, i0 + b)
                return ctrl[rows], off

            state = sim.run(state, batch.rows(rows), Segment(i1 - i0, make, seg.force, seg.hold))
            flagged[rows] |= sim.flagged(state)[: len(rows)]  # a backend may pad its batch
            keep = ~sim.unstable(state)[: len(rows)]
            unstable[rows] |= ~keep
            if check is not None:
                keep &= check(state, rows)
            if not keep.all():
                state, rows = sim.take(state, np.flatnonzero(keep)), rows[keep]
    return state, rows


def _probe(sim: Simulator, state: Any, batch: Batch, rows: np.ndarray, b: int) -> dict[str, np.ndarray]:
    """`sim.probe` of the grasps `rows` (their states: `state`) as arrays over all b grasps, zero elsewhere."""
    if len(rows) == 0:  # every grasp diverged: a backend's probe may need at least one
        return dict(pos=np.zeros((b, 3)), quat=np.zeros((b, 4)), rel=np.zeros((b, 3)), table=np.zeros(b, bool),
                    touch=np.zeros(b, bool))
    return {k: _scatter(v, rows, b) for k, v in sim.probe(state, batch.rows(rows)).items()}


def _void(unstable: np.ndarray, *arrays: np.ndarray) -> None:
    """NaN in the rows of diverged grasps: a move or turn read from a diverged simulation is no measurement."""
    for a in arrays:
        a[unstable] = np.nan



def run_protocol(sim: Simulator, batch: Batch, depth: np.ndarray, cfg: PhysicsConfig, protocol: str
                 ) -> dict[str, np.ndarray]:
    """Execute and test every grasp of `batch` on `sim` (a backend for the protocol's scene). Returns per-grasp
    arrays: success, reason (index into REASONS), move (m), rot (deg), for six-dir move_dir / rot_dir (B, 6), and
    flagged (the backend could not trust the simulation: `runner` runs those grasps again on the CPU).

    A grasp whose simulation diverged at any step (`sim.unstable`) leaves the batch then and fails "unstable",
    whatever it had shown; its move and rot (and move_dir / rot_dir) are NaN.

    Grasps stop being simulated as soon as their failure is certain: a grasp that starts in penetration is not
    simulated (move and rot NaN); in lift-shake a grasp leaves once the hand no longer touches the object and the
    object is `max_slip` or more from its place in the palm (dropped: its move and rot are then those of that
    moment); in six-dir a grasp that lost the object while closing is not pushed, and one that moved or turned
    past a bound in some direction is not pushed further (directions not pushed: NaN in move_dir / rot_dir)."""
    if protocol not in ALL_PROTOCOLS:
        raise FfcgsError(f"unknown protocol {protocol!r}; protocols: {', '.join(ALL_PROTOCOLS)}")
    if dgb.is_bench(protocol):
        return _run_bench(sim, batch, depth, dgb.config(cfg, protocol))
    b = len(depth)
    bad_start = depth > cfg.max_initial_penetration
    flagged, unstable = np.zeros(b, bool), np.zeros(b, bool)
    move, rot = np.full(b, np.nan), np.full(b, np.nan)
    lost = np.zeros(b, bool)
    idx = np.flatnonzero(~bad_start)
    if len(idx) == 0:
        out = dict(success=np.zeros(b, bool), reason=failure_reason(bad_start, lost, lost), move=move, rot=rot)
        if protocol == "six-dir":
            out.update(move_dir=np.full((b, 6), np.nan), rot_dir=np.full((b, 6), np.nan))
        return {**out, "flagged": flagged}
    closed, held = _drive(sim, sim.initial(batch.rows(idx)), batch, idx, closing(batch, cfg), flagged, unstable)
    ref = _probe(sim, closed, batch, held, b)
    if protocol == "lift-shake":
        def dropped(state, rows):
            p = sim.probe(state, batch.rows(rows))
            m = np.linalg.norm(p["rel"] - ref["rel"][rows], axis=1)
            gone = ~p["touch"] & (m >= cfg.max_slip)
            move[rows[gone]], rot[rows[gone]] = m[gone], rotation_angle(p["quat"], ref["quat"][rows])[gone]
            lost[rows[gone]] = True
            return ~gone

        state, rows = _drive(sim, closed, batch, held, lift_shake(batch, cfg), flagged, unstable, dropped)
        table = np.zeros(b, bool)
        if len(rows):
            end = sim.probe(state, batch.rows(rows), np.array([0.0, 0.0, cfg.lift_height]))
            move[rows] = np.linalg.norm(end["rel"] - ref["rel"][rows], axis=1)
            rot[rows] = rotation_angle(end["quat"], ref["quat"][rows])
            lost[rows], table[rows] = ~end["touch"], end["table"]
        _void(unstable, move, rot)
        moved = (move >= cfg.max_slip) | table
        return dict(success=~(bad_start | lost | moved | unstable),
                    reason=failure_reason(bad_start, lost, moved, unstable), move=move, rot=rot, flagged=flagged)
    move_dir, rot_dir = np.full((b, 6), np.nan), np.full((b, 6), np.nan)
    lost[held] = ~ref["touch"][held]
    where = np.zeros(b, np.int64)
    where[held] = np.arange(len(held))  # row of each grasp in the closed states
    failed = bad_start | lost | unstable
    for k, direction in enumerate(DIRECTIONS):
        rows = np.flatnonzero(~failed)
        if len(rows) == 0:
            break
        move_dir[rows, k], rot_dir[rows, k] = 0.0, 0.0

        def pushed(state, rows, k=k):
            p = sim.probe(state, batch.rows(rows))
            move_dir[rows, k] = np.maximum(move_dir[rows, k], np.linalg.norm(p["pos"] - ref["pos"][rows], axis=1))
            rot_dir[rows, k] = np.maximum(rot_dir[rows, k], rotation_angle(p["quat"], ref["quat"][rows]))
            out = (move_dir[rows, k] >= cfg.max_move) | (rot_dir[rows, k] >= cfg.max_rot_deg)
            failed[rows[out]] = True
            return ~out

        _drive(sim, sim.take(closed, where[rows]), batch, rows, [push(batch, cfg, direction, sim.scene.mass)],
               flagged, unstable, pushed)
        failed |= unstable
    _void(unstable, move_dir, rot_dir)
    tried = ~np.isnan(move_dir).all(axis=1)
    move[tried], rot[tried] = np.nanmax(move_dir[tried], axis=1), np.nanmax(rot_dir[tried], axis=1)
    moved = (np.nan_to_num(move) >= cfg.max_move) | (np.nan_to_num(rot) >= cfg.max_rot_deg)
    return dict(success=~(bad_start | lost | moved | unstable), reason=failure_reason(bad_start, lost, moved, unstable),
                move=move, rot=rot, move_dir=move_dir, rot_dir=rot_dir, flagged=flagged)



def grasp_and_squeeze(batch: Batch, cfg: PhysicsConfig) -> list[Segment]:
    """DexGraspBench's execution: servo targets from the pre-grasp (`q_start`) to the grasp (`q_grasp`), then to the
    squeeze (`q_target`), each stage `dgb.STAGE_TIME` long in `dgb.WAYPOINTS` equal steps held constant (the
    first step already moves: the targets at the end of step k of K are k/K of the way)."""
    if batch.q_grasp is None:
        raise FfcgsError("DexGraspBench's protocol needs the grasps' q (Batch.q_grasp): prepare them on its scene")
    n = steps(dgb.STAGE_TIME, cfg.timestep)
    zero = np.zeros((1, 3))

    def stage(a: np.ndarray, b: np.ndarray) -> Segment:
        def make(i0, i1):
            k = (np.floor(np.arange(i0, i1) * dgb.WAYPOINTS / n) + 1) / dgb.WAYPOINTS
            return a[:, None] + k[None, :, None] * (b - a)[:, None], zero

        return Segment(n, make)

    return [stage(batch.q_start, batch.q_grasp), stage(batch.q_grasp, batch.q_target)]


def bench_push(batch: Batch, cfg: PhysicsConfig, direction: np.ndarray, mass: float) -> Segment:
    """DexGraspBench's push: `cfg.accel` x mass along `direction` for `cfg.push_time`, targets held at the squeeze."""
    zero = np.zeros((1, 3))
    return Segment(steps(cfg.push_time, cfg.timestep), lambda i0, i1: (batch.q_target[:, None], zero),
                   force=cfg.accel * mass * direction)


def split_segment(seg: Segment, k: int) -> list[Segment]:
    """A segment of constant control as consecutive segments of at most k steps (a check after each)."""
    return [Segment(min(k, seg.n - i), seg.make, seg.force, seg.hold) for i in range(0, seg.n, k)]


def _run_bench(sim: Simulator, batch: Batch, depth: np.ndarray, cfg: PhysicsConfig) -> dict[str, np.ndarray]:
    """DexGraspBench's test (`dexgraspbench`; `cfg` from `dexgraspbench.config`): grasp and squeeze from the
    pre-grasp once, then from that state each direction's push, the object's pose compared every
    `dgb.CHECK_TIME` with its pose at the pre-grasp; a grasp leaves at its first failing check. Returns the
    arrays of `run_protocol` with move_dir / rot_dir (B, 6): the largest move and turn over each direction's
    checks (NaN where not pushed). Reasons: penetration (at the pre-grasp), unstable (the simulation diverged, as in
    `run_protocol`), lost (failed and no hand contact after the squeeze), slip (failed otherwise)."""
    b = len(depth)
    bad_start = depth > cfg.max_initial_penetration
    flagged, unstable = np.zeros(b, bool), np.zeros(b, bool)
    move, rot = np.full(b, np.nan), np.full(b, np.nan)
    move_dir, rot_dir = np.full((b, 6), np.nan), np.full((b, 6), np.nan)
    lost = np.zeros(b, bool)
    failed = bad_start.copy()
    idx = np.flatnonzero(~bad_start)
    if len(idx):
        start = sim.initial(batch.rows(idx))
        ref = {k: _scatter(v, idx, b) for k, v in sim.probe(start, batch.rows(idx)).items()}  # at the pre-grasp
        squeezed, held = _drive(sim, start, batch, idx, grasp_and_squeeze(batch, cfg), flagged, unstable)
        lost[held] = ~_probe(sim, squeezed, batch, held, b)["touch"][held]
        where = np.zeros(b, np.int64)
        where[held] = np.arange(len(held))  # row of each grasp in the squeezed states
        every = steps(dgb.CHECK_TIME, cfg.timestep)
        failed |= unstable
        for k, direction in enumerate(DIRECTIONS):
            rows = np.flatnonzero(~failed)
            if len(rows) == 0:
                break
            move_dir[rows, k], rot_dir[rows, k] = 0.0, 0.0

            def checked(state, rows, k=k):
                p = sim.probe(state, batch.rows(rows))
                move_dir[rows, k] = np.maximum(move_dir[rows, k], np.linalg.norm(p["pos"] - ref["pos"][rows], axis=1))
                rot_dir[rows, k] = np.maximum(rot_dir[rows, k], rotation_angle(p["quat"], ref["quat"][rows]))
                out = (move_dir[rows, k] >= cfg.max_move) | (rot_dir[rows, k] >= cfg.max_rot_deg)
                failed[rows[out]] = True
                return ~out

            _drive(sim, sim.take(squeezed, where[rows]), batch, rows,
                   split_segment(bench_push(batch, cfg, direction, sim.scene.mass), every), flagged, unstable, checked)
            failed |= unstable
    _void(unstable, move_dir, rot_dir)
    tried = ~np.isnan(move_dir).all(axis=1)
    move[tried], rot[tried] = np.nanmax(move_dir[tried], axis=1), np.nanmax(rot_dir[tried], axis=1)
    moved = failed & ~bad_start
    return dict(success=~failed, reason=failure_reason(bad_start, moved & lost, moved, unstable), move=move, rot=rot,
                move_dir=move_dir, rot_dir=rot_dir, flagged=flagged)


def _scatter(values: np.ndarray, idx: np.ndarray, b: int) -> np.ndarray:
    """Rows `idx` of a (b, ...) array set to `values`, the rest zero."""
    out = np.zeros((b, *values.shape[1:]), values.dtype)
    out[idx] = values
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
