"""Hand forward kinematics through MuJoCo MJX, as pure functions over a `Hand` pytree.

The wrist pose H (4x4, world <- root body) places the hand's root body; q holds the actuated channels and the
MJCF joints follow from the coupling matrix (qpos = coupling @ q). Everything here is written for one hand
configuration; vmap it for batches (see `forward_kinematics_batch`).
"""

import dataclasses
import math
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from jaxtyping import Array, Float

from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.hand.mjx_import import mjx
from ffcgs_jax.hand.spec import HandSpec, load_spec


@dataclasses.dataclass(frozen=True)
class Hand:
    """A hand ready for MJX kinematics: static names and indices, plus the arrays the math needs.

    Attributes:
        spec: the validated spec (names, paths), static.
        model: the MJX model.
        coupling: (J, Q) map from channels to MuJoCo qpos.
        lower, upper: (Q,) channel limits (rad or m).
        root_inv: (4, 4) inverse of the root body's pose in the MJCF world, so FK results are in the root frame.
        palm_normal: (3,) unit palm normal in the root frame.
        sphere_body, sphere_pos, sphere_radius: collision spheres, each rigid in one body (local position).
        box_vertices: (V, 3) corners of every collision geom's box at q = 0, in the root frame.
        tip_body, tip_pos, tip_radius: (C,), (C, T, 3), (C, T): per contact site, the spheres of its body's collision
            geoms (local positions, radii) and the site itself (radius 0, also the padding): where a fingertip can
            touch (`fingertip_spheres`).
        contact_site_ids, palm_site_id, tetrahedron_site_ids: static MuJoCo site ids.
    """

    spec: HandSpec
    model: mjx.Model
    coupling: Float[Array, "J Q"]
    lower: Float[Array, " Q"]
    upper: Float[Array, " Q"]
    root_inv: Float[Array, "4 4"]
    palm_normal: Float[Array, " 3"]
    sphere_body: jax.Array
    sphere_pos: Float[Array, "S 3"]
    sphere_radius: Float[Array, " S"]
    box_vertices: Float[Array, "V 3"]
    tip_body: jax.Array
    tip_pos: Float[Array, "C T 3"]
    tip_radius: Float[Array, "C T"]
    contact_site_ids: tuple[int, ...]
    palm_site_id: int
    tetrahedron_site_ids: tuple[int, ...]

    @property
    def n_channels(self) -> int:
        return len(self.spec.channel_names)

    @property
    def n_contacts(self) -> int:
        return len(self.contact_site_ids)

    @property
    def q_mean(self) -> Float[Array, " Q"]:
        """Mean channel values, the q_i0 of eq. 13."""
        return (self.lower + self.upper) / 2

    @property
    def q_range(self) -> Float[Array, " Q"]:
        return self.upper - self.lower


_DATA = ("model", "coupling", "lower", "upper", "root_inv", "palm_normal", "sphere_body", "sphere_pos", "sphere_radius",
         "box_vertices", "tip_body", "tip_pos", "tip_radius")
_META = ("spec", "contact_site_ids", "palm_site_id", "tetrahedron_site_ids")


def _unflatten_hand(meta, leaves) -> Hand:
    # Bypass __init__: JAX rebuilds pytrees with placeholder leaves (tracers, AOT ArgInfo) that the runtime type
    # checks of the annotated fields would reject.
    h = object.__new__(Hand)
    for k, v in zip(_META + _DATA, (*meta, *leaves)):
        object.__setattr__(h, k, v)
    return h


jax.tree_util.register_pytree_with_keys(
    Hand,
    lambda h: (tuple((jax.tree_util.GetAttrKey(k), getattr(h, k)) for k in _DATA), tuple(getattr(h, k) for k in _META)),
    _unflatten_hand,
    lambda h: (tuple(getattr(h, k) for k in _DATA), tuple(getattr(h, k) for k in _META)),
)


class HandFrames(NamedTuple):
    """Forward-kinematics results in the world frame (after the wrist pose)."""

    contacts: Float[Array, "C 3"]
    body_pos: Float[Array, "N 3"]
    body_rot: Float[Array, "N 3 3"]
    geom_pos: Float[Array, "G 3"]
    geom_rot: Float[Array, "G 3 3"]
    palm_pos: Float[Array, " 3"]
    palm_normal: Float[Array, " 3"]


def load_hand(source: str | Path = "svh") -> Hand:
    """Load a hand from a built-in name ("svh") or a spec TOML path. Arrays use JAX's default float dtype."""
    spec = load_spec(source)
    m = spec.mj_model()
    dtype = jnp.zeros(()).dtype
    coupling = np.zeros((m.nq, len(spec.channel_names)))
    for name, row in zip(spec.coupling_joints, spec.coupling):
        coupling[m.jnt_qposadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, name)]] = row
    root = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, spec.root_body)
    T_root = _pose(m.body_pos[root], m.body_quat[root])
    root_inv = np.linalg.inv(T_root)
    body, pos, rad = _collision_spheres(m)
    site = lambda n: mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, n)  # noqa: E731
    tip_body, tip_pos, tip_rad = _tip_candidates(m, [site(s) for s in spec.contact_sites], body, pos, rad)
    return Hand(
        spec=spec,
        model=mjx.put_model(m),
        coupling=jnp.asarray(coupling, dtype),
        lower=jnp.asarray(spec.lower, dtype),
        upper=jnp.asarray(spec.upper, dtype),
        root_inv=jnp.asarray(root_inv, dtype),
        palm_normal=jnp.asarray(spec.palm_normal, dtype),
        sphere_body=jnp.asarray(body, jnp.int32),
        sphere_pos=jnp.asarray(pos, dtype),
        sphere_radius=jnp.asarray(rad, dtype),
        box_vertices=jnp.asarray(_box_vertices(m, root_inv, open_qpos(coupling, spec)), dtype),
        tip_body=jnp.asarray(tip_body, jnp.int32),
        tip_pos=jnp.asarray(tip_pos, dtype),
        tip_radius=jnp.asarray(tip_rad, dtype),
        contact_site_ids=tuple(site(s) for s in spec.contact_sites),
        palm_site_id=site(spec.palm_site),
        tetrahedron_site_ids=tuple(site(s) for s in spec.tetrahedron_sites),
    )


def channels_to_qpos(hand: Hand, q: Float[Array, " Q"]) -> Float[Array, " J"]:
    """The MuJoCo joint angles that the channel values q drive."""
    return hand.coupling @ q


def mjx_kinematics(hand: Hand, q: Float[Array, " Q"]) -> mjx.Data:
    """MJX kinematics of the hand at joint channels q, in the model's own frame (the root at its MJCF pose)."""
    data = mjx.make_data(hand.model).replace(qpos=channels_to_qpos(hand, q))
    return mjx.kinematics(hand.model, data)


def _apply(T: Float[Array, "4 4"], p: Float[Array, "*N 3"]) -> Float[Array, "*N 3"]:
    return p @ T[:3, :3].T + jnp.expand_dims(T[:3, 3], tuple(range(p.ndim - 1)))


def forward_kinematics(hand: Hand, wrist_pose: Float[Array, "4 4"], q: Float[Array, " Q"]) -> HandFrames:
    """Fingertip contact points and all body/geom frames for one wrist pose and one channel vector.

    Args:
        hand: from `load_hand`.
        wrist_pose: (4, 4) homogeneous transform world <- root body (metres).
        q: (Q,) actuated channel values; not clamped (see `clamp_q`).
    Returns:
        HandFrames in the world frame; contacts are (C, 3) in the spec's contact_sites order.
    """
    d = mjx_kinematics(hand, q)
    T = wrist_pose @ hand.root_inv
    R = T[:3, :3]
    return HandFrames(
        contacts=_apply(T, d.site_xpos[jnp.array(hand.contact_site_ids)]),
        body_pos=_apply(T, d.xpos),
        body_rot=R @ d.xmat,
        geom_pos=_apply(T, d.geom_xpos),
        geom_rot=R @ d.geom_xmat,
        palm_pos=_apply(T, d.site_xpos[hand.palm_site_id]),
        palm_normal=wrist_pose[:3, :3] @ hand.palm_normal,  # given in the root frame
    )


def contact_points(hand: Hand, wrist_pose: Float[Array, "4 4"], q: Float[Array, " Q"]) -> Float[Array, "C 3"]:
    """Fingertip contact points (C, 3) in the world frame."""
    return forward_kinematics(hand, wrist_pose, q).contacts


def contact_jacobian(hand: Hand, wrist_pose: Float[Array, "4 4"], q: Float[Array, " Q"]) -> Float[Array, "C 3 Q"]:
    """d contacts / d q, (C, 3, Q), by forward-mode autodiff through MJX."""
    return jax.jacfwd(lambda qq: contact_points(hand, wrist_pose, qq))(q)


def tetrahedron_points(hand: Hand, wrist_pose: Float[Array, "4 4"]) -> Float[Array, "4 3"]:
    """The 4 palm tetrahedron points in the world frame (they ride on the root body, so q does not matter)."""
    d = mjx_kinematics(hand, jnp.zeros_like(hand.lower))
    return _apply(wrist_pose @ hand.root_inv, d.site_xpos[jnp.array(hand.tetrahedron_site_ids)])


def collision_spheres(
    hand: Hand, wrist_pose: Float[Array, "4 4"], q: Float[Array, " Q"], frames: HandFrames | None = None
) -> tuple[Float[Array, "S 3"], Float[Array, " S"]]:
    """Centres (S, 3) in the world frame and radii (S,) of spheres covering the hand's collision geoms.

    `frames`: `forward_kinematics(hand, wrist_pose, q)` if the caller has it already. Under autodiff this matters:
    XLA merges two identical forward passes, but each keeps its own backward pass through MJX.
    """
    frames = forward_kinematics(hand, wrist_pose, q) if frames is None else frames
    rot = frames.body_rot[hand.sphere_body]
    centres = jnp.einsum("sij,sj->si", rot, hand.sphere_pos) + frames.body_pos[hand.sphere_body]
    return centres, hand.sphere_radius


def fingertip_spheres(hand: Hand, frames: HandFrames) -> tuple[Float[Array, "C T 3"], Float[Array, "C T"]]:
    """World centres and radii of the candidate spheres of each fingertip (`Hand.tip_pos`): the contact point of
    fingertip i is the skin point of its sphere nearest to the object (`energy.fingertip_contacts`)."""
    rot = frames.body_rot[hand.tip_body]
    centres = jnp.einsum("cij,ctj->cti", rot, hand.tip_pos) + frames.body_pos[hand.tip_body][:, None, :]
    return centres, hand.tip_radius


def box_vertices(hand: Hand, wrist_pose: Float[Array, "4 4"]) -> Float[Array, "V 3"]:
    """Corners of the collision geoms' boxes of the open hand (`open_qpos`), in the world frame (the paper's pose
    filter)."""
    return _apply(wrist_pose, hand.box_vertices)


def clamp_q(hand: Hand, q: Float[Array, "*B Q"]) -> Float[Array, "*B Q"]:
    return jnp.clip(q, hand.lower, hand.upper)


forward_kinematics_batch = jax.vmap(forward_kinematics, in_axes=(None, 0, 0))
contact_jacobian_batch = jax.vmap(contact_jacobian, in_axes=(None, 0, 0))


def orthonormalize(poses: np.ndarray) -> np.ndarray:
    """The nearest rigid transforms (rotation by SVD polar projection), float64: poses composed in float32 on a
    GPU drift from orthonormal by ~1e-4 over a descent, which MuJoCo and the metrics should not inherit."""
    a = np.array(poses, dtype=np.float64)
    u, _, vt = np.linalg.svd(a[..., :3, :3])
    a[..., :3, :3] = u @ vt
    a[..., 3, :] = [0.0, 0.0, 0.0, 1.0]
    return a


def check_wrist_poses(poses, name: str = "wrist_pose", atol: float = 2e-3) -> np.ndarray:
    """Host-side validation of (4, 4) or (B, 4, 4) rigid transforms; returns them `orthonormalize`d (float64).
    atol admits float32 rounding drift, not a wrong matrix."""
    a = _real(poses, name)
    if a.ndim not in (2, 3) or a.shape[-2:] != (4, 4):
        raise FfcgsError(f"{name} must have shape (4, 4) or (B, 4, 4), got {a.shape}")
    if a.size == 0:
        raise FfcgsError(f"{name} holds no poses (shape {a.shape})")
    if not np.isfinite(a).all():
        raise FfcgsError(f"{name} contains NaN or inf")
    R = a[..., :3, :3]
    err = np.abs(R @ np.swapaxes(R, -1, -2) - np.eye(3)).max(initial=0.0)
    det = np.linalg.det(R)
    if err > atol or np.any(det < 0) or np.abs(a[..., 3, :] - [0, 0, 0, 1]).max() > atol:
        raise FfcgsError(f"{name} must be rigid transforms (orthonormal rotation, det +1, last row 0 0 0 1); "
                         f"max |R R^T - I| = {err:.2g}")
    return orthonormalize(a)


def _real(values, name: str) -> np.ndarray:
    """`values` as a float64 array, or FfcgsError when they are not real numbers (strings, complex, objects)."""
    a = np.asarray(values)
    if a.dtype.kind not in "biuf":
        raise FfcgsError(f"{name} must hold real numbers, got dtype {a.dtype}")
    return a.astype(np.float64)


def check_q(hand: Hand, q, name: str = "q") -> np.ndarray:
    """Host-side validation of channel vectors (Q,) or (B, Q)."""
    a = _real(q, name)
    if a.ndim not in (1, 2) or a.shape[-1] != hand.n_channels:
        raise FfcgsError(f"{name} must have shape ({hand.n_channels},) or (B, {hand.n_channels}) for hand "
                         f"{hand.spec.name} (channels: {', '.join(hand.spec.channel_names)}), got {a.shape}")
    if not np.isfinite(a).all():
        raise FfcgsError(f"{name} contains NaN or inf")
    return a


def _pose(pos, quat) -> np.ndarray:
    T = np.eye(4)
    R = np.zeros(9)
    mujoco.mju_quat2Mat(R, np.asarray(quat, float))
    T[:3, :3], T[:3, 3] = R.reshape(3, 3), pos
    return T


def hand_geoms(m: mujoco.MjModel) -> list[int]:
    """Ids of the hand's collision geoms: on a body other than the world, colliding with something."""
    return [g for g in range(m.ngeom) if m.geom_bodyid[g] != 0 and (m.geom_contype[g] or m.geom_conaffinity[g])]


def _collision_spheres(m: mujoco.MjModel) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Spheres inside each collision geom, in its body frame: along capsules, on a grid through boxes.

    A capsule gets spheres of its radius spaced at most half a radius apart along its axis: they leave out at most
    r (1 - sqrt(15/16)) ~ 3 % of r at its skin. A box gets spheres of radius min(half extent) on a grid spaced at
    most that radius, which covers it except for rounded edges and corners.
    Other geom types use their bounding box.
    """
    body, pos, rad = [], [], []
    for g in hand_geoms(m):
        t, size = mujoco.mjtGeom(int(m.geom_type[g])), m.geom_size[g]
        if t == mujoco.mjtGeom.mjGEOM_SPHERE:
            local, r = np.zeros((1, 3)), size[0]
        elif t == mujoco.mjtGeom.mjGEOM_CAPSULE:
            r, h = size[0], size[1]
            n = max(2, math.ceil(4 * h / r) + 1)
            local = np.stack([np.zeros(n), np.zeros(n), np.linspace(-h, h, n)], 1)
        else:
            half = size.copy() if t == mujoco.mjtGeom.mjGEOM_BOX else m.geom_aabb[g, 3:].copy()
            centre = np.zeros(3) if t == mujoco.mjtGeom.mjGEOM_BOX else m.geom_aabb[g, :3]
            r = half.min()
            axes = [np.linspace(-(e - r), e - r, max(1, math.ceil(2 * (e - r) / r) + 1)) for e in half]
            local = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3) + centre
        R = np.zeros(9)
        mujoco.mju_quat2Mat(R, m.geom_quat[g])
        body += [m.geom_bodyid[g]] * len(local)
        pos.append(local @ R.reshape(3, 3).T + m.geom_pos[g])
        rad += [r] * len(local)
    return np.array(body), np.concatenate(pos), np.array(rad)


def _tip_candidates(m: mujoco.MjModel, sites: list[int], body: np.ndarray, pos: np.ndarray, rad: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per contact site: its body, and (local position, radius) of the site (radius 0) and of every collision sphere
    of that body, padded with the site to a common count."""
    cands = []
    for s in sites:
        b = m.site_bodyid[s]
        cands.append([(m.site_pos[s], 0.0)] + [(pos[i], rad[i]) for i in np.flatnonzero(body == b)])
    width = max(len(c) for c in cands)
    cands = [c + [c[0]] * (width - len(c)) for c in cands]
    return (np.array([m.site_bodyid[s] for s in sites]), np.array([[p for p, _ in c] for c in cands]),
            np.array([[r for _, r in c] for c in cands]))


def open_qpos(coupling: np.ndarray, spec: HandSpec) -> np.ndarray:
    """MuJoCo qpos of the open hand, where every descent starts: q = 0 clamped into the channel limits (the SVH's
    lower limits are 0; the Allegro's thumb rotation starts at 0.263 rad)."""
    return np.asarray(coupling, np.float64) @ np.clip(0.0, spec.lower, spec.upper)


def _box_vertices(m: mujoco.MjModel, root_inv: np.ndarray, qpos: np.ndarray) -> np.ndarray:
    d = mujoco.MjData(m)
    d.qpos[:] = qpos
    mujoco.mj_kinematics(m, d)
    signs = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1], indexing="ij")).reshape(3, -1).T
    out = []
    for g in hand_geoms(m):
        local = m.geom_aabb[g, :3] + signs * m.geom_aabb[g, 3:]
        out.append(local @ d.geom_xmat[g].reshape(3, 3).T + d.geom_xpos[g])
    v = np.concatenate(out)
    return v @ root_inv[:3, :3].T + root_inv[:3, 3]
