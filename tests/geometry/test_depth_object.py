"""`from_depth`: the table fitted on a sample of the readings (with or without masks, with a workspace box above
the table), the same grid as fusing with the true table height, and the fused mesh on first use."""

import numpy as np
import pytest
import trimesh

from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.geometry import depth_io, depth_object, depth_render, surface_nets

W, H = 160, 120


@pytest.fixture(scope="module")
def frames():
    box = trimesh.creation.box((0.06, 0.08, 0.05)).apply_translation((0.01, 0.0, 0.025 + 0.3))  # table at z = 0.3
    return depth_render.render_views(box, views=4, width=W, height=H, noise=True, seed=2)


@pytest.mark.parametrize("masks", [True, False])
def test_fitted_table_and_grid_match_the_given_height(frames, masks):
    f = frames if masks else frames._replace(mask=None)
    fitted = depth_object.from_depth(f, res=24)
    given = depth_object.from_depth(f, res=24, table_z=0.3)
    assert fitted.table_fitted and not given.table_fitted
    assert abs(fitted.table_z - 0.3) < 1e-3
    h = float(given.grid.voxel_size)
    d = np.abs(np.asarray(fitted.grid.grid[..., 0]) - np.asarray(given.grid.grid[..., 0]))
    assert np.median(d) < 0.05 * h and np.percentile(d, 99) < 0.5 * h


def test_a_box_above_the_table_still_finds_it(frames):
    box = np.array([[-0.1, -0.1, 0.302], [0.1, 0.1, 0.5]])  # the table itself is outside the box
    fo = depth_object.from_depth(frames._replace(mask=None), res=24, bounds=box)
    assert abs(fo.table_z - 0.3) < 1e-3


def test_mesh_is_the_zero_level_made_on_first_use(frames):
    fo = depth_object.from_depth(frames, res=24)
    assert "mesh" not in vars(fo)
    ref = surface_nets.zero_level_mesh(np.asarray(fo.grid.grid[..., 0], np.float64), np.asarray(fo.grid.origin),
                                       float(fo.grid.voxel_size))
    np.testing.assert_allclose(fo.mesh.vertices, ref.vertices)
    assert fo.mesh is fo.mesh  # cached
    np.testing.assert_allclose(fo.mesh.bounds[:, 2], [0.3, 0.35], atol=0.6 * float(fo.grid.voxel_size))


def test_sample_points_are_world_points_of_readings(frames):
    sample = depth_io.sample_points(frames, 500, seed=1)
    every = depth_io.world_points(frames).reshape(-1, 3)
    every = every[np.isfinite(every[:, 0])]
    assert sample.shape == (500, 3)
    exact = [np.min(np.linalg.norm(every - p, axis=1)) for p in sample[:20]]  # each is some reading's point
    assert np.max(exact) < 1e-9


def test_nothing_above_the_given_table_is_one_line(frames):
    with pytest.raises(FfcgsError, match="no depth reading left on the object after removing the table"):
        depth_object.from_depth(frames, res=24, table_z=1.0)
