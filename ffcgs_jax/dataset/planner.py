"""Annotation planner: batched simulated annealing over wrist pose and channels, then Q-distance refinement.

The paper annotated its training grasps with GraspIt!'s simulated annealing. This is the same idea as one
jit-compiled `lax.scan` over a whole population: every candidate random-walks its wrist twist and its channels
under Metropolis acceptance with a geometrically cooling temperature, scored by a cheap energy without the LP
(so thousands of candidates fit in a batch). The best candidates then go through `synthesis.grasp.synthesize(poses=...)`
(the gradient optimiser, filters and the mesh epsilon); `dedupe` drops near-duplicate wrists and `physics_select`
keeps the best that pass both MuJoCo protocols.

Each candidate draws its randomness from `fold_in(key, index)`, never from a split of the whole batch, so its
trajectory does not depend on the population size or on the other candidates.
"""

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import trimesh

from ffcgs_jax.core.config import check_all
from ffcgs_jax.dataset.config import PlannerConfig
from ffcgs_jax.geometry import sdf as sdf_mod
from ffcgs_jax.hand import kinematics as K
from ffcgs_jax.hand.kinematics import Hand
from ffcgs_jax.hand.spec import HandSpec
from ffcgs_jax.physics import runner as physics
from ffcgs_jax.physics.config import PhysicsConfig
from ffcgs_jax.synthesis import filters as F
from ffcgs_jax.synthesis import grasp, samplers
from ffcgs_jax.synthesis.config import FilterConfig, GraspConfig, SamplerConfig
from ffcgs_jax.synthesis.energy import Target, contact_energy, joint_energy, make_target
from ffcgs_jax.synthesis.optimize import twist_pose


def cheap_energy(hand: Hand, target: Target, wrist_pose: jax.Array, q: jax.Array, cfg: PlannerConfig,
                 filters: FilterConfig = FilterConfig()) -> jax.Array:
    """The annealing energy of one grasp: a_c E_c + a_q E_q + a_pen P + a_fc |mean inward normal| + a_up palm-up."""
    c = K.contact_points(hand, wrist_pose, q)
    d, n = sdf_mod.query(target.sdf, c)
    fc = jnp.linalg.norm(jnp.mean(n, axis=0))
    up = jax.nn.relu((wrist_pose[:3, :3] @ hand.palm_normal)[2] - filters.palm_up_max)
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


def start(hand: Hand, target: Target, cfg: PlannerConfig, key: jax.Array, sampling: SamplerConfig = SamplerConfig(),
          filters: FilterConfig = FilterConfig()) -> Start:
    """Geometric start poses, uniform random q within the limits, and each candidate's walk key."""
    k_pose, k_q, k_walk = jax.random.split(key, 3)
    palm_root = K.forward_kinematics(hand, jnp.eye(4, dtype=hand.lower.dtype), jnp.zeros_like(hand.lower)).palm_pos
    poses = samplers.sample_geometric(hand, palm_root, k_pose, target.sdf, cfg.population, sampling, filters)
    idx = jnp.arange(cfg.population)
    u = jax.vmap(lambda i: jax.random.uniform(jax.random.fold_in(k_q, i), hand.lower.shape, hand.lower.dtype))(idx)
    q = hand.lower[None, :] + u * (hand.upper - hand.lower)[None, :]
    keys = jax.vmap(jax.random.fold_in, (None, 0))(k_walk, idx)
    return Start(poses.astype(hand.lower.dtype), q, keys)


def anneal_from(hand: Hand, target: Target, cfg: PlannerConfig, poses: jax.Array, q: jax.Array,
                keys: jax.Array, filters: FilterConfig = FilterConfig()) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Anneal given start states (P, 4, 4), (P, Q) with per-candidate keys (P, 2); returns the best state seen by
    each candidate and its energy. vmap over candidates, so candidate i depends on (poses[i], q[i], keys[i]) only."""
    dtype = q.dtype
    scale = jnp.concatenate([jnp.full(3, cfg.step_rot), jnp.full(3, cfg.step_shift)]).astype(dtype)
    E_one = lambda H, qq: cheap_energy(hand, target, H, qq, cfg, filters)

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


start_jit = jax.jit(start, static_argnames=("cfg", "sampling", "filters"))
anneal_from_jit = jax.jit(anneal_from, static_argnames=("cfg", "filters"))
cheap_energy_batch = jax.jit(jax.vmap(cheap_energy, (None, None, 0, 0, None, None)), static_argnums=(4, 5))


def anneal(hand: Hand, target: Target, cfg: PlannerConfig, key: jax.Array, sampling: SamplerConfig = SamplerConfig(),
           filters: FilterConfig = FilterConfig()) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Simulated annealing of cfg.population candidates from geometric poses (`sampling`) and random q.

    Returns:
        poses (P, 4, 4), q (P, Q) within the limits and cheap energy (P,): the best state each candidate visited.
    """
    cfg.check()
    # two compiled calls rather than one fused: callers (tests, benchmarks) reuse the same executables
    _, sampling = samplers.for_hand("geometric", hand, sampling)  # the hand's standoff where it is 0
    s = start_jit(hand, target, cfg, key, sampling, filters)
    return anneal_from_jit(hand, target, cfg, s.poses, s.q, s.keys, filters)


def plan(hand: Hand, mesh: trimesh.Trimesh, cfg: PlannerConfig = PlannerConfig(),
         grasp_cfg: GraspConfig = GraspConfig(), object_name: str = "object", grid: sdf_mod.GradientSDF | None = None,
         key: jax.Array | None = None) -> grasp.GraspSet:
    """Anneal, refine the cfg.refine lowest-energy candidates with `synthesis.grasp.synthesize`, and return them
    valid first, each group by decreasing epsilon. `key` defaults to PRNGKey(grasp_cfg.seed).

    The refinement restarts the fingers from the open hand rather than from the annealed channels: on the box and
    the mug (512 annealed, best 128 refined) that gave 76 and 73 valid grasps, 34 and 49 with epsilon > 0, against
    42 and 50 (14 and 20 with epsilon > 0) from the annealed channels, whose closed fingers let the wrist settle
    where the open hand collides. The annealing's job is the wrist pose."""
    cfg.check()
    check_all(grasp_cfg)
    if grid is None:
        grid = sdf_mod.build_sdf(mesh, grasp_cfg.sdf)
    key = jax.random.PRNGKey(grasp_cfg.seed) if key is None else key
    poses, _, E = anneal(hand, make_target(grid), cfg, key, grasp_cfg.sampling, grasp_cfg.filters)
    E = np.asarray(E)
    best = np.argsort(np.where(np.isfinite(E), E, np.inf), kind="stable")[:cfg.refine]
    gs = grasp.synthesize(hand, mesh, grasp_cfg, object_name, grid=grid,
                          poses=K.orthonormalize(np.asarray(poses, np.float64)[best]))
    return gs.select(rank(gs))


def rank(gs: grasp.GraspSet) -> np.ndarray:
    """Indices of `gs`: valid grasps first, each group by decreasing epsilon (ties by E)."""
    return np.lexsort((gs["E"], -gs["epsilon"], ~gs["valid"]))


def dedupe(poses: np.ndarray, min_trans: float, min_rot: float) -> np.ndarray:
    """Greedy non-maximum suppression over wrist poses (G, 4, 4) given best first: the indices kept, where a pose
    is dropped if some kept pose is within both `min_trans` metres and `min_rot` radians of it."""
    poses = np.asarray(poses, np.float64)
    keep: list[int] = []
    for i in range(len(poses)):
        if keep:
            k = poses[keep]
            near = np.linalg.norm(k[:, :3, 3] - poses[i, :3, 3], axis=1) < min_trans
            cos = (np.einsum("kij,ij->k", k[:, :3, :3], poses[i, :3, :3]) - 1) / 2
            near &= np.arccos(np.clip(cos, -1, 1)) < min_rot
            if near.any():
                continue
        keep.append(i)
    return np.asarray(keep, dtype=np.int64)


def physics_select(gs: grasp.GraspSet, spec: HandSpec, mesh: trimesh.Trimesh, want: int,
                   physics_cfg: PhysicsConfig = PhysicsConfig(), chunk: int = 128,
                   progress=None) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Test grasps of `gs` in their order, `chunk` at a time, until `want` pass both protocols or none are left.

    Six-dir runs first and lift-shake only on its survivors (six-dir is the cheaper and the stricter test), so a
    grasp failing six-dir has lift_shake_success False without a lift-shake run. Returns the indices of the
    passing grasps (order kept, at most `want`) and per-grasp arrays: tested_six_dir, six_dir_success,
    tested_lift_shake, lift_shake_success (False where not tested)."""
    n = len(gs["valid"])
    out = {k: np.zeros(n, bool) for k in ("tested_six_dir", "six_dir_success", "tested_lift_shake",
                                           "lift_shake_success")}
    passed: list[int] = []
    for start_i in range(0, n, chunk):
        if len(passed) >= want:
            break
        idx = np.arange(start_i, min(start_i + chunk, n))
        six = physics.evaluate(spec, mesh, gs["wrist_pose"][idx], gs["q"][idx], physics_cfg, protocols=("six-dir",))
        out["tested_six_dir"][idx] = True
        out["six_dir_success"][idx] = six["six_dir_success"]
        idx2 = idx[np.asarray(six["six_dir_success"], bool)]
        if len(idx2):
            lift = physics.evaluate(spec, mesh, gs["wrist_pose"][idx2], gs["q"][idx2], physics_cfg,
                                    protocols=("lift-shake",))
            out["tested_lift_shake"][idx2] = True
            out["lift_shake_success"][idx2] = lift["lift_shake_success"]
        passed = np.flatnonzero(out["six_dir_success"] & out["lift_shake_success"]).tolist()
        if progress is not None:
            progress(len(idx), min(len(passed), want))
    return np.asarray(passed[:want], dtype=np.int64), out
