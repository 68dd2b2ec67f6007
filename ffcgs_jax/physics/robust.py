"""The robust verdict: each grasp tried K times under perturbations, a pass rate with its interval per protocol.

One deterministic trial is brittle: a millimetre of other collision geometry flips about 1 grasp in 8, and picking
the grasps that passed it picks the marginal ones (bench/RESULTS.md, issue 45). Here every grasp runs `trials`
times, trial k under the perturbations of `config.RobustConfig` (its docstring states the distribution), and each
protocol's result is the share of trials passed with its Wilson interval; a grasp holds when the interval's lower
bound clears `threshold`.

How a call becomes trials (`runner.evaluate_many` does this when `cfg.robust.trials` > 1): each object's grasps
become K items (`expand`), item k with every grasp's perturbed wrist pose and q and trial k's settings (friction,
mass, geometry); they run as any items do (on MuJoCo Warp all as worlds of the same launches), and `combine` folds
each object's K results into one: per protocol `<p>_trials` (B, K) the outcomes, `<p>_rate`, `<p>_rate_low`,
`<p>_rate_high`, `<p>_success` (holds), `<p>_reason` (the most frequent failure, "ok" where it holds), move and
rot the median over trials.
"""

import dataclasses
import hashlib
from collections.abc import Iterable, Iterator

import numpy as np

from ffcgs_jax.physics import convex
from ffcgs_jax.physics import protocols as physics_protocols
from ffcgs_jax.physics.config import PhysicsConfig, RobustConfig, geometry_settings

# the per-trial results `combine` folds; the rest of a protocol's arrays are per grasp and trial alike
TRIAL_KEYS = ("success", "reason", "move", "rot", "move_dir", "rot_dir", "pregrasp_penetration")
RATE_KEYS = ("trials", "rate", "rate_low", "rate_high")  # what `combine` adds per protocol


@dataclasses.dataclass(frozen=True)
class Trial:
    """Trial k's conditions shared by every grasp: the `PhysicsConfig` fields it sets (friction, mass,
    geometry)."""

    index: int
    settings: dict


def trials(physics: PhysicsConfig) -> list[Trial]:
    """The K trials' shared conditions: friction and mass factors each stratified over K equal bins of their range
    (a random bin order per quantity, a uniform draw within the bin) times the nominal values, geometry
    k % len(geometries)."""
    cfg = physics.robust
    k = cfg.trials
    rng = np.random.default_rng([cfg.trial_seed, 0x7269616C])
    out = []
    strata = [(rng.permutation(k) + rng.random(k)) / k for _ in range(2)]
    for i in range(k):
        (f0, f1), (m0, m1) = cfg.friction_factors, cfg.mass_factors
        friction = physics.sim_friction * (f0 + (f1 - f0) * strata[0][i])
        scale = m0 + (m1 - m0) * strata[1][i]
        mass = dict(density=physics.density * scale) if physics.density > 0 else dict(mass=physics.mass * scale)
        settings = dict(sim_friction=float(friction), **mass,
                        **geometry_settings(cfg.geometries[i % len(cfg.geometries)]))
        out.append(Trial(i, {k_: float(v) if isinstance(v, np.floating) else v for k_, v in settings.items()}))
    return out


def grasp_keys(wrist_pose: np.ndarray, q: np.ndarray) -> np.ndarray:
    """(B,) a 64-bit key of each grasp's own numbers: its draws then do not depend on the grasps beside it."""
    T = np.ascontiguousarray(np.asarray(wrist_pose, np.float64).reshape(-1, 16))
    qq = np.ascontiguousarray(np.asarray(q, np.float64).reshape(len(T), -1))
    return np.array([int.from_bytes(hashlib.blake2b(t.tobytes() + r.tobytes(), digest_size=8).digest(), "little")
                     for t, r in zip(T, qq)], np.uint64)


def _ball(rng: np.random.Generator, radius: float) -> np.ndarray:
    """One point uniform in the 3-D ball of `radius`."""
    v = rng.normal(size=3)
    return v / max(np.linalg.norm(v), 1e-12) * radius * rng.random() ** (1.0 / 3.0)


def perturb(cfg: RobustConfig, trial: int, wrist_pose, q) -> tuple[np.ndarray, np.ndarray]:
    """Trial `trial`'s wrist poses (B, 4, 4) and channels (B, Q) of the grasps (wrist_pose, q): each grasp shifted
    within the `pose_mm` ball, turned about its wrist origin within the `rot_deg` ball of rotation vectors, and
    its channels moved by uniform(-joint_rad, joint_rad) each (not yet clipped to the limits: the runner does)."""
    from scipy.spatial.transform import Rotation

    T = np.array(wrist_pose, np.float64).reshape(-1, 4, 4)
    qq = np.array(q, np.float64).reshape(len(T), -1)
    shift, turn, dq = np.zeros((len(T), 3)), np.zeros((len(T), 3)), np.zeros_like(qq)
    for g, key in enumerate(grasp_keys(T, qq)):
        rng = np.random.default_rng([cfg.trial_seed, trial, int(key)])
        shift[g] = _ball(rng, cfg.pose_mm * 1e-3)
        turn[g] = _ball(rng, np.deg2rad(cfg.rot_deg))
        dq[g] = rng.uniform(-cfg.joint_rad, cfg.joint_rad, qq.shape[1])
    out = T.copy()
    out[:, :3, :3] = Rotation.from_rotvec(turn).as_matrix() @ T[:, :3, :3]
    out[:, :3, 3] += shift
    return out, qq + dq


def expand(items: Iterable, cfg: PhysicsConfig) -> Iterator:
    """Each item (`runner.Item`) as its K trials' items, in order (item 0's trials, then item 1's, ...): perturbed
    grasps and the trial's `settings`. An item's own collision parts are kept for the trials whose geometry is the
    one `cfg` would build them with; each other geometry variant is decomposed once per item and shared by its
    trials (the disk cache would serve them too, at a read and a mesh hash per trial)."""
    plan = trials(cfg)
    for it in items:
        parts: dict[tuple, list | None] = {}
        for t in plan:
            pose, q = perturb(cfg.robust, t.index, it.wrist_pose, it.q)
            geometry = {k: v for k, v in t.settings.items() if k in ("collision", "voxel_cells")}
            key = tuple(sorted(geometry.items()))
            if key not in parts:
                own = all(getattr(cfg, k) == v for k, v in geometry.items())
                parts[key] = (it.parts if own and it.parts is not None
                              else convex.decompose(it.mesh, dataclasses.replace(cfg, **geometry)))
            yield dataclasses.replace(it, wrist_pose=pose, q=q, settings=t.settings, parts=parts[key])


def rates(outcomes: np.ndarray, cfg: RobustConfig) -> dict[str, np.ndarray]:
    """From per-trial outcomes (B, K) bool: rate, rate_low, rate_high and whether each grasp holds."""
    outcomes = np.asarray(outcomes, bool)
    k = outcomes.shape[1]
    passed = outcomes.sum(axis=1)
    low, high = physics_protocols.wilson(passed, k, cfg.confidence)
    return dict(rate=passed / k, rate_low=low, rate_high=high, holds=low >= cfg.threshold)


def _most_frequent_failure(reasons: np.ndarray) -> np.ndarray:
    """(B,) per row of (B, K) reason indices the most frequent nonzero one (the lowest index on ties), 0 if none."""
    n = len(physics_protocols.REASONS)
    counts = np.stack([(reasons == r).sum(axis=1) for r in range(n)], axis=1)
    counts[:, 0] = 0
    out = counts.argmax(axis=1)
    return np.where(counts.max(axis=1) > 0, out, 0).astype(np.int8)


def _median(stack: np.ndarray) -> np.ndarray:
    finite = np.isfinite(stack).any(axis=0)
    out = np.full(stack.shape[1:], np.nan)
    if finite.any():
        out[finite] = np.nanmedian(stack[:, finite], axis=0)
    return out


def combine(results: list[dict[str, np.ndarray]], protocols, cfg: RobustConfig) -> dict[str, np.ndarray]:
    """One object's K trial results (`runner.evaluate` arrays, trial order) as its robust result (module
    docstring). initial_penetration is the median over trials, palm_contact its majority."""
    key = physics_protocols.result_key
    out: dict[str, np.ndarray] = {
        "initial_penetration": _median(np.stack([r["initial_penetration"] for r in results])),
        "palm_contact": np.mean([r["palm_contact"] for r in results], axis=0) >= 0.5,
    }
    if "physics_rerun_cpu" in results[0]:
        out["physics_rerun_cpu"] = np.logical_or.reduce([r["physics_rerun_cpu"] for r in results])
    for p in protocols:
        success = np.stack([np.asarray(r[key(p, "success")], bool) for r in results], axis=1)
        r = rates(success, cfg)
        out[key(p, "trials")] = success
        out.update({key(p, f): r[f] for f in ("rate", "rate_low", "rate_high")})
        out[key(p, "success")] = r["holds"]
        reasons = np.stack([np.asarray(r_[key(p, "reason")]) for r_ in results], axis=1)
        out[key(p, "reason")] = np.where(r["holds"], 0, _most_frequent_failure(reasons)).astype(np.int8)
        for f in ("move", "rot", "move_dir", "rot_dir", "pregrasp_penetration"):
            if key(p, f) in results[0]:
                out[key(p, f)] = _median(np.stack([np.asarray(r_[key(p, f)], np.float64) for r_ in results]))
    return out


def joint(arrays, protocols, cfg: RobustConfig) -> dict[str, np.ndarray] | None:
    """The rate of passing every protocol of `protocols` in the same trial, from their `<p>_trials` arrays:
    `physics_rate`, `physics_rate_low`, `physics_rate_high`, `physics_holds`; None when a protocol has no trials
    (a single-trial check)."""
    key = physics_protocols.result_key
    if not all(key(p, "trials") in arrays for p in protocols):
        return None
    both = np.logical_and.reduce([np.asarray(arrays[key(p, "trials")], bool) for p in protocols])
    r = rates(both, cfg)
    return dict(physics_rate=r["rate"], physics_rate_low=r["rate_low"], physics_rate_high=r["rate_high"],
                physics_holds=r["holds"])
