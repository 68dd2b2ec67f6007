"""`ffcgs show`: a grasp file in an interactive 3D view in the browser (`viz.viewer`, the `viz` extra)."""

import dataclasses
import time

import numpy as np
import tyro

from ffcgs_jax.core.errors import FfcgsError


@dataclasses.dataclass(frozen=True)
class ShowCmd:
    """Show grasps in an interactive 3D view in the browser: the object, the hand at each grasp (step through them in
    ranked order), fingertip contacts with normals and friction cones, physics outcomes when the file has them, and
    on demand the SDF's zero level, an SDF slice and the sampled wrist poses. Needs viser: pip install -e ".[viz]".

    Attributes:
        grasps: a grasp file (.npz from `ffcgs grasp` or `ffcgs eval`).
        hand: built-in hand name or hand-spec TOML; default: the built-in hand whose channels the file names.
        object: the object's mesh or built-in name; default: what the grasp file records.
        scale: mesh scale; default: the recorded one.
        host: address to serve on (127.0.0.1: this machine only; 0.0.0.0 for others on the network).
        port: port to serve on.
        seconds: serve this many seconds, then exit; 0 (default): until Ctrl-C.
    """

    grasps: tyro.conf.Positional[str] = tyro.MISSING
    hand: str | None = None
    object: str | None = None
    scale: float | None = None
    host: str = "127.0.0.1"
    port: int = 8080
    seconds: float = 0.0

    def check(self) -> None:
        if not 0 < self.port < 65536:
            raise FfcgsError(f"--port must be in [1, 65535], got {self.port}")
        if not self.seconds >= 0:
            raise FfcgsError(f"--seconds must be >= 0, got {self.seconds}")


def hand_of(data: dict, hand: str | None) -> str:
    """`hand` if given, else the built-in hand whose channel names the grasp file records."""
    from ffcgs_jax.hand import spec as hand_spec

    if hand:
        return hand
    names = tuple(str(c) for c in np.asarray(data.get("channel_names", [])))
    for name in hand_spec.BUILTIN_HANDS:
        if hand_spec.load_spec(name).channel_names == names:
            return name
    raise FfcgsError("the grasp file's channels match no built-in hand: pass --hand (a built-in name or spec TOML)")


def serve(view, seconds: float) -> None:
    print(f"3D view of the grasps at {view.url} (Ctrl-C to stop)", flush=True)
    try:
        end = time.monotonic() + seconds if seconds else None
        while end is None or time.monotonic() < end:
            time.sleep(0.2)
    finally:
        view.stop()


def run_show(cmd: ShowCmd) -> None:
    from ffcgs_jax.cli.grasp_object import recorded_object
    from ffcgs_jax.geometry import mesh_io, objects
    from ffcgs_jax.hand import kinematics as K
    from ffcgs_jax.synthesis import grasp_io
    from ffcgs_jax.viz import viewer

    data = grasp_io.load_npz(cmd.grasps)
    name, scale = recorded_object(cmd, data, objects.names())
    hand = K.load_hand(hand_of(data, cmd.hand))
    grasp_io.check_hand(data, cmd.grasps, hand.spec)
    view = viewer.show(data, hand, mesh_io.load_mesh(name, scale=scale), host=cmd.host, port=cmd.port)
    serve(view, cmd.seconds)
