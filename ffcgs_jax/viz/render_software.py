"""The "software" backend of `render`: a z-buffered NumPy rasteriser of world-frame triangle meshes.

Scan conversion and the z-test are `kernels.triangles.rasterise`'s (shared with `geometry.depth_render`); the
nearest triangle per pixel is kept through packed depth|id keys; flat Lambert shading with a headlight and a fill
light, thin dark outlines, 2x supersampled. Needs no GL library at all. Alpha is ignored (opaque). The cameras come
fitted by `render`; the lighting constants and the background gradient are shared with its MuJoCo backend.
"""

from typing import NamedTuple

import numpy as np
from jaxtyping import UInt8

from ffcgs_jax.kernels.triangles import rasterise, signed_area

AMBIENT, HEADLIGHT, FILL_LIGHT = 0.25, 0.6, 0.3
SUPERSAMPLE = 2  # `draw` renders at this many times the size and averages down (anti-aliasing)
_OUTLINE = 0.55  # brightness factor of the outline pixels
BG_TOP, BG_BOTTOM = (236, 240, 246), (196, 204, 216)
_MAX_FRAGMENTS = 1 << 22  # pixels rasterised per NumPy batch, bounds memory on big images


class Camera(NamedTuple):
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


def draw(
    meshes: list[tuple[np.ndarray, np.ndarray, np.ndarray]], cam: Camera, supersample: int = SUPERSAMPLE
) -> UInt8[np.ndarray, "height width 3"]:
    """Z-buffered flat-shaded rasterisation of the meshes, one camera, drawn `supersample` times larger and
    averaged down.

    Args:
        meshes: (vertices (n, 3) in metres, faces (m, 3), rgba (4,)) per geom, as `render.geom_meshes` gives.
        cam: the camera (`render` fits one per view).
        supersample: drawing scale before averaging down; 1 draws at the camera's size.

    Returns:
        (cam.height, cam.width, 3) uint8 image on the background gradient.
    """
    if supersample > 1:
        s = supersample
        big = draw(
            meshes, cam._replace(focal=cam.focal * s, width=cam.width * s, height=cam.height * s), supersample=1
        )
        small = big.reshape(cam.height, s, cam.width, s, 3).mean(axis=(1, 3))
        return np.round(small).astype(np.uint8)
    W, H = cam.width, cam.height
    image = background(W, H)
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


def fill_light_direction(cam: Camera) -> np.ndarray:
    """Unit vector toward the fill light: upper left of the camera, a little behind it (both backends use it)."""
    right, up, forward = cam.basis
    towards = -0.5 * right + 0.8 * up - 0.3 * forward
    return towards / np.linalg.norm(towards)


def _shade(verts: np.ndarray, faces: np.ndarray, rgb: np.ndarray, cam: Camera) -> np.ndarray:
    """Per-face colour: ambient + headlight + fill light (upper left of the camera); faces lit on the side seen."""
    tri = verts[faces]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-30)
    to_cam = cam.position - tri.mean(1)
    to_cam /= np.maximum(np.linalg.norm(to_cam, axis=1, keepdims=True), 1e-30)
    normal *= np.where(np.sum(normal * to_cam, 1) < 0, -1.0, 1.0)[:, None]
    fill = fill_light_direction(cam)
    head = np.maximum(-(normal @ cam.basis[2]), 0)  # directional (along the view axis), so a flat face shades evenly
    light = AMBIENT + HEADLIGHT * head + FILL_LIGHT * np.maximum(normal @ fill, 0)
    return rgb * light[:, None]


def _id_bits(n: int) -> int:
    return max(1, int(n).bit_length())


def _rasterise(sx: np.ndarray, sy: np.ndarray, w: np.ndarray, W: int, H: int) -> np.ndarray:
    """Scan-convert triangles (`kernels.triangles.rasterise`), keeping per pixel the nearest one.

    Args:
        sx, sy: (T, 3) pixel coordinates of the corners (x right, y down; pixel centres at +0.5).
        w: (T, 3) inverse depth of the corners, which is affine in screen space; larger is nearer.
        W, H: image size.

    Returns:
        (H * W,) int64: -1 for empty pixels, else (quantised inverse depth << id_bits) | triangle index.
    """
    T = len(sx)
    keys = np.full(H * W, -1, dtype=np.int64)
    if T == 0:
        return keys
    # Inverse depth as a plane over the screen: w = a x + b y + c. The signed area keeps the plane's sign whichever
    # way a triangle winds.
    area = signed_area(sx, sy)
    dx1, dx2 = sx[:, 1] - sx[:, 0], sx[:, 2] - sx[:, 0]
    dy1, dy2 = sy[:, 1] - sy[:, 0], sy[:, 2] - sy[:, 0]
    dw1, dw2 = w[:, 1] - w[:, 0], w[:, 2] - w[:, 0]
    safe = np.where(np.abs(area) > 1e-12, area, 1.0)
    pa = (dw1 * dy2 - dw2 * dy1) / safe
    pb = (dx1 * dw2 - dx2 * dw1) / safe
    pc = w[:, 0] - pa * sx[:, 0] - pb * sy[:, 0]
    w_lo, w_hi = w.min(), w.max()
    bits = _id_bits(T)
    # One int64 per fragment, inverse depth above the triangle index, so a single maximum is the z-test and the
    # winner's id together.
    scale = float((1 << (62 - bits)) - 1) / max(w_hi - w_lo, 1e-30)

    def fragment(tri, row, col):
        depth = pa[tri] * (col + 0.5) + (pb[tri] * (row + 0.5) + pc[tri])
        q = np.clip((depth - w_lo) * scale, 0, scale * (w_hi - w_lo)).astype(np.int64)
        return (q << bits) | tri, None

    return rasterise(sx, sy, W, H, fragment, keys, np.maximum, centre=0.5, batch=_MAX_FRAGMENTS)


def _outline(owner: np.ndarray, key: np.ndarray) -> np.ndarray:
    """Pixels on the near side of a boundary between different geoms (or a geom and the background)."""
    edge = np.zeros(owner.shape, dtype=bool)
    whole, head, tail = slice(None), slice(None, -1), slice(1, None)
    for a, b in (((head, whole), (tail, whole)), ((whole, head), (whole, tail))):  # vertical, horizontal pairs
        differ = owner[a] != owner[b]
        edge[a] |= differ & (key[a] >= key[b]) & (owner[a] >= 0)
        edge[b] |= differ & (key[b] >= key[a]) & (owner[b] >= 0)
    return edge


def background(W: int, H: int) -> UInt8[np.ndarray, "height width 3"]:
    """The sky gradient, BG_TOP at the top row to BG_BOTTOM at the bottom."""
    t = np.linspace(0.0, 1.0, H)[:, None]
    col = (1 - t) * np.array(BG_TOP) + t * np.array(BG_BOTTOM)
    return np.repeat(col[:, None, :], W, axis=1).astype(np.uint8)
