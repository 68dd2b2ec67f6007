"""What one training step costs on this machine, so a time budget can say how many epochs fit (`ffcgs learn`).

`harness.fit` measures each run's steady seconds per Adam step (the epochs after the first, whose time holds the
compile; each epoch's validation included) and keeps them in `ffcgs-train-cost.json` beside the compilation cache
(`runtime.jax_cache`), keyed by what the step's cost depends on (`Task.cost_key`: the model, its batch and size).
Until a machine has run a key, `PRIOR` stands in: figures measured earlier (bench/RESULTS.md), a first guess that
the machine's own runs replace.
"""

from pathlib import Path

from ffcgs_jax.core import files

RECORD_NAME = "ffcgs-train-cost.json"
# seconds per step: the CVAE's shipped training on one H100 (batch 32; bench/RESULTS.md, "Learned sampler: the
# CVAE"), the predictor's robust retraining on the 2-core CPU (batch 256; "Robust labels and the success predictor")
PRIOR = {"sampler": 0.0076, "evaluator": 0.006}
KEEP = 0.5  # weight of a new measurement against the record (an exponential average, as the physics' cost)


def record_path() -> Path | None:
    from ffcgs_jax.runtime import jax_cache

    where = jax_cache.cache_dir()
    return None if where is None else Path(where) / RECORD_NAME


def seconds_per_step(cost_key: str) -> tuple[float, bool]:
    """(seconds per step, whether this machine measured it) for a task's `cost_key` ("sampler ...")."""
    seen = files.read_record(record_path()).get(cost_key)
    if isinstance(seen, (int, float)) and seen > 0:
        return float(seen), True
    return PRIOR.get(cost_key.split()[0], max(PRIOR.values())), False


def remember(cost_key: str, seconds: float) -> None:
    def change(d):
        d[cost_key] = files.blended(d.get(cost_key), seconds, KEEP)

    files.update_record(record_path(), change)


def measured(epoch_rows: list[dict], steps_per_epoch: int) -> float | None:
    """Seconds per step from one call's epoch rows (`elapsed_s` since the call began): the epochs after the first,
    which also paid the compile; None with fewer than two epochs."""
    if len(epoch_rows) < 2 or steps_per_epoch < 1:
        return None
    span = epoch_rows[-1]["elapsed_s"] - epoch_rows[0]["elapsed_s"]
    return span / ((len(epoch_rows) - 1) * steps_per_epoch) if span > 0 else None
