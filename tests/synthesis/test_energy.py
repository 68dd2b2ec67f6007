"""The grasp energy (eq. 5, 12, 13 of the paper) against float64 NumPy formulas and central differences.

Fixture: the two-finger toy hand at the identity wrist pose above the built-in ball (radius 3.5 cm, centre 3.5 cm
above the table): both fingertip sites lie about 6 mm outside the surface (their spheres' skins 1.4 and 2.1 cm
inside), on different normals, so E_g > 0 (two point contacts never reach force closure), the LP solves and E is
smooth in q. Everything is jitted (one compile per
config): eager MJX costs more here than compiling.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ffcgs_jax.geometry import mesh_io
from ffcgs_jax.geometry import sdf as sdf_mod
from ffcgs_jax.geometry.config import SDFConfig
from ffcgs_jax.hand import kinematics as K
from ffcgs_jax.kernels import quality
from ffcgs_jax.synthesis import energy as En
from ffcgs_jax.synthesis import filters as F
from ffcgs_jax.synthesis.config import EnergyConfig

TOY = "tests/data/toy_hand/toy.toml"
TOY_LOWER, TOY_UPPER = np.array([0.0, 0.0]), np.array([1.2, 1.0])  # written out from toy.toml, not read back
Q = np.array([0.3, 0.4])  # a generic channel vector inside the toy's limits
RTOL_FORMULA = 1e-9  # the same float64 formula evaluated two ways
RTOL_FD = 1e-4  # central differences with step 3e-4 rad; the LP is solved to 1e-7 (lp_host.EPS_ABS)
FD_STEP = 3e-4

D0 = 0.004
CFG_W = EnergyConfig(a_c=3.0, a_q=0.7, a_pen=200.0, d0=D0, a_m=0.0)  # margin: elsewhere  # every term on, odd weights
CFG_SMOOTH = EnergyConfig(a_c=0.0, a_pen=0.0, a_m=0.0, normal_grad=True)  # E_g + 0.5 E_q: JAX's own derivatives only
CFG_FIXED = EnergyConfig(a_c=0.0, a_pen=0.0, a_m=0.0, normal_grad=False)
CFG_C1 = EnergyConfig(a_c=1.0, a_pen=0.0, a_m=0.0, normal_grad=True, d0=D0)  # CFG_SMOOTH + E_c (with d0)

energy_jit = jax.jit(En.energy, static_argnums=4)
value_and_grad = jax.jit(jax.value_and_grad(En.energy, argnums=3, has_aux=True), static_argnums=4)
fk_jit = jax.jit(K.forward_kinematics)
spheres_jit = jax.jit(lambda hand, H, q: K.fingertip_spheres(hand, K.forward_kinematics(hand, H, q)))
query_jit = jax.jit(sdf_mod.query)
distance_jit = jax.jit(sdf_mod.distance)


def tips_reference(hand, target, H, q):
    """NumPy: per fingertip, the candidate sphere whose skin is nearest to the surface (index k), its gap, normal
    and skin point (the contact)."""
    centres, radii = (np.asarray(a) for a in spheres_jit(hand, H, q))
    C, T = radii.shape
    gaps = np.asarray(distance_jit(target.sdf, jnp.asarray(centres.reshape(-1, 3)))).reshape(C, T) - radii
    k = gaps.argmin(axis=1)
    centre, r = centres[np.arange(C), k], radii[np.arange(C), k]
    n = np.asarray(query_jit(target.sdf, jnp.asarray(centre))[1])
    return {"k": k, "gap": gaps[np.arange(C), k], "n": n, "point": centre - r[:, None] * n, "centre": centre}


def centre_jacobian(hand, H, q, k, step=1e-6):
    """(C, 3, Q) central differences of the chosen spheres' centres (k held fixed), float64."""
    def centres(x):
        c = np.asarray(spheres_jit(hand, H, jnp.asarray(x))[0])
        return c[np.arange(len(k)), k]
    q = np.asarray(q)
    return np.stack([(centres(q + step * e) - centres(q - step * e)) / (2 * step) for e in np.eye(len(q))], -1)


@pytest.fixture(scope="module")
def toy():
    hand = K.load_hand(TOY)
    target = En.make_target(sdf_mod.build_sdf(mesh_io.load_mesh("ball"), SDFConfig(res=16)))
    return hand, target, jnp.eye(4)


# ---------------------------------------------------------------------------------------------------------------
# E_c and E_q as formulas
# ---------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("d0", [0.0, 0.005, -0.003])
def test_contact_energy_is_rms_of_offset_distances(d0):
    d = np.random.default_rng(0).uniform(-0.02, 0.05, 5)
    expected = np.sqrt(np.mean((d + d0) ** 2))
    np.testing.assert_allclose(float(En.contact_energy(jnp.asarray(d), d0)), expected, rtol=RTOL_FORMULA)


def test_contact_energy_gradient_finite_when_every_tip_is_at_minus_d0():
    d0 = 0.005
    g = jax.grad(En.contact_energy)(jnp.full(5, -d0), d0)
    assert np.isfinite(np.asarray(g)).all()
    assert float(En.contact_energy(jnp.full(5, -d0), d0)) < 1e-5


def test_joint_energy_matches_eq13(toy):
    hand = toy[0]
    mid, span = (TOY_LOWER + TOY_UPPER) / 2, TOY_UPPER - TOY_LOWER
    for q in (np.random.default_rng(1).uniform(TOY_LOWER, TOY_UPPER), TOY_LOWER, TOY_UPPER, mid):
        expected = np.mean(((q - mid) / span) ** 2)
        np.testing.assert_allclose(float(En.joint_energy(hand, jnp.asarray(q))), expected, rtol=RTOL_FORMULA,
                                   atol=1e-300)
    assert float(En.joint_energy(hand, jnp.asarray(TOY_UPPER))) == pytest.approx(0.25)  # (1/2)^2 at a limit
    # its derivative 2/d (q - q0) / range^2 (eq. 13 as printed lacks one factor of the range)
    np.testing.assert_allclose(np.asarray(jax.grad(lambda x: En.joint_energy(hand, x))(jnp.asarray(Q))),
                               (Q - mid) / span**2, rtol=RTOL_FORMULA)


# ---------------------------------------------------------------------------------------------------------------
# energy(): parts, weights, d0
# ---------------------------------------------------------------------------------------------------------------


def test_energy_terms_sum_with_configured_weights(toy):
    hand, target, H = toy
    q = jnp.asarray(Q)
    E, t = energy_jit(hand, target, H, q, CFG_W)
    assert float(t.P) > 1e-4 and float(t.E_g) > 0.1 and float(t.E_c) > 1e-3 and bool(t.lp_ok)  # all in play
    expected = float(t.E_g) + 3.0 * float(t.E_c) + 0.7 * float(t.E_q) + 200.0 * float(t.P)
    np.testing.assert_allclose(float(E), expected, rtol=RTOL_FORMULA)
    assert float(t.E) == float(E)
    # each part is what its own function gives at the fingertips' skin points
    ref = tips_reference(hand, target, H, q)
    np.testing.assert_allclose(np.asarray(t.contacts), ref["point"], atol=1e-15)
    d = ref["gap"]
    np.testing.assert_allclose(float(t.E_c), np.sqrt(np.mean((d + D0) ** 2)), rtol=1e-7)
    np.testing.assert_allclose(float(t.E_q), float(En.joint_energy(hand, q)), rtol=RTOL_FORMULA)
    np.testing.assert_allclose(float(t.P), float(jax.jit(F.penetration_penalty)(hand, target.sdf, H, q)), rtol=1e-12)


def test_no_penalty_weight_means_no_penalty_term(toy):
    hand, target, H = toy
    (E, t), _ = value_and_grad(hand, target, H, jnp.asarray(Q), CFG_C1)
    assert float(energy_jit(hand, target, H, jnp.asarray(Q), CFG_W)[1].P) > 0  # the hand does penetrate here
    assert float(t.P) == 0.0
    np.testing.assert_allclose(float(E), float(t.E_g) + float(t.E_c) + 0.5 * float(t.E_q), rtol=RTOL_FORMULA)


def test_d0_shifts_contact_energy_as_eq12_says(toy):
    hand, target, H = toy
    q = jnp.asarray(Q)
    d = tips_reference(hand, target, H, q)["gap"]
    (_, t0), _ = value_and_grad(hand, target, H, q, CFG_SMOOTH)  # d0 = 0
    (_, t), _ = value_and_grad(hand, target, H, q, CFG_C1)  # d0 = D0
    np.testing.assert_allclose(float(t0.E_c), np.sqrt(np.mean(d**2)), rtol=1e-7)
    np.testing.assert_allclose(float(t.E_c), np.sqrt(np.mean((d + D0) ** 2)), rtol=1e-7)
    # E_c^2 grows by 2 d0 mean(d) + d0^2, and nothing else moves
    np.testing.assert_allclose(float(t.E_c) ** 2 - float(t0.E_c) ** 2, 2 * D0 * d.mean() + D0**2, rtol=1e-5)
    # the toy's fingertip skins reach into the ball here (gaps -2.1 and -1.4 cm): d0 > 0 moves them towards 0
    assert d.max() < -D0 and float(t.E_c) < float(t0.E_c)
    assert float(t.E_g) == pytest.approx(float(t0.E_g), rel=1e-12) and float(t.E_q) == float(t0.E_q)


# ---------------------------------------------------------------------------------------------------------------
# Gradients
# ---------------------------------------------------------------------------------------------------------------


def test_gradient_matches_central_differences(toy):
    """E_g + a_q E_q: every derivative is JAX's own (the LP's through its custom VJP), so they must agree with
    central differences of E. (E_c and P take the Gradient-SDF's derivative instead: next test.)"""
    hand, target, H = toy
    (E, t), g = value_and_grad(hand, target, H, jnp.asarray(Q), CFG_SMOOTH)
    assert float(t.E_g) > 0.1 and bool(t.lp_ok)  # well inside a smooth piece of E_g
    f = lambda q: float(value_and_grad(hand, target, H, jnp.asarray(q), CFG_SMOOTH)[0][0])  # noqa: E731
    fd = np.array([(f(Q + FD_STEP * e) - f(Q - FD_STEP * e)) / (2 * FD_STEP) for e in np.eye(2)])
    g = np.asarray(g)
    assert np.abs(g).max() > 0.1
    np.testing.assert_allclose(g, fd, rtol=RTOL_FD)


def test_contact_energy_gradient_is_eq12_with_the_gradient_channel(toy):
    """dE_c/dq = sum_i (phi_i + d0) n_i^T J_i / (n E_c) with phi_i the gap of fingertip i's nearest sphere, J_i the
    Jacobian of that sphere's centre and n_i the Gradient-SDF's interpolated gradient channel there (not the
    derivative of the interpolated distance, which jumps between voxels)."""
    hand, target, H = toy
    q = jnp.asarray(Q)
    _, g1 = value_and_grad(hand, target, H, q, CFG_C1)
    _, g0 = value_and_grad(hand, target, H, q, CFG_SMOOTH)
    g = np.asarray(g1) - np.asarray(g0)  # the two differ by 1 * E_c only
    ref = tips_reference(hand, target, H, q)
    d, n = ref["gap"], ref["n"]
    J = centre_jacobian(hand, H, q, ref["k"])  # (C, 3, Q)
    E_c = np.sqrt(np.mean((d + D0) ** 2))
    expected = np.einsum("c,ci,ciq->q", d + D0, n, J) / (len(d) * E_c)
    assert np.abs(expected).max() > 1e-3
    np.testing.assert_allclose(g, expected, rtol=1e-6)


@pytest.mark.e2e  # over 20 s on the 2-core CPU: kept out of plain `pytest` (README)
def test_fixed_normals_change_the_gradient_only_through_the_normals(toy):
    """normal_grad=False is the gradient of E_g(c(q), n held at the current q) + a_q E_q; True differs from it."""
    hand, target, H = toy
    q = jnp.asarray(Q)
    (E_on, _), g_on = value_and_grad(hand, target, H, q, CFG_SMOOTH)
    (E_off, _), g_off = value_and_grad(hand, target, H, q, CFG_FIXED)
    ref = tips_reference(hand, target, H, q)
    n_fixed, offset, k = jnp.asarray(ref["n"]), jnp.asarray(ref["point"] - ref["centre"]), jnp.asarray(ref["k"])

    @jax.jit
    def fixed(x):  # the chosen spheres' centres move with x; their skin offsets and normals are held
        centres, _ = K.fingertip_spheres(hand, K.forward_kinematics(hand, H, x))
        c = jnp.take_along_axis(centres, k[:, None, None], axis=1)[:, 0] + offset
        E_g, _ = quality.q_distance(c, n_fixed, target.centre, target.radius,
                                    CFG_FIXED.lp_friction, CFG_FIXED.cone_edges, CFG_FIXED.basis_size)
        return E_g + CFG_FIXED.a_q * En.joint_energy(hand, x)

    g_on, g_off = np.asarray(g_on), np.asarray(g_off)
    np.testing.assert_allclose(g_off, np.asarray(jax.grad(fixed)(q)), rtol=1e-9)
    assert np.isfinite(g_on).all() and np.isfinite(g_off).all()
    assert np.abs(g_on - g_off).max() > 0.1 * np.abs(g_on).max()
    assert float(E_on) == pytest.approx(float(E_off), rel=1e-12)  # the value does not depend on the switch


def test_far_from_the_object_energy_and_gradient_stay_finite(toy):
    """Tips a metre outside the grid: distances extend linearly, normals point back; nothing is NaN."""
    hand, target, _ = toy
    H = jnp.eye(4).at[:3, 3].set(jnp.array([1.0, 0.0, 0.5]))
    (E, t), g = value_and_grad(hand, target, H, jnp.asarray(Q), CFG_C1)
    assert np.isfinite(float(E)) and np.isfinite(np.asarray(g)).all()
    assert float(t.E_c) > 0.9  # about a metre away
