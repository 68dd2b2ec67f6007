"""`LearnConfig`: what `ffcgs learn HAND` (and `fj.learn_hand`) runs with."""

import dataclasses

import tyro

from ffcgs_jax.core.config import check_choice, check_integer, is_finite
from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.dataset.config import Engine
from ffcgs_jax.physics.config import PhysicsConfig
from ffcgs_jax.synthesis.config import GraspConfig

HELD_OUT_SEED = 4600
"""The complex shapes every learn report holds out (`geometry.procedural.HELD_OUT_SEEDS`): never training data."""


@dataclasses.dataclass(frozen=True)
class LearnConfig:
    """Learn a hand's CVAE sampler and success predictor from its spec, report them against the geometric sampler
    ranked by E on held-out objects, and install them where `synthesize` finds them when they do better.

    Attributes:
        hand: built-in hand name or hand-spec TOML.
        out: the work folder (default learn_NAME): labels, runs, report; running the command again resumes it.
        objects: a folder of meshes (metres, z up): its train split joins the training objects, its test split
            (sorted index % 5 == 4) the held-out ones. "" = generated shapes only.
        minutes: time budget of the whole run. The first stage labels the held-out objects and measures the time
            per object; the training objects then fill 60 % of what is left: the folder's train split first (whole),
            generated shapes after it. 0 = no budget (`train_objects`).
        train_objects: generated training shapes (a quarter simple, the rest complex) when `minutes` is 0; with a
            budget, the most it may choose.
        held_out: complex shapes of the held-out seed in the report's set (besides the folder's test split).
        per_object: candidates labelled per object (robust verdict, three protocols).
        seed: the training shapes' seed (a held-out seed is refused).
        cvae_epochs: the CVAE's training passes without a budget; with one, the most it may take: as many as its
            share of the time left holds (`plan.fitting_epochs`, said in one line; the report states them).
        predictor_epochs: the success predictor's passes, chosen the same way.
        install: put the learned parts in the user folder when they beat the geometric sampler on the held-out
            objects (`learning.weights.installed_dir`).
        engine, address: the data engine, as `ffcgs dataset build` (a local Ray instance or plain; a cluster).
        grasp: the synthesis of the candidates (SDF, iterations).
        physics: the physics test and its robust verdict.
    """

    hand: tyro.conf.Positional[str] = "svh"
    out: str = ""
    objects: str = ""
    minutes: float = 60.0
    train_objects: int = 2000
    held_out: int = 40
    per_object: int = 64
    seed: int = 7
    cvae_epochs: int = 40
    predictor_epochs: int = 30
    install: bool = True
    engine: Engine = "auto"
    address: str = ""
    grasp: GraspConfig = GraspConfig()
    physics: PhysicsConfig = PhysicsConfig()

    def check(self) -> None:
        if not (is_finite(self.minutes) and self.minutes >= 0):
            raise FfcgsError(f"--minutes must be >= 0 (0: no budget), got {self.minutes!r}")
        check_integer("train_objects", self.train_objects, 1, 1_000_000)
        check_integer("held_out", self.held_out, 0, 100_000)
        check_integer("per_object", self.per_object, 2, 100_000)
        check_integer("seed", self.seed, 0, 2**31 - 1)
        check_integer("cvae_epochs", self.cvae_epochs, 1, 100_000)
        check_integer("predictor_epochs", self.predictor_epochs, 1, 100_000)
        check_choice("engine", self.engine, ("auto", "plain", "ray"))
        if self.seed == HELD_OUT_SEED:
            raise FfcgsError(f"--seed {self.seed} is the held-out seed of the learn report; choose another")

    def folder(self, hand_name: str) -> str:
        return self.out or f"learn_{hand_name}"
