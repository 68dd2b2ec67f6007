"""The physics protocols: their open-loop segments, how a backend executes them, their success rules, and each
protocol as one registered object (`registry.Protocol`: name, scene, steps, success rule, fixed settings).

`closing` (ours), `lift_shake`, `push` (six-dir), `grasp_and_squeeze` and `bench_push` (DexGraspBench's, described
in `dexgraspbench`) turn a `Batch` into `Segment`s; `run_protocol` drives a backend (`backend.Simulator`) through a
protocol and judges it by the protocol's rule (the rules are described in `runner`). The built-in protocols
register here: `get(name)` returns one, `names()` lists them (`config.ALL_PROTOCOLS` names the same, for the CLI
to check a name without importing this module; they are checked equal on import); `register` adds another.
"""

import dataclasses
from collections.abc import Callable
from typing import Any

import numpy as np
import scipy.stats

from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.physics import dexgraspbench as dgb
from ffcgs_jax.physics.backend import CHUNK, Batch, Segment, Simulator
from ffcgs_jax.physics.config import ALL_PROTOCOLS, PROTOCOLS, PhysicsConfig
# the registry, reached through this module: importing it registers the built-in protocols below
from ffcgs_jax.physics.registry import KINDS, Protocol, get, names, register, say_overrides  # noqa: F401

LIFT_HOLD = 0.25  # seconds of rest between the lift and the shaking


DIRECTIONS = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], np.float64)
DIRECTION_NAMES = ("+x", "-x", "+y", "-y", "+z", "-z")


# a grasp's `reason` is its index here: new reasons go at the end, so files written before them read the same
REASONS = ("ok", "penetration", "lost", "slip", "unstable")
UNSTABLE = REASONS.index("unstable")


def result_key(protocol: str, field: str) -> str:
    """The name of a per-grasp result of `runner.evaluate`, e.g. ("six-dir", "success") -> "six_dir_success"."""
    return f"{protocol.replace('-', '_')}_{field}"



def wilson(successes, n: int, confidence: float = 0.95):
    """The two-sided Wilson score interval at `confidence` of `successes` (an int, or an array of them) in `n`
    trials: SciPy's `binomtest(...).proportion_ci(method="wilson")` in closed form, vectorised (the robust
    verdict's rates use it too); (0, 1) when n = 0. Floats for an int, arrays for an array."""
    if n == 0:
        return 0.0, 1.0
    z = float(scipy.stats.norm.ppf(0.5 + confidence / 2))
    p = np.asarray(successes, np.float64) / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    low, high = np.clip(centre - half, 0.0, 1.0), np.clip(centre + half, 0.0, 1.0)
    return (float(low), float(high)) if np.ndim(successes) == 0 else (low, high)


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



@dataclasses.dataclass
class Trial:
    """What a protocol's execution measured of each of a batch's b grasps: `bad` (started in penetration, not
    simulated), `flagged` (the backend could not trust it), `unstable` (diverged), `lost` (no hand contact), `table`
    (the object touches the table), `move` (m) and `rot` (deg), and for the six-direction tests `move_dir` and
    `rot_dir` (b, 6): per direction the largest move and turn (NaN where not pushed)."""

    bad: np.ndarray
    flagged: np.ndarray
    unstable: np.ndarray
    lost: np.ndarray
    table: np.ndarray
    move: np.ndarray
    rot: np.ndarray
    move_dir: np.ndarray | None = None
    rot_dir: np.ndarray | None = None

    @classmethod
    def start(cls, depth: np.ndarray, cfg: PhysicsConfig, directions: bool) -> "Trial":
        b = len(depth)
        no, nan = (lambda: np.zeros(b, bool)), (lambda *s: np.full((b, *s), np.nan))
        return cls(depth > cfg.max_initial_penetration, no(), no(), no(), no(), nan(), nan(),
                   nan(6) if directions else None, nan(6) if directions else None)

    @property
    def b(self) -> int:
        return len(self.bad)

    def outcome(self, protocol: Protocol, cfg: PhysicsConfig) -> dict[str, np.ndarray]:
        """`run_protocol`'s arrays: the measurements (NaN where diverged; with directions, move and rot the largest
        over the directions pushed) judged by the protocol's rule."""
        move, rot = self.move, self.rot
        if self.move_dir is None:
            _void(self.unstable, move, rot)
        else:
            _void(self.unstable, self.move_dir, self.rot_dir)
            tried = ~np.isnan(self.move_dir).all(axis=1)
            move[tried], rot[tried] = np.nanmax(self.move_dir[tried], axis=1), np.nanmax(self.rot_dir[tried], axis=1)
        success, reason = protocol.rule(self.bad, self.lost, move, rot, self.table, self.unstable, cfg)
        out = dict(success=success, reason=reason, move=move, rot=rot)
        if self.move_dir is not None:
            out.update(move_dir=self.move_dir, rot_dir=self.rot_dir)
        return {**out, "flagged": self.flagged}


def run_protocol(sim: Simulator, batch: Batch, depth: np.ndarray, cfg: PhysicsConfig, protocol: str
                 ) -> dict[str, np.ndarray]:
    """Execute and test every grasp of `batch` on `sim` (a backend for the protocol's scene) under `cfg` with the
    protocol's fixed settings (`Protocol.settings`). Returns per-grasp arrays: success, reason (index into
    REASONS), move (m), rot (deg), for the six-direction tests move_dir / rot_dir (B, 6), and flagged (the backend
    could not trust the simulation: `runner` runs those grasps again on the CPU).

    A grasp whose simulation diverged at any step (`sim.unstable`) leaves the batch then and fails "unstable",
    whatever it had shown; its move and rot (and move_dir / rot_dir) are NaN.

    Grasps stop being simulated as soon as their failure is certain: a grasp that starts in penetration is not
    simulated (move and rot NaN); in lift-shake a grasp leaves once the hand no longer touches the object and the
    object is `max_slip` or more from its place in the palm (dropped: its move and rot are then those of that
    moment); in six-dir a grasp that lost the object while closing is not pushed, and one that moved or turned
    past a bound in some direction is not pushed further (directions not pushed: NaN in move_dir / rot_dir)."""
    p = get(protocol)
    cfg = p.settings(cfg)
    trial = Trial.start(depth, cfg, p.directions)
    if not trial.bad.all():
        p.execute(sim, batch, cfg, trial)
    return trial.outcome(p, cfg)


def _closed(sim: Simulator, batch: Batch, cfg: PhysicsConfig, t: Trial) -> tuple[Any, np.ndarray, dict]:
    """Our protocols' closing of the grasps that start well: their states, which of them are left (not diverged)
    and the object's pose and contacts then (`_probe`, over all grasps)."""
    idx = np.flatnonzero(~t.bad)
    closed, held = _drive(sim, sim.initial(batch.rows(idx)), batch, idx, closing(batch, cfg), t.flagged, t.unstable)
    return closed, held, _probe(sim, closed, batch, held, t.b)


def _execute_lift_shake(sim: Simulator, batch: Batch, cfg: PhysicsConfig, t: Trial) -> None:
    closed, held, ref = _closed(sim, batch, cfg, t)

    def dropped(state, rows):
        p = sim.probe(state, batch.rows(rows))
        m = np.linalg.norm(p["rel"] - ref["rel"][rows], axis=1)
        gone = ~p["touch"] & (m >= cfg.max_slip)
        t.move[rows[gone]], t.rot[rows[gone]] = m[gone], rotation_angle(p["quat"], ref["quat"][rows])[gone]
        t.lost[rows[gone]] = True
        return ~gone

    state, rows = _drive(sim, closed, batch, held, lift_shake(batch, cfg), t.flagged, t.unstable, dropped)
    if len(rows):
        end = sim.probe(state, batch.rows(rows), np.array([0.0, 0.0, cfg.lift_height]))
        t.move[rows] = np.linalg.norm(end["rel"] - ref["rel"][rows], axis=1)
        t.rot[rows] = rotation_angle(end["quat"], ref["quat"][rows])
        t.lost[rows], t.table[rows] = ~end["touch"], end["table"]


def _execute_six_dir(sim: Simulator, batch: Batch, cfg: PhysicsConfig, t: Trial) -> None:
    closed, held, ref = _closed(sim, batch, cfg, t)
    t.lost[held] = ~ref["touch"][held]
    _push_each_direction(sim, closed, batch, held, ref, t, t.bad | t.lost | t.unstable, cfg,
                         lambda direction: [push(batch, cfg, direction, sim.scene.mass)])


def _execute_bench(sim: Simulator, batch: Batch, cfg: PhysicsConfig, t: Trial) -> None:
    """DexGraspBench's test (`dexgraspbench`): grasp and squeeze from the pre-grasp once, then from that state each
    direction's push, the object's pose compared every `dgb.CHECK_TIME` with its pose at the pre-grasp; a grasp
    leaves at its first failing check. A grasp that lost hand contact after the squeeze is still pushed."""
    idx = np.flatnonzero(~t.bad)
    start = sim.initial(batch.rows(idx))
    ref = {k: _scatter(v, idx, t.b) for k, v in sim.probe(start, batch.rows(idx)).items()}  # at the pre-grasp
    squeezed, held = _drive(sim, start, batch, idx, grasp_and_squeeze(batch, cfg), t.flagged, t.unstable)
    t.lost[held] = ~_probe(sim, squeezed, batch, held, t.b)["touch"][held]
    every = steps(dgb.CHECK_TIME, cfg.timestep)
    _push_each_direction(sim, squeezed, batch, held, ref, t, t.bad | t.unstable, cfg,
                         lambda direction: split_segment(bench_push(batch, cfg, direction, sim.scene.mass), every))


def _push_each_direction(sim: Simulator, branch: Any, batch: Batch, held: np.ndarray, ref: dict, t: Trial,
                         failed: np.ndarray, cfg: PhysicsConfig, segments: Callable[[np.ndarray], list[Segment]]
                         ) -> None:
    """The six-direction push of six-dir and DexGraspBench's test: from `branch` (the states of the grasps `held`),
    `segments(direction)` along each of `DIRECTIONS` in turn, recording in `t.move_dir` / `t.rot_dir` the largest
    distance and turn from `ref`'s pose at the checks (`_drive`). A grasp past `max_move` or `max_rot_deg` (or
    diverged) joins `failed` and is not pushed further; those in `failed` from the start are never pushed."""
    where = np.zeros(t.b, np.int64)
    where[held] = np.arange(len(held))  # row of each grasp in the branch states
    failed |= t.unstable
    for k, direction in enumerate(DIRECTIONS):
        rows = np.flatnonzero(~failed)
        if len(rows) == 0:
            break
        t.move_dir[rows, k], t.rot_dir[rows, k] = 0.0, 0.0

        def pushed(state, rows, k=k):
            p = sim.probe(state, batch.rows(rows))
            t.move_dir[rows, k] = np.maximum(t.move_dir[rows, k], np.linalg.norm(p["pos"] - ref["pos"][rows], axis=1))
            t.rot_dir[rows, k] = np.maximum(t.rot_dir[rows, k], rotation_angle(p["quat"], ref["quat"][rows]))
            out = (t.move_dir[rows, k] >= cfg.max_move) | (t.rot_dir[rows, k] >= cfg.max_rot_deg)
            failed[rows[out]] = True
            return ~out

        _drive(sim, sim.take(branch, where[rows]), batch, rows, segments(direction), t.flagged, t.unstable, pushed)
        failed |= t.unstable


def _moved(move: np.ndarray, rot: np.ndarray, cfg: PhysicsConfig) -> np.ndarray:
    return (np.nan_to_num(move) >= cfg.max_move) | (np.nan_to_num(rot) >= cfg.max_rot_deg)


def _rule_lift_shake(bad, lost, move, rot, table, unstable, cfg: PhysicsConfig):
    """Held: still touched, within `max_slip` of its place in the palm, off the table."""
    moved = (np.nan_to_num(move) >= cfg.max_slip) | table
    return ~(bad | lost | moved | unstable), failure_reason(bad, lost, moved, unstable)


def _rule_six_dir(bad, lost, move, rot, table, unstable, cfg: PhysicsConfig):
    """Touched after closing, and within `max_move` and `max_rot_deg` in every push."""
    moved = _moved(move, rot, cfg)
    return ~(bad | lost | moved | unstable), failure_reason(bad, lost, moved, unstable)


def _rule_bench(bad, lost, move, rot, table, unstable, cfg: PhysicsConfig):
    """Within the bounds at every check (a grasp without contact may pass by caging); "lost" names a failure
    without hand contact after the squeeze."""
    moved = _moved(move, rot, cfg)
    return ~(bad | moved | unstable), failure_reason(bad, moved & lost, moved, unstable)


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
    """DexGraspBench's push: `cfg.accel` x mass along `direction` for `cfg.push_time`, targets held at the squeeze
    (`push`'s segment, under the benchmark's settings)."""
    return push(batch, cfg, direction, mass)


def split_segment(seg: Segment, k: int) -> list[Segment]:
    """A segment of constant control as consecutive segments of at most k steps (a check after each)."""
    return [Segment(min(k, seg.n - i), seg.make, seg.force, seg.hold) for i in range(0, seg.n, k)]


def _scatter(values: np.ndarray, idx: np.ndarray, b: int) -> np.ndarray:
    """Rows `idx` of a (b, ...) array set to `values`, the rest zero."""
    out = np.zeros((b, *values.shape[1:]), values.dtype)
    out[idx] = values
    return out



def summary_rows(results: dict[str, np.ndarray], protocols) -> list[tuple[str, str]]:
    """Success rates over all tested grasps with 95 % Wilson intervals, and failure reasons; with robust trials
    (`<p>_trials`) success means the grasp holds (`robust`), and a row gives the share of all trials passed."""
    rows = []
    for p in protocols:
        ok, reason = results[result_key(p, "success")], results[result_key(p, "reason")]
        k, n = int(ok.sum()), len(ok)
        lo, hi = wilson(k, n)
        rate = f"{100 * k / n:.1f} %" if n else "-"
        trials = results.get(result_key(p, "trials"))
        label = f"{p} holds (all)" if trials is not None else f"{p} success (all)"
        rows.append((label, f"{k} / {n} = {rate}  (95 % CI {100 * lo:.1f}-{100 * hi:.1f} %)"))
        if trials is not None and np.size(trials):
            t = np.asarray(trials, bool)
            rows.append((f"{p} trials passed", f"{int(t.sum())} / {t.size} = {100 * t.mean():.1f} % ({t.shape[1]} "
                         f"perturbed trials per grasp; a grasp holds when its 90 % interval's lower bound >= the "
                         f"threshold)"))
        counts = ", ".join(f"{r} {int((reason == i).sum())}" for i, r in enumerate(REASONS) if i)
        rows.append((f"{p} failures", counts))
    return rows


def _phases_lift_shake(batch: Batch, cfg: PhysicsConfig, mass: float) -> list[tuple[str, Segment, bool]]:
    close, settle = closing(batch, cfg)
    segs = lift_shake(batch, cfg)  # lift, hold, then shake unless shake_cycles is 0
    return [("closing", close, False), ("settle", settle, False)] + [
        (name, seg, False) for name, seg in zip(("lift", "hold", "shake"), segs, strict=False)]


def _phases_six_dir(batch: Batch, cfg: PhysicsConfig, mass: float) -> list[tuple[str, Segment, bool]]:
    close, settle = closing(batch, cfg)
    return [("closing", close, False), ("settle", settle, False)] + [
        (f"push {name}", push(batch, cfg, direction, mass), True)
        for name, direction in zip(DIRECTION_NAMES, DIRECTIONS, strict=True)]


def _phases_bench(batch: Batch, cfg: PhysicsConfig, mass: float) -> list[tuple[str, Segment, bool]]:
    grasp, squeeze = grasp_and_squeeze(batch, cfg)
    return [("grasp", grasp, False), ("squeeze", squeeze, False)] + [
        (f"push {name}", bench_push(batch, cfg, direction, mass), True)
        for name, direction in zip(DIRECTION_NAMES, DIRECTIONS, strict=True)]


register(Protocol(
    "lift-shake", "the paper's real-robot test: lift, then shake along x; the object must stay in the palm",
    kind="ours", gravity=True, table=True, hold=False, execute=_execute_lift_shake, rule=_rule_lift_shake,
    phases=_phases_lift_shake, default=True))
register(Protocol(
    "six-dir", "a force of accel x mass along +-x, +-y, +-z in turn, gravity off; the object must stay put",
    kind="ours", gravity=False, table=False, hold=True, execute=_execute_six_dir, rule=_rule_six_dir,
    phases=_phases_six_dir, default=True, directions=True))
for _name, _version in dgb.VERSIONS.items():
    register(Protocol(
        _name, f"DexGraspBench's MuJoCo test, {_version.source}", kind="dexgraspbench", gravity=False, table=False,
        hold=False, execute=_execute_bench, rule=_rule_bench, phases=_phases_bench, fixed=dgb.fixed(_version),
        directions=True))
if names() != ALL_PROTOCOLS or names(default=True) != PROTOCOLS:  # the names the CLI offers are these protocols
    raise FfcgsError(f"the registered protocols {names()} differ from physics.config's {ALL_PROTOCOLS}")
