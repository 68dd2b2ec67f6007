"""The final projection (`synthesis.project`): a fingertip sunk into a ball comes back to its surface, batched equals
a loop of singles, and a grasp that does not penetrate is not moved."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ffcgs_jax.core.config import from_dict
from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.geometry import sdf as S
from ffcgs_jax.hand import kinematics as K
from ffcgs_jax.synthesis import filters as F
from ffcgs_jax.synthesis.config import GraspConfig
from ffcgs_jax.synthesis.energy import fingertip_contacts
from ffcgs_jax.synthesis.project import project, project_batch

from paths import DATA

TOY = DATA / "toy_hand" / "toy.toml"  # two fingers, two channels: MJX compiles fast
R = 0.02  # m, the ball's radius
SUNK = 0.003  # m the fingertip starts inside the ball
TOL = 3e-4  # m: the ball's grid is exact up to its trilinear blend of curvature (about h^2 / 8R = 0.04 mm)
STEPS = 8


@pytest.fixture(scope="module")
def toy():
    return K.load_hand(TOY)


def ball_grid(centre: np.ndarray, h: float = 0.0025, res: int = 64) -> S.GradientSDF:
    """A ball of radius R at `centre` as an exact-distance grid (first-order corners: d and its unit gradient),
    the table far below."""
    origin = centre - h * (res - 1) / 2
    ijk = np.stack(np.meshgrid(*(np.arange(res),) * 3, indexing="ij"), -1)
    p = origin + h * ijk - centre
    n = np.linalg.norm(p, axis=-1, keepdims=True)
    grid = np.concatenate([n - R, p / np.maximum(n, 1e-12)], -1)
    return S.with_cells(S.GradientSDF(jnp.asarray(grid, jnp.float32), jnp.asarray(origin, jnp.float32),
                                      jnp.asarray(h, jnp.float32), jnp.asarray(-10.0, jnp.float32)))


@functools.partial(jax.jit, static_argnums=2)
def tip_and_jacobian(hand, q, t: int):
    """Finger a's fingertip sphere t: its centre and d centre / d q, at the identity wrist."""
    tip = lambda x: K.fingertip_spheres(hand, K.forward_kinematics(hand, jnp.eye(4), x))[0][0, t]  # noqa: E731
    return tip(q), jax.jacfwd(tip)(q)


def sunk_tip(toy, depth: float):
    """(ball grid, q) with finger a's largest fingertip sphere `depth` metres into a ball placed along the
    direction channel a moves it (so opening the finger backs it out), the wrist at the identity."""
    q = 0.5 * (toy.lower + toy.upper)
    radii = np.asarray(toy.tip_radius[0])
    t = int(np.argmax(radii))
    c, J = tip_and_jacobian(toy, q, t)
    c, u = np.asarray(c, np.float64), np.asarray(J[:, 0], np.float64)
    u = u / np.linalg.norm(u)
    return ball_grid(c + u * (R + radii[t] - depth)), q


measure = jax.jit(lambda hand, sdf, q: (
    F.hand_penetration(hand, sdf, jnp.eye(4), q)[0],
    fingertip_contacts(hand, sdf, K.forward_kinematics(hand, jnp.eye(4), q)).gaps))
run = jax.jit(project, static_argnums=4)  # allow traced: one compile for every allowance
run_batch = jax.jit(project_batch, static_argnums=4)


@pytest.mark.e2e  # over 20 s on the 2-core CPU: kept out of plain `pytest` (README)
def test_a_fingertip_3mm_inside_a_ball_ends_on_its_surface(toy):
    sdf, q = sunk_tip(toy, SUNK)
    pen0, gaps0 = measure(toy, sdf, q)
    assert float(pen0) == pytest.approx(SUNK, abs=TOL)  # the set-up: only that sphere sinks, by 3 mm
    assert float(gaps0[0]) == pytest.approx(-SUNK, abs=TOL)
    q1 = run(toy, sdf, jnp.eye(4), q, STEPS, 0.0)
    pen1, gaps1 = measure(toy, sdf, q1)
    assert float(pen1) <= TOL  # out of the ball ...
    assert abs(float(gaps1[0])) <= TOL  # ... and on its surface, still touching: the known answer
    assert float(gaps1[1]) == pytest.approx(float(gaps0[1]), abs=1e-5)  # the other finger, hovering, stays
    assert float(q1[0]) < float(q[0])  # the finger opened: the ball sits where closing it moves the tip


@pytest.mark.e2e  # about 30 s on the 2-core CPU: kept out of plain `pytest` (README)
def test_an_allowance_leaves_that_much_overlap(toy):
    sdf, q = sunk_tip(toy, SUNK)
    q1 = run(toy, sdf, jnp.eye(4), q, STEPS, 0.001)
    pen1, _ = measure(toy, sdf, q1)
    assert float(pen1) == pytest.approx(0.001, abs=TOL)  # lifted to the allowance, not past it


@pytest.mark.e2e  # 25-38 s on the 2-core CPU: kept out of plain `pytest` (README)
def test_a_grasp_that_does_not_penetrate_is_not_moved(toy):
    for depth in (-0.004, -0.0005, -0.0001):  # hovering 4 mm, 0.5 mm off, touching 0.1 mm off
        sdf, q = sunk_tip(toy, depth)
        assert float(measure(toy, sdf, q)[0]) == 0.0  # the set-up: no sphere overlaps
        q1 = run(toy, sdf, jnp.eye(4), q, STEPS, 0.0)
        np.testing.assert_allclose(np.asarray(q1), np.asarray(q), atol=1e-6, err_msg=f"tip {depth} m off")
    sdf, q = sunk_tip(toy, 0.0008)  # 0.8 mm in, 1 mm allowed
    np.testing.assert_allclose(np.asarray(run(toy, sdf, jnp.eye(4), q, STEPS, 0.001)), np.asarray(q), atol=1e-6)
    assert np.array_equal(np.asarray(run(toy, sdf, jnp.eye(4), q, 0, 0.0)), np.asarray(q))  # 0 steps: as given


@pytest.mark.e2e  # over 20 s on the 2-core CPU: kept out of plain `pytest` (README)
def test_batched_equals_a_loop_of_singles(toy):
    sdf, q = sunk_tip(toy, SUNK)
    qs = jnp.stack([q, q + jnp.array([0.05, 0.0]), q - jnp.array([0.3, 0.2]), q + jnp.array([0.02, 0.1])])
    Hs = jnp.stack([jnp.eye(4)] * 4).at[1, 0, 3].set(0.001)  # one wrist shifted 1 mm: its own pose is used
    batched = np.asarray(run_batch(toy, sdf, Hs, qs, STEPS, 0.0))
    loop = np.stack([np.asarray(run(toy, sdf, H, x, STEPS, 0.0)) for H, x in zip(Hs, qs)])
    np.testing.assert_allclose(batched, loop, atol=1e-6)
    assert not np.allclose(batched[0], np.asarray(qs[0]), atol=1e-3)  # the batch did project (the sunk one moved)


def test_the_projection_settings_are_checked_in_one_line():
    """As a TOML or the command line hands them over (`core.config.from_dict`, which checks)."""
    for field, bad in (("project_steps", -1), ("project_steps", 2.5), ("project_allow", 0.02),
                       ("project_allow", -0.001)):
        with pytest.raises(FfcgsError, match=f"optim.{field} must be"):
            from_dict(GraspConfig, {"optim": {field: bad}})
    assert from_dict(GraspConfig, {"optim": {"project_steps": 5}}).optim.project_steps == 5
