"""The zero level of a distance field as a mesh: closed, wound outward, on the surface, for closed-form shapes."""

import numpy as np
import pytest

from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.geometry.surface_nets import zero_level_mesh

RES, H = 40, 0.005
ORIGIN = np.full(3, -0.1)


def _axes():
    a = ORIGIN[0] + H * np.arange(RES)
    return np.meshgrid(a, a, a, indexing="ij")


def test_sphere_is_closed_outward_and_on_the_surface():
    X, Y, Z = _axes()
    r = 0.06
    mesh = zero_level_mesh(np.sqrt(X**2 + Y**2 + Z**2) - r, ORIGIN, H)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume > 0  # outward normals: trimesh's volume is negative for inward winding
    assert abs(mesh.volume / (4 / 3 * np.pi * r**3) - 1) < 0.02
    assert np.abs(np.linalg.norm(mesh.vertices, axis=1) - r).max() < 0.1 * H


def test_box_volume_and_flipped_field():
    X, Y, Z = _axes()
    field = np.maximum(np.abs(X) - 0.03, np.maximum(np.abs(Y - 0.01) - 0.05, np.abs(Z) - 0.02))
    mesh = zero_level_mesh(field, ORIGIN, H)
    assert mesh.is_watertight and abs(mesh.volume / (0.06 * 0.1 * 0.04) - 1) < 0.05  # corners cut by < 1 voxel
    np.testing.assert_allclose(mesh.bounds, [[-0.03, -0.04, -0.02], [0.03, 0.06, 0.02]], atol=0.6 * H)
    inverted = zero_level_mesh(-field, ORIGIN, H)  # inside out: the same surface, wound the other way
    assert inverted.volume < 0


@pytest.mark.parametrize("field, message", [
    (np.ones((8, 8, 8)), "no zero level"),
    (np.full((8, 8, 8), np.nan), "NaN or inf"),
])
def test_bad_fields_raise_one_line(field, message):
    with pytest.raises(FfcgsError, match=message):
        zero_level_mesh(field, ORIGIN, H)
