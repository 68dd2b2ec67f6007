"""Shared cases of test_worlds.py: the ball's grasps as `worlds.Job`s, the protocols' own segments at a step, and a
simulator that only counts steps (where `protocols.run_protocol` looks at the object)."""

import types

import numpy as np

from ffcgs_jax.physics import protocols as P
from ffcgs_jax.physics import runner, worlds
from ffcgs_jax.physics.config import PhysicsConfig
from physics_trials import ONE_TRIAL

from test_runner import SPEC, ball_grasps, enveloping_ball_grasp

FAST = PhysicsConfig(robust=ONE_TRIAL, sim_friction=1.0, close_time=0.2, settle_time=0.1, lift_height=0.03, shake_cycles=1,
                     shake_amplitude=0.02, push_time=0.2)
PROTOCOLS = ("lift-shake", "six-dir", "dexgraspbench")


def four_grasps() -> tuple[np.ndarray, np.ndarray]:
    """Three enveloping ball grasps and one 5 cm off that touches nothing (fails "lost" on every protocol)."""
    Ts, qs = ball_grasps(3)
    far, q = enveloping_ball_grasp(shift=0.05)
    return np.concatenate([Ts, far[None]]), np.concatenate([qs, q[None]])


def make_jobs(mesh, key, Ts, qs, protocols=PROTOCOLS, cfg=FAST, parts=None) -> list[worlds.Job]:
    """One `worlds.Job` per protocol of `mesh`'s grasps, as `runner.evaluate_many` builds them."""
    scenes = runner.scenes(SPEC, mesh, cfg, protocols, parts=parts)
    jobs = []
    for p in protocols:
        pcfg = P.get(p).settings(cfg)
        batch, depth, _ = runner.prepare(scenes[p], mesh, Ts, qs, pcfg)
        jobs.append(worlds.Job(scenes[p], batch, depth, pcfg, p, object_key=key))
    return jobs


def at(segs: list, t: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool]:
    """(servo targets (B, Q), wrist offset (3,), force (3,), hold) of step t of the segments run in turn."""
    for seg in segs:
        if t < seg.n:
            ctrl, off = seg.make(t, t + 1)
            force = np.zeros(3) if seg.force is None else np.asarray(seg.force, float)
            return np.asarray(ctrl)[:, 0], np.asarray(off)[0], force, seg.hold
        t -= seg.n
    raise IndexError("past the last segment")


class StepCounter:
    """A `backend.Simulator` whose state is each grasp's count of steps run: `probed` collects the counts at
    which the protocol reads the object (`probe`). The object never moves, the hand always touches it."""

    def __init__(self, mass: float = 0.1):
        self.scene = types.SimpleNamespace(mass=mass)
        self.probed: list[np.ndarray] = []

    def initial(self, batch):
        return np.zeros(len(batch.wrist_pos), np.int64)

    def run(self, state, batch, seg, track=None):
        return state + seg.n

    def probe(self, state, batch, offset=(0.0, 0.0, 0.0)):
        self.probed.append(np.array(state))
        b = len(state)
        return dict(pos=np.zeros((b, 3)), quat=np.tile([1.0, 0.0, 0.0, 0.0], (b, 1)), rel=np.zeros((b, 3)),
                    table=np.zeros(b, bool), touch=np.ones(b, bool))

    def take(self, state, idx):
        return state[idx]

    def flagged(self, state):
        return np.zeros(len(state), bool)

    def unstable(self, state):
        return np.zeros(len(state), bool)

    def times(self) -> list[int]:
        return sorted({int(t) for s in self.probed for t in s})
