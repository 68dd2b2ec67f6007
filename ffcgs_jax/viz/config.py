"""Pictures: `RenderConfig`."""

import dataclasses
from typing import Literal

from ffcgs_jax.core.config import check_choice, check_integer

RenderBackend = Literal["auto", "mujoco", "software"]


@dataclasses.dataclass(frozen=True)
class RenderConfig:
    """Pictures of the hand (and object).

    Attributes:
        width, height: size of one view in pixels.
        backend: "auto" tries MuJoCo's OpenGL renderer and falls back to the built-in software rasteriser;
            "mujoco" or "software" force one.
    """

    width: int = 480
    height: int = 480
    backend: RenderBackend = "auto"

    def check(self) -> None:
        check_integer("render.width", self.width, 64, 4096)
        check_integer("render.height", self.height, 64, 4096)
        check_choice("render.backend", self.backend, RenderBackend)
