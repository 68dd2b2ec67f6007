"""A video of one grasp going through a physics protocol: what `protocols.run_protocol` does to it, to watch.

The grasp (one row of a `backend.Batch`) is replayed with `mujoco.mj_step` on a single MjData, with the open-loop
segments of `protocols.closing`, `protocols.lift_shake` and `protocols.push` applied as `backend_cpu.CpuSim.run`
applies them:
before every step the servo targets (ctrl), the wrist target (mocap: the grasp's wrist position plus the segment's
offset, its orientation), the force on the object (`xfrc_applied`, zero when the segment has none) and whether the
object is held in place (six-dir's `hold_eq` weld while closing). For six-dir every push starts again from the
closed state, as in `protocols.run_protocol`; DexGraspBench's protocols (`dexgraspbench`) show grasp, squeeze and
each push from the squeezed state. The replay is of the same plan, not
bit-for-bit the batch run: `mujoco.rollout` restarts its solver's warm start every `backend.CHUNK` steps.

A frame is drawn every 1/fps seconds of simulated time (so the video plays in real time) from one fixed camera,
fitted to the scene at the start and to everywhere the wrist will carry the hand and the object, labelled with the
protocol, the phase (closing, settle, lift, hold, shake, push +x ...) and the simulated time.

Formats, from the file suffix: `.gif` (Pillow, one palette from the first frame, no dithering, so the still
background costs nothing after the first frame) or `.mp4` (H.264 through the optional `imageio-ffmpeg`).
"""

import math
from collections.abc import Callable
from pathlib import Path

import mujoco
import numpy as np
from PIL import Image, ImageDraw, ImageFont

from ffcgs_jax.core import files
from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.physics import backend as physics_backend
from ffcgs_jax.physics import protocols as physics_protocols
from ffcgs_jax.physics.config import PhysicsConfig
from ffcgs_jax.physics.scene import PhysicsScene
from ffcgs_jax.viz import render

FORMATS = (".gif", ".mp4")
# Per format: fps, width, height. A GIF of the whole lift-shake (~26 s simulated) stays a few MB at these.
DEFAULTS = {".gif": (15.0, 320, 240), ".mp4": (30.0, 480, 360)}
DIRECTION_NAMES = physics_protocols.DIRECTION_NAMES  # protocols.DIRECTIONS, in order
_LABEL_INK, _LABEL_BOX = (30, 30, 38), (255, 255, 255, 170)
_RESTART = mujoco.mjtState.mjSTATE_INTEGRATION  # everything a step reads: the push restarts exactly


def phases(scene: PhysicsScene, batch: physics_backend.Batch, cfg: PhysicsConfig, protocol: str
           ) -> list[tuple[str, physics_backend.Segment, bool]]:
    """The protocol's steps (`Protocol.phases`, under its fixed settings) as (label, segment, starts again from the
    closed state) in order."""
    p = physics_protocols.get(protocol)
    return p.phases(batch, p.settings(cfg), scene.mass)


def frame_count(scene: PhysicsScene, batch: physics_backend.Batch, cfg: PhysicsConfig, protocol: str, fps: float | int,
                max_seconds: float | int | None = None) -> int:
    """How many frames `record` writes (the first, at time 0, included), e.g. for a progress bar's total."""
    cfg = physics_protocols.get(protocol).settings(cfg)
    steps = sum(seg.n for _, seg, _ in phases(scene, batch, cfg, protocol))
    if max_seconds is not None:
        steps = min(steps, _step_limit(max_seconds, cfg.timestep))
    return 1 + _due(steps, cfg.timestep, float(fps))


def record(scene: PhysicsScene, batch: physics_backend.Batch, index: int, cfg: PhysicsConfig, protocol: str,
           path: str | Path, fps: float | int | None = None, width: int | None = None, height: int | None = None,
           backend: str = "auto", progress: Callable[[int], None] | None = None,
           max_seconds: float | int | None = None, view: str = "front", title: str | None = None) -> int:
    """Replay grasp `index` of `batch` (from `runner.prepare` on `scene`) through `protocol` and write a video.

    Args:
        scene: the protocol's compiled scene (`runner.scenes(...)[protocol]`).
        batch, index: the grasps and which one to film.
        cfg: the physics settings the batch was prepared with.
        protocol: one of `config.ALL_PROTOCOLS` (DexGraspBench's use their own timestep, as `runner.scenes`).
        path: the video file: `.gif` or `.mp4` (needs `pip install imageio-ffmpeg`); its folder is created, and it
            is written atomically (an interrupted recording leaves no partial file).
        fps: frames per simulated second (the video plays in real time); default 15 for GIF, 30 for MP4.
        width, height: frame size in pixels; default 320 x 240 for GIF, 480 x 360 for MP4 (MP4 rounds odd sizes
            up to even ones, as H.264 in yuv420p needs).
        backend: renderer, as `viz.render.render_scene`: "auto", "mujoco" or "software" (slower).
        progress: called with 1 after each frame (`frame_count` gives the total).
        max_seconds: record only this much simulated time from the start; None = the whole protocol.
        view: the camera, one of `viz.render.VIEWS`; "front" looks along +y, across the shaking (along x).
        title: the start of every frame's label; default "<protocol>  grasp <index>".

    Returns:
        The number of frames written.
    """
    physics_protocols.say_overrides(cfg, (protocol,))
    cfg = physics_protocols.get(protocol).settings(cfg)
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in FORMATS:
        raise FfcgsError(f"unknown video format {path.suffix or '(no suffix)'!r} for {path}; use .gif or .mp4")
    if suffix == ".mp4":
        try:
            import imageio_ffmpeg
        except ImportError:
            raise FfcgsError("writing .mp4 needs imageio-ffmpeg: pip install imageio-ffmpeg (or write a .gif)"
                             ) from None
    d_fps, d_width, d_height = DEFAULTS[suffix]
    fps = d_fps if fps is None else fps
    width, height = d_width if width is None else width, d_height if height is None else height
    top = 1.0 / cfg.timestep  # at most a frame a step
    if not (isinstance(fps, (int, float, np.integer, np.floating)) and math.isfinite(fps) and 0 < fps <= top):
        raise FfcgsError(f"fps must be in (0, {top:g}] (one frame per physics step at most), got {fps}")
    fps = float(fps)
    if max_seconds is not None and not (math.isfinite(max_seconds) and max_seconds >= 0):
        raise FfcgsError(f"max_seconds must be >= 0 seconds or None, got {max_seconds}")
    if backend not in render.BACKENDS:
        raise FfcgsError(f"unknown render backend {backend!r}; valid backends: {', '.join(render.BACKENDS)}")
    b = len(batch.q_start)
    if not isinstance(index, (int, np.integer)) or not 0 <= index < b:
        raise FfcgsError(f"grasp index must be an integer in [0, {b}), got {index!r}")
    if suffix == ".mp4":
        width, height = width + width % 2, height + height % 2
    one = batch.rows(slice(index, index + 1))
    plan = phases(scene, one, cfg, protocol)
    limit = sum(seg.n for _, seg, _ in plan)
    if max_seconds is not None:
        limit = min(limit, _step_limit(max_seconds, cfg.timestep))

    m = scene.model
    d = mujoco.MjData(m)
    pos, quat = one.wrist_pos[0], one.wrist_quat[0]
    physics_backend.pose_hand(scene, d, pos, quat, one.q_start[0])
    mujoco.mj_forward(m, d)
    reach = _reach(m, d, plan)
    cameras = render.fit_cameras(m, d, width, height, (view,), points=reach)
    font = _font(height)
    title = f"{protocol}  grasp {index}" if title is None else title
    tick = progress or (lambda n: None)
    path = files.check_output(path, "video")
    with files.atomic_path(path) as tmp:
        return _write(tmp, suffix, fps, width, height, m, d, cameras, backend, reach, plan, limit, pos, quat, cfg,
                      scene, title, font, tick, imageio_ffmpeg if suffix == ".mp4" else None)


def _write(path, suffix, fps, width, height, m, d, cameras, backend, reach, plan, limit, pos, quat, cfg, scene,
           title, font, tick, imageio_ffmpeg) -> int:
    """Render `plan` into the video file `path` (a temporary name: `record` moves it in place); frames written."""
    writer = _GifWriter(path, fps) if suffix == ".gif" else _Mp4Writer(imageio_ffmpeg, path, fps, width, height)
    frames = 0
    try:
        with render.SceneRenderer(m, cameras, backend, around=reach) as renderer:

            def shoot(label: str) -> None:
                nonlocal frames
                mujoco.mj_kinematics(m, d)  # after mj_step the poses are those of the step's start
                image = renderer.render(d)[0]
                writer.add(_label(image, f"{title}  {label}  t = {d.time:.2f} s", font))
                frames += 1
                tick(1)

            shoot(plan[0][0])
            closed = np.zeros(mujoco.mj_stateSize(m, _RESTART))
            step = 0
            for label, seg, restart in plan:
                if step >= limit:
                    break
                if restart:
                    mujoco.mj_setState(m, d, closed, _RESTART)
                n = min(seg.n, limit - step)  # the steps of this segment to record
                for i0 in range(0, n, physics_backend.CHUNK):
                    i1 = min(n, i0 + physics_backend.CHUNK)
                    ctrl, off = seg.make(i0, i1)
                    for j in range(i1 - i0):
                        d.ctrl[:] = ctrl[0, min(j, ctrl.shape[1] - 1)]
                        d.mocap_pos[0] = pos + off[min(j, len(off) - 1)]
                        d.mocap_quat[0] = quat
                        d.xfrc_applied[:] = 0.0
                        if seg.force is not None:
                            d.xfrc_applied[scene.obj_body, :3] = seg.force
                        if scene.hold_eq >= 0:
                            d.eq_active[:] = 1
                            d.eq_active[scene.hold_eq] = seg.hold
                        mujoco.mj_step(m, d)
                        step += 1
                        if _due(step, cfg.timestep, fps) > _due(step - 1, cfg.timestep, fps):
                            shoot(label)
                if label in ("settle", "squeeze"):  # the closed state the pushes start from
                    mujoco.mj_getState(m, d, closed, _RESTART)
        writer.close()
    except BaseException:
        writer.abort()
        raise
    return frames


def _step_limit(seconds: float, dt: float) -> int:
    return int(math.floor(seconds / dt + 1e-9))


def _due(step: int, dt: float, fps: float) -> int:
    """Frames due after `step` steps, the one at time 0 not counted."""
    return int(math.floor(step * dt * fps + 1e-9))


def _reach(m: mujoco.MjModel, d: mujoco.MjData, plan) -> np.ndarray:
    """World points the camera must see: the hand and object now and moved by the extremes of the wrist offsets."""
    solid = [v for v, _, _ in render.geom_meshes(m, d, include_planes=False)]
    points = np.concatenate(solid) if solid else d.xpos.copy()
    offsets = np.concatenate([seg.make(0, seg.n)[1] for _, seg, _ in plan])
    lo, hi = offsets.min(0), offsets.max(0)
    corners = np.unique(np.array([[(lo, hi)[(k >> i) & 1][i] for i in range(3)] for k in range(8)]), axis=0)
    return np.concatenate([points + c for c in corners])


def _font(height: int):
    try:
        return ImageFont.load_default(size=max(10, height // 24))
    except (TypeError, OSError, ImportError):  # Pillow without FreeType: the fixed bitmap font
        return ImageFont.load_default()


def _label(image: np.ndarray, text: str, font) -> np.ndarray:
    pil = Image.fromarray(image).convert("RGBA")
    overlay = Image.new("RGBA", pil.size, (0, 0, 0, 0))
    draw = ImageDraw.Draw(overlay)
    x0, y0, x1, y1 = draw.textbbox((6, 4), text, font=font)
    draw.rectangle((x0 - 3, y0 - 2, x1 + 3, y1 + 2), fill=_LABEL_BOX)
    draw.text((6, 4), text, fill=_LABEL_INK, font=font)
    return np.asarray(Image.alpha_composite(pil, overlay).convert("RGB"))


class _GifWriter:
    """Frames in memory as palette images, written on close. One palette, the first frame's median cut, with
    exact nearest-colour mapping through a lookup table over all 2^24 colours, filled as colours appear
    (Pillow's `quantize(palette=...)` looks colours up on a coarse grid, which shifts flat areas such as the
    background between frames and defeats GIF's frame differencing)."""

    def __init__(self, path: Path, fps: float):
        self.path, self.fps = path, fps
        self.frames: list[Image.Image] = []
        self.palette: np.ndarray | None = None  # (k, 3) int
        self.lut = np.full(1 << 24, 256, np.uint16)  # 0xRRGGBB -> palette entry, 256 = not seen yet

    def add(self, image: np.ndarray) -> None:
        if self.palette is None:
            first = Image.fromarray(image).quantize(colors=256, dither=Image.Dither.NONE)
            self.palette = np.asarray(first.getpalette(), np.int64).reshape(-1, 3)[:256]
        packed = ((image[..., 0].astype(np.int32) << 16) | (image[..., 1].astype(np.int32) << 8)
                  | image[..., 2].astype(np.int32)).ravel()
        index = self.lut[packed]
        unseen = index == 256
        if unseen.any():
            new = np.unique(packed[unseen]).astype(np.int64)
            rgb = np.stack([new >> 16, (new >> 8) & 255, new & 255], axis=1)
            self.lut[new] = np.argmin(((rgb[:, None, :] - self.palette[None]) ** 2).sum(-1), axis=1)
            index = self.lut[packed]
        h, w = image.shape[:2]
        frame = Image.frombytes("P", (w, h), index.astype(np.uint8).tobytes())
        frame.putpalette(self.palette.astype(np.uint8).ravel().tolist())
        self.frames.append(frame)

    def close(self) -> None:
        # GIF delays are whole centiseconds: round the cumulative times, so the average rate is exactly fps.
        ends = [round(100 * (k + 1) / self.fps) for k in range(len(self.frames))]
        durations = [10 * max(1, e - s) for s, e in zip([0] + ends[:-1], ends, strict=True)]
        try:
            self.frames[0].save(self.path, format="GIF", save_all=True, append_images=self.frames[1:],
                                duration=durations, loop=0, optimize=False, disposal=1)
        except OSError as e:
            raise FfcgsError(f"cannot write GIF {self.path}: {e.strerror or e}") from None

    def abort(self) -> None:
        self.frames.clear()


class _Mp4Writer:
    """H.264 frames streamed to ffmpeg as they come."""

    def __init__(self, imageio_ffmpeg, path: Path, fps: float, width: int, height: int):
        self.path = path
        self.gen = imageio_ffmpeg.write_frames(str(path), (width, height), fps=fps, codec="libx264",
                                               pix_fmt_out="yuv420p", macro_block_size=2, quality=7)
        self.gen.send(None)

    def add(self, image: np.ndarray) -> None:
        self.gen.send(np.ascontiguousarray(image))

    def close(self) -> None:
        try:
            self.gen.close()
        except (OSError, RuntimeError) as e:
            raise FfcgsError(f"cannot write MP4 {self.path}: {e}") from None

    def abort(self) -> None:
        try:
            self.gen.close()
        except Exception:  # noqa: BLE001 -- already failing: keep the first error
            pass
        self.path.unlink(missing_ok=True)
