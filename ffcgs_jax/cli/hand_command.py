"""`ffcgs hand`: the hand posed (optionally beside an object) in a picture, and its fingertip contact points."""

import dataclasses

import numpy as np

from ffcgs_jax.core import files
from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.viz.config import RenderConfig


@dataclasses.dataclass(frozen=True)
class HandCmd:
    """Pose the hand (optionally beside an object) and draw it to a PNG; print its fingertip contact points.

    Attributes:
        q: channel values in hand-spec order (rad), e.g. 9 numbers for the SVH, 16 for the Allegro; default: the
            open hand (q = 0 within the limits).
        close: when q is not given, set every channel to lower + close * (upper - lower), 0..1.
        wrist: wrist pose as X Y Z ROLL PITCH YAW (metres, radians; URDF fixed-axis rpy). Default: the identity,
            or with an object the palm facing down 3 cm above it.
        object: built-in name or mesh file to draw with the hand; it rests on a table at its lowest point.
        hand: built-in hand name or a hand-spec TOML.
        png: output picture.
        views: any of front, side, top.
        scale: multiplies the object's coordinates (0.001 for millimetre meshes).
    """

    q: tuple[float, ...] | None = None
    close: float = 0.0
    wrist: tuple[float, float, float, float, float, float] | None = None
    object: str | None = None
    hand: str = "svh"
    png: str = "hand.png"
    views: tuple[str, ...] = ("front", "side", "top")
    scale: float = 1.0
    render: RenderConfig = RenderConfig()


def run_hand(cmd: HandCmd) -> None:
    from ffcgs_jax.hand import kinematics as K
    from ffcgs_jax.viz import render, scene

    if not 0 <= cmd.close <= 1:
        raise FfcgsError(f"--close must be in [0, 1], got {cmd.close}")
    unknown = [v for v in cmd.views if v not in render.VIEWS]
    if unknown or not cmd.views:
        raise FfcgsError(f"--views: unknown view(s) {unknown}; valid: {', '.join(render.VIEWS)}")
    hand = K.load_hand(cmd.hand)
    lo, hi = np.asarray(hand.lower), np.asarray(hand.upper)
    q = K.check_q(hand, cmd.q, "--q") if cmd.q is not None else lo + cmd.close * (hi - lo)
    outside = np.flatnonzero((q < lo - 1e-9) | (q > hi + 1e-9))
    if outside.size:
        names = [hand.spec.channel_names[i] for i in outside]
        raise FfcgsError(f"--q outside the joint limits for channel(s) {names}: "
                         + ", ".join(f"{n} in [{lo[i]:.4g}, {hi[i]:.4g}]" for n, i in zip(names, outside)))
    obj = None
    if cmd.object is not None:
        from ffcgs_jax.geometry import mesh_io

        obj = mesh_io.load_mesh(cmd.object, scale=cmd.scale)
    if cmd.wrist is not None:
        T = pose_from_xyzrpy(cmd.wrist)
    elif obj is not None:
        m, d = scene.build_scene(hand.spec, np.eye(4))
        scene.set_channels(m, d, np.asarray(hand.coupling), q)
        T = scene.default_wrist_pose(obj, d.site_xpos[hand.palm_site_id], np.asarray(hand.palm_normal))
    else:
        T = np.eye(4)
    # One picture needs one FK: MuJoCo C gives it without JIT compilation (tests hold MJX equal to it).
    m, d = scene.build_scene(hand.spec, T, obj, table_z=None if obj is None else float(obj.bounds[0, 2]))
    scene.set_channels(m, d, np.asarray(hand.coupling), q)
    image, backend = render.render_scene(m, d, cmd.render.width, cmd.render.height, cmd.render.backend, cmd.views)
    render.save_png(image, cmd.png)
    contacts = d.site_xpos[list(hand.contact_site_ids)]
    print(f"{'contact site':<14} {'x (m)':>9} {'y (m)':>9} {'z (m)':>9}")
    for name, p in zip(hand.spec.contact_sites, contacts):
        print(f"{name:<14} {p[0]:>9.4f} {p[1]:>9.4f} {p[2]:>9.4f}")
    files.announce(f"wrote {cmd.png} ({backend} renderer)")


def pose_from_xyzrpy(v) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    v = np.asarray(v, float)
    if v.shape != (6,) or not np.isfinite(v).all():
        raise FfcgsError(f"--wrist needs 6 finite numbers X Y Z ROLL PITCH YAW, got {v.tolist()}")
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", v[3:]).as_matrix()
    T[:3, 3] = v[:3]
    return T
