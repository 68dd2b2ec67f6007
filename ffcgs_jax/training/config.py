"""Configs of the networks' training: frozen dataclasses read from TOML by `config.load`, overridable from the command
line (`ffcgs train --optim.lr 3e-4`), and `to_toml`, which writes a run's resolved config back.

The sampler's defaults follow the paper (section IV.A): Adam, learning rate 1e-4, batch 32, 100 epochs, five-fold
cross-validation, beta cycling from 0 to 0.005.
"""

import dataclasses
import math
from typing import Any

from ffcgs_jax.core.config import check_integer, is_finite
from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.learning.config import EvaluatorNetConfig, ModelConfig


def check_adam(optim) -> None:
    """The Adam fields every training's optim section has (lr, b1, b2, eps), refused in one line when out of range."""
    if not (is_finite(optim.lr) and 0 < optim.lr <= 1):
        raise FfcgsError(f"optim.lr must be in (0, 1], got {optim.lr!r}")
    for name in ("b1", "b2"):
        v = getattr(optim, name)
        if not (is_finite(v) and 0 <= v < 1):
            raise FfcgsError(f"optim.{name} must be in [0, 1), got {v!r}")
    if not (is_finite(optim.eps) and 0 < optim.eps <= 1):
        raise FfcgsError(f"optim.eps must be in (0, 1], got {optim.eps!r}")


@dataclasses.dataclass(frozen=True)
class TrainOptimConfig:
    """Adam and the epoch loop.

    Attributes:
        lr: Adam step size (paper: 1e-4), constant.
        b1, b2, eps: Adam's moment decay rates and denominator guard.
        batch: grasps per step (paper: 32).
        epochs: passes over the training grasps (paper: 100).
        grad_clip: rescale the gradient to at most this global norm; 0 turns clipping off (the paper does not clip).
    """

    lr: float = 1e-4
    b1: float = 0.9
    b2: float = 0.999
    eps: float = 1e-8
    batch: int = 32
    epochs: int = 100
    grad_clip: float = 0.0

    def check(self) -> None:
        check_adam(self)
        check_integer("optim.batch", self.batch, 1, 65536)
        check_integer("optim.epochs", self.epochs, 1, 100_000)
        if not (is_finite(self.grad_clip) and self.grad_clip >= 0):
            raise FfcgsError(f"optim.grad_clip must be >= 0 (0: off), got {self.grad_clip!r}")


@dataclasses.dataclass(frozen=True)
class KLConfig:
    """The cyclical annealing of beta_t (Fu et al. 2019, the paper's [29]).

    The run is cut into `cycles` equal cycles; in each, beta rises linearly from 0 to `beta_max` over the first
    `ramp` fraction of the cycle and stays there for the rest.
    """

    beta_max: float = 0.005
    cycles: int = 4
    ramp: float = 0.5

    def check(self) -> None:
        if not (is_finite(self.beta_max) and self.beta_max >= 0):
            raise FfcgsError(f"kl.beta_max must be >= 0, got {self.beta_max!r}")
        check_integer("kl.cycles", self.cycles, 1, 100_000)
        if not (is_finite(self.ramp) and 0 < self.ramp <= 1):
            raise FfcgsError(f"kl.ramp must be in (0, 1], got {self.ramp!r}")


@dataclasses.dataclass(frozen=True)
class DataConfig:
    """Where the grasps come from and how batches are drawn.

    Attributes:
        path: the training dataset, an MCAP file from `ffcgs dataset build`.
        noisy: also train on each grasp's stored noisy copy (the paper's Gaussian-noise augmentation), doubling the
            samples per epoch.
        grasps_per_sdf: a batch holds batch / grasps_per_sdf objects with this many grasps each. The U-Net runs once
            per object in the batch, so 4 makes a step about 3x cheaper; 1 is the paper's plain shuffled batch.
    """

    path: str = "data/train.mcap"
    noisy: bool = True
    grasps_per_sdf: int = 1

    def check(self) -> None:
        if not isinstance(self.path, str) or not self.path:
            raise FfcgsError("data.path must name a dataset file (.mcap)")
        check_integer("data.grasps_per_sdf", self.grasps_per_sdf, 1, 4096)


@dataclasses.dataclass(frozen=True)
class CVConfig:
    """Cross-validation split by object: objects are dealt into `folds` folds (seeded shuffle of their names).

    Attributes:
        folds: number of folds (paper: 5).
        fold: the fold held out for validation; -1 trains on every object (the shipped model).
        all: run every fold in turn and write their comparison (`cv.md`); `fold` is then ignored.
    """

    folds: int = 5
    fold: int = 0
    all: bool = False

    def check(self) -> None:
        check_integer("cv.folds", self.folds, 2, 1000)
        check_integer("cv.fold", self.fold, -1, self.folds - 1)


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """`python -m train.sampler`: everything one training run needs.

    Attributes:
        out: output folder: config.toml, metrics.jsonl, metrics.png, checkpoint.npz, weights.npz.
        seed: seeds the initial parameters, the batch order and the latent noise.
        log_every: steps between metric log lines (the loss is averaged over them).
        steps_per_call: optimiser steps fused into one compiled call (a lax.scan): fewer host round trips on GPU.
        hand: the hand the sampler is for (built-in name or hand-spec TOML); "" = the hand the dataset was built
            for (its stored build config). A hand other than the dataset's is refused.
    """

    out: str = "runs/sampler"
    hand: str = ""
    seed: int = 0
    log_every: int = 50
    steps_per_call: int = 50
    model: ModelConfig = ModelConfig()
    optim: TrainOptimConfig = TrainOptimConfig()
    kl: KLConfig = KLConfig()
    data: DataConfig = DataConfig()
    cv: CVConfig = CVConfig()

    def check(self) -> None:
        check_integer("seed", self.seed, 0, 2**31 - 1)
        check_integer("log_every", self.log_every, 1, 10**9)
        check_integer("steps_per_call", self.steps_per_call, 1, 100_000)
        if self.optim.batch % self.data.grasps_per_sdf:
            raise FfcgsError(f"optim.batch ({self.optim.batch}) must be a multiple of data.grasps_per_sdf "
                             f"({self.data.grasps_per_sdf})")


# ----------------------------------------------------------------------------------------------------------------
# The success predictor (`learning.evaluator`): `ffcgs train --model evaluator`
# ----------------------------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class EvaluatorOptimConfig:
    """Adam on the mean binary cross-entropy of every head.

    Attributes:
        lr: Adam step size, cosine-decayed to 0 over the run.
        b1, b2, eps: Adam's moment decay rates and denominator guard.
        batch: grasps per step.
        epochs: passes over the training grasps.
        weight_decay: decoupled L2 shrinkage per step, times lr (AdamW); 0 turns it off. Strong (1) by default:
            a network that fits its training objects perfectly ranks unseen ones worse (bench/RESULTS.md).
    """

    lr: float = 1e-3
    b1: float = 0.9
    b2: float = 0.999
    eps: float = 1e-8
    batch: int = 256
    epochs: int = 30
    weight_decay: float = 1.0

    def check(self) -> None:
        check_adam(self)
        check_integer("optim.batch", self.batch, 1, 1 << 20)
        check_integer("optim.epochs", self.epochs, 1, 100_000)
        if not (is_finite(self.weight_decay) and 0 <= self.weight_decay and self.lr * self.weight_decay < 1):
            raise FfcgsError(f"optim.weight_decay must be >= 0 with optim.lr * optim.weight_decay < 1 (each step "
                             f"shrinks the weights by that factor), got {self.weight_decay!r}")


@dataclasses.dataclass(frozen=True)
class EvaluatorDataConfig:
    """path: a labelled dataset file (`ffcgs dataset build --keep all`), training objects only."""

    path: str = "data/labels.mcap"

    def check(self) -> None:
        if not isinstance(self.path, str) or not self.path:
            raise FfcgsError("data.path must name a labelled dataset file (.mcap)")


@dataclasses.dataclass(frozen=True)
class EvaluatorTrainConfig:
    """`ffcgs train --model evaluator`: one training run of the success predictor.

    Attributes:
        out: output folder: config.toml, metrics.jsonl, metrics.png, checkpoint.npz, weights.npz, summary.json.
        hand: the hand (built-in name or hand-spec TOML); "" = the dataset's.
        seed: seeds the initial parameters and the batch order.
        cv: as the sampler's: folds by object, `fold` held out (-1: train on every object), `all`: every fold.
    """

    out: str = "runs/evaluator"
    hand: str = ""
    seed: int = 0
    net: EvaluatorNetConfig = EvaluatorNetConfig()
    optim: EvaluatorOptimConfig = EvaluatorOptimConfig()
    data: EvaluatorDataConfig = EvaluatorDataConfig()
    cv: CVConfig = CVConfig()

    def check(self) -> None:
        check_integer("seed", self.seed, 0, 2**31 - 1)


def to_toml(cfg: Any) -> str:
    """A config dataclass as TOML that `config.load` reads back into the same config (sections for nested ones)."""
    flat, tables = [], []

    def value(v):
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, str):
            # TOML's basic strings hold no raw control characters (a newline in a path would break the file)
            return '"' + "".join(c if c not in '"\\' and 0x20 <= ord(c) != 0x7F else f"\\u{ord(c):04x}"
                                 for c in v) + '"'
        if isinstance(v, float):
            return repr(v) if math.isfinite(v) else ("inf" if v > 0 else "-inf" if v < 0 else "nan")
        if isinstance(v, (tuple, list)):
            return "[" + ", ".join(value(x) for x in v) + "]"
        return repr(v)

    def walk(obj, prefix):
        rows = []
        for f in dataclasses.fields(obj):
            v = getattr(obj, f.name)
            if dataclasses.is_dataclass(v):
                walk(v, prefix + [f.name])
            else:
                rows.append(f"{f.name} = {value(v)}")
        (tables.append((".".join(prefix), rows)) if prefix else flat.extend(rows))

    walk(cfg, [])
    text = "\n".join(flat) + "\n"
    for name, rows in sorted(tables):
        if rows:
            text += f"\n[{name}]\n" + "\n".join(rows) + "\n"
    return text
