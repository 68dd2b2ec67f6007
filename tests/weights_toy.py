"""Weights files of the toy hand's networks, untrained, in the formats training writes (their metadata included):
what the loaders, the user folder and `ffcgs learn`'s install are tested with."""

import jax
import numpy as np

from ffcgs_jax.learning import checkpoint, cvae, evaluator
from ffcgs_jax.learning.config import ModelConfig
from ffcgs_jax.training import evaluator_train
from ffcgs_jax.training import train as cvae_train
from ffcgs_jax.training.config import EvaluatorTrainConfig, TrainConfig


def cvae_file(path, hand) -> None:
    cfg = TrainConfig(model=ModelConfig(width=2, features=4, head=4, mlp=8))
    params = jax.tree.map(lambda x: np.asarray(x, np.float32), cvae.init(jax.random.key(0), cfg.model))
    checkpoint.save(path, {"params": params}, cvae_train.weights_meta(cfg, hand, {}))


def evaluator_file(path, hand) -> None:
    cfg = EvaluatorTrainConfig()
    net = evaluator.init(jax.random.key(0), evaluator.feature_width(hand), 3, cfg.net.hidden, cfg.net.depth)
    norm = {"mean": np.zeros(evaluator.feature_width(hand), np.float32),
            "scale": np.ones(evaluator.feature_width(hand), np.float32)}
    meta = evaluator_train.weights_meta(cfg, hand, ("lift_shake", "six_dir", "all"), evaluator.feature_width(hand), {})
    checkpoint.save(path, {"net": jax.tree.map(np.asarray, net), "norm": norm}, meta)
