"""Pictures of a MuJoCo scene (hand, object, ground) as PNG files, with or without OpenGL.

Two backends draw the same cameras:

- "mujoco": MuJoCo's own OpenGL renderer, offscreen. The GL platform comes from `MUJOCO_GL` (egl, osmesa,
  glfw) when it is set, else EGL then OSMesa are tried. The platform is chosen here at call time rather than
  through `mujoco.Renderer`, because `import mujoco` fixes the Renderer's platform from `MUJOCO_GL` once (to
  GLFW when unset, which needs a display), so setting the variable later has no effect.
- "software": a z-buffered NumPy rasteriser of `geom_meshes` (`render_software`: flat shading, outlines,
  supersampling). Needs no GL library at all. Alpha is ignored (opaque).

Views (world z up; MuJoCo free-camera azimuth/elevation in degrees, the camera looks along
(cos el cos az, cos el sin az, sin el)):

    front  azimuth  90, elevation -20: looks along +y from slightly above, +x to the right.
    side   azimuth 180, elevation -20: looks along -x from slightly above, +y to the right.
    top    azimuth  90, elevation -90: looks down -z, +x to the right, +y up in the image.

Every view is a perspective camera with the model's `vis.global_.fovy`, aimed at the centre of the
bounding box of all non-plane geoms and pulled back until all of their vertices fit with a margin.

For animations (`viz.physics_video`), `fit_cameras` fits the cameras once and `SceneRenderer` draws every frame with
them, keeping one GL context open.
"""

import contextlib
import copy
import functools
import importlib
import os
from pathlib import Path

import mujoco
import numpy as np
from jaxtyping import Float, Int, UInt8
from PIL import Image, ImageDraw

from ffcgs_jax.core import files
from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.runtime import compiled
from ffcgs_jax.viz.render_software import AMBIENT, FILL_LIGHT, HEADLIGHT, Camera, background, draw, fill_light_direction

BACKENDS = ("auto", "mujoco", "software")
VIEWS = {"front": (90.0, -20.0), "side": (180.0, -20.0), "top": (90.0, -90.0)}

_FILL = 0.85  # fraction of the half-width / half-height that the fitted geometry may occupy
_PLANE_SCALE = 2.0  # a plane is drawn out to this many scene radii around the scene centre
_PLANE_CELLS = 8  # planes are split into a grid so that near-camera clipping drops little
_SPHERE_RINGS, _SPHERE_SEGMENTS = 16, 32  # latitude rings (even, so capsules split at the equator), longitudes
_DEFAULT_RGBA = np.array([0.5, 0.5, 0.5, 1.0])  # MuJoCo's geom rgba default: a material's rgba wins over it
_DEFAULT_GROUPS = 3  # MuJoCo shows geom groups 0, 1, 2 by default
# Safety latch, the module's only state: once creating an MjrContext has failed, MuJoCo aborts the whole process
# (libc++ "recursive initialization") on the next attempt, so the GL path is never tried again after that.
_MJR_FAILURE: list[str] = []
# Geom types as plain ints: NumPy integers do not compare equal to MuJoCo's enum members inside `in`.
_PLANE, _HFIELD, _SPHERE, _CAPSULE, _ELLIPSOID, _CYLINDER, _BOX, _MESH, _SDF = (
    int(getattr(mujoco.mjtGeom, "mjGEOM_" + n))
    for n in ("PLANE", "HFIELD", "SPHERE", "CAPSULE", "ELLIPSOID", "CYLINDER", "BOX", "MESH", "SDF")
)


def render_scene(
    model: mujoco.MjModel,
    data: mujoco.MjData,
    width: int = 480,
    height: int = 480,
    backend: str = "auto",
    views: tuple[str, ...] = ("front", "side", "top"),
) -> tuple[UInt8[np.ndarray, "height total_width 3"], str]:
    """Draw the scene from each named view and put the pictures side by side.

    Args:
        model: the MuJoCo model.
        data: its data with kinematics already computed (`mj_kinematics` or `mj_forward`).
        width, height: size of one view in pixels.
        backend: "auto" (MuJoCo's OpenGL renderer, else the software rasteriser), "mujoco" or "software".
        views: names from `VIEWS` ("front", "side", "top"), drawn left to right, each labelled top-left.

    Returns:
        The image, (height, width * len(views), 3) uint8, and the backend used: "mujoco" or "software".
    """
    _check_backend(backend)
    cameras = fit_cameras(model, data, width, height, views)
    with SceneRenderer(model, cameras, backend) as renderer:
        images = renderer.render(data)
        used = renderer.used
    labelled = [_label(img, name) for img, name in zip(images, views)]
    return np.concatenate(labelled, axis=1), used


def fit_cameras(
    model: mujoco.MjModel,
    data: mujoco.MjData,
    width: int = 480,
    height: int = 480,
    views: tuple[str, ...] = ("front", "side", "top"),
    points: Float[np.ndarray, "n 3"] | None = None,
) -> list[Camera]:
    """The cameras `render_scene` uses, fitted once: to keep them fixed over the frames of a moving scene.

    Args:
        model, data: the scene, kinematics computed; its visible non-plane geoms are fitted.
        width, height: size of one view in pixels.
        views: names from `VIEWS`.
        points: extra world points (n, 3) to keep in frame too (where the scene will move to).

    Returns:
        One camera per view.
    """
    unknown = [v for v in views if v not in VIEWS]
    if not views:
        raise FfcgsError(f"views must name at least one view; valid views: {', '.join(VIEWS)}")
    if unknown:
        raise FfcgsError(f"unknown view(s) {', '.join(map(repr, unknown))}; valid views: {', '.join(VIEWS)}")
    for name, value in (("width", width), ("height", height)):
        if not isinstance(value, (int, np.integer)) or not 16 <= value <= 4096:
            raise FfcgsError(f"render {name} must be in [16, 4096] pixels, got {value}")
    _check_data(model, data)
    tagged = _geom_meshes(model, data, include_planes=True)
    solid = [v for g, (v, _, _) in tagged if model.geom_type[g] != _PLANE]
    fit = solid or [v for _, (v, _, _) in tagged] or [np.zeros((1, 3))]
    if points is not None:
        fit = fit + [np.asarray(points, np.float64).reshape(-1, 3)]
    fit_points = np.concatenate(fit)
    fovy = float(model.vis.global_.fovy)
    return [_fit_camera(fit_points, *VIEWS[v], fovy, int(width), int(height)) for v in views]


class SceneRenderer:
    """Draws frames of one model from fixed cameras (`fit_cameras`), for animations; a context manager.

    The MuJoCo backend keeps its GL and render contexts for all frames (`render_scene` makes them per call,
    several times the cost of a frame). With "auto", any GL failure switches to the software rasteriser;
    `used` says which backend drew the last frame. Planes are drawn (software) around `around` (world points,
    (n, 3)) when given, so that they stay put while the scene moves, else around the current geoms.
    """

    def __init__(self, model: mujoco.MjModel, cameras: list[Camera], backend: str = "auto",
                 around: Float[np.ndarray, "n 3"] | None = None):
        _check_backend(backend)
        if not cameras or len({(c.width, c.height) for c in cameras}) != 1:
            raise FfcgsError("SceneRenderer needs at least one camera, all of the same size")
        self.model, self.cameras, self.backend = model, list(cameras), backend
        self.around = None if around is None else np.asarray(around, np.float64).reshape(-1, 3)
        self.used = "software"
        self._gl: _GlSession | None = None
        if backend in ("auto", "mujoco"):
            try:
                with _gl_errors():
                    self._gl = _GlSession(model, self.cameras)
                self.used = "mujoco"
            except FfcgsError:
                if backend == "mujoco":
                    raise

    def render(self, data: mujoco.MjData) -> list[UInt8[np.ndarray, "height width 3"]]:
        """One (height, width, 3) uint8 image per camera of `data` (kinematics computed), unlabelled."""
        _check_data(self.model, data)
        if self._gl is not None:
            try:
                with _gl_errors():
                    return self._gl.draw(data)
            except FfcgsError:
                if self.backend == "mujoco":
                    raise
                self.close()
                self.used = "software"
        meshes = [mesh for _, mesh in _geom_meshes(self.model, data, include_planes=True, around=self.around)]
        return [draw(meshes, cam) for cam in self.cameras]

    def close(self) -> None:
        if self._gl is not None:
            self._gl.close()
            self._gl = None

    def __enter__(self) -> "SceneRenderer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _check_backend(backend: str) -> None:
    if backend not in BACKENDS:
        raise FfcgsError(f"unknown render backend {backend!r}; valid backends: {', '.join(BACKENDS)}")


def save_png(image: UInt8[np.ndarray, "height width 3"], path: str | Path) -> None:
    """Write an RGB image as a PNG file, creating its folder.

    Args:
        image: (height, width, 3) uint8.
        path: where to write; an existing file is replaced.
    """
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise FfcgsError(f"save_png needs a (height, width, 3) uint8 image, got {image.shape} {image.dtype}")
    path = files.check_output(path, "PNG")
    files.atomic_write(path, lambda f: Image.fromarray(np.ascontiguousarray(image)).save(f, format="PNG"))


def geom_meshes(
    model: mujoco.MjModel, data: mujoco.MjData, include_planes: bool = True
) -> list[tuple[Float[np.ndarray, "_ 3"], Int[np.ndarray, "_ 3"], Float[np.ndarray, " 4"]]]:
    """World-frame triangle meshes of the visible geoms.

    A geom is visible when its rgba (the material's when the geom keeps MuJoCo's default rgba) has alpha > 0
    and its group is one MuJoCo shows by default (0-2); when that would hide every non-plane geom, groups
    are ignored. Boxes, spheres, capsules, cylinders, ellipsoids and meshes are drawn; height fields and SDFs
    are skipped. Planes become a finite square around the other geoms (within the plane's own size if it
    has one), split into a grid.

    Args:
        model: the MuJoCo model.
        data: its data with kinematics computed.
        include_planes: whether to add the plane squares.

    Returns:
        One (vertices (n, 3) float64 in metres, faces (m, 3) int64, rgba (4,) float64) per drawn geom, in
        geom order.
    """
    _check_data(model, data)
    return [mesh for _, mesh in _geom_meshes(model, data, include_planes)]


def _geom_meshes(
    model: mujoco.MjModel, data: mujoco.MjData, include_planes: bool, around: np.ndarray | None = None
) -> list[tuple[int, tuple[np.ndarray, np.ndarray, np.ndarray]]]:
    """`geom_meshes`, each tagged with its geom index; planes around the points `around` when given."""
    chosen = _visible_geoms(model)
    planes = model.geom_type == _PLANE
    out: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
    for g in chosen:
        if planes[g]:
            continue
        local, faces = _local_mesh(model, g)
        if local is None:
            continue
        world = local @ data.geom_xmat[g].reshape(3, 3).T + data.geom_xpos[g]
        out[g] = (world, np.array(faces), _geom_rgba(model, g))  # a writable copy of the cached faces
    if include_planes:
        solids = [v for v, _, _ in out.values()] if around is None else [around]
        for g in chosen:
            if planes[g]:
                mesh = _plane_mesh(model, data, g, np.concatenate(solids) if solids else None)
                if mesh is not None:
                    out[g] = (*mesh, _geom_rgba(model, g))
    return [(g, out[g]) for g in sorted(out)]


def _check_data(model: mujoco.MjModel, data: mujoco.MjData) -> None:
    if data.geom_xpos.shape[0] != model.ngeom:
        raise FfcgsError(f"data has {data.geom_xpos.shape[0]} geoms, the model {model.ngeom}: not its data")
    if model.ngeom and not np.any(data.geom_xmat):
        raise FfcgsError("data has no geom poses yet: call mujoco.mj_kinematics(model, data) before rendering")


def _visible_geoms(model: mujoco.MjModel) -> list[int]:
    types = np.asarray(model.geom_type, dtype=np.int64)
    supported = ~np.isin(types, [_HFIELD, _SDF])
    alpha = np.array([_geom_rgba(model, g)[3] for g in range(model.ngeom)])
    candidates = supported & (alpha > 0)
    shown = candidates & (model.geom_group < _DEFAULT_GROUPS)
    if not np.any(shown & (types != _PLANE)):
        shown = candidates
    return [int(g) for g in np.flatnonzero(shown)]


def _geom_rgba(model: mujoco.MjModel, g: int) -> np.ndarray:
    rgba = np.array(model.geom_rgba[g], dtype=np.float64)
    mat = model.geom_matid[g]
    if mat >= 0 and np.allclose(rgba, _DEFAULT_RGBA):
        rgba = np.array(model.mat_rgba[mat], dtype=np.float64)
    return rgba


def _local_mesh(model: mujoco.MjModel, g: int) -> tuple[np.ndarray | None, np.ndarray]:
    """Vertices in the geom frame and faces, or (None, _) for a type that is not drawn."""
    kind = int(model.geom_type[g])
    size = np.asarray(model.geom_size[g], dtype=np.float64)
    if kind == _BOX:
        v, f = _unit_box()
        return v * size, f
    if kind in (_SPHERE, _ELLIPSOID):
        v, f = _unit_sphere()
        return v * (size[0] if kind == _SPHERE else size), f
    if kind == _CAPSULE:
        v, f = _unit_sphere()
        v = v * size[0]
        v[:, 2] += np.where(np.arange(len(v)) < len(v) // 2, size[1], -size[1])
        return v, f
    if kind == _CYLINDER:
        v, f = _unit_cylinder()
        return v * np.array([size[0], size[0], size[1]]), f
    if kind == _MESH:
        m = model.geom_dataid[g]
        if m < 0:
            return None, np.zeros((0, 3), np.int64)
        va, vn = model.mesh_vertadr[m], model.mesh_vertnum[m]
        fa, fn = model.mesh_faceadr[m], model.mesh_facenum[m]
        return model.mesh_vert[va : va + vn].astype(np.float64), model.mesh_face[fa : fa + fn].astype(np.int64)
    return None, np.zeros((0, 3), np.int64)


def _plane_mesh(
    model: mujoco.MjModel, data: mujoco.MjData, g: int, solids: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray] | None:
    """A grid square on plane `g` around the scene, clipped to the plane's own half-sizes where nonzero."""
    rot = data.geom_xmat[g].reshape(3, 3)
    pos = data.geom_xpos[g]
    own = np.where(model.geom_size[g][:2] > 0, model.geom_size[g][:2], np.inf)
    if solids is None:
        centre, half = np.zeros(2), np.where(np.isfinite(own), own, 1.0)
    else:
        lo, hi = solids.min(0), solids.max(0)
        centre = (((lo + hi) / 2 - pos) @ rot)[:2]
        half = np.full(2, _PLANE_SCALE * max(np.linalg.norm(hi - lo) / 2, 1e-3))
    a, b = np.maximum(centre - half, -own), np.minimum(centre + half, own)
    if np.any(b <= a):
        return None
    n = _PLANE_CELLS
    xs, ys = np.linspace(a[0], b[0], n + 1), np.linspace(a[1], b[1], n + 1)
    gx, gy = np.meshgrid(xs, ys, indexing="xy")
    local = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], axis=1)
    idx = np.arange((n + 1) * (n + 1)).reshape(n + 1, n + 1)
    c00, c10, c01, c11 = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    faces = np.concatenate([np.stack([c00, c10, c11], 1), np.stack([c00, c11, c01], 1)])
    return local @ rot.T + pos, faces


def _frozen(*arrays: np.ndarray) -> tuple[np.ndarray, ...]:
    for a in arrays:
        a.flags.writeable = False
    return arrays


@functools.cache
def _unit_box() -> tuple[np.ndarray, np.ndarray]:
    v = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    f = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))], dtype=np.int64)
    return _frozen(v, f)


@functools.cache
def _unit_sphere() -> tuple[np.ndarray, np.ndarray]:
    """UV sphere of radius 1; the first half of the vertices have z >= 0 (poles kept as rings)."""
    rings, segs = _SPHERE_RINGS, _SPHERE_SEGMENTS
    # Two equator rings (one per hemisphere) so a capsule can pull the halves apart along z.
    lat = np.concatenate([np.linspace(np.pi / 2, 0, rings // 2 + 1), np.linspace(0, -np.pi / 2, rings // 2 + 1)])
    lon = np.linspace(0, 2 * np.pi, segs, endpoint=False)
    la, lo = np.meshgrid(lat, lon, indexing="ij")
    v = np.stack([np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)], -1).reshape(-1, 3)
    idx = np.arange(len(lat) * segs).reshape(len(lat), segs)
    a, b = idx[:-1], np.roll(idx[:-1], -1, axis=1)
    c, d = idx[1:], np.roll(idx[1:], -1, axis=1)
    f = np.concatenate([np.stack([a, c, d], -1).reshape(-1, 3), np.stack([a, d, b], -1).reshape(-1, 3)])
    return _frozen(v, f)


@functools.cache
def _unit_cylinder() -> tuple[np.ndarray, np.ndarray]:
    """Cylinder of radius 1 from z=-1 to z=1 with capped ends."""
    segs = _SPHERE_SEGMENTS
    ang = np.linspace(0, 2 * np.pi, segs, endpoint=False)
    ring = np.stack([np.cos(ang), np.sin(ang)], 1)
    v = np.concatenate([np.c_[ring, np.full(segs, -1.0)], np.c_[ring, np.ones(segs)], [[0, 0, -1], [0, 0, 1]]])
    i = np.arange(segs)
    j = (i + 1) % segs
    bottom, top = 2 * segs, 2 * segs + 1
    side = [np.stack([i, j, j + segs], 1), np.stack([i, j + segs, i + segs], 1)]
    caps = [np.stack([np.full(segs, bottom), j, i], 1), np.stack([np.full(segs, top), i + segs, j + segs], 1)]
    return _frozen(v, np.concatenate(side + caps).astype(np.int64))


compiled.register("viz.render unit box", _unit_box)  # one entry each (no arguments): constant meshes of a few KB
compiled.register("viz.render unit sphere", _unit_sphere)
compiled.register("viz.render unit cylinder", _unit_cylinder)


def _fit_camera(points: np.ndarray, azimuth: float, elevation: float, fovy: float, width: int, height: int) -> Camera:
    """Aim at the points' bounding-box centre and back off until every point is inside the frame."""
    az, el = np.radians(azimuth), np.radians(elevation)
    forward = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    up = np.array([-np.sin(el) * np.cos(az), -np.sin(el) * np.sin(az), np.cos(el)])
    basis = np.stack([np.cross(forward, up), up, forward])
    lo, hi = points.min(0), points.max(0)
    centre = (lo + hi) / 2
    radius = max(np.linalg.norm(hi - lo) / 2, 1e-3)
    ty = np.tan(np.radians(fovy) / 2)
    tx = ty * width / height
    rel = (points - centre) @ basis.T
    need = np.maximum(np.abs(rel[:, 0]) / (tx * _FILL), np.abs(rel[:, 1]) / (ty * _FILL)) - rel[:, 2]
    distance = float(max(need.max(), (-rel[:, 2]).max() + 0.2 * radius, 0.5 * radius))
    position = centre - distance * forward
    return Camera(position, basis, height / 2 / ty, width, height, centre, distance, azimuth, elevation)


def _label(image: np.ndarray, text: str) -> np.ndarray:
    pil = Image.fromarray(image)
    ImageDraw.Draw(pil).text((5, 4), text, fill=(40, 40, 48))
    return np.asarray(pil)


def _gl_context_class() -> tuple[str, type]:
    """The first MuJoCo GL context class that imports, with its platform name: MUJOCO_GL's, else EGL, OSMesa."""
    requested = os.environ.get("MUJOCO_GL", "").strip().lower()
    if requested in ("disable", "disabled", "off", "false", "0"):
        raise FfcgsError(f"MuJoCo OpenGL rendering is disabled by MUJOCO_GL={requested!r}")
    modules = {"egl": "mujoco.egl", "osmesa": "mujoco.osmesa"}
    names = [requested] if requested else ["egl", "osmesa"]
    errors = []
    for name in names:
        try:
            return name, importlib.import_module(modules.get(name, "mujoco.glfw")).GLContext
        except Exception as e:  # noqa: BLE001 -- broken GL installs raise anything from ImportError to AttributeError
            errors.append(f"{name}: {type(e).__name__}: {e}")
    raise FfcgsError(_gl_message(errors))


def _gl_message(errors: list[str]) -> str:
    return (
        "MuJoCo's OpenGL renderer is unavailable (" + "; ".join(errors) + "). Set MUJOCO_GL to egl, osmesa "
        "or glfw for a working platform, or use backend='software'"
    )


def _add_fill_light(scene: mujoco.MjvScene, cam: Camera) -> None:
    """The software renderer's fill light as a directional light; no shadows (acne on small scenes)."""
    towards = fill_light_direction(cam)
    light = scene.lights[scene.nlight]
    light.type = mujoco.mjtLightType.mjLIGHT_DIRECTIONAL
    light.dir[:] = -towards
    light.pos[:] = cam.lookat + towards * cam.distance
    light.diffuse[:] = FILL_LIGHT
    light.ambient[:] = 0
    light.specular[:] = 0.1
    light.headlight = 0
    light.castshadow = 0
    scene.nlight += 1


@contextlib.contextmanager
def _gl_errors():
    """Any GL failure inside becomes an FfcgsError naming the GL platform."""
    try:
        yield
    except FfcgsError:
        raise
    except Exception as e:  # noqa: BLE001 -- GL failures surface as RuntimeError, FatalError, OpenGL errors
        name = os.environ.get("MUJOCO_GL", "") or "egl/osmesa"
        raise FfcgsError(_gl_message([f"{name}: {type(e).__name__}: {e}"])) from None


class _GlSession:
    """An offscreen GL context and MuJoCo render context for drawing `cameras` (all one size) of a model."""

    def __init__(self, model: mujoco.MjModel, cameras: list[Camera]):
        if _MJR_FAILURE:
            raise FfcgsError(_gl_message(_MJR_FAILURE + ["not retried: a second MjrContext after a failed one aborts"]))
        self.cameras = cameras
        W, H = cameras[0].width, cameras[0].height
        platform, context_cls = _gl_context_class()
        # A private copy, so the caller's model keeps its offscreen buffer size, clip planes and headlight.
        m = copy.copy(model)
        m.vis.global_.offwidth = max(m.vis.global_.offwidth, W)
        m.vis.global_.offheight = max(m.vis.global_.offheight, H)
        extent = max(float(m.stat.extent), 1e-6)
        m.vis.map.znear = 0.02 * min(c.distance for c in cameras) / extent
        m.vis.map.zfar = 20 * max(c.distance for c in cameras) / extent
        if m.nlight == 0:  # MuJoCo's default headlight alone leaves light-less models dim
            m.vis.headlight.ambient[:] = AMBIENT
            m.vis.headlight.diffuse[:] = HEADLIGHT
            m.vis.headlight.specular[:] = 0.2
        self.model = m
        self.option = mujoco.MjvOption()
        if any(model.geom_group[g] >= _DEFAULT_GROUPS for g in _visible_geoms(model)):
            self.option.geomgroup[:] = 1  # same fallback as geom_meshes: show every group
        self.gl, self.ctx = None, None
        try:
            self.gl = context_cls(W, H)
            self.gl.make_current()  # EGL and OSMesa raise here when they fail
            if platform not in ("egl", "osmesa") and not importlib.import_module("glfw").get_current_context():
                raise FfcgsError(_gl_message([f"{platform}: GLFW could not open a window (no display?)"]))
            try:
                self.ctx = mujoco.MjrContext(m, mujoco.mjtFontScale.mjFONTSCALE_100.value)
            except Exception as e:  # noqa: BLE001 -- MuJoCo's FatalError
                _MJR_FAILURE.append(f"{platform}: {type(e).__name__}: {e}")
                raise
            mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN.value, self.ctx)
            self.ctx.readDepthMap = mujoco.mjtDepthMap.mjDEPTH_ZEROFAR
            self.scene = mujoco.MjvScene(m, maxgeom=max(1000, 2 * m.ngeom))
        except BaseException:
            self.close()
            raise

    def draw(self, data: mujoco.MjData) -> list[np.ndarray]:
        m, scene, ctx = self.model, self.scene, self.ctx
        W, H = self.cameras[0].width, self.cameras[0].height
        self.gl.make_current()
        rect = mujoco.MjrRect(0, 0, W, H)
        images = []
        for cam in self.cameras:
            mjcam = mujoco.MjvCamera()
            mjcam.type = mujoco.mjtCamera.mjCAMERA_FREE
            mjcam.lookat[:] = cam.lookat
            mjcam.distance, mjcam.azimuth, mjcam.elevation = cam.distance, cam.azimuth, cam.elevation
            mujoco.mjv_updateScene(m, data, self.option, None, mjcam, mujoco.mjtCatBit.mjCAT_ALL.value, scene)
            if m.nlight == 0 and scene.nlight < len(scene.lights):
                _add_fill_light(scene, cam)
            mujoco.mjr_render(rect, scene, ctx)
            rgb = np.empty((H, W, 3), dtype=np.uint8)
            depth = np.empty((H, W), dtype=np.float32)
            mujoco.mjr_readPixels(rgb, depth, rect, ctx)
            rgb, depth = rgb[::-1], depth[::-1]  # OpenGL rows run bottom to top
            images.append(np.where((depth > 0)[..., None], rgb, background(W, H)))  # far plane reads 0
        return images

    def close(self) -> None:
        """Free the contexts; cleanup after a failure must not mask it."""
        if self.ctx is not None:
            with contextlib.suppress(Exception):
                self.gl.make_current()
                self.ctx.free()
            self.ctx = None
        if self.gl is not None:
            with contextlib.suppress(Exception):
                self.gl.free()
            self.gl = None
