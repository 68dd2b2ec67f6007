"""How a mesh becomes a Gradient-SDF grid: `SDFConfig`."""

import dataclasses

from ffcgs_jax.core.config import check_integer, check_range, is_finite
from ffcgs_jax.core.errors import FfcgsError


@dataclasses.dataclass(frozen=True)
class SDFConfig:
    """How a mesh becomes a Gradient-SDF grid.

    Attributes:
        res: voxels along each axis of the cube (16-128; the paper uses 32).
        margin: free space around the object on each side, as a fraction of its largest extent. 0.15 leaves room
            for fingertips that approach from outside while keeping voxels small.
        min_margin: lower bound on that margin in metres, so tiny objects still get a band of free space.
        scale: multiplies the mesh's coordinates on load (0.001 turns millimetres into metres).
    """

    res: int = 32
    margin: float = 0.15
    min_margin: float = 0.01
    scale: float = 1.0

    def check(self) -> None:
        check_integer("sdf.res", self.res, 16, 128)
        check_range("sdf.margin", self.margin, 0.0, 2.0)
        check_range("sdf.min_margin", self.min_margin, 0.0, 1.0)
        if not (is_finite(self.scale) and self.scale > 0):  # inf would scale every vertex to inf
            raise FfcgsError(f"sdf.scale must be > 0 and finite, got {self.scale}")
