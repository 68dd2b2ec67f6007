# Copyright 2025 The ffcgs-jax Authors.
# SPDX-License-Identifier: Apache-2.0
"""Tests of the NumPy/SciPy grasp metrics against closed forms (sphere, box, cross polytope)."""

import math

import numpy as np
import pytest
import scipy.optimize
import trimesh

from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.evaluation import metrics
from ffcgs_jax.kernels import directions

R = 0.05  # sphere radius, metres
MU = 0.2
M = 8
LP_TOL = 1e-9  # HiGHS primal feasibility is ~1e-9 relative
CLOSED_FORM_TOL = 1e-12
SAG_TOL = 5e-5  # metres: the subdivision-4 icosphere's flat facets lie up to ~3.3e-5 inside the true sphere


@pytest.fixture(scope="module")
def sphere():
    return trimesh.creation.icosphere(subdivisions=4, radius=R)


@pytest.fixture(scope="module")
def basis():
    return directions.sphere_basis(64)


def _on_sphere(polar: float, azimuth: float, r: float = R) -> np.ndarray:
    return r * np.array([math.sin(polar) * math.cos(azimuth), math.sin(polar) * math.sin(azimuth), math.cos(polar)])


def _bipyramid() -> np.ndarray:
    """Poles plus three equatorial points 120 degrees apart: a well-spread 5-contact grasp."""
    equator = [_on_sphere(math.pi / 2, 2 * math.pi * k / 3) for k in range(3)]
    return np.stack([_on_sphere(0, 0), _on_sphere(math.pi, 0), *equator])


def _ring(polar_deg: float, n: int = 5) -> np.ndarray:
    """n contacts evenly spaced on the circle at polar angle `polar_deg` around +z (a cap of that half-angle)."""
    return np.stack([_on_sphere(math.radians(polar_deg), 2 * math.pi * k / n) for k in range(n)])


def _wrenches(mesh, points: np.ndarray) -> np.ndarray:
    closest, normals, _ = metrics.mesh_contacts(mesh, points[None])
    return metrics.primitive_wrenches(closest[0], normals[0], np.zeros(3), R, MU, M)


# ------------------------------------------------------------------------------------------------ sphere grasps


def test_spread_contacts_on_sphere_are_force_closure(sphere, basis):
    w = _wrenches(sphere, _bipyramid() * 1.01)  # 0.5 mm outside: mesh_contacts projects them back
    assert w.shape == (5 * M, 6)
    eps = metrics.epsilon_q1(w)
    assert eps > 0.1  # ~0.153 with mu = 0.2, m = 8
    assert metrics.q_distance_reference(w, basis) == pytest.approx(0.0, abs=LP_TOL)


def test_contacts_in_a_cap_are_not_force_closure(sphere, basis):
    w = _wrenches(sphere, _ring(20.0))
    assert metrics.epsilon_q1(w) == 0.0
    assert metrics.q_distance_reference(w, basis) > 0.5  # ~0.85


def test_q_distance_decreases_as_the_cap_opens(sphere, basis):
    angles = [5.0, 15.0, 30.0, 45.0, 60.0, 75.0]
    qd = [metrics.q_distance_reference(_wrenches(sphere, _ring(a)), basis) for a in angles]
    assert all(x > 0 for x in qd)
    assert np.all(np.diff(qd) < 0), qd


def test_ring_force_closure_threshold_matches_friction_angle(sphere, basis):
    # A ring of contacts holds the sphere iff the friction cone reaches the equator plane's normal: polar angle
    # > 90 deg - atan(mu) = 78.7 deg (the 8-sided cone is inscribed, so up to 90 - atan(mu cos(pi/8)) = 79.5).
    below, above = _wrenches(sphere, _ring(77.0)), _wrenches(sphere, _ring(81.0))
    assert metrics.epsilon_q1(below) == 0.0
    assert metrics.q_distance_reference(below, basis) > 0
    assert metrics.epsilon_q1(above) > 0
    assert metrics.q_distance_reference(above, basis) == pytest.approx(0.0, abs=LP_TOL)


def test_coincident_contacts_are_degenerate_not_errors(sphere, basis):
    p = np.repeat(_on_sphere(0.3, 0.2)[None], 5, axis=0)
    w = _wrenches(sphere, p)
    assert metrics.epsilon_q1(w) == 0.0
    assert metrics.q_distance_reference(w, basis) > 0.5
    assert metrics.epsilon_q1(w[:3]) == 0.0  # fewer than 7 wrenches
    two = _wrenches(sphere, np.stack([_on_sphere(0, 0), _on_sphere(math.pi, 0)]))  # antipodal pair: rank < 6
    assert metrics.epsilon_q1(two) == 0.0


# ------------------------------------------------------------------------------------------------ closed forms


def test_epsilon_of_cross_polytope_is_one_over_sqrt6():
    w = np.concatenate([np.eye(6), -np.eye(6)])
    assert metrics.epsilon_q1(w) == pytest.approx(1 / math.sqrt(6), abs=CLOSED_FORM_TOL)
    assert metrics.epsilon_q1(2.5 * w) == pytest.approx(2.5 / math.sqrt(6), abs=CLOSED_FORM_TOL)
    # origin-centred ball shrinks when the polytope moves: shift by s along e_1 -> facet distances (1 - s)/sqrt(6)
    assert metrics.epsilon_q1(w + [0.3, 0, 0, 0, 0, 0]) == pytest.approx(0.7 / math.sqrt(6), abs=CLOSED_FORM_TOL)
    assert metrics.epsilon_q1(w + [1.5, 0, 0, 0, 0, 0]) == 0.0  # origin outside


def test_q_distance_of_a_single_wrench_is_its_gauge(basis):
    w = np.tile([0.3, 0, 0, 0, 0, 0], (4, 1))
    assert metrics.q_distance_reference(w, basis) == pytest.approx(0.3, abs=LP_TOL)
    axes = np.concatenate([np.eye(6), -np.eye(6)]).T  # gauge of the cross polytope is the l1 norm
    v = np.array([[0.1, -0.2, 0.0, 0.05, 0.0, 0.3]])
    assert metrics.q_distance_reference(v, axes) == pytest.approx(0.65, abs=LP_TOL)


def test_q_distance_is_bracketed_by_euclidean_distance(sphere, basis):
    # |x| <= gauge(x) <= |x| / r, r = inradius of conv{u_k} = epsilon_q1 of the basis, so the Q-distance lies
    # between the Euclidean distance d from the origin to the hull and d / r.
    w = _wrenches(sphere, _ring(40.0))
    n = len(w)
    res = scipy.optimize.minimize(
        lambda a: 0.5 * np.sum((w.T @ a) ** 2),
        np.full(n, 1 / n),
        jac=lambda a: w @ (w.T @ a),
        bounds=[(0, None)] * n,
        constraints=[{"type": "eq", "fun": lambda a: a.sum() - 1}],
        method="SLSQP",
        options={"ftol": 1e-15, "maxiter": 1000},
    )
    d = float(np.linalg.norm(w.T @ res.x))
    r = metrics.epsilon_q1(basis.T)
    assert 0.5 < r < 1.0
    qd = metrics.q_distance_reference(w, basis)
    assert d - 1e-6 <= qd <= d / r + 1e-6, (d, qd, r)


def test_primitive_wrenches_geometry():
    c = np.array([[0.0, 0.0, 0.1]])
    n = np.array([[0.0, 0.0, 2.0]])  # not unit: normalised inside
    w = metrics.primitive_wrenches(c, n, np.zeros(3), 0.1, 0.2, 6)
    f, tau = w[:, :3], w[:, 3:]
    np.testing.assert_allclose(np.linalg.norm(f, axis=1), 1.0, atol=CLOSED_FORM_TOL)
    np.testing.assert_allclose(f[:, 2], -1 / math.sqrt(1 + 0.04), atol=CLOSED_FORM_TOL)  # cone half-angle atan(mu)
    np.testing.assert_allclose(f.mean(axis=0), [0, 0, -1 / math.sqrt(1.04)], atol=CLOSED_FORM_TOL)
    np.testing.assert_allclose(tau, np.cross(c / 0.1, f), atol=CLOSED_FORM_TOL)


# --------------------------------------------------------------------------------------------- mesh contacts


def test_mesh_contacts_on_a_box():
    box = trimesh.creation.box(extents=(0.1, 0.2, 0.3))  # half extents 0.05, 0.1, 0.15
    pts = np.array(
        [
            # outside: face, face, edge, corner
            [[0.08, 0.01, 0.02], [0.0, 0.0, -0.2], [0.07, 0.13, 0.0], [0.06, 0.11, 0.17]],
            [[0.04, 0.0, 0.0], [0.0, -0.08, 0.01], [0.0, 0.0, 0.14], [0.01, 0.02, -0.145]],  # inside, nearest face
        ]
    )
    closest, normals, sd = metrics.mesh_contacts(box, pts)
    want_closest = np.array(
        [
            [[0.05, 0.01, 0.02], [0.0, 0.0, -0.15], [0.05, 0.1, 0.0], [0.05, 0.1, 0.15]],
            [[0.05, 0.0, 0.0], [0.0, -0.1, 0.01], [0.0, 0.0, 0.15], [0.01, 0.02, -0.15]],
        ]
    )
    dirs = pts[0] - want_closest[0]
    want_normals = np.concatenate(
        [dirs / np.linalg.norm(dirs, axis=1, keepdims=True), [[1, 0, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]]]
    ).reshape(2, 4, 3)
    want_sd = np.array(
        [[0.03, 0.05, math.hypot(0.02, 0.03), math.sqrt(0.01**2 + 0.01**2 + 0.02**2)], [-0.01, -0.02, -0.01, -0.005]]
    )
    np.testing.assert_allclose(closest, want_closest, atol=1e-12)
    np.testing.assert_allclose(normals, want_normals, atol=1e-12)
    np.testing.assert_allclose(sd, want_sd, atol=1e-12)


def test_mesh_contacts_sphere_signed_distance(sphere):
    p = np.stack([_bipyramid() * 1.2, _bipyramid() * 0.8])
    _, normals, sd = metrics.mesh_contacts(sphere, p)
    np.testing.assert_allclose(sd, [[0.01] * 5, [-0.01] * 5], atol=SAG_TOL)
    np.testing.assert_allclose(normals, np.stack([_bipyramid() / R] * 2), atol=0.05)
    # points exactly at mesh vertices (the poles are icosphere vertices): the shared normal of the adjacent faces
    # is radial to 0.005, where any single face normal is off by ~0.046
    _, n_on, sd_on = metrics.mesh_contacts(sphere, _bipyramid()[None])
    np.testing.assert_allclose(sd_on, 0.0, atol=SAG_TOL)
    np.testing.assert_allclose(n_on[0], _bipyramid() / R, atol=0.005)


# -------------------------------------------------------------------------------------------------- basis


def test_sphere_basis_deterministic_unit_and_spanning():
    u = directions.sphere_basis(64)
    assert u.shape == (6, 64)
    np.testing.assert_array_equal(u, directions.sphere_basis(64))
    assert not np.allclose(u, directions.sphere_basis(64, seed=1))
    np.testing.assert_allclose(np.linalg.norm(u, axis=0), 1.0, atol=1e-14)
    np.testing.assert_array_equal(u[:, :12:2], np.eye(6))
    np.testing.assert_array_equal(u[:, 1:12:2], -np.eye(6))
    gram = u.T @ u - 2 * np.eye(64)
    assert gram.max() < 0.8  # well spread: no two directions within 37 degrees
    d = np.random.default_rng(123).standard_normal((1000, 6))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    assert (d @ u).max(axis=1).min() > 1 / math.sqrt(6)  # the ±e_i alone guarantee >= 1/sqrt(6)
    assert directions.sphere_basis(12).shape == (6, 12)


# ------------------------------------------------------------------------------------------------- energies


def test_energies_and_joint_limit_use_by_hand():
    dist = np.array([[0.01, -0.01], [0.0, 0.0]])
    q = np.array([[2.0, 0.0], [1.0, 0.5]])
    lo, hi = np.array([0.0, -1.0]), np.array([2.0, 1.0])
    e_g = np.array([0.1, 0.0])
    cfg = metrics.MetricsConfig(d0=0.005)
    out = metrics.energies(dist, q, lo, hi, e_g, cfg)
    e_c = np.array([math.sqrt((0.015**2 + 0.005**2) / 2), 0.005])
    e_q = np.array([(0.5**2 + 0.0) / 2, (0.0 + 0.25**2) / 2])
    np.testing.assert_allclose(out["E_c"], e_c, atol=CLOSED_FORM_TOL)
    np.testing.assert_allclose(out["E_c_cm"], 100 * e_c, atol=CLOSED_FORM_TOL)
    np.testing.assert_allclose(out["E_q"], e_q, atol=CLOSED_FORM_TOL)
    np.testing.assert_allclose(out["E"], e_g + 5.0 * e_c + 0.5 * e_q, atol=CLOSED_FORM_TOL)
    np.testing.assert_array_equal(out["E_g"], e_g)
    zero = metrics.energies(dist, q, lo, hi, e_g, metrics.MetricsConfig())
    np.testing.assert_allclose(zero["E_c"], [0.01, 0.0], atol=CLOSED_FORM_TOL)
    np.testing.assert_allclose(metrics.joint_limit_use(q, lo, hi), [1.0, 0.5], atol=CLOSED_FORM_TOL)


# ------------------------------------------------------------------------------------------- evaluate/summary


def test_evaluate_and_summary(sphere):
    contacts = np.stack([_bipyramid() * 1.1, _ring(20.0), _ring(85.0)])
    lo, hi = np.zeros(3), np.ones(3)
    q = np.array([[0.5, 0.5, 0.5], [1.0, 0.5, 0.5], [0.25, 0.5, 0.5]])
    # the bipyramid's tips are 5 mm off the sphere: they count as contacts only with a tolerance above that
    res = metrics.evaluate(sphere, contacts, q, lo, hi, metrics.MetricsConfig(contact_tol=0.006),
                           penetration=[0.0, 0.001, 0.0])
    np.testing.assert_array_equal(res["force_closure"], [True, False, True])
    assert res["epsilon"][0] > 0.1 and res["epsilon"][1] == 0.0
    np.testing.assert_allclose(res["E_g"][[0, 2]], 0.0, atol=LP_TOL)
    assert res["E_g"][1] > 0.5
    assert res["contact_dist"].shape == (3, 5)
    np.testing.assert_allclose(res["contact_dist"][0], 0.005, atol=SAG_TOL)
    np.testing.assert_allclose(res["E_c"][0], 0.005, atol=SAG_TOL)
    np.testing.assert_allclose(res["joint_limit_use"], [0.0, 1.0, 0.5], atol=CLOSED_FORM_TOL)
    np.testing.assert_allclose(res["E"], res["E_g"] + 5 * res["E_c"] + 0.5 * res["E_q"], atol=CLOSED_FORM_TOL)
    assert np.isnan(metrics.evaluate(sphere, contacts[:1], q[:1], lo, hi)["penetration"]).all()

    s = metrics.summary(res, None)
    assert s["n"] == 3 and s["n_valid"] == 3 and s["n_force_closure"] == 2
    assert s["force_closure_share"] == pytest.approx(2 / 3)
    assert s["median_joint_limit_use"] == pytest.approx(0.5)
    s2 = metrics.summary(res, np.array([False, True, True]))
    assert s2["n_valid"] == 2 and s2["force_closure_share"] == pytest.approx(0.5)
    assert s2["median_penetration"] == pytest.approx(0.0005)
    assert math.isnan(metrics.summary(res, np.zeros(3, bool))["median_E"])


def test_only_touching_fingertips_count(sphere):
    """A fingertip farther from the mesh than contact_tol exerts no force: the same five points around the sphere
    are force closure when they touch, not when they stand 5 mm or 1 cm off, and a grasp with one tip lifted
    1 cm is judged on the four that touch."""
    on = _bipyramid()  # on the surface
    lift = on.copy()
    lift[0] *= 1.0 + 0.01 / np.linalg.norm(on[0])  # one tip 1 cm out
    contacts = np.stack([on, on * 1.1, on * 1.2, lift])
    q, lo, hi = np.full((4, 1), 0.5), np.zeros(1), np.ones(1)
    res = metrics.evaluate(sphere, contacts, q, lo, hi)
    np.testing.assert_array_equal(res["n_contacts"], [5, 0, 0, 4])
    assert res["force_closure"][0] and not res["force_closure"][1:3].any()
    assert np.isnan(res["E_g"][1]) and res["epsilon"][1] == 0.0
    four = metrics.evaluate(sphere, on[None, 1:], q[:1], lo, hi)  # the four touching tips alone
    assert res["epsilon"][3] == pytest.approx(four["epsilon"][0], abs=1e-12)
    assert res["E_g"][3] == pytest.approx(four["E_g"][0], abs=1e-12)
    wide = metrics.evaluate(sphere, contacts, q, lo, hi, metrics.MetricsConfig(contact_tol=0.03))
    np.testing.assert_array_equal(wide["n_contacts"], [5, 5, 5, 5])  # projected, as before the tolerance existed


def test_wilcoxon_paired():
    rng = np.random.default_rng(0)
    a = rng.uniform(0, 1, 30)
    stat, p = metrics.wilcoxon(a, a + 0.1)
    assert stat == 0.0 and p < 1e-3
    _, p_same = metrics.wilcoxon(a, a[::-1])  # symmetric differences: no evidence
    assert p_same > 0.5
    assert metrics.wilcoxon(a, a) == (0.0, 1.0)


# ------------------------------------------------------------------------------------------------- bad input


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"lp_friction": -0.1}, "metrics.lp_friction"),
        ({"d0": float("nan")}, "metrics.d0"),
        ({"cone_edges": 2}, "metrics.cone_edges"),
        ({"basis_size": 11}, "metrics.basis_size"),
        ({"a_q": -1.0}, "metrics.a_q"),
    ],
)
def test_bad_config(kwargs, match):
    with pytest.raises(FfcgsError, match=match):
        metrics.MetricsConfig(**kwargs).check()


def test_bad_inputs(sphere, basis):
    with pytest.raises(FfcgsError, match=r"points must have shape \(\*, \*, 3\), got \(5, 3\)"):
        metrics.mesh_contacts(sphere, _bipyramid())
    with pytest.raises(FfcgsError, match="mesh has no triangles"):
        metrics.mesh_contacts(trimesh.Trimesh(), _bipyramid()[None])
    with pytest.raises(FfcgsError, match="wrenches contains NaN"):
        metrics.epsilon_q1(np.full((8, 6), np.nan))
    with pytest.raises(FfcgsError, match=r"basis must have shape \(6, \*\)"):
        metrics.q_distance_reference(np.ones((3, 6)), basis.T)
    with pytest.raises(FfcgsError, match="normals must be non-zero"):
        metrics.primitive_wrenches(np.zeros((1, 3)), np.zeros((1, 3)), np.zeros(3), 0.1, 0.2, 8)
    with pytest.raises(FfcgsError, match="radius must be"):
        metrics.primitive_wrenches(np.zeros((1, 3)), np.ones((1, 3)), np.zeros(3), -1.0, 0.2, 8)
    with pytest.raises(FfcgsError, match="sphere_basis needs an integer K >= 12"):
        directions.sphere_basis(6)
    with pytest.raises(FfcgsError, match="q_upper must exceed q_lower on every channel.*\\[1\\]"):
        metrics.joint_limit_use(np.zeros((2, 2)), np.zeros(2), np.array([1.0, 0.0]))
    with pytest.raises(FfcgsError, match=r"q must have shape \(3, \*\)"):
        metrics.evaluate(sphere, np.zeros((3, 5, 3)), np.zeros((2, 4)), np.zeros(4), np.ones(4))
    with pytest.raises(FfcgsError, match=r"b must have shape \(3,\)"):
        metrics.wilcoxon([1.0, 2.0, 3.0], [1.0, 2.0])
    with pytest.raises(FfcgsError, match="valid must be a boolean array"):
        metrics.summary({"epsilon": np.zeros(3)}, np.ones(3))
