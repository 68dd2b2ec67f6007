"""Annotation planner: batched simulated annealing over wrist pose and channels, then Q-distance refinement.

The paper annotated its training grasps with GraspIt!'s simulated annealing. This is the same idea as one
jit-compiled `lax.scan` over a whole population: every candidate random-walks its wrist twist and its 9 channels
under Metropolis acceptance with a geometrically cooling temperature, scored by a cheap energy without the LP
(so thousands of candidates fit in a batch). The best candidates then go through `grasp.synthesize(poses=...)`
(the gradient optimiser, filters and the mesh epsilon), and `physics_filter` keeps those that pass MuJoCo.

Each candidate draws its randomness from `fold_in(key, index)`, never from a split of the whole batch, so its
trajectory does not depend on the population size or on the other candidates.
"""

import dataclasses
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import trimesh

from ffcgs_jax import filters as F
from ffcgs_jax import grasp, physics, samplers
from ffcgs_jax import kinematics as K
from ffcgs_jax import sdf as sdf_mod
from ffcgs_jax.config import FilterConfig, GraspConfig, PhysicsConfig, SamplerConfig
from ffcgs_jax.energy import Target, contact_energy, joint_energy, make_target
from ffcgs_jax.errors import FfcgsError
from ffcgs_jax.hand_spec import HandSpec
from ffcgs_jax.kinematics import Hand
from ffcgs_jax.optimize import twist_pose


@dataclasses.dataclass(frozen=True)
class PlannerConfig:
    """Simulated annealing settings (frozen: a static jit argument).

    Attributes:
        population: candidates annealed as one batch.
        steps: Metropolis steps per candidate.
        t0, t_end: temperature at the first and the last step (geometric cooling in between), in units of the
            cheap energy: 0.05 accepts a 1 cm RMS fingertip regression (a_c 5) about a third of the time at first.
        step_shift, step_rot, step_q: standard deviation of the proposal's wrist translation (m, hand frame), wrist
            rotation (rad) and channels (rad) at t0. They shrink with sqrt(T / t0), so late steps fine-tune
            instead of jumping out of the basin they cooled into.
        a_c, a_q, a_pen: weights of E_c, E_q and the whole-hand penetration penalty, as in `EnergyConfig`.
        a_fc: weight of the force-closure proxy |sum of inward unit contact normals| / C (0 when opposed).
        a_up: weight of how far the palm normal's z exceeds filters.palm_up_max (that filter would drop it later).
        seed: PRNG seed of `plan`.
        sampling, filters: the geometric sampler giving the start poses.
    """

    population: int = 1024
    steps: int = 100
    t0: float = 0.05
    t_end: float = 1e-3
    step_shift: float = 0.01
    step_rot: float = 0.1
    step_q: float = 0.2
    a_c: float = 5.0
    a_q: float = 0.5
    a_pen: float = 1e4
    a_fc: float = 0.1
    a_up: float = 1.0
    seed: int = 0
    sampling: SamplerConfig = SamplerConfig()
    filters: FilterConfig = FilterConfig()

    def check(self) -> None:
        for name, lo, hi in (("population", 1, 1_000_000), ("steps", 1, 1_000_000), ("seed", 0, 2**63 - 1)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
                raise FfcgsError(f"planner.{name} must be an integer in [{lo}, {hi}], got {v!r}")
        for name in ("t0", "t_end", "step_shift", "step_rot", "step_q", "a_c", "a_q", "a_pen", "a_fc", "a_up"):
            v = getattr(self, name)
            positive = name in ("t0", "t_end")
            if not (isinstance(v, (int, float)) and math.isfinite(v) and (v > 0 if positive else v >= 0)):
                raise FfcgsError(f"planner.{name} must be a finite number {'> 0' if positive else '>= 0'}, got {v!r}")
        if self.t_end > self.t0:
            raise FfcgsError(f"planner.t_end ({self.t_end}) must not exceed planner.t0 ({self.t0}): it cools")
        self.sampling.check()
        self.filters.check()


def cheap_energy(hand: Hand, target: Target, wrist_pose: jax.Array, q: jax.Array, cfg: PlannerConfig) -> jax.Array:
    """The annealing energy of one grasp: a_c E_c + a_q E_q + a_pen P + a_fc |mean inward normal| + a_up palm-up."""
    c = K.contact_points(hand, wrist_pose, q)
    d, n = sdf_mod.query(target.sdf, c)
    fc = jnp.linalg.norm(jnp.mean(n, axis=0))
    up = jax.nn.relu((wrist_pose[:3, :3] @ hand.palm_normal)[2] - cfg.filters.palm_up_max)
    E = cfg.a_c * contact_energy(d, 0.0) + cfg.a_q * joint_energy(hand, q) + cfg.a_fc * fc + cfg.a_up * up
    if cfg.a_pen > 0:
        E = E + cfg.a_pen * F.penetration_penalty(hand, target.sdf, wrist_pose, q)
    return E


def metropolis_accept(E_old: jax.Array, E_new: jax.Array, temperature: jax.Array, u: jax.Array) -> jax.Array:
    """Accept with probability min(1, exp(-(E_new - E_old) / T)), given u ~ U(0, 1). A NaN proposal is refused."""
    return jnp.log(u) < -(E_new - E_old) / temperature


def temperatures(cfg: PlannerConfig, dtype=jnp.float64) -> jax.Array:
    """(steps,) geometric cooling from t0 to t_end."""
    frac = jnp.arange(cfg.steps, dtype=dtype) / max(cfg.steps - 1, 1)
    return cfg.t0 * (cfg.t_end / cfg.t0) ** frac


class Start(NamedTuple):
    poses: jax.Array  # (P, 4, 4)
    q: jax.Array  # (P, Q)
    keys: jax.Array  # (P, 2) per-candidate walk keys


def start(hand: Hand, target: Target, cfg: PlannerConfig, key: jax.Array) -> Start:
    """Geometric start poses, uniform random q within the limits, and each candidate's walk key."""
    k_pose, k_q, k_walk = jax.random.split(key, 3)
    palm_root = K.forward_kinematics(hand, jnp.eye(4, dtype=hand.lower.dtype), jnp.zeros_like(hand.lower)).palm_pos
    poses = samplers.sample_geometric(hand, palm_root, k_pose, target.sdf, cfg.population, cfg.sampling, cfg.filters)
    idx = jnp.arange(cfg.population)
    u = jax.vmap(lambda i: jax.random.uniform(jax.random.fold_in(k_q, i), hand.lower.shape, hand.lower.dtype))(idx)
    q = hand.lower[None, :] + u * (hand.upper - hand.lower)[None, :]
    keys = jax.vmap(jax.random.fold_in, (None, 0))(k_walk, idx)
    return Start(poses.astype(hand.lower.dtype), q, keys)


def anneal_from(hand: Hand, target: Target, cfg: PlannerConfig, poses: jax.Array, q: jax.Array,
                keys: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Anneal given start states (P, 4, 4), (P, Q) with per-candidate keys (P, 2); returns the best state seen by
    each candidate and its energy. vmap over candidates, so candidate i depends on (poses[i], q[i], keys[i]) only."""
    dtype = q.dtype
    scale = jnp.concatenate([jnp.full(3, cfg.step_rot), jnp.full(3, cfg.step_shift)]).astype(dtype)
    E_one = lambda H, qq: cheap_energy(hand, target, H, qq, cfg)

    def one(H, q0, key):
        def step(carry, xs):
            H, q, E, bH, bq, bE = carry
            t, temp = xs
            k_xi, k_q, k_u = jax.random.split(jax.random.fold_in(key, t), 3)
            s = jnp.sqrt(temp / cfg.t0)
            H2 = twist_pose(H, s * scale * jax.random.normal(k_xi, (6,), dtype))
            q2 = jnp.clip(q + s * cfg.step_q * jax.random.normal(k_q, q.shape, dtype), hand.lower, hand.upper)
            E2 = E_one(H2, q2)
            ok = metropolis_accept(E, E2, temp, jax.random.uniform(k_u, (), dtype))
            H, q, E = jnp.where(ok, H2, H), jnp.where(ok, q2, q), jnp.where(ok, E2, E)
            better = E < bE
            return (H, q, E, jnp.where(better, H, bH), jnp.where(better, q, bq), jnp.where(better, E, bE)), None

        E0 = E_one(H, q0)
        # a NaN start (grid edge) must not count as best forever: any finite state beats +inf
        bE0 = jnp.where(jnp.isfinite(E0), E0, jnp.inf)
        xs = (jnp.arange(cfg.steps), temperatures(cfg, dtype))
        (_, _, _, bH, bq, bE), _ = jax.lax.scan(step, (H, q0, E0, H, q0, bE0), xs)
        return bH, bq, bE

    return jax.vmap(one)(poses, q, keys)


start_jit = jax.jit(start, static_argnames="cfg")
anneal_from_jit = jax.jit(anneal_from, static_argnames="cfg")
cheap_energy_batch = jax.jit(jax.vmap(cheap_energy, (None, None, 0, 0, None)), static_argnums=4)


def anneal(hand: Hand, target: Target, cfg: PlannerConfig, key: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Simulated annealing of cfg.population candidates from geometric poses and random q.

    Returns:
        poses (P, 4, 4), q (P, Q) within the limits and cheap energy (P,): the best state each candidate visited.
    """
    cfg.check()
    # two compiled calls rather than one fused: callers (tests, benchmarks) reuse the same executables
    s = start_jit(hand, target, cfg, key)
    return anneal_from_jit(hand, target, cfg, s.poses, s.q, s.keys)


def plan(hand: Hand, mesh: trimesh.Trimesh, cfg: PlannerConfig = PlannerConfig(), keep: int = 32,
         grasp_cfg: GraspConfig = GraspConfig(), object_name: str = "object",
         grid: sdf_mod.GradientSDF | None = None) -> grasp.GraspSet:
    """Anneal, refine the `keep` lowest-energy candidates with `grasp.synthesize` (which restarts q from 0 and
    refines the wrist), and return them valid first, each group by decreasing epsilon."""
    cfg.check()
    if isinstance(keep, bool) or not isinstance(keep, int) or not 1 <= keep <= cfg.population:
        raise FfcgsError(f"keep must be an integer in [1, population={cfg.population}], got {keep!r}")
    if grid is None:
        grid = sdf_mod.build_sdf(mesh, grasp_cfg.sdf)
    poses, _, E = anneal(hand, make_target(grid), cfg, jax.random.PRNGKey(cfg.seed))
    E = np.asarray(E)
    best = np.argsort(np.where(np.isfinite(E), E, np.inf), kind="stable")[:keep]
    gs = grasp.synthesize(hand, mesh, grasp_cfg, object_name, grid=grid,
                          poses=K.orthonormalize(np.asarray(poses, np.float64)[best]))
    return gs.select(np.lexsort((-gs["epsilon"], ~gs["valid"])))


def physics_filter(gs: grasp.GraspSet, spec: HandSpec, mesh: trimesh.Trimesh,
                   physics_cfg: PhysicsConfig = PhysicsConfig()) -> grasp.GraspSet:
    """The grasps of `gs` that pass both physics protocols (lift-shake and six-dir), order kept."""
    if len(gs["valid"]) == 0:
        return gs
    r = physics.evaluate(spec, mesh, gs["wrist_pose"], gs["q"], physics_cfg, protocols=("lift-shake", "six-dir"))
    return gs.select(np.flatnonzero(np.asarray(r["lift_shake_success"]) & np.asarray(r["six_dir_success"])))
