"""Physics-checked ranking: the way to ask for the best grasp of an object (`ffcgs grasp --validate`,
`ffcgs_jax.validate`).

The analytic order (valid, then by E) finds a grasp that holds on most objects but often does not put it first
(bench/RESULTS.md, "Grasp quality"). `validate` simulates the candidates with the protocols asked for and ranks
them: those that pass every protocol first, then the others, each group in the analytic order
(`evaluation.ranking`). Nothing is dropped: the grasp set comes back whole, with the physics results per grasp and
what was checked, so a file records which protocols, backend and settings judged it.
"""

import dataclasses
import json
import os
import time
from collections.abc import Callable, Mapping

import numpy as np
import trimesh

from ffcgs_jax.core.errors import FfcgsError, check_grasp_set
from ffcgs_jax.evaluation import ranking
from ffcgs_jax.hand.spec import HandSpec
from ffcgs_jax.physics import evaluate_physics
from ffcgs_jax.physics import protocols as physics_protocols
from ffcgs_jax.physics import robust, runner
from ffcgs_jax.physics.config import PROTOCOLS, PhysicsConfig


def validate(hand, mesh: trimesh.Trimesh, grasps, cfg: PhysicsConfig = PhysicsConfig(), *, protocols=PROTOCOLS,
             progress: Callable[[int], None] | None = None, candidates: str = "valid", need: int = 0):
    """Simulate `grasps` on `mesh` and return them ranked with the outcome first. The public argument order: hand,
    object, grasps, cfg, then keywords.

    Args:
        hand: the `Hand` the grasps were made with (or its `HandSpec`).
        mesh: the object, in the grasps' object frame.
        grasps: a `GraspSet` (from `synthesize` or `load_grasps`).
        cfg: the physics settings; `cfg.backend` "auto" takes MuJoCo Warp where it is faster
            (`runner.resolve_backend`).
        protocols: physics protocols, any of `physics.config.ALL_PROTOCOLS` ("lift-shake", "six-dir",
            "dexgraspbench", ...), or one protocol's name; a grasp passes when it passes every one.
        progress: called with the number of trials done, as they finish.
        candidates: "valid" simulates the grasps the synthesis marked valid (the others cannot come first and are
            left untested), "all" every grasp.
        need: 0 simulates every candidate with every protocol. k > 0 stops once k grasps pass: the candidates go
            in the analytic order, a chunk at a time (`chunk_size`), each protocol only on the grasps that passed
            the ones before it (six-dir first: it rejects the most). The grasp a user gets first is then found in
            a fraction of the time; the candidates after the last chunk stay untested (`physics_tested` False),
            and a protocol not run on a grasp that already failed another has no result (NaN / False / -1).
            On MuJoCo Warp every candidate and protocol runs at once instead (one launch: its time is the longest
            program's, not the number of grasps), so every candidate gets every result.

    Returns:
        The same grasp set with, per grasp, the runner's results (`<protocol>_success`, `_reason`, `_move`, ...;
        NaN / False / -1 where untested), `physics_tested` and `physics_passed` (tested and passed every
        protocol), and the record of the check: `physics_protocols` (JSON list), `physics_backend`,
        `physics_config_json`, `physics_s`. Its `order()` puts the grasps that passed first.

        With robust trials (`cfg.robust.trials` > 1, the default: `robust`), each protocol's `_success` is its
        robust verdict and `_rate`, `_rate_low`, `_rate_high`, `_trials` (B, K) come with it; `physics_rate`,
        `physics_rate_low`, `physics_rate_high` are those of passing every protocol in the same trial, and
        `physics_passed` is whether that holds (lower bound >= `cfg.robust.threshold`); the order then puts the
        grasps by decreasing lower bound after the passers are first.
    """
    if candidates not in ("valid", "all"):
        raise FfcgsError(f"candidates must be 'valid' or 'all', got {candidates!r}")
    evaluate_physics.check_cfg(cfg, "validate")
    check_grasp_set(grasps, "validate")
    protocols = (protocols,) if isinstance(protocols, str) else protocols
    tested = np.ones(len(grasps["q"]), bool) if candidates == "all" else np.asarray(grasps["valid"], bool)
    arrays = check(getattr(hand, "spec", hand), mesh, grasps.arrays, tested, protocols, cfg, progress, need)
    return grasps.with_arrays(arrays)


# what `runner.evaluate` returns per protocol (`<protocol>_<result>`)
RESULTS = ("success", "reason", "move", "rot", "move_dir", "rot_dir", "pregrasp_penetration", *robust.RATE_KEYS)
# the joint verdict over a check's protocols (`robust.joint`), replaced whole by every check
JOINT = ("physics_rate", "physics_rate_low", "physics_rate_high", "physics_holds", "physics_trials")


def chunk_size() -> int:
    """Candidates simulated at a time when stopping early: one round of the CPU backend's threads."""
    return max(8, os.cpu_count() or 1)


def check(spec: HandSpec, mesh: trimesh.Trimesh, arrays: Mapping[str, np.ndarray], tested: np.ndarray, protocols,
          cfg: PhysicsConfig = PhysicsConfig(), progress: Callable[[int], None] | None = None, need: int = 0
          ) -> dict[str, np.ndarray]:
    """`validate` on a grasp file's arrays (`wrist_pose`, `q`, optional `squeeze_dir`): a copy with the results
    of the grasps where `tested` is True (with `need`, of those simulated before enough passed) and the record of
    the check added."""
    protocols = tuple(protocols)
    if not protocols:
        raise FfcgsError("the physics check needs at least one protocol")
    for p in protocols:
        physics_protocols.get(p)  # an unknown name: one line listing the registered ones
    if isinstance(need, bool) or not isinstance(need, (int, np.integer)) or need < 0:
        raise FfcgsError(f"need must be an integer >= 0, got {need!r}")
    n = len(arrays["q"])
    tested = np.asarray(tested, bool)
    idx = np.flatnonzero(tested)
    if len(idx):  # before any simulation, the grasps numbered as in the file
        runner.check_reach(spec, mesh, np.asarray(arrays["wrist_pose"])[idx], idx)
    stale = {physics_protocols.result_key(p, s) for p in protocols for s in RESULTS}  # an earlier check's
    arrays = {k: v for k, v in arrays.items() if k not in stale and k not in JOINT}
    backend, _ = runner.resolve_backend(cfg.backend, max(len(idx), 1), protocols, cfg)
    t0 = time.perf_counter()
    squeeze = arrays.get("squeeze_dir")

    def run(at: np.ndarray, which) -> dict[str, np.ndarray]:
        return runner.evaluate(spec, mesh, arrays["wrist_pose"][at], arrays["q"][at], cfg, which, backend,
                               progress=progress, squeeze_dir=None if squeeze is None else squeeze[at])

    if len(idx) and (not need or backend == "warp"):
        arrays.update(spread(run(idx, protocols), idx, n))
    elif len(idx):
        tested = _until_enough(arrays, idx, n, protocols, need, run)
    for p in protocols:  # nothing simulated (no candidate): the record still says what would have judged them
        arrays.setdefault(physics_protocols.result_key(p, "success"), np.zeros(n, bool))
    arrays.update(verdict(arrays, tested, protocols, cfg))
    arrays.update(physics_tested=tested,
                  physics_protocols=np.array(json.dumps(list(protocols))), physics_backend=np.array(backend),
                  physics_config_json=np.array(json.dumps(dataclasses.asdict(cfg))),
                  physics_s=np.asarray(time.perf_counter() - t0, np.float64))
    return arrays


def verdict(arrays: Mapping[str, np.ndarray], tested: np.ndarray, protocols, cfg: PhysicsConfig = PhysicsConfig()
            ) -> dict[str, np.ndarray]:
    """The joint verdict over `protocols` of arrays carrying their per-grasp results for the `tested` grasps, what
    `check` adds and `ranking.ranked` reads: `physics_passed` (passed every protocol; with robust trials, held them
    all in the same trials) and, with trials, `physics_rate*`, `physics_holds` and `physics_trials`."""
    tested = np.asarray(tested, bool)
    out: dict[str, np.ndarray] = {}
    passed = np.logical_and.reduce([arrays[physics_protocols.result_key(p, "success")] for p in protocols]) & tested
    both = robust.joint(arrays, protocols, cfg.robust) if tested.any() else None
    if both is not None:
        out = {k: np.where(tested, v, False if v.dtype == bool else np.nan) for k, v in both.items()}
        passed = out["physics_holds"] & tested
        out["physics_trials"] = np.asarray(cfg.robust.trials, np.int64)
    out["physics_passed"] = passed
    return out


def _until_enough(arrays: dict, idx: np.ndarray, n: int, protocols, need: int, run) -> np.ndarray:
    """Simulate the candidates `idx` in the analytic order, a chunk at a time, each protocol (six-dir first) on the
    survivors of the ones before, until `need` grasps passed them all; their results go into `arrays`. Returns
    which grasps were simulated."""
    analytic = {k: v for k, v in arrays.items() if k != "physics_passed"}  # not an earlier check's order
    candidates = set(idx.tolist())
    queue = [int(i) for i in ranking.ranked(analytic) if i in candidates]
    order = sorted(protocols, key=lambda p: p != "six-dir")
    tested = np.zeros(n, bool)
    passed, size, fresh = 0, chunk_size(), set()
    for start in range(0, len(queue), size):
        alive = np.asarray(queue[start:start + size])
        tested[alive] = True
        for p in order:
            res = run(alive, (p,))
            _place(arrays, res, alive, n, fresh)
            alive = alive[np.asarray(res[physics_protocols.result_key(p, "success")], bool)]
            if not len(alive):
                break
        passed += len(alive)
        if passed >= need:
            break
    return tested


def _place(arrays: dict, results: dict[str, np.ndarray], idx: np.ndarray, n: int, fresh: set) -> None:
    """`spread` `results` into `arrays`: a key this check already wrote (`fresh`) keeps its other rows; any other
    (absent, or a stale result of an earlier check) is replaced whole."""
    for k, full in spread(results, idx, n).items():
        if k in fresh:
            arrays[k][idx] = full[idx]
        else:
            arrays[k] = full
            fresh.add(k)


def spread(results: dict[str, np.ndarray], idx: np.ndarray, n: int) -> dict[str, np.ndarray]:
    """Per-grasp physics results of the grasps at `idx` as arrays over all `n` grasps; the grasps not tested get
    NaN (floats), False (flags) or -1 (reasons)."""
    out = {}
    for k, v in results.items():
        fill = False if v.dtype == bool else (-1 if v.dtype.kind == "i" else np.nan)
        full = np.full((n, *v.shape[1:]), fill, dtype=v.dtype)
        full[idx] = v
        out[k] = full
    return out


def summary_rows(grasps, protocols) -> list[tuple[str, str]]:
    """The lines `ffcgs grasp --validate` prints: per protocol the share that passed, then how many passed them all
    and whether the grasp offered first is one of them."""
    tested = np.asarray(grasps["physics_tested"], bool)
    res = {k: np.asarray(v)[tested] for k, v in grasps.arrays.items()
           if k.endswith(("_success", "_reason", "_move", "_rot", "_trials")) and np.ndim(v) and len(v) == len(tested)}
    rows = physics_protocols.summary_rows(res, protocols) if tested.any() else []
    passed = int(np.sum(grasps["physics_passed"]))
    first = ranking.ranked(grasps.arrays)[0] if len(tested) else None
    trials = int(grasps.arrays.get("physics_trials", 1))
    verdict = f"hold (in the same trials of {trials}, 95 % sure of most)" if trials > 1 else "pass"
    rows.append(("physics-checked", f"{passed} of {int(tested.sum())} tested grasps {verdict} "
                 f"{' and '.join(protocols)} ({float(grasps['physics_s']):.1f} s, physics backend "
                 f"{grasps['physics_backend']}); the first grasp "
                 f"{'passes' if first is not None and grasps['physics_passed'][first] else 'does not pass'}"))
    return rows
