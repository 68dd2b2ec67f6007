"""Videos of one grasp through a physics protocol (`video.record`): frame count, motion, formats."""

import math
import sys

import mujoco
import numpy as np
import pytest
from PIL import Image, ImageSequence

from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.geometry import mesh_io
from ffcgs_jax.hand import spec as hand_spec
from ffcgs_jax.physics import config as physics_config
from ffcgs_jax.physics import protocols as physics_protocols
from ffcgs_jax.physics import runner as physics
from ffcgs_jax.viz import physics_video
from ffcgs_jax.physics.config import PhysicsConfig
from physics_trials import ONE_TRIAL
from ffcgs_jax.viz import scene

SPEC = hand_spec.load_spec("svh")
BALL = mesh_io.load_mesh("ball")
CFG = PhysicsConfig(robust=ONE_TRIAL, close_time=0.1, settle_time=0.05, lift_height=0.01, shake_cycles=0, push_time=0.05)
W, H = 64, 48
LABEL_ROWS = 20  # the phase label sits in the top rows


def _seconds(protocol: str) -> float:
    """Simulated time of the protocol under CFG, step counts rounded as `protocols` does."""
    dt = CFG.timestep
    steps = round(CFG.close_time / dt) + round(CFG.settle_time / dt)
    if protocol == "lift-shake":
        steps += round(CFG.lift_height / CFG.lift_speed / dt) + round(physics_protocols.LIFT_HOLD / dt)
    else:
        steps += 6 * round(CFG.push_time / dt)
    return steps * dt


@pytest.fixture(scope="module")
def grasp():
    """Palm down over the ball (the picture pose of `ffcgs hand`), fingers a third of the way closed."""
    m = SPEC.mj_model()
    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)
    palm = d.site_xpos[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, SPEC.palm_site)].copy()
    T = scene.default_wrist_pose(BALL, palm, np.asarray(SPEC.palm_normal))
    q = np.asarray(SPEC.lower) + (np.asarray(SPEC.upper) - np.asarray(SPEC.lower)) / 3
    out = {}
    for p, sc in physics.scenes(SPEC, BALL, CFG, physics_config.PROTOCOLS).items():
        batch, _, _ = physics.prepare(sc, BALL, T[None], q[None], CFG)
        out[p] = (sc, batch)
    return out


def _frames(path) -> tuple[list[np.ndarray], list[int]]:
    with Image.open(path) as im:
        frames, durations = [], []
        for f in ImageSequence.Iterator(im):
            durations.append(f.info["duration"])
            frames.append(np.asarray(f.convert("RGB"), np.int16))
    return frames, durations


@pytest.mark.parametrize("backend", ["software", "auto"])
def test_gif_has_a_frame_every_1_over_fps_seconds_and_shows_motion(grasp, tmp_path, backend):
    sc, batch = grasp["lift-shake"]
    fps, path = 20, tmp_path / "out" / "lift.gif"
    ticks = []
    n = physics_video.record(sc, batch, 0, CFG, "lift-shake", path, fps=fps, width=W, height=H, backend=backend,
                             progress=ticks.append)
    expected = 1 + math.floor(_seconds("lift-shake") * fps + 1e-9)
    assert n == expected == physics_video.frame_count(sc, batch, CFG, "lift-shake", fps) == sum(ticks)
    frames, durations = _frames(path)
    assert len(frames) == n and frames[0].shape == (H, W, 3)
    assert abs(sum(durations) - 1000 * n / fps) <= 10  # plays in real time
    # The fingers close and the hand lifts: below the label (whose time changes anyway) the picture changes from
    # frame to frame while closing, and most between the first and the last frame.
    body = [f[LABEL_ROWS:] for f in frames]
    change = [float(np.abs(b - a).mean()) for a, b in zip(body, body[1:], strict=False)]
    closing = round(CFG.close_time * fps)
    assert all(c > 0.2 for c in change[:closing]), change
    assert np.abs(body[-1] - body[0]).mean() > max(change[:closing]), change


def test_six_dir_pushes_restart_and_max_seconds_caps(grasp, tmp_path):
    sc, batch = grasp["six-dir"]
    fps = 100
    n = physics_video.record(sc, batch, 0, CFG, "six-dir", tmp_path / "six.gif", fps=fps, width=W, height=H,
                             backend="software")
    assert n == 1 + math.floor(_seconds("six-dir") * fps + 1e-9)
    short = physics_video.record(sc, batch, 0, CFG, "six-dir", tmp_path / "short.gif", fps=fps, width=W, height=H,
                                 backend="software", max_seconds=0.1)
    assert short == 1 + 10 == len(_frames(tmp_path / "short.gif")[0])


def test_bad_arguments(grasp, tmp_path):
    sc, batch = grasp["lift-shake"]
    with pytest.raises(FfcgsError, match=r"\.gif or \.mp4"):
        physics_video.record(sc, batch, 0, CFG, "lift-shake", tmp_path / "out.avi")
    with pytest.raises(FfcgsError, match="grasp index"):
        physics_video.record(sc, batch, 1, CFG, "lift-shake", tmp_path / "out.gif")
    with pytest.raises(FfcgsError, match="unknown protocol"):
        physics_video.record(sc, batch, 0, CFG, "drop", tmp_path / "out.gif")
    with pytest.raises(FfcgsError, match="fps"):
        physics_video.record(sc, batch, 0, CFG, "lift-shake", tmp_path / "out.gif", fps=0)
    assert not list(tmp_path.iterdir())


def test_mp4_without_imageio_ffmpeg_says_how_to_get_it(grasp, tmp_path, monkeypatch):
    sc, batch = grasp["lift-shake"]
    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)  # import now raises ImportError
    with pytest.raises(FfcgsError, match="pip install imageio-ffmpeg"):
        physics_video.record(sc, batch, 0, CFG, "lift-shake", tmp_path / "out.mp4")


def test_mp4(grasp, tmp_path):
    imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg")
    sc, batch = grasp["lift-shake"]
    path = tmp_path / "lift.mp4"
    n = physics_video.record(sc, batch, 0, CFG, "lift-shake", path, fps=30, width=W + 1, height=H,
                             backend="software")
    assert n == 1 + math.floor(_seconds("lift-shake") * 30 + 1e-9)
    reader = imageio_ffmpeg.read_frames(str(path))
    meta = reader.__next__()
    assert tuple(meta["size"]) == (W + 2, H)  # odd widths round up to even for yuv420p
    assert sum(1 for _ in reader) == n
