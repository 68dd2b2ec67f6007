"""Searching further for a weak object (`GraspConfig.search`): more batches of the same compiled program, pooled.

`synthesize` runs one batch of `n` grasps with `PRNGKey(seed)`. Where that batch's best `n` hold fewer than
`min_valid` valid grasps, or (ranked by the success predictor) no valid grasp predicted to hold with at least
`min_predicted`, `further` asks for another batch with the key `round_key(seed, r)`, pools every batch's grasps,
keeps the best `n` in the offered order (`evaluation.ranking`), and asks again while the shortfall stays, up to
`max_rounds` batches and within `budget` seconds. Only the key changes between batches, so every batch runs
through the executables the first one compiled; an object whose first batch is good enough gets it unchanged.

What was done rides in the grasp set, and so in its grasp file:
    search_round   (B,) int, the batch each grasp came from (0: the first, `PRNGKey(seed)`)
    search_rounds  () int, batches run (1: no further search)
    search_s       () float, seconds the further batches took
    search_why     () str, the first batch's shortfall ("valid 0 < 1; best predicted 0.31 < 0.5"), "" when none
    search_stop    () str, why the search ended ("enough", "max_rounds 4", "budget: ...", "given poses ...")
"""

import time
from collections.abc import Callable

import jax
import numpy as np

from ffcgs_jax.evaluation import ranking
from ffcgs_jax.synthesis.config import SearchConfig
from ffcgs_jax.synthesis.grasp_set import GraspSet

RECORD = ("search_round", "search_rounds", "search_s", "search_why", "search_stop")
"""The arrays `further` adds."""
SUMMED = ("synthesis_s", "evaluation_s")
"""Per-batch seconds that the pooled set reports summed over its batches."""


def round_key(seed: int, r: int) -> jax.Array:
    """The sampler's key of batch `r`: `PRNGKey(seed)` for the first (today's call, unchanged), the round folded
    into it for the others, so each batch draws other poses and a seed's batches are reproducible."""
    key = jax.random.PRNGKey(seed)
    return key if r == 0 else jax.random.fold_in(key, r)


def shortfall(gs: GraspSet, cfg: SearchConfig) -> str:
    """Why `gs` is not good enough under `cfg`, as "valid 1 < 4; best predicted 0.31 < 0.5"; "" when it is. The
    prediction counts only where the set is ranked by it (`ranking.rank_by`)."""
    valid = np.asarray(gs["valid"], bool)
    why = []
    if valid.sum() < cfg.min_valid:
        why.append(f"valid {int(valid.sum())} < {cfg.min_valid}")
    if ranking.rank_by(gs.arrays) == "predicted" and cfg.min_predicted > 0:
        if not valid.any():
            if not why:  # with min_valid 0: no valid grasp, so none predicted to hold
                why.append(f"no valid grasp predicted >= {cfg.min_predicted:g}")
        else:
            best = float(np.max(np.asarray(gs["pred_success"])[valid]))
            if best < cfg.min_predicted:
                why.append(f"best predicted {best:.2f} < {cfg.min_predicted:g}")
    return "; ".join(why)


def pool(sets: list[GraspSet], n: int) -> GraspSet:
    """The best `n` grasps of `sets` (batches of one call: same config, hand and object) in the offered order's
    sense (`ranking.ranked` of all of them), kept in pool order (batch by batch), with `search_round` saying
    each one's batch. Per-grasp arrays and trace columns are concatenated; `SUMMED` seconds add up; other
    scalars (and the per-channel names) are the first batch's."""
    first = sets[0]
    rows = [len(s["valid"]) for s in sets]
    arrays = {}
    for k, v in first.arrays.items():
        per_grasp = v.ndim >= 1 and v.shape[0] == rows[0] and v.dtype.kind != "U"  # channel/joint names are text
        if per_grasp:
            arrays[k] = np.concatenate([s[k] for s in sets])
        elif k in SUMMED:
            arrays[k] = np.asarray(sum(float(s[k]) for s in sets), np.float64)
        else:
            arrays[k] = v
    arrays["search_round"] = np.concatenate([np.full(m, r, np.int64) for r, m in enumerate(rows)])
    trace = {k: np.concatenate([s.trace[k] for s in sets], axis=1) for k in first.trace
             if all(k in s.trace for s in sets)}
    pooled = GraspSet(arrays, trace, first.config, first.object_name)
    return pooled.select(np.sort(ranking.ranked(pooled.arrays)[:n]))


def further(first: GraspSet, cfg: SearchConfig, seed: int, again: Callable[[jax.Array], GraspSet] | None,
            clock: Callable[[], float] = time.perf_counter) -> GraspSet:
    """`first` (batch 0) searched further as the module docstring says, with `search_*` recorded.

    Args:
        first: the call's first batch, `PRNGKey(seed)`; its `synthesis_s + evaluation_s` estimates a batch's cost.
        cfg: when to search and for how long.
        seed: the call's seed (`GraspConfig.seed`); batch r draws with `round_key(seed, r)`.
        again: a batch of the same call with another key, through the same executables; None where the batch
            does not depend on the key (given wrist poses): nothing further is searched, the record says why.
        clock: seconds, for the budget (a test passes its own).
    """
    n = len(first["valid"])
    why = shortfall(first, cfg)
    sets, spent, stop = [first], 0.0, "enough"
    # a batch's cost, without the compiles and SDF build of a process's first call
    last = float(first["synthesis_s"]) + float(first["evaluation_s"]) if "evaluation_s" in first else 0.0
    best = first
    while shortfall(best, cfg):
        if again is None:
            stop = "given poses: another key draws nothing new"
            break
        if len(sets) >= cfg.max_rounds:
            stop = f"max_rounds {cfg.max_rounds}"
            break
        if spent + last > cfg.budget:
            stop = f"budget: {spent:.3g} s spent, a batch takes about {last:.3g} s, budget {cfg.budget:g} s"
            break
        t0 = clock()
        sets.append(again(round_key(seed, len(sets))))
        last = clock() - t0
        spent += last
        best = pool(sets, n)
    if len(sets) == 1:
        best = first.with_arrays(search_round=np.zeros(n, np.int64))
    if not why:
        stop = "enough"
    return best.with_arrays(search_rounds=np.asarray(len(sets), np.int64), search_s=np.asarray(spent, np.float64),
                            search_why=np.array(why), search_stop=np.array(stop))
