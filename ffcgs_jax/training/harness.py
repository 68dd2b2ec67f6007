"""The one training loop: every network `ffcgs train` trains (the CVAE, the success predictor, the next ones) is a
`Task` that `fit` runs.

A task supplies what is specific to its network: the initial parameters (and the fixed arrays saved beside them,
such as the predictor's standardiser), the compiled steps of an epoch, in calls of one or more Adam steps each
(`kernels.adam`), and the figures of the validation at the end of each epoch. `fit` owns the rest:
    epochs          from the checkpoint's epoch (a resumed run) to `epochs`, or `until_epoch` (an interruption)
    Adam state      initialised once, saved and restored with the parameters
    checkpoint.npz  one schema (`CHECKPOINT_FORMAT`) for every task, written atomically at the end of every epoch:
                    {"params", "opt": {"count", "mu", "nu"}, "consts"} and, in its metadata, the task, epoch, step,
                    seed, config and the epoch rows so far
    metrics.jsonl   per-step rows every `log_every` steps (tasks that log steps) and one row per epoch; a resumed
                    run drops the rows written after its checkpoint
    progress        a bar of steps, and a ticker while the first call compiles

Randomness is a function of (seed, epoch) for the batch order and (seed, step) inside the steps, never a state
carried from step to step, so the checkpoint's seed and step are the whole random state: a resumed run computes the
same parameters, bit for bit, as an uninterrupted one.
"""

import dataclasses
import json
import time
from collections.abc import Callable, Iterable
from contextlib import nullcontext
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from ffcgs_jax.core import files
from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.kernels.adam import AdamState, adam_init
from ffcgs_jax.learning import checkpoint
from ffcgs_jax.runtime.progress import compiling
from ffcgs_jax.training import step_cost
from ffcgs_jax.training.run import RunFolder, read_metrics, truncate_log

CHECKPOINT_FORMAT = "ffcgs-train-checkpoint-2"
"""The checkpoint schema `fit` writes. Checkpoints of the two loops before it (no format in their metadata) are read
through the task's `legacy`."""


@dataclasses.dataclass(frozen=True)
class Chunk:
    """One compiled call's worth of an epoch: `live` steps (the call may run more, masked off) from `start` (its
    first step within the epoch), and the call's batch `inputs`, as the task's `step` takes them."""

    start: int
    live: int
    inputs: Any


@dataclasses.dataclass(frozen=True)
class Task:
    """What `fit` needs of one network's training.

    Attributes:
        name: the model ("sampler", "evaluator"), recorded in the checkpoint: another model's checkpoint is refused.
        step_name: what the first call compiles, for its ticker ("the CVAE's training step").
        seed: the run's seed (batch order and noise derive from it); recorded and checked on resume.
        epochs: the epochs of a whole run.
        steps_per_epoch: Adam steps per epoch.
        init: () -> (params, consts): the initial trained parameters, and fixed arrays saved with them ({}: none).
        chunks: epoch -> its `Chunk`s, in order.
        step: (params, opt, consts, first global step, inputs) -> (params, opt, {metric: (steps,) array}); one
            compiled call. Metrics past the chunk's `live` steps are ignored; "loss" must be among them.
        evaluate: (params, consts) -> the epoch row's validation entries ({} without a held-out set).
        log_every: write a per-step row (means over the steps since the last one) every this many steps and at each
            epoch's end; 0 writes epoch rows only.
        epoch_means: metrics whose epoch mean goes into the epoch row (in the metrics' own dtype).
        nonfinite_hint: what to change when the loss becomes non-finite ("lower optim.lr").
        postfix: (last call's metrics, epoch row or None) -> the progress bar's postfix.
        legacy: (tree of a checkpoint written before `CHECKPOINT_FORMAT`) -> (params, consts), or None where that
            tree is not this model's.
        cost_key: what a step's cost depends on ("sampler batch 32 res 32 ..."): `fit` records the seconds per
            step it measured under it (`step_cost`); "" records nothing.
    """

    name: str
    step_name: str
    seed: int
    epochs: int
    steps_per_epoch: int
    init: Callable[[], tuple[dict, dict]]
    chunks: Callable[[int], Iterable[Chunk]]
    step: Callable[..., tuple[Any, AdamState, dict]]
    evaluate: Callable[[Any, dict], dict]
    log_every: int = 0
    epoch_means: tuple[str, ...] = ()
    nonfinite_hint: str = "lower optim.lr"
    postfix: Callable[[dict, dict | None], dict] = lambda metrics, row: {}
    legacy: Callable[[dict], tuple[dict, dict] | None] = lambda tree: None
    cost_key: str = ""


@dataclasses.dataclass
class Fitted:
    """What `fit` ends with: the trained params and consts, and the last epoch row of this call (None when it ran
    none: a finished run started again)."""

    params: Any
    consts: dict
    last_row: dict | None


def save_state(path, task: Task, params, opt: AdamState, consts: dict, epoch: int, config: str,
               history: list[dict]) -> None:
    """The checkpoint of `task` after `epoch` epochs, in the one schema."""
    tree = {"params": params, "opt": {"count": opt.count, "mu": opt.mu, "nu": opt.nu}}
    if consts:
        tree["consts"] = consts
    checkpoint.save(path, tree, {"format": CHECKPOINT_FORMAT, "task": task.name, "epoch": epoch,
                                 "step": epoch * task.steps_per_epoch, "seed": task.seed, "config": config,
                                 "history": history})


def load_state(path, task: Task) -> tuple[Any, AdamState, dict, int, list[dict] | None]:
    """(params, opt, consts, epoch, epoch rows) of a checkpoint `fit` or an older version's loop wrote (the rows
    None: those checkpoints did not hold them); one line saying how to go on for one this task cannot continue."""
    tree, meta = checkpoint.load(path)
    start_over = f"delete {path} to train from the start, or choose another --out"
    epoch = meta.get("epoch")
    if meta.get("format") is None:  # the two loops before the harness: {"epoch", "config"} only
        state = task.legacy(tree) if "opt" in tree and isinstance(epoch, int) else None
        if state is None:
            raise FfcgsError(f"{path} is not a training checkpoint of the {task.name!r} model; {start_over}")
        (params, consts), step = state, epoch * task.steps_per_epoch
        history = None  # rebuilt from metrics.jsonl once it is truncated to the checkpoint
    elif meta["format"] != CHECKPOINT_FORMAT:
        raise FfcgsError(f"{path} is a training checkpoint of another ffcgs version ({meta['format']!r}); "
                         f"{start_over}")
    else:
        if meta.get("task") != task.name:
            raise FfcgsError(f"{path} is a training checkpoint of the {meta.get('task')!r} model, not of "
                             f"{task.name!r}; {start_over}")
        if meta.get("seed") != task.seed:
            raise FfcgsError(f"{path} was trained with seed {meta.get('seed')}, not {task.seed}; {start_over}")
        params, consts, step = tree.get("params"), tree.get("consts", {}), meta.get("step")
        history = meta.get("history") if isinstance(meta.get("history"), list) else None
    if not isinstance(epoch, int) or step != epoch * task.steps_per_epoch or not 0 <= epoch <= task.epochs:
        raise FfcgsError(f"{path} stopped at step {step} (epoch {epoch}), which this dataset's {task.steps_per_epoch} "
                         f"steps per epoch over {task.epochs} epochs cannot continue (the dataset changed?); "
                         f"{start_over}")
    opt = tree.get("opt", {})
    if params is None or not isinstance(opt, dict) or set(opt) != {"count", "mu", "nu"}:
        raise FfcgsError(f"{path} lacks the parameters or the Adam state of a training checkpoint; {start_over}")
    return params, AdamState(opt["count"], opt["mu"], opt["nu"]), consts, epoch, history


def fit(task: Task, run: RunFolder, *, until_epoch: int | None = None, progress: bool = True) -> Fitted | None:
    """Train `task` in `run`'s folder from its checkpoint (or from the start), to `task.epochs` or `until_epoch`
    (then None: checkpointed, and the same call continues it). Nothing is written before the checkpoint is read
    and accepted: a refused resume leaves the folder as it was."""
    state = load_state(run.checkpoint, task) if run.checkpoint.is_file() else None
    files.check_folder(run.out, "--out")
    files.write_text(run.config, run.text)
    if state is None:
        params, consts = task.init()
        opt, start, history = adam_init(params), 0, []
        if run.log.exists():
            run.log.unlink()
    else:
        params, opt, consts, start, history = state
        truncate_log(run.log, start * task.steps_per_epoch)
        if history is None:
            history = [r for r in read_metrics(run.log) if "elapsed_s" in r] if run.log.exists() else []
    params, opt, consts = jax.tree.map(jnp.asarray, (params, opt, consts))

    spe = task.steps_per_epoch
    last_row = None
    stop = task.epochs if until_epoch is None else min(until_epoch, task.epochs)
    t_start = time.perf_counter()
    # drawn from its first update on (`delay`): before it, the first call's compile has its own line
    bar = tqdm(total=spe * task.epochs, initial=start * spe, desc=f"train {run.out.name}", unit="step",
               disable=not progress, dynamic_ncols=True, delay=1e-3)
    first = True
    rows: list[dict] = []
    with open(run.log, "a") as log:
        for epoch in range(start, stop):
            acc: dict[str, list] = {}
            parts: dict[str, list] = {}
            for chunk in task.chunks(epoch):
                step0 = epoch * spe + chunk.start
                # the first call compiles (minutes on a small CPU): a ticker says so; later calls only dispatch
                with compiling(task.step_name, show=progress) if first else nullcontext():
                    params, opt, m = task.step(params, opt, consts, step0, chunk.inputs)
                first = False
                m = {key: np.asarray(v)[:chunk.live] for key, v in m.items()}
                if not np.isfinite(m["loss"]).all():
                    bad = step0 + int(np.argmin(np.isfinite(m["loss"])))
                    raise FfcgsError(f"the loss became non-finite at step {bad} (epoch {epoch}); {task.nonfinite_hint}")
                for key, v in m.items():
                    parts.setdefault(key, []).append(v)
                if task.log_every:
                    _log_steps(log, m, acc, step0, epoch, (epoch + 1) * spe, task.log_every)
                bar.update(chunk.live)
                bar.set_postfix(**task.postfix(m, None))
            row = {"epoch": epoch + 1, "step": (epoch + 1) * spe}
            row |= {key: float(np.concatenate(parts[key]).mean()) for key in task.epoch_means}
            row |= {"elapsed_s": time.perf_counter() - t_start} | task.evaluate(params, consts)
            log.write(json.dumps(row) + "\n")
            log.flush()
            history.append(row)
            rows.append(row)
            save_state(run.checkpoint, task, params, opt, consts, epoch + 1, run.text, history)
            bar.set_postfix(**task.postfix(m, row))
            last_row = row
    bar.close()
    per_step = step_cost.measured(rows, spe)
    if task.cost_key and per_step is not None:
        step_cost.remember(task.cost_key, per_step)
    if stop < task.epochs:
        return None
    return Fitted(params, consts, last_row)


def _log_steps(log, m: dict, acc: dict, step0: int, epoch: int, epoch_end: int, every: int) -> None:
    """The per-step rows of one call's metrics `m`: the mean of each metric since the last row (`acc` carries them
    over calls), every `every` steps and at the epoch's end."""
    for i in range(len(m["loss"])):
        for key, v in m.items():
            acc.setdefault(key, []).append(float(v[i]))
        gstep = step0 + i + 1
        if gstep % every == 0 or gstep == epoch_end:
            log.write(json.dumps({"step": gstep, "epoch": epoch} | {key: float(np.mean(v)) for key, v in acc.items()})
                      + "\n")
            acc.clear()
