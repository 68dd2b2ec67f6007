"""Synthetic scenes around an object, for tests and bench/depth.py: what real cameras see besides the object.

`render_views` alone draws the object on an infinite table plane. A real camera 45 cm from a small object also
sees the table's edges and sides, the floor below, a wall behind and other things on the table; `scene_mesh`
builds those as triangles (a finite table box whose top is the object's lowest z, a floor, a wall, a second
object beside the first) and `render_scene` renders the object among them. Only the object is in the masks.
"""

import dataclasses

import numpy as np
import trimesh

from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.geometry import depth_render
from ffcgs_jax.geometry.depth_io import Frames


@dataclasses.dataclass(frozen=True)
class Scene:
    """What stands around the object (metres; the object's centre in x-y is the origin of the offsets).

    Attributes:
        table: (x, y) size of the table top, centred under the object.
        thickness: the table top's thickness (its sides are seen below the top).
        floor: height of the table top above the floor; None: no floor.
        wall: distance from the object's centre to a wall behind it (+y side, facing -y); None: no wall.
        second: (x, y) offset of a second object (a 5 x 5 x 8 cm box standing on the table); None: none.
    """

    table: tuple[float, float] = (1.0, 1.0)
    thickness: float = 0.03
    floor: float | None = 0.75
    wall: float | None = None
    second: tuple[float, float] | None = None

    def check(self) -> None:
        if not (min(self.table) > 0 and self.thickness > 0):
            raise FfcgsError(f"scene: table size and thickness must be > 0, got {self.table}, {self.thickness}")
        if self.floor is not None and not self.floor > self.thickness:
            raise FfcgsError(f"scene: the floor must lie below the table top's underside, got {self.floor} m")
        if self.wall is not None and not self.wall > 0:
            raise FfcgsError(f"scene: the wall distance must be > 0, got {self.wall}")


# the scenes the tests and bench/depth.py name
SCENES = {"table": Scene(), "clutter": Scene(wall=0.6, second=(0.16, 0.08))}
SECOND_SIZE = (0.05, 0.05, 0.08)  # m: the second object's box
_ROOM = 6.0  # m: side of the floor and width of the wall (past every view at these distances)


def _box(lo, hi) -> trimesh.Trimesh:
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    return trimesh.creation.box(hi - lo).apply_translation((lo + hi) / 2)


def scene_mesh(mesh: trimesh.Trimesh, scene: Scene) -> trimesh.Trimesh:
    """The background of `scene` around `mesh` (which rests on the table top at its lowest z) as one mesh."""
    scene.check()
    lo, hi = np.asarray(mesh.bounds, np.float64)
    cx, cy = (lo[:2] + hi[:2]) / 2
    top = lo[2]
    tx, ty = scene.table[0] / 2, scene.table[1] / 2
    parts = [_box((cx - tx, cy - ty, top - scene.thickness), (cx + tx, cy + ty, top))]
    if scene.floor is not None:
        z = top - scene.floor
        parts.append(_box((cx - _ROOM / 2, cy - _ROOM / 2, z - 0.01), (cx + _ROOM / 2, cy + _ROOM / 2, z)))
    if scene.wall is not None:
        y = cy + scene.wall
        floor = top - (scene.floor if scene.floor is not None else 1.0)
        parts.append(_box((cx - _ROOM / 2, y, floor), (cx + _ROOM / 2, y + 0.05, top + 1.5)))
    if scene.second is not None:
        sx, sy, sz = SECOND_SIZE
        x, y = cx + scene.second[0], cy + scene.second[1]
        parts.append(_box((x - sx / 2, y - sy / 2, top), (x + sx / 2, y + sy / 2, top + sz)))
    return trimesh.util.concatenate(parts)


def render_scene(mesh: trimesh.Trimesh, scene: Scene | str = "table", views: int = 5, width: int = 640,
                 height: int = 480, noise: bool = False, seed: int | np.random.Generator = 0, **kwargs) -> Frames:
    """`depth_render.render_views` of `mesh` standing in `scene` (a `Scene` or a name of `SCENES`) instead of on
    an infinite table plane; `kwargs` go to `render_views` (elevation_deg, distance, noise_a, dropout). The masks
    hold the object only."""
    if isinstance(scene, str):
        if scene not in SCENES:
            raise FfcgsError(f"unknown scene {scene!r}; known: {', '.join(SCENES)}")
        scene = SCENES[scene]
    return depth_render.render_views(mesh, views, width, height, noise, seed, table=False,
                                     scene=scene_mesh(mesh, scene), **kwargs)
