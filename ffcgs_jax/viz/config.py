"""Pictures: `RenderConfig`."""

import dataclasses

from ffcgs_jax.core.config import check_integer
from ffcgs_jax.core.errors import FfcgsError


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
    backend: str = "auto"

    def check(self) -> None:
        check_integer("render.width", self.width, 64, 4096)
        check_integer("render.height", self.height, 64, 4096)
        if self.backend not in ("auto", "mujoco", "software"):
            raise FfcgsError(f"render.backend must be one of auto, mujoco, software; got {self.backend!r}")
