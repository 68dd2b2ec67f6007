"""Train the package's networks on a dataset from `ffcgs dataset build`: the CVAE wrist-pose sampler (the default,
`--model sampler`) or the grasp-success predictor (`--model evaluator`, on a labelled build: `--keep all`).

    ffcgs train --config configs/sampler.toml [--optim.lr 3e-4 ...] [--cv.all]
    ffcgs train --config configs/sampler.toml --sweep optim.lr=1e-4,3e-4 model.width=8,16
    ffcgs train --model evaluator --data.path labels.mcap --cv.all --out runs/evaluator
    ffcgs train --model evaluator --data.path labels.mcap --sweep optim.weight_decay=0.3,1,3 --cv.fold 0

Any config field is a flag (`--help` lists them). `--cv.all` runs every cross-validation fold and writes
OUT/cv.md; `--sweep` runs the grid of the listed values (each run in OUT/sweep/<name>/, sequentially) and writes
OUT/sweep.md. A run resumes where it stopped when started again with the same config and --out.
`python -m train.sampler` (a checkout's old entry) is an alias that runs this module.
"""

import dataclasses
import itertools
import json
import sys
import time
import typing
from pathlib import Path

import numpy as np

from ffcgs_jax.core import files
from ffcgs_jax.cli import smoke
from ffcgs_jax.core.config import coerce, check_all, split_config_arg, with_overrides
from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.training.config import EvaluatorTrainConfig, TrainConfig

MODELS = {"sampler": TrainConfig, "evaluator": EvaluatorTrainConfig}

# The training code imports JAX: `training.data` and `training.train` are imported where they run, so that
# `ffcgs --help` (which names this command) stays quick.


def split_model(argv: list[str]) -> tuple[str, list[str]]:
    """(the model `--model NAME` or `--model=NAME` names, "sampler" without one; the other arguments).
    `--model.res ...` (the sampler's network section) is not this flag."""
    model, rest, i = "sampler", [], 0
    while i < len(argv):
        a = argv[i]
        if a == "--model" or a.startswith("--model="):
            if a == "--model":
                if i + 1 >= len(argv) or argv[i + 1].startswith("--"):
                    raise FfcgsError(f"--model needs a name: {', '.join(MODELS)}")
                model, i = argv[i + 1], i + 2
            else:
                model, i = a.split("=", 1)[1], i + 1
            if model not in MODELS:
                raise FfcgsError(f"unknown --model {model!r}; models: {', '.join(MODELS)}")
            continue
        rest.append(a)
        i += 1
    return model, rest


# the network section only the other model's config has, and that model's --model name
_OTHER_SECTION = {"sampler": ("net", "evaluator"), "evaluator": ("model", "sampler")}


def other_model_hint(message: str, model: str) -> str:
    """`message` with a hint when it refuses the network section of the other model's config (a run folder's
    config.toml of `--model evaluator` given without it): the section is right, the model is not."""
    section, other = _OTHER_SECTION[model]
    if message.startswith(f"unknown config key(s) {section};"):
        return f"{message} ([{section}] is the {other}'s section: add --model {other})"
    return message


def split_args(argv: list[str]) -> tuple[str | None, list[str], list[str]]:
    """(--config path, sweep specs "key=v1,v2", the remaining override flags)."""
    path, argv = split_config_arg(argv)  # the same --config handling as the `ffcgs` commands
    sweep, rest = [], []
    i = 0
    while i < len(argv):
        if argv[i] == "--sweep":
            i += 1
            while i < len(argv) and not argv[i].startswith("--"):
                sweep.append(argv[i])
                i += 1
            if not sweep:
                raise FfcgsError("--sweep needs at least one KEY=V1,V2,... spec")
        else:
            rest.append(argv[i])
            i += 1
    return path, sweep, rest


def _field(cfg, dotted: str):
    """The type of the field a dotted key names, naming the valid keys when it names none."""
    *path, name = dotted.split(".")
    obj = cfg
    for p in path:
        if not dataclasses.is_dataclass(obj) or p not in {f.name for f in dataclasses.fields(obj)}:
            raise FfcgsError(f"unknown sweep key {dotted!r}")
        obj = getattr(obj, p)
    hints = typing.get_type_hints(type(obj))
    if name not in hints or dataclasses.is_dataclass(hints[name]):
        valid = ", ".join(f.name for f in dataclasses.fields(obj) if not dataclasses.is_dataclass(hints[f.name]))
        raise FfcgsError(f"unknown sweep key {dotted!r}; valid keys there: {valid}")
    return hints[name]


def parse_sweep(cfg: TrainConfig | EvaluatorTrainConfig, specs: list[str]) -> list[tuple[str, list]]:
    """["optim.lr=1e-4,3e-4"] -> [("optim.lr", [1e-4, 3e-4])], values converted to the field's type."""
    grid = []
    for spec in specs:
        if "=" not in spec:
            raise FfcgsError(f"sweep spec {spec!r} must look like KEY=V1,V2,...")
        key, values = spec.split("=", 1)
        hint = _field(cfg, key)
        conv = {bool: lambda v: {"true": True, "false": False}[v.lower()], int: int, float: float, str: str}[hint]
        try:
            vals = [coerce(hint, conv(v), key) for v in values.split(",") if v != ""]
        except (ValueError, KeyError):
            raise FfcgsError(f"sweep values of {key} must be {hint.__name__}s, got {values!r}") from None
        if not vals:
            raise FfcgsError(f"sweep spec {spec!r} has no values")
        grid.append((key, vals))
    return grid


def replace(cfg, dotted: str, value):
    head, _, rest = dotted.partition(".")
    if not rest:
        return dataclasses.replace(cfg, **{head: value})
    return dataclasses.replace(cfg, **{head: replace(getattr(cfg, head), rest, value)})


def run_cv_evaluator(cfg: EvaluatorTrainConfig) -> dict:
    """Every fold of the predictor's cross-validation in OUT/fold<k>/, then OUT/cv.md; the mean summary."""
    from ffcgs_jax.hand import kinematics as K
    from ffcgs_jax.training import evaluator_data, evaluator_train
    from ffcgs_jax.training.run import dataset_hand

    data = evaluator_data.load(cfg.data.path, K.load_hand(dataset_hand(cfg.data.path, cfg.hand)))
    rows = []
    for k in range(cfg.cv.folds):
        sub = replace(replace(cfg, "cv.fold", k), "out", str(Path(cfg.out) / f"fold{k}"))
        t0 = time.perf_counter()
        rows.append(evaluator_train.train(sub, data=data) | {"fold": k, "time_s": time.perf_counter() - t0})
    text = evaluator_train.cv_table(rows)
    files.write_text(Path(cfg.out) / "cv.md", text + "\n")
    print(text)
    keys = [k for k in rows[0] if k.startswith("val_") and isinstance(rows[0][k], float)]
    def mean(k):  # a figure a fold could not measure (no held-out object with both outcomes) is NaN there
        finite = [r[k] for r in rows if np.isfinite(r[k])]
        return float(np.mean(finite)) if finite else float("nan")

    return {k: mean(k) for k in keys} | {"time_s": sum(r["time_s"] for r in rows)}


def run_cv(cfg: TrainConfig | EvaluatorTrainConfig) -> dict:
    """Every fold of cfg.cv in OUT/fold<k>/, then OUT/cv.md; returns the mean summary."""
    from ffcgs_jax.training import data as cvae_data

    if isinstance(cfg, EvaluatorTrainConfig):
        return run_cv_evaluator(cfg)
    from ffcgs_jax.training.train import train

    rows = []
    data = cvae_data.load(cfg.data.path, cfg.data.noisy)  # once: the folds differ only in the objects held out
    for k in range(cfg.cv.folds):
        sub = replace(replace(cfg, "cv.fold", k), "out", str(Path(cfg.out) / f"fold{k}"))
        t0 = time.perf_counter()
        rows.append(train(sub, data=data) | {"fold": k, "time_s": time.perf_counter() - t0})
    val = np.array([r["val_rec"] for r in rows])
    lines = ["| fold | validation objects | train grasps | train rec (cm) | val rec (cm) | val KL | time (s) |",
             "|---|---|---|---|---|---|---|"]
    lines += [f"| {r['fold']} | {', '.join(r['val_objects'])} | {r['train_grasps']} | {100 * r['train_rec']:.2f} | "
              f"{100 * r['val_rec']:.2f} | {r['val_kl']:.2f} | {r['time_s']:.0f} |" for r in rows]
    lines.append(f"\nvalidation reconstruction over {len(rows)} folds: {100 * val.mean():.2f} ± "
                 f"{100 * val.std():.2f} cm (mean ± std)")
    files.write_text(Path(cfg.out) / "cv.md", "\n".join(lines) + "\n")
    print("\n".join(lines))
    return {"val_rec": float(val.mean()), "val_rec_std": float(val.std()),
            "train_rec": float(np.mean([r["train_rec"] for r in rows])),
            "val_kl": float(np.mean([r["val_kl"] for r in rows])), "time_s": sum(r["time_s"] for r in rows)}


def run_one(cfg: TrainConfig | EvaluatorTrainConfig) -> dict:
    if cfg.cv.all:
        return run_cv(cfg)
    if isinstance(cfg, EvaluatorTrainConfig):
        from ffcgs_jax.training.evaluator_train import train
    else:
        from ffcgs_jax.training.train import train
    t0 = time.perf_counter()
    return train(cfg) | {"time_s": time.perf_counter() - t0}


def run_sweep(cfg: TrainConfig | EvaluatorTrainConfig, grid: list[tuple[str, list]]) -> list[dict]:
    keys = [k for k, _ in grid]
    rows = []
    for values in itertools.product(*(v for _, v in grid)):
        name = "_".join(f"{k}={v}" for k, v in zip(keys, values))
        sub = replace(cfg, "out", str(Path(cfg.out) / "sweep" / name))
        for k, v in zip(keys, values):
            sub = replace(sub, k, v)
        check_all(sub)
        rows.append({"name": name, "values": values} | run_one(sub))
    if isinstance(cfg, EvaluatorTrainConfig):
        from ffcgs_jax.training.evaluator_train import summary_columns

        names, cells = summary_columns()
    else:
        fmt = lambda v: "-" if v is None else f"{100 * v:.2f}"  # noqa: E731
        names = ["train rec (cm)", "val rec (cm)", "val KL", "time (s)"]
        cells = lambda r: [fmt(r["train_rec"]), fmt(r["val_rec"]),  # noqa: E731
                           "-" if r["val_kl"] is None else format(r["val_kl"], ".2f"), f"{r['time_s']:.0f}"]
    lines = ["| " + " | ".join(keys + names) + " |", "|" + "---|" * (len(keys) + len(names))]
    lines += ["| " + " | ".join([str(v) for v in r["values"]] + cells(r)) + " |" for r in rows]
    Path(cfg.out).mkdir(parents=True, exist_ok=True)
    files.write_text(Path(cfg.out) / "sweep.md", "\n".join(lines) + "\n")
    files.write_text(Path(cfg.out) / "sweep.json", json.dumps(rows, indent=1, default=str))
    print("\n".join(lines))
    return rows


def main(argv: list[str] | None = None, prog: str = "ffcgs train", name: str = "ffcgs") -> int:
    """Run `prog ARGV`; errors are one line `NAME: error: ...` on stderr with exit status 2. `ffcgs train` and
    `python -m train.sampler` both land here and differ only in `prog` (help's usage line) and `name`."""
    argv = sys.argv[1:] if argv is None else argv
    try:
        model, argv = split_model(argv)
        path, specs, rest = split_args(argv)
        try:
            cfg = with_overrides(MODELS[model], rest if path is None else ["--config", path, *rest], prog,
                                 keep_prefixes=True, description=__doc__)
        except FfcgsError as e:
            raise FfcgsError(other_model_hint(str(e), model)) from None
        cfg = smoke.scaled("train", cfg)  # FFCGS_SMOKE: one epoch, a sweep's first point
        from ffcgs_jax.runtime import jax_cache

        # as the other commands: a fold, a sweep point or a resumed run loads the training step's executables
        # from disk instead of compiling them again (minutes on a CPU; FFCGS_JAX_CACHE=off: compile every time)
        jax_cache.enable()
        if specs:
            run_sweep(cfg, smoke.sweep(parse_sweep(cfg, specs)))
        else:
            summary = run_one(cfg)
            print(json.dumps({k: v for k, v in summary.items() if not isinstance(v, list)}, indent=1))
    except FfcgsError as e:
        print(f"{name}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{name}: interrupted (run it again to resume)", file=sys.stderr)
        return 130
    return 0
