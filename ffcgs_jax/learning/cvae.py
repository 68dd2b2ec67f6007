"""The learned wrist-pose sampler of the paper (section IV.A, Fig. 2): a CVAE conditioned on the Gradient-SDF.

    features(sdf)            3-D residual U-Net: (R, R, R, 4) -> (R/2)^3 x `features` channels (32x16^3 at R = 32)
    encode(features, g)      FCN: g concatenated to every voxel -> N(mu, sigma) of z (training only)
    decode(features, z)      FCN: z concatenated to every voxel -> g_hat
    sample(sdf, n)           decode with z ~ N(0, I): n wrist poses

Both FCNs are 4 convolutions interleaved with stride-2 max pooling, then a global mean and an MLP head.

Pose vector g (9 numbers), in the grid's normalised frame so one network serves objects of any size and place:
    g[0:3]  palm centre (not the root origin: its error is then independent of the rotation error), as
            (p - grid centre) / grid half-width
    g[3:9]  the first two columns of the rotation. The 6-D representation is continuous (Zhou et al., CVPR 2019):
            every rotation has one representation and nearby rotations nearby ones, which quaternions (q and -q)
            and Euler angles (gimbal jumps) do not give, and a regression target needs. `rotation_6d_to_matrix`
            maps any two non-parallel 3-vectors back to a rotation by Gram-Schmidt.

Exact shortcut: the first FCN convolution sees [features, g broadcast to every voxel]. A convolution is linear, so
that equals conv(features) + sum_j g_j * conv(e_j), where conv(e_j) is the convolution of a one-hot constant field
(it differs from the plain kernel sum only at the zero-padded border). conv(features) runs once per object, the
rest is a (9 x voxels x head) contraction per grasp, so many grasps per object cost little.

Loss (eq. 2-3): the mean distance between the 4 palm-tetrahedron vertices of the true and predicted poses, in
metres, plus beta_t * KL(q(z | g, sdf) || N(0, I)).
"""

import jax
import jax.numpy as jnp
import numpy as np

from ffcgs_jax.learning import layers as nn
from ffcgs_jax.learning.config import ModelConfig
from ffcgs_jax.core.types import Array, Float

POSE_DIM = 9


# ----------------------------------------------------------------------------------------------------------------
# Pose <-> vector
# ----------------------------------------------------------------------------------------------------------------


def rotation_6d_to_matrix(r6: Float[Array, " 6"]) -> Float[Array, "3 3"]:
    """Rotation whose first two columns are the Gram-Schmidt orthonormalisation of r6[:3], r6[3:]."""
    a, b = r6[:3], r6[3:]
    x = a / jnp.sqrt(jnp.sum(a * a) + 1e-12)
    b = b - jnp.sum(x * b) * x
    y = b / jnp.sqrt(jnp.sum(b * b) + 1e-12)
    return jnp.stack([x, y, jnp.cross(x, y)], axis=1)


def grid_frame(origin: Float[Array, " 3"], voxel_size: Float[Array, ""], res: int):
    """Centre (3,) and half-width () of the cube a grid of `res` voxels covers."""
    return origin + voxel_size * (res - 1) / 2, voxel_size * res / 2


def pose_to_vector(pose: Float[Array, "4 4"], palm_root: Float[Array, " 3"], centre: Float[Array, " 3"],
                   half: Float[Array, ""]) -> Float[Array, " 9"]:
    """The network's 9-vector of a wrist pose (world <- hand root); see the module docstring."""
    R = pose[:3, :3]
    palm = R @ palm_root + pose[:3, 3]
    return jnp.concatenate([(palm - centre) / half, R[:, 0], R[:, 1]])


def vector_to_pose(g: Float[Array, " 9"], palm_root: Float[Array, " 3"], centre: Float[Array, " 3"],
                   half: Float[Array, ""]) -> Float[Array, "4 4"]:
    """Inverse of `pose_to_vector` (exact on its image; any 9-vector with non-parallel columns maps to a pose)."""
    R = rotation_6d_to_matrix(g[3:])
    palm = centre + half * g[:3]
    return jnp.eye(4, dtype=g.dtype).at[:3, :3].set(R).at[:3, 3].set(palm - R @ palm_root)


# ----------------------------------------------------------------------------------------------------------------
# Parameters
# ----------------------------------------------------------------------------------------------------------------


def init(key: jax.Array, cfg: ModelConfig) -> dict:
    """Parameters of the U-Net, the encoder and the decoder, a nested dict of float32 arrays."""
    w1, w2, w4 = cfg.width, 2 * cfg.width, 4 * cfg.width
    k = iter(jax.random.split(key, 16))
    unet = {
        "stem": nn.init_conv(next(k), 4, w1),
        "down1": nn.init_conv(next(k), w1, w2), "res1": nn.init_resblock(next(k), w2),
        "down2": nn.init_conv(next(k), w2, w4), "res2": nn.init_resblock(next(k), w4),
        "down3": nn.init_conv(next(k), w4, w4), "res3": nn.init_resblock(next(k), w4),
        "up2": nn.init_conv(next(k), 2 * w4, w4), "res_up2": nn.init_resblock(next(k), w4),
        "up1": nn.init_conv(next(k), w4 + w2, cfg.features),
    }
    params = {"unet": unet, "encoder": _init_fcn(next(k), cfg, POSE_DIM, 2 * cfg.latent),
              "decoder": _init_fcn(next(k), cfg, cfg.latent, POSE_DIM, bias=_DECODER_BIAS)}
    return jax.tree.map(lambda x: jnp.asarray(x, jnp.float32), params)  # float32 whether or not x64 is on


# The decoder starts at the grid centre and the identity rotation: Gram-Schmidt of a near-zero 6-vector would
# give a random, badly conditioned rotation and gradients.
_DECODER_BIAS = np.array([0, 0, 0, 1, 0, 0, 0, 1, 0], np.float32)


def _init_fcn(key: jax.Array, cfg: ModelConfig, c_cond: int, c_out: int, bias=None) -> dict:
    k = jax.random.split(key, 6)
    h = cfg.head
    out = nn.init_dense(k[5], cfg.mlp, c_out, scale=0.01)
    if bias is not None:
        out["b"] = jnp.asarray(bias)
    return {
        "conv0": nn.init_conv(k[0], cfg.features + c_cond, h),
        "conv1": nn.init_conv(k[1], h, h), "conv2": nn.init_conv(k[2], h, h), "conv3": nn.init_conv(k[3], h, h),
        "mlp": nn.init_dense(k[4], h, cfg.mlp), "out": out,
    }


# ----------------------------------------------------------------------------------------------------------------
# Networks (one object's volume at a time; vmapped by the callers)
# ----------------------------------------------------------------------------------------------------------------


def normalise_grid(grid: Float[Array, "R R R 4"], half: Float[Array, ""]) -> Float[Array, "R R R 4"]:
    """Distances in grid half-widths (so about [-1, 1] for any object size); gradients are unit vectors already."""
    return jnp.concatenate([grid[..., :1] / half, grid[..., 1:]], axis=-1)


def features(params: dict, grid: Float[Array, "R R R 4"]) -> Float[Array, "r r r F"]:
    """The U-Net: a normalised (R, R, R, 4) Gradient-SDF to its (R/2)^3 x F feature volume."""
    p = params["unet"]
    x = nn.conv(p["stem"], grid[None])
    s1 = nn.resblock(p["res1"], nn.conv(p["down1"], jax.nn.silu(x), 2))  # R/2
    s2 = nn.resblock(p["res2"], nn.conv(p["down2"], jax.nn.silu(s1), 2))  # R/4
    s3 = nn.resblock(p["res3"], nn.conv(p["down3"], jax.nn.silu(s2), 2))  # R/8
    u2 = nn.conv(p["up2"], jax.nn.silu(jnp.concatenate([nn.upsample(s3), s2], -1)))
    u2 = nn.resblock(p["res_up2"], u2)  # R/4
    u1 = nn.conv(p["up1"], jax.nn.silu(jnp.concatenate([nn.upsample(u2), s1], -1)))  # R/2
    return u1[0]


def fcn_base(p: dict, feats: Float[Array, "r r r F"]) -> tuple[Float[Array, "r r r H"], Float[Array, "K r r r H"]]:
    """The per-object part of an FCN's first convolution (see the module docstring): conv of the features, and
    conv of each one-hot constant conditioning channel. Both depend on the object and the weights, not on g or z."""
    n_feat = feats.shape[-1]
    w = p["conv0"]["w"]
    a = nn.conv({"w": w[..., :n_feat, :], "b": p["conv0"]["b"]}, feats[None])[0]
    k = w.shape[-2] - n_feat
    onehot = jnp.broadcast_to(jnp.eye(k, dtype=feats.dtype)[:, None, None, None, :], (k, *feats.shape[:3], k))
    b = nn.conv({"w": w[..., n_feat:, :], "b": jnp.zeros_like(p["conv0"]["b"])}, onehot)
    return a, b


def fcn_head(p: dict, base: tuple, cond: Float[Array, " K"]) -> Float[Array, " O"]:
    """An FCN for one conditioning vector, from its `fcn_base`: four convolutions with max pooling, mean, MLP."""
    a, b = base
    x = a + jnp.einsum("k,kdhwc->dhwc", cond.astype(a.dtype), b)
    x = nn.max_pool(jax.nn.silu(x)[None])
    for name in ("conv1", "conv2", "conv3"):
        x = nn.max_pool(jax.nn.silu(nn.conv(p[name], x)))
    x = jnp.mean(x[0], axis=(0, 1, 2))
    return nn.dense(p["out"], jax.nn.silu(nn.dense(p["mlp"], x)))


def encode(params: dict, base: tuple, g: Float[Array, " 9"]) -> tuple[Float[Array, " Z"], Float[Array, " Z"]]:
    """mu and log sigma^2 of q(z | g, object), from the encoder's `fcn_base`."""
    out = fcn_head(params["encoder"], base, g)
    z = out.shape[0] // 2
    return out[:z], jnp.clip(out[z:], -12.0, 6.0)  # keeps exp() finite early in training


def decode(params: dict, base: tuple, z: Float[Array, " Z"]) -> Float[Array, " 9"]:
    return fcn_head(params["decoder"], base, z)


def kl_divergence(mu: Float[Array, " Z"], logvar: Float[Array, " Z"]) -> Float[Array, ""]:
    """KL(N(mu, diag exp(logvar)) || N(0, I)), nats."""
    return 0.5 * jnp.sum(mu * mu + jnp.exp(logvar) - 1.0 - logvar)


def tetrahedron_error(pose: Float[Array, "4 4"], pose_hat: Float[Array, "4 4"],
                      tet_root: Float[Array, "4 3"]) -> Float[Array, ""]:
    """Eq. 3: mean Euclidean distance (m) between the palm tetrahedron's vertices under the two poses."""
    a = tet_root @ pose[:3, :3].T + pose[None, :3, 3]
    b = tet_root @ pose_hat[:3, :3].T + pose_hat[None, :3, 3]
    return jnp.mean(jnp.sqrt(jnp.sum((a - b) ** 2, axis=-1) + 1e-12))


def beta(step, total_steps, beta_max: float, cycles: int, ramp: float):
    """Cyclical annealing: within each of `cycles` equal cycles beta rises linearly from 0 to beta_max over the first
    `ramp` fraction, then holds (Fu et al. 2019). `step` and `total_steps` may be traced."""
    period = jnp.maximum(jnp.asarray(total_steps, jnp.float32) / cycles, 1.0)
    tau = jnp.mod(jnp.asarray(step, jnp.float32), period) / period
    return beta_max * jnp.minimum(tau / ramp, 1.0)


def sample_vectors(params: dict, grid: Float[Array, "R R R 4"], half: Float[Array, ""], key: jax.Array, n: int,
                   latent: int) -> Float[Array, "B 9"]:
    """n pose vectors for one object, z ~ N(0, I) (the encoder is not used)."""
    z = jax.random.normal(key, (n, latent), dtype=grid.dtype)
    return decode_many(params, decoder_base(params, grid, half), z)


def decoder_base(params: dict, grid: Float[Array, "R R R 4"], half: Float[Array, ""]) -> tuple:
    """The per-object part of sampling: the U-Net's features and the decoder's `fcn_base`."""
    return fcn_base(params["decoder"], features(params, normalise_grid(grid, half)))


def decode_many(params: dict, base: tuple, z: Float[Array, "B Z"]) -> Float[Array, "B 9"]:
    """Pose vectors for latent codes z, from `decoder_base`."""
    # Chunks bound the memory: each candidate's first layer is a full (R/2)^3 x head volume, 0.5 MB at R = 32, so
    # 65536 poses x 4 candidates at once would need 128 GB.
    return jax.lax.map(lambda zz: decode(params, base, zz), z, batch_size=_DECODE_CHUNK)


_DECODE_CHUNK = 1024


def apply(params: dict, grid: Float[Array, "R R R 4"], half: Float[Array, ""], g: Float[Array, "K 9"],
          key: jax.Array) -> tuple[Float[Array, "K 9"], Float[Array, "K Z"], Float[Array, "K Z"]]:
    """Training forward for one object and K of its grasps: reconstructions g_hat, and mu, log sigma^2 of z."""
    feats = features(params, normalise_grid(grid, half))
    enc, dec = fcn_base(params["encoder"], feats), fcn_base(params["decoder"], feats)
    mu, logvar = jax.vmap(lambda gg: encode(params, enc, gg))(g)
    z = mu + jnp.exp(0.5 * logvar) * jax.random.normal(key, mu.shape, mu.dtype)
    return jax.vmap(lambda zz: decode(params, dec, zz))(z), mu, logvar
