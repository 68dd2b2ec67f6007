"""`ffcgs learn HAND`: the hand's learned sampler and ranker, one resumable run (`learn.pipeline`)."""

from ffcgs_jax.learn.config import LearnConfig


def run_learn(cfg: LearnConfig) -> None:
    from ffcgs_jax.learn.pipeline import learn_hand

    learn_hand(cfg)
