"""Configs of the networks: the CVAE wrist-pose sampler's shapes (`ModelConfig`) and the success predictor's MLP
(`EvaluatorNetConfig`). Their training configs, which nest these, are in `training.config`.
"""

import dataclasses

from ffcgs_jax.core.config import check_integer
from ffcgs_jax.core.errors import FfcgsError


@dataclasses.dataclass(frozen=True)
class ModelConfig:
    """Shapes of the CVAE (see `cvae.py`); all of them are static, so they live here and not in the params.

    Attributes:
        res: resolution R of the input Gradient-SDF, a multiple of 8 (the U-Net halves it three times).
        width: U-Net channels at full resolution; level l below it has width * 2^l (at most 4 * width).
        features: channels of the U-Net output volume at R/2 (the paper's 32x16^3).
        head: channels of the encoder's and decoder's four convolutions.
        mlp: hidden units of their MLP heads.
        latent: dimension of z (the paper's 2).
    """

    res: int = 32
    width: int = 8
    features: int = 32
    head: int = 32
    mlp: int = 128
    latent: int = 2

    def check(self) -> None:
        check_integer("model.res", self.res, 8, 256)
        if self.res % 8:
            raise FfcgsError(f"model.res must be a multiple of 8 (the U-Net halves it three times), got {self.res}")
        for name in ("width", "features", "head", "mlp"):
            check_integer(f"model.{name}", getattr(self, name), 1, 1024)
        check_integer("model.latent", self.latent, 1, 64)


@dataclasses.dataclass(frozen=True)
class EvaluatorNetConfig:
    """The predictor's MLP: `depth` hidden layers of `hidden` units (the features are `evaluator.features`)."""

    hidden: int = 256
    depth: int = 3

    def check(self) -> None:
        check_integer("net.hidden", self.hidden, 1, 8192)
        check_integer("net.depth", self.depth, 1, 32)
