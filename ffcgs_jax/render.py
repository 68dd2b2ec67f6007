"""Pictures of a MuJoCo scene (hand, object, ground) as PNG files, with or without OpenGL.

Two backends draw the same cameras:

- "mujoco": MuJoCo's own OpenGL renderer, offscreen. The GL platform comes from `MUJOCO_GL` (egl, osmesa,
  glfw) when it is set, else EGL then OSMesa are tried. The platform is chosen here at call time rather than
  through `mujoco.Renderer`, because `import mujoco` fixes the Renderer's platform from `MUJOCO_GL` once (to
  GLFW when unset, which needs a display), so setting the variable later has no effect.
- "software": a z-buffered NumPy rasteriser of `geom_meshes` (scanline spans expanded in batches, nearest
  triangle per pixel by one `np.maximum.at` on packed depth|id keys), flat Lambert shading with a headlight and
  a fill light, thin dark outlines, 2x supersampled. Needs no GL library at all. Alpha is ignored (opaque).

Views (world z up; MuJoCo free-camera azimuth/elevation in degrees, the camera looks along
(cos el cos az, cos el sin az, sin el)):

    front  azimuth  90, elevation -20: looks along +y from slightly above, +x to the right.
    side   azimuth 180, elevation -20: looks along -x from slightly above, +y to the right.
    top    azimuth  90, elevation -90: looks down -z, +x to the right, +y up in the image.

Every view is a perspective camera with the model's `vis.global_.fovy`, aimed at the centre of the
bounding box of all non-plane geoms and pulled back until all of their vertices fit with a margin.
"""

import contextlib
import copy
import functools
import importlib
import os
from pathlib import Path
from typing import NamedTuple

import mujoco
import numpy as np
from jaxtyping import Float, Int, UInt8
from PIL import Image, ImageDraw

from ffcgs_jax.errors import FfcgsError

BACKENDS = ("auto", "mujoco", "software")
VIEWS = {"front": (90.0, -20.0), "side": (180.0, -20.0), "top": (90.0, -90.0)}

_FILL = 0.85  # fraction of the half-width / half-height that the fitted geometry may occupy
_PLANE_SCALE = 2.0  # a plane is drawn out to this many scene radii around the scene centre
_PLANE_CELLS = 8  # planes are split into a grid so that near-camera clipping drops little
_SPHERE_RINGS, _SPHERE_SEGMENTS = 16, 32  # latitude rings (even, so capsules split at the equator), longitudes
_AMBIENT, _HEADLIGHT, _FILL_LIGHT = 0.25, 0.6, 0.3
_OUTLINE = 0.55  # brightness factor of the outline pixels
_BG_TOP, _BG_BOTTOM = (236, 240, 246), (196, 204, 216)
_DEFAULT_RGBA = np.array([0.5, 0.5, 0.5, 1.0])  # MuJoCo's geom rgba default: a material's rgba wins over it
_SUPERSAMPLE = 2  # the software renderer draws at this many times the size and averages down (anti-aliasing)
_MAX_FRAGMENTS = 1 << 22  # pixels rasterised per NumPy batch, bounds memory on big images
_DEFAULT_GROUPS = 3  # MuJoCo shows geom groups 0, 1, 2 by default
# Safety latch, the module's only state: once creating an MjrContext has failed, MuJoCo aborts the whole process
# (libc++ "recursive initialization") on the next attempt, so the GL path is never tried again after that.
_MJR_FAILURE: list[str] = []
# Geom types as plain ints: NumPy integers do not compare equal to MuJoCo's enum members inside `in`.
_PLANE, _HFIELD, _SPHERE, _CAPSULE, _ELLIPSOID, _CYLINDER, _BOX, _MESH, _SDF = (
    int(getattr(mujoco.mjtGeom, "mjGEOM_" + n))
    for n in ("PLANE", "HFIELD", "SPHERE", "CAPSULE", "ELLIPSOID", "CYLINDER", "BOX", "MESH", "SDF")
)


class _Camera(NamedTuple):
    """A pinhole camera: `basis` rows are image right, image up and viewing direction in world coordinates."""

    position: np.ndarray  # (3,)
    basis: np.ndarray  # (3, 3)
    focal: float  # pixels
    width: int
    height: int
    lookat: np.ndarray  # (3,)
    distance: float
    azimuth: float
    elevation: float


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
    if backend not in BACKENDS:
        raise FfcgsError(f"unknown render backend {backend!r}; valid backends: {', '.join(BACKENDS)}")
    if not views:
        raise FfcgsError(f"views must name at least one view; valid views: {', '.join(VIEWS)}")
    unknown = [v for v in views if v not in VIEWS]
    if unknown:
        raise FfcgsError(f"unknown view(s) {', '.join(map(repr, unknown))}; valid views: {', '.join(VIEWS)}")
    for name, value in (("width", width), ("height", height)):
        if not isinstance(value, (int, np.integer)) or not 16 <= value <= 4096:
            raise FfcgsError(f"render {name} must be in [16, 4096] pixels, got {value}")
    _check_data(model, data)

    tagged = _geom_meshes(model, data, include_planes=True)
    meshes = [mesh for _, mesh in tagged]
    solid = [v for g, (v, _, _) in tagged if model.geom_type[g] != _PLANE]
    points = np.concatenate(solid or [v for v, _, _ in meshes] or [np.zeros((1, 3))])
    fovy = float(model.vis.global_.fovy)
    cameras = [_fit_camera(points, *VIEWS[v], fovy, width, height) for v in views]

    images, used = None, "software"
    if backend in ("auto", "mujoco"):
        try:
            images, used = _render_gl(model, data, cameras), "mujoco"
        except FfcgsError:
            if backend == "mujoco":
                raise
    if images is None:
        images = [_render_software(meshes, cam, _SUPERSAMPLE) for cam in cameras]
    labelled = [_label(img, name) for img, name in zip(images, views)]
    return np.concatenate(labelled, axis=1), used


def save_png(image: UInt8[np.ndarray, "height width 3"], path: str | Path) -> None:
    """Write an RGB image as a PNG file, creating its folder.

    Args:
        image: (height, width, 3) uint8.
        path: where to write; an existing file is replaced.
    """
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise FfcgsError(f"save_png needs a (height, width, 3) uint8 image, got {image.shape} {image.dtype}")
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(np.ascontiguousarray(image)).save(path, format="PNG")
    except OSError as e:
        raise FfcgsError(f"cannot write PNG {path}: {e.strerror or e}") from None


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
    model: mujoco.MjModel, data: mujoco.MjData, include_planes: bool
) -> list[tuple[int, tuple[np.ndarray, np.ndarray, np.ndarray]]]:
    """`geom_meshes`, each tagged with its geom index."""
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
        solids = [v for v, _, _ in out.values()]
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


def _fit_camera(points: np.ndarray, azimuth: float, elevation: float, fovy: float, width: int, height: int) -> _Camera:
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
    return _Camera(position, basis, height / 2 / ty, width, height, centre, distance, azimuth, elevation)


def _render_software(
    meshes: list[tuple[np.ndarray, np.ndarray, np.ndarray]], cam: _Camera, supersample: int = 1
) -> np.ndarray:
    """Z-buffered flat-shaded rasterisation of the meshes, one camera, drawn `supersample` times larger and
    averaged down."""
    if supersample > 1:
        s = supersample
        big = _render_software(meshes, cam._replace(focal=cam.focal * s, width=cam.width * s, height=cam.height * s))
        small = big.reshape(cam.height, s, cam.width, s, 3).mean(axis=(1, 3))
        return np.round(small).astype(np.uint8)
    W, H = cam.width, cam.height
    image = _background(W, H)
    if not meshes:
        return image
    counts = [len(v) for v, _, _ in meshes]
    offsets = np.cumsum([0] + counts[:-1])
    verts = np.concatenate([v for v, _, _ in meshes])
    faces = np.concatenate([f + o for (_, f, _), o in zip(meshes, offsets)])
    geom = np.concatenate([np.full(len(f), i) for i, (_, f, _) in enumerate(meshes)])
    rgb = np.stack([c[:3] for _, _, c in meshes])[geom]

    cam_xyz = (verts - cam.position) @ cam.basis.T
    z = cam_xyz[:, 2]
    near = 1e-3 * cam.distance
    keep = np.all(z[faces] > near, axis=1)
    faces, geom, rgb = faces[keep], geom[keep], rgb[keep]
    zs = np.maximum(z, near)
    sx = W / 2 + cam.focal * cam_xyz[:, 0] / zs
    sy = H / 2 - cam.focal * cam_xyz[:, 1] / zs
    colour = _shade(verts, faces, rgb, cam)
    key = _rasterise(sx[faces], sy[faces], 1.0 / zs[faces], W, H)
    hit = key >= 0
    if not np.any(hit):
        return image
    bits = _id_bits(len(faces))
    tri = np.where(hit, key & ((1 << bits) - 1), 0)
    flat = image.reshape(-1, 3)
    flat[hit] = np.clip(colour[tri[hit]] * 255, 0, 255).astype(np.uint8)
    owner = np.where(hit, geom[tri], -1).reshape(H, W)
    edge = _outline(owner, key.reshape(H, W))
    image[edge] = (image[edge] * _OUTLINE).astype(np.uint8)
    return image


def _shade(verts: np.ndarray, faces: np.ndarray, rgb: np.ndarray, cam: _Camera) -> np.ndarray:
    """Per-face colour: ambient + headlight + fill light (upper left of the camera); faces lit on the side seen."""
    tri = verts[faces]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-30)
    to_cam = cam.position - tri.mean(1)
    to_cam /= np.maximum(np.linalg.norm(to_cam, axis=1, keepdims=True), 1e-30)
    normal *= np.where(np.sum(normal * to_cam, 1) < 0, -1.0, 1.0)[:, None]
    right, up, forward = cam.basis
    fill = -0.5 * right + 0.8 * up - 0.3 * forward
    fill /= np.linalg.norm(fill)
    head = np.maximum(-(normal @ forward), 0)  # directional, so a flat face shades evenly
    light = _AMBIENT + _HEADLIGHT * head + _FILL_LIGHT * np.maximum(normal @ fill, 0)
    return rgb * light[:, None]


def _id_bits(n: int) -> int:
    return max(1, int(n).bit_length())


def _rasterise(sx: np.ndarray, sy: np.ndarray, w: np.ndarray, W: int, H: int) -> np.ndarray:
    """Scan-convert triangles, keeping per pixel the nearest one.

    Args:
        sx, sy: (T, 3) pixel coordinates of the corners (x right, y down; pixel centres at +0.5).
        w: (T, 3) inverse depth of the corners, which is affine in screen space; larger is nearer.
        W, H: image size.

    Returns:
        (H * W,) int64: -1 for empty pixels, else (quantised inverse depth << id_bits) | triangle index.
    """
    T = len(sx)
    sx, sy, w = sx.copy(), sy.copy(), w.copy()  # reordered in place below
    keys = np.full(H * W, -1, dtype=np.int64)
    if T == 0:
        return keys
    # Orient counter-clockwise in (x, y-down) coordinates so "inside" is the same sign for every edge.
    area = (sx[:, 1] - sx[:, 0]) * (sy[:, 2] - sy[:, 0]) - (sx[:, 2] - sx[:, 0]) * (sy[:, 1] - sy[:, 0])
    flip = area < 0
    for a in (sx, sy, w):
        a[flip, 1], a[flip, 2] = a[flip, 2].copy(), a[flip, 1].copy()
    area = np.abs(area)
    y0 = np.maximum(np.ceil(sy.min(1) - 0.5), 0)
    y1 = np.minimum(np.floor(sy.max(1) - 0.5), H - 1)
    x0 = np.maximum(np.ceil(sx.min(1) - 0.5), 0)
    x1 = np.minimum(np.floor(sx.max(1) - 0.5), W - 1)
    live = np.flatnonzero((area > 1e-12) & (y1 >= y0) & (x1 >= x0))
    if len(live) == 0:
        return keys

    # Inverse depth as a plane over the screen: w = a x + b y + c.
    dx1, dx2 = sx[:, 1] - sx[:, 0], sx[:, 2] - sx[:, 0]
    dy1, dy2 = sy[:, 1] - sy[:, 0], sy[:, 2] - sy[:, 0]
    dw1, dw2 = w[:, 1] - w[:, 0], w[:, 2] - w[:, 0]
    safe = np.where(area > 1e-12, area, 1.0)
    pa = (dw1 * dy2 - dw2 * dy1) / safe
    pb = (dx1 * dw2 - dx2 * dw1) / safe
    pc = w[:, 0] - pa * sx[:, 0] - pb * sy[:, 0]
    w_lo, w_hi = w.min(), w.max()
    bits = _id_bits(T)
    scale = float((1 << (62 - bits)) - 1) / max(w_hi - w_lo, 1e-30)

    # One entry per (triangle, pixel row) it covers.
    rows = (y1[live] - y0[live] + 1).astype(np.int64)
    t = np.repeat(live, rows)
    y = y0[t] + (np.arange(len(t)) - np.repeat(np.cumsum(rows) - rows, rows))
    yc = y + 0.5
    # Edge k from corner k to corner k+1; a pixel centre is inside when cross(edge, p - start) >= 0 for all k,
    # i.e. A x + B >= 0 with A = -(ey) and B = ex (yc - sy_k) + ey sx_k.
    lo = x0[t] - 0.5
    hi = x1[t] + 0.5
    empty = np.zeros(len(t), dtype=bool)
    for k in range(3):
        ax, ay = sx[t, k], sy[t, k]
        ex, ey = sx[t, (k + 1) % 3] - ax, sy[t, (k + 1) % 3] - ay
        A = -ey
        B = ex * (yc - ay) + ey * ax
        with np.errstate(divide="ignore", invalid="ignore"):
            bound = -B / A
        lo = np.where(A > 0, np.maximum(lo, bound - 1e-9), lo)
        hi = np.where(A < 0, np.minimum(hi, bound + 1e-9), hi)
        empty |= (A == 0) & (B < 0)
    xs = np.maximum(np.ceil(lo - 0.5), x0[t]).astype(np.int64)
    xe = np.minimum(np.floor(hi - 0.5), x1[t]).astype(np.int64)
    span = np.where(empty, 0, np.maximum(xe - xs + 1, 0))
    row_w = pb[t] * yc + pc[t]

    # Expand rows into pixels in batches of about _MAX_FRAGMENTS.
    ends = np.cumsum(span)
    start = 0
    while start < len(span):
        stop = int(np.searchsorted(ends, (ends[start - 1] if start else 0) + _MAX_FRAGMENTS, side="right"))
        stop = max(stop, start + 1)
        s = span[start:stop]
        n = int(s.sum())
        if n:
            r = np.repeat(np.arange(start, stop), s)
            x = xs[r] + (np.arange(n) - np.repeat(np.cumsum(s) - s, s))
            depth = pa[t[r]] * (x + 0.5) + row_w[r]
            q = np.clip((depth - w_lo) * scale, 0, scale * (w_hi - w_lo)).astype(np.int64)
            np.maximum.at(keys, y[r].astype(np.int64) * W + x, (q << bits) | t[r])
        start = stop
    return keys


def _outline(owner: np.ndarray, key: np.ndarray) -> np.ndarray:
    """Pixels on the near side of a boundary between different geoms (or a geom and the background)."""
    edge = np.zeros(owner.shape, dtype=bool)
    whole, head, tail = slice(None), slice(None, -1), slice(1, None)
    for a, b in (((head, whole), (tail, whole)), ((whole, head), (whole, tail))):  # vertical, horizontal pairs
        differ = owner[a] != owner[b]
        edge[a] |= differ & (key[a] >= key[b]) & (owner[a] >= 0)
        edge[b] |= differ & (key[b] >= key[a]) & (owner[b] >= 0)
    return edge


def _background(W: int, H: int) -> np.ndarray:
    t = np.linspace(0.0, 1.0, H)[:, None]
    col = (1 - t) * np.array(_BG_TOP) + t * np.array(_BG_BOTTOM)
    return np.repeat(col[:, None, :], W, axis=1).astype(np.uint8)


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


def _add_fill_light(scene: mujoco.MjvScene, cam: _Camera) -> None:
    """The software renderer's fill light as a directional light; no shadows (acne on small scenes)."""
    right, up, forward = cam.basis
    towards = -0.5 * right + 0.8 * up - 0.3 * forward
    light = scene.lights[scene.nlight]
    light.type = mujoco.mjtLightType.mjLIGHT_DIRECTIONAL
    light.dir[:] = -towards / np.linalg.norm(towards)
    light.pos[:] = cam.lookat + towards * cam.distance
    light.diffuse[:] = _FILL_LIGHT
    light.ambient[:] = 0
    light.specular[:] = 0.1
    light.headlight = 0
    light.castshadow = 0
    scene.nlight += 1


def _render_gl(model: mujoco.MjModel, data: mujoco.MjData, cameras: list[_Camera]) -> list[np.ndarray]:
    """Offscreen MuJoCo rendering of each camera; any failure becomes an FfcgsError naming the GL platform."""
    try:
        return _render_gl_unchecked(model, data, cameras)
    except FfcgsError:
        raise
    except Exception as e:  # noqa: BLE001 -- GL failures surface as RuntimeError, FatalError, OpenGL errors
        name = os.environ.get("MUJOCO_GL", "") or "egl/osmesa"
        raise FfcgsError(_gl_message([f"{name}: {type(e).__name__}: {e}"])) from None


def _render_gl_unchecked(model: mujoco.MjModel, data: mujoco.MjData, cameras: list[_Camera]) -> list[np.ndarray]:
    if _MJR_FAILURE:
        raise FfcgsError(_gl_message(_MJR_FAILURE + ["not retried: a second MjrContext after a failed one aborts"]))
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
        m.vis.headlight.ambient[:] = _AMBIENT
        m.vis.headlight.diffuse[:] = _HEADLIGHT
        m.vis.headlight.specular[:] = 0.2
    option = mujoco.MjvOption()
    if any(model.geom_group[g] >= _DEFAULT_GROUPS for g in _visible_geoms(model)):
        option.geomgroup[:] = 1  # same fallback as geom_meshes: show every group

    gl, ctx = None, None
    try:
        gl = context_cls(W, H)
        gl.make_current()  # EGL and OSMesa raise here when they fail
        if platform not in ("egl", "osmesa") and not importlib.import_module("glfw").get_current_context():
            raise FfcgsError(_gl_message([f"{platform}: GLFW could not open a window (no display?)"]))
        try:
            ctx = mujoco.MjrContext(m, mujoco.mjtFontScale.mjFONTSCALE_100.value)
        except Exception as e:  # noqa: BLE001 -- MuJoCo's FatalError
            _MJR_FAILURE.append(f"{platform}: {type(e).__name__}: {e}")
            raise
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN.value, ctx)
        ctx.readDepthMap = mujoco.mjtDepthMap.mjDEPTH_ZEROFAR
        scene = mujoco.MjvScene(m, maxgeom=max(1000, 2 * m.ngeom))
        rect = mujoco.MjrRect(0, 0, W, H)
        images = []
        for cam in cameras:
            mjcam = mujoco.MjvCamera()
            mjcam.type = mujoco.mjtCamera.mjCAMERA_FREE
            mjcam.lookat[:] = cam.lookat
            mjcam.distance, mjcam.azimuth, mjcam.elevation = cam.distance, cam.azimuth, cam.elevation
            mujoco.mjv_updateScene(m, data, option, None, mjcam, mujoco.mjtCatBit.mjCAT_ALL.value, scene)
            if m.nlight == 0 and scene.nlight < len(scene.lights):
                _add_fill_light(scene, cam)
            mujoco.mjr_render(rect, scene, ctx)
            rgb = np.empty((H, W, 3), dtype=np.uint8)
            depth = np.empty((H, W), dtype=np.float32)
            mujoco.mjr_readPixels(rgb, depth, rect, ctx)
            rgb, depth = rgb[::-1], depth[::-1]  # OpenGL rows run bottom to top
            images.append(np.where((depth > 0)[..., None], rgb, _background(W, H)))  # far plane reads 0
        return images
    finally:  # cleanup after a failure must not mask it
        if ctx is not None:
            with contextlib.suppress(Exception):
                gl.make_current()
                ctx.free()
        if gl is not None:
            with contextlib.suppress(Exception):
                gl.free()
