"""An object seen only through depth frames, ready for the grasp planner: `from_depth`.

The steps a user would otherwise chain by hand: read the frames (`depth_io.load_frames`), find the table (the
given height, or RANSAC on the readings: `depth_io.remove_table`), isolate the object from the rest of the scene
when no masks are given (`depth_isolate.isolate`: the connected part above the table nearest the views' focus),
fuse into a Gradient-SDF (`tsdf.fuse`, its grid fitted to that part), and
take its zero level as a mesh (`surface_nets`) for what needs one (the evaluation's closest points when no true
mesh is given, pictures). The object frame is the cameras' world frame: the grid sits where the object was seen,
and the table is at its fused height.
"""

import dataclasses
import functools
import pathlib
import time

import jax
import numpy as np
import trimesh

from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.geometry import depth_io, depth_isolate, surface_nets, tsdf
from ffcgs_jax.geometry.sdf import GradientSDF

_FIT_SAMPLE = 100_000  # readings the table fit sees (as `depth_io.fit_table` draws at most)
_LEVEL_DEG = 0.3  # a fitted table tilted less than this is cut as level (1 mm over 20 cm): fuse cuts it on the device


@dataclasses.dataclass(frozen=True)
class FusedObject:
    """An object fused from depth frames.

    Attributes:
        grid: the Gradient-SDF (object frame = the cameras' world frame).
        table_z: the table height in metres (given, or fitted to the readings).
        table_fitted: True when the table height came from the RANSAC fit.
        frames: the frames fused (checked; the table band and the bounds are cut inside the fusion, or in the
            masks for a tilted table).
        fuse_s: seconds from the frames in memory to the grid (table fit and isolation included, not the reading).
        isolation: what `depth_isolate.isolate` kept and removed; None when it did not run (masks given, turned
            off, or nothing near the cameras' focus).
        masks_given: the frames came with object masks (which take the isolation's place).
    """

    grid: GradientSDF
    table_z: float
    table_fitted: bool
    frames: depth_io.Frames
    fuse_s: float
    isolation: depth_isolate.Isolation | None = None
    masks_given: bool = False

    @functools.cached_property
    def mesh(self) -> trimesh.Trimesh:
        """The grid's zero level as a triangle mesh, metres (closed above the table: the underside the cameras
        cannot see lies on the table plane), made on first use: for pictures and `ffcgs fuse --mesh`; the
        evaluation reads the SDF itself."""
        return surface_nets.zero_level_mesh(np.asarray(self.grid.grid[..., 0], np.float64),
                                            np.asarray(self.grid.origin, np.float64), float(self.grid.voxel_size))


def from_depth(source: str | pathlib.Path | depth_io.Frames, res: int = 32, table_z: float | None = None,
               bounds=None, trunc_voxels: float = 4.0, margin: float = 0.15, min_margin: float = 0.01,
               isolate: bool = True) -> FusedObject:
    """Depth frames of one object on a table to a `FusedObject`.

    Without masks, the object is isolated from the rest of the scene (`depth_isolate`): the connected part of the
    readings above the table nearest the cameras' focus is fused, in a grid fitted to it; the rest (table edges
    and sides, floor, walls, other objects, stray readings) is background. Masks given with the frames take its
    place (they are the user's isolation). An explicit `bounds` box keeps its meaning (readings outside are
    background, the grid is the cube around it) and the isolation runs inside it.

    Args:
        source: a depth folder or .npz (`depth_io.load_frames`), or `Frames` already in memory.
        res: voxels along each axis of the grid (16-128).
        table_z: table height in metres; None: fitted to the readings (RANSAC on near-horizontal planes).
        bounds: (2, 3) workspace box (min and max corners, metres) or None (`tsdf.fuse`).
        trunc_voxels, margin, min_margin: as `tsdf.fuse`.
        isolate: isolate the object when there are no masks (False: every reading above the table is fused).

    Returns:
        The fused object.

    Raises:
        FfcgsError with one line: unreadable frames, no table found (give table_z), nothing left on the object.

    Warns:
        when the isolated part, or the object the masks hold, is implausible for a graspable object
        (`depth_isolate.isolate`, `depth_isolate.check_masked`).
    """
    frames = depth_io.load_frames(source) if not isinstance(source, depth_io.Frames) else \
        depth_io.check_frames(source)
    fitted, masks_given = table_z is None, frames.mask is not None
    t0 = time.perf_counter()
    bounds = None if bounds is None else depth_io.check_bounds(bounds)
    if fitted:  # on a sample of the readings over the box (clutter beside it cannot win the fit)
        plane, table_z = depth_io.fit_table(depth_io.sample_points(frames, _FIT_SAMPLE, bounds=bounds))
        if plane[2] < np.cos(np.radians(_LEVEL_DEG)):  # tilted: the device's level band would not follow it
            points = depth_io.world_points(frames)
            frames, table_z = depth_io.remove_table(depth_io.crop(frames, bounds, points) if bounds is not None
                                                    else frames, None, points=points)
    elif not np.isfinite(table_z):
        raise FfcgsError(f"table_z must be finite, got {table_z}")
    else:
        plane = np.array([0.0, 0.0, 1.0, -table_z])
    iso = None
    if isolate and not masks_given:
        frames, iso = depth_isolate.isolate(frames, plane, bounds)
    elif masks_given:
        depth_isolate.check_masked(frames, plane, bounds)
    try:
        grid = tsdf.fuse(frames, res, trunc_voxels, bounds, table_z, margin, min_margin,
                         crop=None if iso is None else iso.box)
    except FfcgsError as e:
        if "no depth reading on the object" not in str(e):
            raise
        raise FfcgsError(f"no depth reading left on the object after removing the table at z = {table_z:.4f} m "
                         f"({'fitted' if fitted else 'given'}){' and the bounds' if bounds is not None else ''}") \
            from None
    jax.block_until_ready(grid.grid)
    return FusedObject(grid, float(table_z), fitted, frames, time.perf_counter() - t0, iso, masks_given)
