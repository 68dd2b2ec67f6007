"""The CVAE sampler network (`cvae.py`, `layers.py`), its Adam (`kernels/adam.py`) and checkpoints, against
float64 references and finite differences."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.learning import checkpoint, cvae
from ffcgs_jax.learning import layers as nn
from ffcgs_jax.learning.config import ModelConfig
from ffcgs_jax.kernels.adam import adam_init, adam_update

from cvae_toy import sphere_grid

CFG = ModelConfig(res=8, width=2, features=4, head=4, mlp=8, latent=2)


@pytest.fixture(scope="module")
def params():
    p = cvae.init(jax.random.key(0), CFG)
    # Non-zero residual branches and output heads: the zero/small init would hide errors in those paths.
    leaves, tree = jax.tree.flatten(p)
    keys = jax.random.split(jax.random.key(1), len(leaves))
    return jax.tree.unflatten(tree, [x.astype(jnp.float64) + 0.1 * jax.random.normal(k, x.shape, jnp.float64)
                                     for x, k in zip(leaves, keys)])


@pytest.fixture(scope="module")
def grid():
    g, origin, h = sphere_grid(0.04, np.array([0.0, 0.0, 0.04]), CFG.res)
    return jnp.asarray(g, jnp.float64), jnp.asarray(origin), jnp.asarray(h)


def random_pose(rng):
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                  [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                  [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, rng.normal(0, 0.05, 3)
    return T


def test_shapes(params, grid):
    g, origin, h = grid
    feats = cvae.features(params, g)
    assert feats.shape == (CFG.res // 2,) * 3 + (CFG.features,)
    half = h * CFG.res / 2
    gs = jnp.asarray(np.random.default_rng(0).normal(size=(5, 9)))
    g_hat, mu, logvar = cvae.apply(params, g, half, gs, jax.random.key(0))
    assert g_hat.shape == (5, 9) and mu.shape == logvar.shape == (5, CFG.latent)
    v = cvae.sample_vectors(params, g, half, jax.random.key(1), 7, CFG.latent)
    assert v.shape == (7, 9) and bool(jnp.all(jnp.isfinite(v)))
    assert nn.num_params(params) == sum(x.size for x in jax.tree.leaves(params))


def test_first_layer_shortcut_equals_concatenated_convolution(params, grid):
    """conv([features, broadcast g]) computed directly == conv(features) + sum_j g_j conv(e_j)."""
    g, _, h = grid
    feats = cvae.features(params, g)
    p = params["encoder"]
    cond = jnp.asarray(np.random.default_rng(2).normal(size=9))
    full = jnp.concatenate([feats, jnp.broadcast_to(cond, feats.shape[:3] + (9,))], -1)
    direct = nn.conv(p["conv0"], full[None])[0]
    a, b = cvae.fcn_base(p, feats)
    shortcut = a + jnp.einsum("k,kdhwc->dhwc", cond, b)
    np.testing.assert_allclose(shortcut, direct, rtol=1e-10, atol=1e-12)


def test_conv_matches_numpy_reference():
    rng = np.random.default_rng(3)
    x = rng.normal(size=(1, 5, 4, 3, 2))
    p = {"w": rng.normal(size=(3, 3, 3, 2, 3)), "b": rng.normal(size=3)}
    y = np.asarray(nn.conv(jax.tree.map(jnp.asarray, p), jnp.asarray(x)))
    xp = np.pad(x[0], ((1, 1), (1, 1), (1, 1), (0, 0)))
    ref = np.zeros((5, 4, 3, 3))
    for i in range(5):
        for j in range(4):
            for k in range(3):
                ref[i, j, k] = np.einsum("abcd,abcde->e", xp[i:i + 3, j:j + 3, k:k + 3], p["w"]) + p["b"]
    np.testing.assert_allclose(y[0], ref, rtol=1e-10, atol=1e-12)
    y2 = np.asarray(nn.conv(jax.tree.map(jnp.asarray, p), jnp.asarray(x), stride=2))
    # SAME with stride 2 pads (k - 1 + odd(n)) ... split low-first, so the windows centre on even voxels of odd
    # sizes and odd voxels of even sizes
    np.testing.assert_allclose(y2[0], ref[0::2, 1::2, 0::2], rtol=1e-10, atol=1e-12)


def test_pose_vector_round_trip_and_6d_rotation():
    rng = np.random.default_rng(4)
    palm = jnp.asarray([0.01, -0.02, 0.08])
    centre, half = jnp.asarray([0.0, 0.1, 0.05]), jnp.asarray(0.12)
    for _ in range(5):
        T = jnp.asarray(random_pose(rng))
        v = cvae.pose_to_vector(T, palm, centre, half)
        np.testing.assert_allclose(cvae.vector_to_pose(v, palm, centre, half), T, atol=1e-10)
        # any two non-parallel vectors give a proper rotation
        R = np.asarray(cvae.rotation_6d_to_matrix(jnp.asarray(rng.normal(size=6))))
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-10)  # the sqrt guard: 1e-12
        assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-10)


def test_kl_matches_closed_form_reference():
    rng = np.random.default_rng(5)
    mu, logvar = rng.normal(size=3), rng.normal(size=3)
    var = np.exp(logvar)
    # KL(N(mu, var) || N(0, 1)) per dimension = log(1 / sd) + (var + mu^2) / 2 - 1/2
    ref = np.sum(-0.5 * logvar + (var + mu**2) / 2 - 0.5)
    assert float(cvae.kl_divergence(jnp.asarray(mu), jnp.asarray(logvar))) == pytest.approx(ref, rel=1e-12)
    assert float(cvae.kl_divergence(jnp.zeros(2), jnp.zeros(2))) == 0.0


def test_tetrahedron_error():
    tet = jnp.asarray(np.random.default_rng(6).normal(0, 0.04, (4, 3)))
    T = jnp.asarray(random_pose(np.random.default_rng(7)))
    assert float(cvae.tetrahedron_error(T, T, tet)) == pytest.approx(0.0, abs=1e-5)  # the sqrt guard
    shifted = T.at[:3, 3].add(jnp.asarray([0.03, 0.0, 0.04]))
    assert float(cvae.tetrahedron_error(T, shifted, tet)) == pytest.approx(0.05, rel=1e-6)


@pytest.mark.parametrize("step, want", [(0, 0.0), (25, 0.0025), (50, 0.005), (99, 0.005), (100, 0.0),
                                        (125, 0.0025), (399, 0.005)])
def test_beta_schedule_values(step, want):
    """400 steps, 4 cycles of 100, beta ramps over the first half of each: 0 -> 0.005 at step 50, then holds."""
    assert float(cvae.beta(step, 400, 0.005, 4, 0.5)) == pytest.approx(want, abs=1e-9)


def test_apply_batched_equals_loop(params, grid):
    g, _, h = grid
    half = h * CFG.res / 2
    gs = jnp.asarray(np.random.default_rng(8).normal(size=(3, 9)))
    key = jax.random.key(3)
    g_hat, mu, logvar = cvae.apply(params, g, half, gs, key)
    feats = cvae.features(params, cvae.normalise_grid(g, half))
    enc, dec = cvae.fcn_base(params["encoder"], feats), cvae.fcn_base(params["decoder"], feats)
    eps = jax.random.normal(key, mu.shape, mu.dtype)
    for i in range(3):
        m, lv = cvae.encode(params, enc, gs[i])
        np.testing.assert_allclose(m, mu[i], rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(cvae.decode(params, dec, m + jnp.exp(0.5 * lv) * eps[i]), g_hat[i], rtol=1e-10,
                                   atol=1e-12)


def test_loss_gradient_matches_finite_differences(params, grid):
    """d loss / d params along random directions, central differences in float64."""
    from ffcgs_jax.training.train import batch_loss

    g, origin, h = grid
    rng = np.random.default_rng(9)
    pose = jnp.asarray(np.stack([random_pose(rng) for _ in range(2)]))[None]
    pose = pose.at[..., :3, 3].multiply(0.3)
    palm, tet = jnp.asarray([0.0, 0.0, 0.08]), jnp.asarray(rng.normal(0, 0.04, (4, 3)))
    args = (g[None], origin[None], h[None], pose, jax.random.key(4), 0.005, palm, tet)

    @jax.jit
    def f(p):
        return batch_loss(p, *args)[0]

    grads = jax.jit(jax.grad(f))(params)
    leaves, tree = jax.tree.flatten(params)
    for trial in range(3):
        d = [jnp.asarray(np.random.default_rng(10 + trial).normal(size=x.shape)) for x in leaves]
        direction = jax.tree.unflatten(tree, d)
        eps = 1e-6
        plus = f(jax.tree.map(lambda p, v: p + eps * v, params, direction))
        minus = f(jax.tree.map(lambda p, v: p - eps * v, params, direction))
        fd = (plus - minus) / (2 * eps)
        an = sum(jnp.sum(a * b) for a, b in zip(jax.tree.leaves(grads), d))
        assert float(an) == pytest.approx(float(fd), rel=1e-5, abs=1e-9)


def test_adam_matches_float64_reference_step():
    rng = np.random.default_rng(11)
    p = {"a": rng.normal(size=(3, 2)), "b": {"c": rng.normal(size=4)}}
    grads = [jax.tree.map(lambda x: rng.normal(size=x.shape), p) for _ in range(3)]
    lr, b1, b2, eps = 1e-3, 0.9, 0.999, 1e-8
    state = adam_init(jax.tree.map(jnp.asarray, p))
    params = jax.tree.map(jnp.asarray, p)
    m = jax.tree.map(np.zeros_like, p)
    v = jax.tree.map(np.zeros_like, p)
    ref = p
    for t, g in enumerate(grads, start=1):
        upd, state = adam_update(jax.tree.map(jnp.asarray, g), state, lr, b1, b2, eps)
        params = jax.tree.map(jnp.add, params, upd)
        m = jax.tree.map(lambda a, b: b1 * a + (1 - b1) * b, m, g)
        v = jax.tree.map(lambda a, b: b2 * a + (1 - b2) * b * b, v, g)
        ref = jax.tree.map(lambda x, mm, vv: x - lr * (mm / (1 - b1**t)) / (np.sqrt(vv / (1 - b2**t)) + eps), ref, m,
                           v)
        jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-15), params, ref)
    assert int(state.count) == 3


def test_checkpoint_round_trip(tmp_path, params):
    meta = {"epoch": 3, "note": "x"}
    path = checkpoint.save(tmp_path / "c.npz", {"params": params, "opt": {"count": np.int32(5)}}, meta)
    tree, meta2 = checkpoint.load(path)
    assert meta2 == meta
    jax.tree.map(lambda a, b: np.testing.assert_array_equal(np.asarray(a), b), params, tree["params"])
    assert int(tree["opt"]["count"]) == 5
    assert not (tmp_path / "c.npz.tmp").exists()


def test_checkpoint_bad_input(tmp_path):
    with pytest.raises(FfcgsError, match="not found"):
        checkpoint.load(tmp_path / "missing.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(FfcgsError, match="not a readable"):
        checkpoint.load(tmp_path / "junk.npz")
    np.savez(tmp_path / "plain.npz", a=np.zeros(2))
    with pytest.raises(FfcgsError, match="not an ffcgs checkpoint"):
        checkpoint.load(tmp_path / "plain.npz")
    with pytest.raises(FfcgsError, match="without '/'"):
        checkpoint.save(tmp_path / "x.npz", {"a/b": np.zeros(1)})
