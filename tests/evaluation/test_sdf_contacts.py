"""Evaluation on an object known only by its Gradient-SDF (fused from depth): contacts, normals and epsilon from the
SDF agree with the same from the object's mesh."""

import numpy as np
import trimesh

from ffcgs_jax.evaluation import metrics
from ffcgs_jax.geometry import sdf
from ffcgs_jax.geometry.config import SDFConfig

R = 0.04


def test_sdf_contacts_of_a_sphere_match_the_closed_form():
    grid = sdf.build_sdf(trimesh.creation.icosphere(subdivisions=5, radius=R), SDFConfig(res=48))
    rng = np.random.default_rng(0)
    u = rng.normal(size=(6, 4, 3))
    u /= np.linalg.norm(u, axis=-1, keepdims=True)
    r = rng.uniform(R - 0.004, R + 0.01, size=(6, 4, 1))
    closest, normals, signed = metrics.sdf_contacts(grid, r * u)
    h = float(grid.voxel_size)
    np.testing.assert_allclose(signed, r[..., 0] - R, atol=0.05 * h)
    np.testing.assert_allclose(normals, u, atol=0.02)
    np.testing.assert_allclose(closest, R * u, atol=0.1 * h)


def test_evaluate_on_the_sdf_agrees_with_the_mesh():
    """Five fingertips around a box: the same touching set, force closure and nearly the same epsilon."""
    box = trimesh.creation.box((0.06, 0.08, 0.05))
    grid = sdf.build_sdf(box, SDFConfig(res=48))
    tips = np.array([[[0.031, 0.0, 0.0], [-0.0305, 0.01, 0.005], [-0.0305, -0.01, -0.005], [0.0, 0.0405, 0.0],
                      [0.0, -0.05, 0.0]]])  # the last one is 1 cm off: not a contact
    q = np.zeros((1, 2))
    cfg = metrics.MetricsConfig(lp_friction=0.6)
    centre, radius = np.zeros(3), 0.06
    on_mesh = metrics.evaluate(box, tips, q, -np.ones(2), np.ones(2), cfg, centre=centre, radius=radius)
    on_sdf = metrics.evaluate(grid, tips, q, -np.ones(2), np.ones(2), cfg, centre=centre, radius=radius)
    assert on_mesh["n_contacts"][0] == on_sdf["n_contacts"][0] == 4
    np.testing.assert_allclose(on_sdf["contact_dist"], on_mesh["contact_dist"], atol=2e-4)
    assert on_mesh["force_closure"][0] and on_sdf["force_closure"][0]
    np.testing.assert_allclose(on_sdf["epsilon"], on_mesh["epsilon"], rtol=0.05)
