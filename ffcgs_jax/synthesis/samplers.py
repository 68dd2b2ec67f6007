"""Wrist pose samplers: the baselines of the paper's Table I behind one interface.

A sampler is a function `sample(key, sdf, n) -> (n, 4, 4)` wrist poses (world <- hand root), built by
`make_sampler(name, hand, cfg)`. Each draws from `jax.random` only, so a key fixes its output, and runs as one
jit-compiled function per n (n is static); calling `sample` inside an outer `jax.jit` works too (with n static).

- "cvae": the learned sampler of the paper (`learning/cvae.py`), weights shipped in the package (`weights_path`).

- "random": palm centre uniform in a box around the object, rotation uniform on SO(3); no filtering (section
  V.A.1: the optimiser's filters flag the bad ones).
- "geometric": the palm faces the surface at a fixed standoff, its normal along the SDF gradient at a surface
  point; candidates that fail the pose filters of Algorithm 1 are dropped (see `geometric_candidates`).
"""

import dataclasses
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh

from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.geometry import sdf as S
from ffcgs_jax.geometry.sdf import GradientSDF
from ffcgs_jax.hand.kinematics import Hand
from ffcgs_jax.hand.sites import default_standoff, palm_centre_root
from ffcgs_jax.core.files import check_file
from ffcgs_jax.learning import cvae
from ffcgs_jax.learning.weights import cached, default_weights, load_weights
from ffcgs_jax.synthesis import filters as F
from ffcgs_jax.runtime import sharding
from ffcgs_jax.synthesis.config import SAMPLERS, SamplerConfig
from ffcgs_jax.core.types import Array, Bool, Float

Sampler = Callable[[jax.Array, GradientSDF, int], jax.Array]




def quat_to_matrix(quat: Float[Array, " 4"]) -> Float[Array, "3 3"]:
    """Rotation matrix of a quaternion (w, x, y, z); it need not be normalised (it is, here)."""
    w, x, y, z = quat / jnp.linalg.norm(quat)
    return jnp.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def _frame(a: Float[Array, " 3"]) -> Float[Array, "3 3"]:
    """A right-handed orthonormal basis (u, v, a) as columns, for a unit vector a."""
    # The helper axis only needs to be far from parallel to a; which one is chosen does not matter because the
    # callers add a uniform random spin about a.
    helper = jnp.where(jnp.abs(a[0]) < 0.9, jnp.array([1.0, 0.0, 0.0]), jnp.array([0.0, 1.0, 0.0]))
    u = helper - (helper @ a) * a
    u = u / jnp.linalg.norm(u)
    return jnp.stack([u, jnp.cross(a, u), a], axis=1)


def _spin_z(theta: Float[Array, ""]) -> Float[Array, "3 3"]:
    c, s = jnp.cos(theta), jnp.sin(theta)
    return jnp.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _pose(R: Float[Array, "3 3"], t: Float[Array, " 3"]) -> Float[Array, "4 4"]:
    return jnp.eye(4, dtype=R.dtype).at[:3, :3].set(R).at[:3, 3].set(t)


def palm_facing_pose(
    hand: Hand, palm_root: Float[Array, " 3"], palm_world: Float[Array, " 3"], normal: Float[Array, " 3"],
    theta: Float[Array, ""],
) -> Float[Array, "4 4"]:
    """Wrist pose putting the palm centre at palm_world with the palm normal along -normal, spun by theta about it.

    Args:
        hand: gives the palm normal in the root frame.
        palm_root: (3,) palm centre in the root frame.
        palm_world: (3,) where the palm centre goes, metres.
        normal: (3,) unit outward surface normal the palm faces (the palm normal becomes -normal).
        theta: () spin about the normal, rad.
    Returns:
        (4, 4) world <- hand root.
    """
    R = _frame(-normal) @ _spin_z(theta) @ _frame(hand.palm_normal).T  # maps palm_normal to -normal
    return _pose(R, palm_world - R @ palm_root)


# ----------------------------------------------------------------------------------------------------------------
# Grid helpers (pure JAX, so the samplers trace with the SDF as an argument)
# ----------------------------------------------------------------------------------------------------------------


def _voxel_centres(sdf: GradientSDF) -> Float[Array, "P 3"]:
    res = sdf.grid.shape[0]
    ijk = jnp.stack(jnp.meshgrid(*(jnp.arange(res),) * 3, indexing="ij"), -1).reshape(-1, 3)
    return sdf.origin[None, :] + sdf.voxel_size * ijk.astype(sdf.origin.dtype)


def bounding_box(sdf: GradientSDF) -> tuple[Float[Array, " 3"], Float[Array, " 3"]]:
    """The lo, hi of `geometry.sdf.object_extent`, in JAX: bounds of the inside voxels widened by half a voxel.

    Like object_extent, objects thinner than a voxel fall back to the voxels within half a voxel of the surface.
    An SDF with neither gives an infinite box (the host wrapper refuses it before this runs).
    """
    d = sdf.grid[..., 0].reshape(-1)
    h = sdf.voxel_size
    inside = jnp.where(jnp.any(d <= 0), d <= 0, d <= 0.5 * h)
    p = _voxel_centres(sdf)
    lo = jnp.min(jnp.where(inside[:, None], p, jnp.inf), axis=0) - 0.5 * h
    hi = jnp.max(jnp.where(inside[:, None], p, -jnp.inf), axis=0) + 0.5 * h
    return lo, hi


def surface_points(
    key: jax.Array, sdf: GradientSDF, m: int, min_normal_z: float = -1.0
) -> tuple[Float[Array, "M 3"], Float[Array, "M 3"]]:
    """m points drawn uniformly (with replacement) from the voxels within one voxel of the surface, projected.

    Each chosen voxel centre v moves to v - d(v) g(v), its first-order closest surface point; the normal is the
    SDF gradient queried there. Voxels whose stored gradient has z below min_normal_z are left out (the geometric
    sampler uses this to skip normals whose facing palm would point up), unless that leaves none.

    Args:
        key: PRNG key.
        sdf: the object grid.
        m: number of points (static).
        min_normal_z: lowest z component of the normal at the voxels drawn from (-1: all of them).
    Returns:
        points (m, 3) near the surface and outward unit normals (m, 3).
    """
    flat = sdf.grid.reshape(-1, 4)
    near = jnp.abs(flat[:, 0]) < sdf.voxel_size
    wanted = near & (flat[:, 3] >= min_normal_z)
    # Without such voxels p would be 0 / 0: fall back to all near-surface voxels, then to all voxels (the host
    # wrapper refuses grids without a surface, so the last only keeps traced calls finite).
    w = jnp.where(jnp.any(wanted), wanted, jnp.where(jnp.any(near), near, True)).astype(flat.dtype)
    idx = jax.random.choice(key, flat.shape[0], (m,), replace=True, p=w / jnp.sum(w))
    v = _voxel_centres(sdf)[idx]
    p = v - flat[idx, :1] * flat[idx, 1:]
    _, n = S.query(sdf, p)
    return p, n


# ----------------------------------------------------------------------------------------------------------------
# The samplers' cores (one item of math each, batched with vmap; jitted once per sampler in make_sampler)
# ----------------------------------------------------------------------------------------------------------------


def sample_random(
    hand: Hand, palm_root: Float[Array, " 3"], key: jax.Array, sdf: GradientSDF, n: int, cfg: SamplerConfig,
    filters: F.FilterConfig = F.FilterConfig(), params: dict | None = None, res: int | None = None,
    mesh: Mesh | None = None,
) -> Float[Array, "B 4 4"]:
    """Table I's random baseline: palm centre uniform in the scaled bounding box, rotation uniform on SO(3).

    A normalised 4-D Gaussian is uniform on the unit quaternions, hence its rotation uniform on SO(3).
    """
    del hand, filters, params, res, mesh  # one signature for all samplers; random poses are not filtered (paper)
    k_t, k_q = jax.random.split(key)
    lo, hi = bounding_box(sdf)
    centre, half = (lo + hi) / 2, cfg.translation_scale * (hi - lo) / 2
    u = jax.random.uniform(k_t, (n, 3), dtype=lo.dtype)
    palm = centre[None, :] + (2 * u - 1) * half[None, :]
    R = jax.vmap(quat_to_matrix)(jax.random.normal(k_q, (n, 4), dtype=lo.dtype))
    t = palm - jnp.einsum("bij,j->bi", R, palm_root)
    return jax.vmap(_pose)(R, t)


class Candidates(NamedTuple):
    """Geometric candidates before selection.

    Attributes:
        poses: (M, 4, 4) wrist poses, world <- hand root.
        surface: (M, 3) surface points they face; normal: (M, 3) outward normals there.
        valid: (M,) passed both pose filters.
        violation: (M,) how far each misses them: metres a box corner lies inside object or table (beyond the
            clearance) plus how far the palm normal's z exceeds palm_up_max; 0 for valid ones.
    """

    poses: Float[Array, "M 4 4"]
    surface: Float[Array, "M 3"]
    normal: Float[Array, "M 3"]
    valid: Bool[Array, " M"]
    violation: Float[Array, " M"]


def geometric_candidates(
    hand: Hand, palm_root: Float[Array, " 3"], key: jax.Array, sdf: GradientSDF, m: int, cfg: SamplerConfig,
    filters: F.FilterConfig = F.FilterConfig(), mesh: Mesh | None = None,
) -> Candidates:
    """m unfiltered geometric poses: palm centre at p + standoff n facing the surface, random spin about n.

    Args:
        hand: from `hand.kinematics.load_hand`.
        palm_root: (3,) palm centre in the root frame (`hand.sites.palm_centre_root`).
        key: PRNG key.
        sdf: the object grid (object and table).
        m: number of candidates (static).
        cfg: standoff (> 0: `for_hand` turns the default 0 into the hand's).
        filters: thresholds of the pose filters (default: the paper's).
        mesh: devices to split the filters' work over (`sharding.split`); None: the default device.
    Returns:
        Candidates, with the filter verdicts.
    """
    if cfg.standoff == 0:  # static: raised while tracing
        raise FfcgsError("sampler.standoff 0 means 'derived from the hand': resolve it with samplers.for_hand first")
    k_p, k_s = jax.random.split(key)
    f = filters
    # The palm faces -n, so the palm-up filter rejects exactly the normals with n_z < -palm_up_max: draw only
    # from surface voxels that pass it (same poses as drawing all and rejecting, at half the cost on typical
    # objects). The filter still runs below on the normal at the projected point, which may differ slightly.
    p, n = surface_points(k_p, sdf, m, -f.palm_up_max)
    theta = jax.random.uniform(k_s, (m,), dtype=p.dtype, maxval=2 * jnp.pi)
    poses = jax.vmap(palm_facing_pose, (None, None, 0, 0, 0))(hand, palm_root, p + cfg.standoff * n, n, theta)
    valid, violation = sharding.split(lambda h, s_, x: pose_verdicts(h, s_, x, f), mesh, (hand, sdf), (poses,))
    return Candidates(poses, p, n, valid, violation)


def pose_verdicts(hand: Hand, sdf: GradientSDF, poses: Float[Array, "M 4 4"],
                  filters: F.FilterConfig) -> tuple[Bool[Array, " M"], Float[Array, " M"]]:
    """Whether each pose passes the pose filters of Algorithm 1, and by how much it misses them (see Candidates)."""
    f = filters
    clearance = F.pose_clearance_batch(hand, sdf, poses)
    up = jnp.einsum("bij,j->bi", poses[:, :3, :3], hand.palm_normal)[:, 2]
    valid = ~F.pose_collides_batch(hand, sdf, poses, f) & ~F.palm_up_batch(hand, poses, f)
    violation = jax.nn.relu(f.clearance - clearance) + jax.nn.relu(up - f.palm_up_max)
    return valid, jnp.where(valid, 0.0, violation)


def _valid_first(poses: Float[Array, "M 4 4"], valid: Bool[Array, " M"], violation: Float[Array, " M"],
                 n: int) -> Float[Array, "B 4 4"]:
    """The first n valid poses in draw order, then the invalid ones by increasing violation (fixed shapes)."""
    order = jnp.argsort(jnp.where(valid, -1.0, violation), stable=True)
    return poses[order[:n]]


def sample_geometric(
    hand: Hand, palm_root: Float[Array, " 3"], key: jax.Array, sdf: GradientSDF, n: int, cfg: SamplerConfig,
    filters: F.FilterConfig = F.FilterConfig(), params: dict | None = None, res: int | None = None,
    mesh: Mesh | None = None,
) -> Float[Array, "B 4 4"]:
    """The first n valid of oversample * n geometric candidates, topped up with the least violating invalid ones.

    With fewer than n valid candidates the result still has n poses (fixed shapes under jit): the rest are the
    invalid candidates that miss the filters by the least (see `Candidates.violation`), so callers that need
    only valid poses re-check them with `filters`.
    """
    del params, res
    c = geometric_candidates(hand, palm_root, key, sdf, cfg.oversample * n, cfg, filters, mesh)
    return _valid_first(c.poses, c.valid, c.violation, n)


def sample_cvae(
    hand: Hand, palm_root: Float[Array, " 3"], key: jax.Array, sdf: GradientSDF, n: int, cfg: SamplerConfig,
    filters: F.FilterConfig = F.FilterConfig(), params: dict | None = None, res: int | None = None,
    mesh: Mesh | None = None,
) -> Float[Array, "B 4 4"]:
    """The learned sampler (`learning/cvae.py`): cvae_oversample * n poses decoded from z ~ N(0, I), valid ones first.

    The network rarely proposes a colliding pose, but a few per object do; drawing a few more than needed and
    keeping the ones that pass the pose filters costs one batched decoder call (the U-Net runs once).
    `params` are the network's weights (`learning.weights.load_weights`); the latent size is read from their shapes.
    `res` is the SDF resolution they were trained at: a grid of another resolution is resampled to it for the
    network (`geometry.sdf.resample`); the pose filters still use the grid given. With a `mesh` of several devices each
    decodes and filters its share of the candidates (the same poses as on one device).
    """
    if params is None:
        raise FfcgsError("the cvae sampler needs its weights (params=...)")
    latent = params["decoder"]["conv0"]["w"].shape[-2] - params["unet"]["up1"]["w"].shape[-1]
    net_sdf = sdf if res is None or res == sdf.grid.shape[0] else S.resample(sdf, res)
    centre, half = cvae.grid_frame(net_sdf.origin, net_sdf.voxel_size, net_sdf.grid.shape[0])
    m = cfg.cvae_oversample * n
    base = cvae.decoder_base(params, net_sdf.grid, half)  # once per object, on every device
    z = jax.random.normal(key, (m, latent), dtype=net_sdf.grid.dtype)

    def per_candidate(params, base, palm_root, centre, half, hand, sdf, z):
        g = cvae.decode_many(params, base, z).astype(sdf.grid.dtype)
        poses = jax.vmap(cvae.vector_to_pose, (0, None, None, None))(g, palm_root, centre, half)
        return (poses, *pose_verdicts(hand, sdf, poses, filters))

    # the decoder is most of the sampler's work: each device decodes its share of the candidates, and the first n
    # valid ones are then picked over all of them, so the poses do not depend on the number of devices
    poses, valid, violation = sharding.split(per_candidate, mesh, (params, base, palm_root, centre, half, hand, sdf),
                                             (z,))
    return _valid_first(poses, valid, violation, n)


# The cores by name, (hand, palm_root, key, sdf, n, cfg, filters, params, res, mesh) -> (n, 4, 4): for pipelines that
# jit around them (no host checks; palm_root from `hand.sites.palm_centre_root`). `make_sampler` wraps one with the
# checks and its own jit.
CORES = {"random": sample_random, "geometric": sample_geometric, "cvae": sample_cvae}
assert sorted(CORES) == sorted(SAMPLERS), "synthesis.config.SAMPLERS must name the samplers implemented here"


def names() -> list[str]:
    """Names `make_sampler` accepts."""
    return sorted(CORES)


def make_sampler(
    name: str, hand: Hand, cfg: SamplerConfig = SamplerConfig(), filters: F.FilterConfig = F.FilterConfig()
) -> Sampler:
    """Build a sampler `sample(key, sdf, n) -> (n, 4, 4)` wrist poses, world <- hand root.

    The returned function checks n and the grid on the host, then calls the sampler's core, jit-compiled once
    here (one compilation per n); it is deterministic for a fixed key.

    Args:
        name: "random", "geometric", "cvae" (see the module docstring) or "auto" (`for_hand`).
        hand: from `hand.kinematics.load_hand`.
        cfg: sampler options, checked here (`cfg.weights`: the cvae's weights file, "" for the shipped ones;
            `cfg.standoff` 0: derived from the hand).
        filters: thresholds of the pose filters the geometric and cvae samplers apply (default: the paper's).
    Returns:
        The sampler function.
    """
    if name not in CORES and name != "auto":
        raise FfcgsError(f"unknown sampler {name!r}; valid names: auto, {', '.join(names())}")
    cfg.check()
    filters.check()
    name, cfg = for_hand(name, hand, cfg)
    palm_root = jnp.asarray(palm_centre_root(hand))
    params, res = sampler_params(name, hand, cfg)
    core = jax.jit(partial(CORES[name], cfg=cfg, filters=filters, res=res), static_argnames="n")

    def sample(key: jax.Array, sdf: GradientSDF, n: int) -> Float[Array, "B 4 4"]:
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
            raise FfcgsError(f"n (number of wrist poses) must be an integer >= 1, got {n!r}")
        _check_sdf(sdf)
        return core(hand, palm_root, key, sdf, n=int(n), params=params)

    sample.__name__ = sample.__qualname__ = f"sample_{name}"
    return sample


def for_hand(name: str, hand: Hand, cfg: SamplerConfig) -> tuple[str, SamplerConfig]:
    """The sampler name and options with the hand-dependent defaults filled in: "auto" becomes "cvae" where
    weights are installed or ship for the hand or `cfg.weights` names a file, else "geometric"; a standoff of 0 becomes
    `hand.sites.default_standoff(hand)`."""
    if name == "auto":
        name = "cvae" if cfg.weights or default_weights("cvae", hand.spec.name).is_file() else "geometric"
    if cfg.standoff == 0:
        cfg = dataclasses.replace(cfg, standoff=default_standoff(hand))
    return name, cfg


def weights_path(hand: Hand, weights: str = "") -> Path:
    """The cvae weights file: `weights` if given, else the one installed or shipped for this hand."""
    if weights:
        return Path(weights)
    path = default_weights("cvae", hand.spec.name)
    if not path.is_file():
        raise FfcgsError(f"no cvae weights are installed or ship for hand {hand.spec.name!r}; learn them (`ffcgs "
                         f"learn`, or python -m train.sampler and pass the weights.npz as sampling.weights)")
    return path


def sampler_params(name: str, hand: Hand, cfg: SamplerConfig, dtype=None) -> tuple[dict | None, int | None]:
    """(params, SDF resolution they expect) for the cvae sampler, loaded once per file version (`weights.cached`),
    and cast to `dtype` once: casting ~50 leaves per call cost a millisecond of dispatch; (None, None) otherwise."""
    if name != "cvae":
        return None, None
    path = check_file(weights_path(hand, cfg.weights), "cvae weights file")
    hand_name = hand.spec.name
    loaded = lambda: load_weights(path, hand_name, hand.spec)  # noqa: E731
    if dtype is None:
        params, model = cached(path, ("cvae", hand_name), loaded)
    else:
        dt = np.dtype(dtype).name

        def cast():
            params, model = cached(path, ("cvae", hand_name), loaded)
            return jax.tree.map(lambda x: x.astype(dt), params), model

        params, model = cached(path, ("cvae", hand_name, dt), cast)
    return params, model.res


def _check_sdf(sdf: GradientSDF) -> None:
    """Host checks of the grid: shape always; a surface to sample when the values are concrete."""
    g = sdf.grid
    if g.ndim != 4 or g.shape[-1] != 4 or not g.shape[0] == g.shape[1] == g.shape[2] >= 2:
        raise FfcgsError(f"sdf.grid must have shape (R, R, R, 4) with R >= 2, got {tuple(g.shape)}")
    if isinstance(g, jax.core.Tracer):
        return  # under an outer jit the values are unknown; the cores stay finite on empty grids
    d = np.asarray(g[..., 0])
    h = float(sdf.voxel_size)
    if not np.any(np.abs(d) < h) or not np.any(d <= 0.5 * h):
        raise FfcgsError("the SDF has no voxel on or inside the object surface; is it empty?")

