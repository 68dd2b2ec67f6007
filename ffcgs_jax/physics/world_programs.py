"""What each GPU world runs, where its checks fall, and how its results become a protocol's outcome.

- `Layout`: the columns of the per-world float and int arrays the kernels (`world_kernels`) read and write.
- `Schedule`: each program's events (reference pose, checks, the branch to the pushes, the end), taken from the
  protocols' own segments (`protocols`), so the device checks where `protocols.run_protocol` checks on the CPU.
- `Block`: tasks waiting for worlds; `Stats`: what a run cost.
- `JobState`: one job's results as its worlds finish, and at the end the arrays of `run_protocol`, directions
  after the first failing one blanked as the CPU, which pushes them in turn and stops there, leaves them.
"""

import dataclasses

import numpy as np

from ffcgs_jax.physics import dexgraspbench as dgb
from ffcgs_jax.physics import protocols as P
from ffcgs_jax.physics import world_kernels as K
from ffcgs_jax.physics.backend import CHUNK, Batch
from ffcgs_jax.physics.config import PhysicsConfig


class Layout:
    """Columns of the per-world float (`fp`) and int (`ip`) arrays; `col` is the index array the kernels read."""

    def __init__(self, nu: int):
        q = nu
        self.QS, self.QT, self.QG, self.WP, self.WQ, self.F = 0, q, 2 * q, 3 * q, 3 * q + 3, 3 * q + 7
        self.RP, self.RQ, self.RR, self.MOVE, self.ROT, self.TZ = 3 * q + 10, 3 * q + 13, 3 * q + 17, 3 * q + 20, \
            3 * q + 21, 3 * q + 22
        self.nf = 3 * q + 23
        self.KIND, self.T, self.EVP, self.EVE, self.ST, self.UNST, self.FLAG, self.TOUCH, self.LOST, self.TABLE, \
            self.OBJ = range(11)
        self.ni = 11
        self.col = np.array([self.KIND, self.T, self.EVP, self.EVE, self.ST, self.QS, self.QT, self.QG, self.WP,
                             self.WQ, self.F, self.RP, self.RQ, self.RR, self.UNST, self.FLAG, self.MOVE, self.ROT,
                             self.TOUCH, self.LOST, self.TABLE, self.OBJ, self.TZ], np.int32)


class Schedule:
    """Each program's length and its events (step, code), from the protocols' own segments (`protocols`): the
    checks fall where `protocols.run_protocol` checks on the CPU (after each `CHUNK` of a segment and at its end;
    DexGraspBench's every `dexgraspbench.CHECK_TIME`)."""

    def __init__(self, cfg: PhysicsConfig, nu: int):
        dt = cfg.timestep
        z = np.zeros((1, nu))
        one = Batch(np.zeros((1, 3)), np.array([[1.0, 0, 0, 0]]), z, z, z)
        close = sum(s.n for s in P.closing(one, cfg))
        ev = {K.LIFT: [(close, K.REF)] + _checks(P.lift_shake(one, cfg), close),
              K.SIX_CLOSE: [(close, K.BRANCH)],
              K.SIX_PUSH: _checks([P.push(one, cfg, P.DIRECTIONS[0], 1.0)], 0),
              K.BENCH_SQUEEZE: [(0, K.REF), (sum(s.n for s in P.grasp_and_squeeze(one, cfg)), K.BRANCH)],
              K.BENCH_PUSH: _checks(P.split_segment(P.bench_push(one, cfg, P.DIRECTIONS[0], 1.0),
                                                    P.steps(dgb.CHECK_TIME, dt)), 0)}
        self.adr, self.num, t, code = {}, {}, [], []
        for kind, events in ev.items():
            self.adr[kind], self.num[kind] = len(t), len(events)
            t += [e[0] for e in events]
            code += [e[1] for e in events]
        self.ev_t, self.ev_code = np.array(t, np.int32), np.array(code, np.int32)
        period = 4 * cfg.shake_amplitude / cfg.shake_speed
        n_shake = P.steps(cfg.shake_cycles * period, dt) if cfg.shake_cycles else 0
        self.ints = np.array([P.steps(cfg.close_time, dt), P.steps(cfg.settle_time, dt),
                              P.steps(cfg.lift_height / cfg.lift_speed, dt), P.steps(P.LIFT_HOLD, dt), n_shake,
                              P.steps(dgb.STAGE_TIME, dt), dgb.WAYPOINTS], np.int32)
        self.floats = np.array([dt, cfg.lift_height, cfg.shake_amplitude, period], np.float32)
        self.bounds = np.array([cfg.max_slip, cfg.max_move, cfg.max_rot_deg], np.float32)
        self.length = {kind: events[-1][0] + 1 for kind, events in ev.items()}  # step calls a program takes


def _checks(segs: list, start: int) -> list[tuple[int, int]]:
    """(step, CHECK) after each `CHUNK` of each segment and at its end, from step `start`; the last is FINAL."""
    out, t = [], start
    for seg in segs:
        for i0 in range(0, seg.n, CHUNK):
            out.append((t + min(seg.n, i0 + CHUNK), K.CHECK))
        t += seg.n
    if out:
        out[-1] = (out[-1][0], K.FINAL)
    return out


class JobState:
    """A job's results as they come in, and its outcome in `run_protocol`'s arrays (`result`)."""

    def __init__(self, job):  # a `worlds.Job`
        b = len(job.depth)
        self.job, self.b = job, b
        self.bad_start = np.asarray(job.depth) > job.cfg.max_initial_penetration
        self.move, self.rot = np.full(b, np.nan), np.full(b, np.nan)
        self.lost, self.table = np.zeros(b, bool), np.zeros(b, bool)
        self.unstable, self.flagged = np.zeros(b, bool), np.zeros(b, bool)
        self.move_dir, self.rot_dir = np.full((b, 6), np.nan), np.full((b, 6), np.nan)
        self.unstable_dir = np.zeros((b, 6), bool)
        self.pushed = np.zeros((b, 6), bool)
        self.open = 0  # worlds of this job placed or queued and not finished
        self.cpu: str | None = None  # why this job could not run as worlds (the caller runs it on the CPU)

    def result(self) -> dict[str, np.ndarray] | None:
        if self.cpu is not None:
            return None
        protocol, cfg = P.get(self.job.protocol), self.job.cfg
        bad, unstable = self.bad_start, self.unstable.copy()
        if not protocol.directions:
            return P.Trial(bad, self.flagged, unstable, self.lost, self.table, self.move.copy(), self.rot.copy()
                           ).outcome(protocol, cfg)
        # the CPU pushes the directions in turn and stops a grasp at its first failing one (six-dir does not push a
        # grasp that lost the object while closing): the directions after it are not pushed there (NaN), which the
        # arrays here repeat
        failed = bad | unstable | (self.lost if protocol.kind == "ours" else np.zeros_like(self.lost))
        move_dir, rot_dir = np.full((self.b, 6), np.nan), np.full((self.b, 6), np.nan)
        for k in range(6):
            rows = ~failed & self.pushed[:, k]
            move_dir[rows, k], rot_dir[rows, k] = self.move_dir[rows, k], self.rot_dir[rows, k]
            out = (self.move_dir[:, k] >= cfg.max_move) | (self.rot_dir[:, k] >= cfg.max_rot_deg)
            unstable |= rows & self.unstable_dir[:, k]
            failed |= rows & (out | self.unstable_dir[:, k])
        nan = np.full(self.b, np.nan)
        return P.Trial(bad, self.flagged, unstable, self.lost, self.table, nan, nan.copy(), move_dir, rot_dir
                       ).outcome(protocol, cfg)


@dataclasses.dataclass
class Block:
    """Tasks waiting for worlds: their int and float rows and initial states; `tag` (n, 3): job, grasp, direction."""

    ip: np.ndarray
    fp: np.ndarray
    qpos: np.ndarray
    qvel: np.ndarray
    warm: np.ndarray
    tag: np.ndarray

    def split(self, n: int) -> tuple["Block", "Block"]:
        f = dataclasses.fields(self)
        return (Block(*(getattr(self, x.name)[:n] for x in f)), Block(*(getattr(self, x.name)[n:] for x in f)))


@dataclasses.dataclass
class Stats:
    """What a run cost: step calls (`steps` of `worlds` worlds each), world-steps of programs that were running
    (`busy_steps`), objects, and seconds spent placing, stepping (launch to status read) and reading results."""

    steps: int = 0
    world_steps: int = 0
    busy_steps: int = 0
    objects: int = 0
    place_s: float = 0.0
    step_s: float = 0.0
    read_s: float = 0.0
    setup_s: float = 0.0
