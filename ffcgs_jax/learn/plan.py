"""What a learn run builds: the hand's object scale, the dataset configs of its training and held-out objects, and
how many training objects fit its time budget.

Objects are scaled to the hand: the SVH's training shapes are 0.8-1.2 of their generated size, and another hand's
are that times the ratio of its span to the SVH's (the farthest fingertip contact from the palm, open hand), so a
hand half the SVH's size grasps shapes half the size. The held-out objects are the folder's test split and complex
shapes of `config.HELD_OUT_SEED`, never a training seed (the dataset refuses held-out seeds without `allow_test`,
and the run checks that no held-out object shares a name or geometry with a training one).
"""

import dataclasses
import math

import jax.numpy as jnp
import numpy as np

from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.dataset.config import DatasetConfig
from ffcgs_jax.hand import kinematics as K
from ffcgs_jax.learn.config import HELD_OUT_SEED, LearnConfig

SHARES = {"labels": 0.6, "cvae": 0.15, "predictor": 0.05, "held_learned": 0.2}
"""Budget shares after the held-out labels (held_learned: the learned candidates' held-out labels and the report).
Each stage gets its share of what is left when it starts, so one that overran is paid for by the ones after it."""
SIMPLE_SHARE = 0.25  # of the generated training shapes: boxes, cylinders, ...; the rest complex
FEWEST_OBJECTS = 4  # below this a budget trains nothing worth reporting


def span(hand: K.Hand) -> float:
    """The open hand's farthest fingertip contact from the palm site (m)."""
    frames = K.forward_kinematics(hand, jnp.eye(4, dtype=hand.lower.dtype), hand.lower)
    return float(np.max(np.linalg.norm(np.asarray(frames.contacts) - np.asarray(frames.palm_pos), axis=1)))


def scale(hand: K.Hand) -> float:
    """The hand's size relative to the SVH's (`span`), within [0.25, 4]."""
    return float(np.clip(span(hand) / span(K.load_hand("svh")), 0.25, 4.0))


def dataset(cfg: LearnConfig, s: float, out: str, **kw) -> DatasetConfig:
    """A labelled build (`keep all`, robust verdicts, three protocols) of this run, its objects scaled by `s` (the
    check stage's `scale`, kept in the run's state): `kw` picks its objects."""
    base = DatasetConfig(hand=cfg.hand, out=out, keep="all", per_object=cfg.per_object, rotations=1,
                         scale_min=0.8 * s, scale_max=1.2 * s, engine=cfg.engine, address=cfg.address,
                         grasp=cfg.grasp, physics=cfg.physics, sampler="geometric")
    return dataclasses.replace(base, **kw)


def training(cfg: LearnConfig, s: float, out: str, count: int) -> DatasetConfig:
    simple = int(round(count * SIMPLE_SHARE))
    return dataset(cfg, s, out, objects=cfg.objects, split="train", procedural=simple, complex=count - simple,
                   seed=cfg.seed)


def held_out(cfg: LearnConfig, s: float, out: str, sampler: str = "geometric", grasp=None) -> list[DatasetConfig]:
    """The report's held-out builds: the folder's test split (when there is a folder) and the held-out complex
    shapes, scaled by `s`, with candidates from `sampler`."""
    kw = dict(sampler=sampler, allow_test=True, **({"grasp": grasp} if grasp is not None else {}))
    out_stem = out.removesuffix(".mcap")
    builds = []
    if cfg.objects:
        builds.append(dataset(cfg, s, f"{out_stem}_test.mcap", objects=cfg.objects, split="test", **kw))
    if cfg.held_out:
        builds.append(dataset(cfg, s, f"{out_stem}_complex.mcap", split="train", complex=cfg.held_out,
                              seed=HELD_OUT_SEED, **kw))
    if not builds:
        raise FfcgsError("the report needs held-out objects: --held-out N (complex shapes) or --objects with a test "
                         "split")
    return builds


def stage_seconds(cfg: LearnConfig, stage: str, spent_s: float) -> float:
    """The seconds `stage` may take: its share of the budget left after `spent_s` among it and the stages after."""
    later = list(SHARES)[list(SHARES).index(stage):]
    return max(0.0, cfg.minutes * 60 - spent_s) * SHARES[stage] / sum(SHARES[k] for k in later)


def folder_training(cfg: LearnConfig) -> int:
    """How many of the --objects folder's meshes are training objects (its train split; 0 without a folder)."""
    from ffcgs_jax.dataset.objects import split_files

    return len(split_files(cfg.objects, "train")) if cfg.objects else 0


def fitting_objects(cfg: LearnConfig, seconds_per_object: float, spent_s: float, folder: int = 0) -> tuple[int, str]:
    """(generated training shapes, the sentence that says why) for the budget left after `spent_s`. The folder's
    `folder` training objects are labelled first and count against the budget: the generated shapes fill the rest."""
    if cfg.minutes == 0:
        extra = f" and the folder's {folder}" if folder else ""
        return cfg.train_objects, f"{cfg.train_objects} generated training objects{extra} (no time budget)"
    left = cfg.minutes * 60 - spent_s
    fit = int(stage_seconds(cfg, "labels", spent_s) / max(seconds_per_object, 1e-3))
    n = min(cfg.train_objects, max(fit - folder, 0))
    if n + folder < FEWEST_OBJECTS:
        raise FfcgsError(f"a budget of {cfg.minutes:g} min is too small to train anything: labelling takes "
                         f"{seconds_per_object:.1f} s per object here and {FEWEST_OBJECTS} objects at least are "
                         f"needed ({math.ceil((FEWEST_OBJECTS * seconds_per_object / SHARES['labels'] + spent_s) / 60)}"
                         " min or more)")
    why = (f"{n + folder} training objects ({folder} of the folder, {n} generated)" if folder
           else f"{n} training objects")
    why += (f": {seconds_per_object:.1f} s per object of {cfg.per_object} candidates here, {SHARES['labels']:.0%} of "
            f"the {left / 60:.1f} min left of {cfg.minutes:g}")
    if folder > fit:  # the folder is labelled whole: the budget does not choose among the user's own objects
        why += (f"; the folder's training split alone is more than the {fit} that fit, so the run takes about "
                f"{(folder - fit) * seconds_per_object / 60:.0f} min longer")
    return n, why


def fitting_epochs(cfg: LearnConfig, stage: str, most: int, steps_per_epoch: int, spent_s: float,
                   seconds_per_step: float, measured: bool) -> tuple[int, str]:
    """(epochs, the sentence that says why) of a training stage ("cvae", "predictor"): `most` without a budget,
    else as many as its share of the time left holds at `seconds_per_step` (`training.step_cost`), 1 to `most`."""
    what = {"cvae": "CVAE", "predictor": "success predictor"}[stage]
    if cfg.minutes == 0:
        return most, f"{what}: {most} epochs of {steps_per_epoch} steps (no time budget)"
    allowed = stage_seconds(cfg, stage, spent_s)
    epoch_s = steps_per_epoch * seconds_per_step
    n = int(np.clip(allowed // max(epoch_s, 1e-9), 1, most))
    source = "measured on this machine" if measured else "a first guess: no training measured on this machine yet"
    return n, (f"{what}: {n} epochs of {steps_per_epoch} steps fit in {allowed / 60:.1f} min "
               f"({seconds_per_step * 1e3:.1f} ms per step, {source}; at most {most})")
