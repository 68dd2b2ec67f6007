"""The grasp-success predictor: the probability that a grasp passes each physics protocol, from what the synthesis
already knows, in the same call.

    grasp_inputs(arrays)                    host: the per-grasp numbers a GraspSet (or a labelled record) carries
    features(hand, sdf, pose, q, contacts, inputs)   one grasp's feature vector (pure JAX)
    logits(params, x) / predict(...)        the network: features -> one logit per head

Features of one grasp, all in the object's grid frame (centre and half-width of the SDF cube, so one network serves
objects of any size), z up as in the physics test:
    - per fingertip contact: position, the SDF's distance and normal there, and the distance on a 3x3x3 stencil of
      `STENCIL_STEP` around it (the local shape the finger presses on: curvature, edges, a rim);
    - per collision sphere of the hand (152 on the SVH): its clearance to the object, sdf(centre) - radius (palm
      and phalanx contacts, near misses), and the lowest sphere's height above the table;
    - the wrist rotation, the palm's position and normal, the channels within their limits, the squeeze direction;
    - the analytic metrics of the synthesis (`METRICS`, and each fingertip's contact distance);
    - the object's size (the cube's half-width) and the table's height in the cube.
Metrics and distances pass through asinh(x / scale): linear near 0, logarithmic in the tails (E spans 1e-3..1e4).

The network is an MLP over the standardised features (mean and scale of the training set, stored with the weights,
never trained), SiLU, one logit per head: each protocol of the training data, then "all" (passed every one of
them), which is what `GraspSet.order` ranks by (`pred_success`). Params are nested dicts of arrays (no flax).
"""

import jax
import jax.numpy as jnp
import numpy as np

from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.geometry import sdf as sdf_mod
from ffcgs_jax.hand import kinematics as K
from ffcgs_jax.learning import layers as nn
from ffcgs_jax.core.types import Array, Float

METRICS = {"epsilon": 0.01, "E": 0.1, "E_g": 0.01, "E_c": 0.001, "E_q": 0.1, "E_m": 0.01, "support_min": 0.01,
           "penetration": 0.001, "table_penetration": 0.001}
"""Per-grasp analytic figures the predictor reads, with the scale of their asinh transform."""
FLAGS = ("valid", "force_closure")
STENCIL_STEP = 0.006  # m: about a fingertip's radius, 1.5 voxels of a 13 cm object's grid
_STENCIL = np.stack(np.meshgrid(*[np.arange(-1.0, 2.0)] * 3, indexing="ij"), -1).reshape(-1, 3)
FEATURE_VERSION = 1
"""Bumped whenever `features` changes: weights record it and are refused by another version."""


def input_width(hand) -> int:
    """Columns of `grasp_inputs` for `hand`: the metrics, the flags, the fingertips touching, per-tip distances,
    the squeeze direction."""
    return len(METRICS) + len(FLAGS) + 1 + len(hand.spec.contact_sites) + hand.lower.shape[0]


def grasp_inputs(arrays: dict, n_tips: int) -> np.ndarray:
    """(G, input_width) float64 from a GraspSet's arrays or a labelled record's: the raw numbers `features` reads
    besides the pose, channels and contacts. Missing metrics (older files) are refused: a prediction from made-up
    numbers would be a silent wrong answer."""
    missing = [k for k in (*METRICS, *FLAGS, "n_contacts", "contact_dist", "squeeze_dir") if k not in arrays]
    if missing:
        raise FfcgsError(f"the grasps lack {', '.join(missing)}, which the success predictor reads; synthesize them "
                         "again with this version")
    cols = [np.asarray(arrays[k], np.float64)[:, None] for k in (*METRICS, *FLAGS)]
    cols.append(np.asarray(arrays["n_contacts"], np.float64)[:, None] / n_tips)
    cols += [np.asarray(arrays["contact_dist"], np.float64), np.asarray(arrays["squeeze_dir"], np.float64)]
    return np.nan_to_num(np.concatenate(cols, axis=1), nan=0.0, posinf=1e6, neginf=-1e6)


def _scales(hand) -> np.ndarray:
    c = len(hand.spec.contact_sites)
    return np.concatenate([list(METRICS.values()), np.ones(len(FLAGS) + 1), np.full(c, 0.001),
                           np.ones(hand.lower.shape[0])])


def features(hand: K.Hand, sdf: sdf_mod.GradientSDF, pose: Float[Array, "4 4"], q: Float[Array, " Q"],
             contacts: Float[Array, "C 3"], inputs: Float[Array, " M"]) -> Float[Array, " F"]:
    """One grasp's feature vector (module docstring); `inputs` is its row of `grasp_inputs`."""
    dt = sdf.grid.dtype
    res = sdf.grid.shape[0]
    centre = sdf.origin + sdf.voxel_size * (res - 1) / 2
    half = sdf.voxel_size * res / 2
    frames = K.forward_kinematics(hand, pose, q)
    spheres, radii = K.collision_spheres(hand, pose, q, frames)
    d_sph, _ = sdf_mod.query(sdf, spheres)
    clearance = jnp.arcsinh((d_sph - radii) / 0.004)
    above_table = jnp.arcsinh(jnp.min(spheres[:, 2] - radii - sdf.table_z) / 0.01)
    d_tip, n_tip = sdf_mod.query(sdf, contacts)
    stencil = (contacts[:, None, :] + STENCIL_STEP * jnp.asarray(_STENCIL, dt)[None]).reshape(-1, 3)
    d_st, _ = sdf_mod.query(sdf, stencil)
    span = jnp.where(hand.upper > hand.lower, hand.upper - hand.lower, 1.0)
    parts = [
        ((contacts - centre[None, :]) / half).ravel(), jnp.arcsinh(d_tip / 0.002), n_tip.ravel(),
        jnp.arcsinh(d_st / 0.005), clearance, above_table[None],
        pose[:3, :3].ravel(), (frames.palm_pos - centre) / half, frames.palm_normal,
        (q - hand.lower) / span, jnp.arcsinh(inputs / jnp.asarray(_scales(hand), dt)),
        jnp.arcsinh(half / 0.05)[None], ((sdf.table_z - centre[2]) / half)[None],
    ]
    return jnp.concatenate([jnp.asarray(p, dt).ravel() for p in parts])


def feature_width(hand) -> int:
    c = len(hand.spec.contact_sites)
    return (c * (3 + 1 + 3 + len(_STENCIL)) + hand.sphere_radius.shape[0] + 1 + 9 + 3 + 3 + hand.lower.shape[0]
            + input_width(hand) + 2)


def batch_features(hand, sdf, poses, q, contacts, inputs) -> Float[Array, "G F"]:
    return jax.vmap(features, (None, None, 0, 0, 0, 0))(hand, sdf, poses, q, contacts, inputs)


batch_features_jit = jax.jit(batch_features)


# ----------------------------------------------------------------------------------------------------------------
# The network
# ----------------------------------------------------------------------------------------------------------------


def init(key: jax.Array, n_in: int, n_out: int, hidden: int, depth: int) -> dict:
    """MLP params: `depth` hidden layers of `hidden` units, a head of `n_out` logits (small initial scale, so every
    prediction starts near the base rate the bias learns first)."""
    keys = jax.random.split(key, depth + 1)
    widths = [n_in] + [hidden] * depth
    net = {f"l{i}": nn.init_dense(keys[i], widths[i], widths[i + 1]) for i in range(depth)}
    net["head"] = nn.init_dense(keys[-1], widths[-1], n_out, scale=0.1)
    return net


def logits(net: dict, norm: dict, x: Float[Array, "*B F"]) -> Float[Array, "*B H"]:
    """Head logits of feature rows `x`, standardised with `norm` ({"mean", "scale"}) first."""
    lead = (1,) * (x.ndim - 1)
    h = (x - norm["mean"].astype(x.dtype).reshape(*lead, -1)) / norm["scale"].astype(x.dtype).reshape(*lead, -1)
    depth = len(net) - 1
    for i in range(depth):
        h = jax.nn.silu(nn.dense(net[f"l{i}"], h))
    return nn.dense(net["head"], h)


@jax.jit
def predict(weights: dict, hand, sdf, poses, q, contacts, inputs) -> Float[Array, "G H"]:
    """Probabilities (G, H) of each head for G grasps of one object (`weights`: {"net", "norm"})."""
    x = batch_features(hand, sdf, poses, q, contacts, inputs)
    return jax.nn.sigmoid(logits(weights["net"], weights["norm"], x))


def standardiser(x: np.ndarray) -> dict:
    """{"mean", "scale"} of training features (columns that never vary get scale 1: they carry no information)."""
    mean = x.mean(0)
    std = x.std(0)
    return {"mean": mean.astype(np.float32), "scale": np.where(std > 1e-6, std, 1.0).astype(np.float32)}


def bce(z: Float[Array, "*B H"], y: Float[Array, "*B H"]) -> Float[Array, "*B H"]:
    """Binary cross-entropy of logits z against labels y in [0, 1], stable for any z."""
    return jnp.maximum(z, 0) - z * y + jnp.log1p(jnp.exp(-jnp.abs(z)))

