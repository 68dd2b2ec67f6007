"""Synthetic depth frames of a mesh on a table, for tests and demos of TSDF fusion (host NumPy and trimesh).

Depth is ray cast: one ray through each pixel centre, against the mesh's triangles (Moller-Trumbore, each triangle
against the pixels its projection covers only), against the table plane z = table_z, and against the
triangles of a background scene if one is given (a finite table, a floor, a wall, other objects: `depth_scene`),
which are clipped at the camera's plane first, as a room around the camera reaches behind it. Cameras follow
`depth_io`'s conventions (OpenCV axes, depth = camera z, camera-to-world poses, world z up). trimesh's intersector
(`mesh.ray.intersects_location`, without embree) finds the same hits (the tests compare), but its broad phase lets
each ray through ~240 of the mug's 1020 triangles: 2.5-18 s per 640x480 view, 44 s for five views, against 0.36 s
for five here (2-core CPU).

Noise follows the stereo-depth error model: with depth = f B / disparity, a disparity error of one subpixel step
gives a depth error z^2 * subpixel / (f B), growing with the square of the distance (Grunnet-Jepsen et al., Intel's
RealSense D400 white papers: about 1.5 mm at 1 m for a D415, f ~ 1000 px, B = 55 mm, subpixel 0.08; Nguyen, Izadi
and Lovell 2012 fit the same quadratic growth for the Kinect). So readings get Gaussian noise of sigma = a z^2 with
a = 0.0015 per metre, and a share of them drop out (set to 0) as on dark, shiny or grazing surfaces.
"""

import numpy as np
import trimesh

from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.geometry.depth_io import Frames, pixel_rays, transform
from ffcgs_jax.kernels.triangles import rasterise
from ffcgs_jax.core.types import Bool, Float

FOCAL_640 = 615.0  # px: a RealSense D435's colour-aligned focal length at 640x480
NOISE_A = 0.0015  # 1/m: sigma = NOISE_A * z^2 (module docstring)
DROPOUT = 0.02  # share of readings lost
_MIN_DEPTH = 1e-6  # m: mesh points nearer the camera plane cannot be projected
_NEAR = 1e-3  # m: background triangles are clipped to camera z >= this (the room extends behind the camera)
_PAIRS = 1 << 20  # (triangle, pixel) pairs per batch of `_cast`: ~200 MB of temporaries
_COVER_MARGIN = 0.5  # px: far above the ~1e-10 px by which the ray test and the 2-D cover round apart


def camera_K(width: int = 640, height: int = 480) -> Float[np.ndarray, "3 3"]:
    """RealSense-like intrinsics for a width x height image: fx = fy = 615 px scaled by width / 640, principal
    point at the image centre (320, 240 at 640x480)."""
    f = FOCAL_640 * width / 640.0
    return np.array([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])


def look_at(eye: Float[np.ndarray, " 3"], target: Float[np.ndarray, " 3"]) -> Float[np.ndarray, "4 4"]:
    """Camera-to-world pose of a camera at `eye` looking at `target` (OpenCV axes: z forward, x right, y down, with
    world z up appearing up in the image). The view must not be vertical."""
    eye, target = np.asarray(eye, np.float64), np.asarray(target, np.float64)
    f = target - eye
    f = f / np.linalg.norm(f)
    x = np.cross(f, (0.0, 0.0, 1.0))
    if np.linalg.norm(x) < 1e-9:
        raise FfcgsError("look_at: the camera looks straight up or down, so its image axes are undefined")
    x = x / np.linalg.norm(x)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([x, np.cross(f, x), f], 1)
    pose[:3, 3] = eye
    return pose


def view_poses(centre: Float[np.ndarray, " 3"], views: int = 5, elevation_deg: float = 35.0,
               distance: float = 0.45, azimuth_deg: float = 0.0) -> Float[np.ndarray, "N 4 4"]:
    """`views` cameras on a circle around `centre`, evenly spaced in azimuth (the first at `azimuth_deg`), each
    `distance` metres away at `elevation_deg` above the horizontal, looking at `centre`."""
    if views < 1:
        raise FfcgsError(f"views must be >= 1, got {views}")
    if not 0 < elevation_deg < 90:
        raise FfcgsError(f"elevation_deg must be in (0, 90), got {elevation_deg}")
    e = np.radians(elevation_deg)
    az = np.radians(azimuth_deg) + 2 * np.pi * np.arange(views) / views
    eyes = centre + distance * np.stack([np.cos(e) * np.cos(az), np.cos(e) * np.sin(az), np.full(views, np.sin(e))], 1)
    return np.stack([look_at(eye, centre) for eye in eyes])


def _cast(tris: np.ndarray, K: np.ndarray, width: int, height: int) -> np.ndarray:
    """Camera depth (H * W,) of the nearest of the triangles `tris` (T, 3, 3), in camera coordinates, along each
    pixel-centre ray; inf where none is hit.

    Rays from one point through pixel centres are tested only against the triangles whose projection, widened by
    half a pixel, holds the pixel (`kernels.triangles.rasterise`), Moller-Trumbore on each such pair, so the work is
    the projected area rather than rays x triangles. The ray test, not the 2-D cover, decides a hit: the widening
    only has to cover the rounding by which the two can disagree.
    """
    if not (tris[..., 2] > _MIN_DEPTH).all():
        raise FfcgsError("render_depth: part of the mesh is behind the camera or around it; move the camera back")
    uv = tris @ K.T
    uv = uv[..., :2] / uv[..., 2:]
    Kinv = np.linalg.inv(K)

    def fragment(tri, row, col):
        d = col[:, None] * Kinv[:, 0] + row[:, None] * Kinv[:, 1] + Kinv[:, 2]  # ray from the camera centre, z = 1
        v0, e1, e2 = tris[tri, 0], tris[tri, 1] - tris[tri, 0], tris[tri, 2] - tris[tri, 0]
        p = np.cross(d, e2)
        det = np.einsum("ij,ij->i", e1, p)
        inv = 1.0 / np.where(det != 0, det, 1.0)
        q = np.cross(-v0, e1)
        a = -np.einsum("ij,ij->i", v0, p) * inv  # barycentric coordinates of the hit
        b = np.einsum("ij,ij->i", d, q) * inv
        t = np.einsum("ij,ij->i", e2, q) * inv  # ray parameter = camera depth
        return t, (det != 0) & (a >= 0) & (b >= 0) & (a + b <= 1) & (t > 0)

    # OpenCV pixel centres lie on the integers
    return rasterise(uv[..., 0], uv[..., 1], width, height, fragment, np.full(width * height, np.inf), np.minimum,
                     centre=0.0, margin=_COVER_MARGIN, batch=_PAIRS)


def clip_near(tris: Float[np.ndarray, "T 3 3"], near: float = _NEAR) -> Float[np.ndarray, "U 3 3"]:
    """The parts of camera-frame triangles `tris` at camera z >= `near`, as triangles (a triangle with one vertex
    behind becomes two, with two behind one, with three none)."""
    behind = tris[..., 2] < near
    count = behind.sum(1)
    # the odd vertex out (the one behind, or the one in front) first, the order kept cyclic so windings survive
    odd = np.where(count == 1, np.argmax(behind, 1), np.argmin(behind, 1))
    t = np.take_along_axis(tris, ((odd[:, None] + np.arange(3)) % 3)[..., None], 1)
    a, b, c = t[:, 0], t[:, 1], t[:, 2]

    def cut(p, q):  # the point of segment p-q at z = near
        s = (near - p[:, 2]) / np.where(q[:, 2] != p[:, 2], q[:, 2] - p[:, 2], 1.0)
        return p + s[:, None] * (q - p)

    ab, ac = cut(a, b), cut(a, c)
    one = count == 1  # a behind: the quad ab b c ac
    two = count == 2  # b, c behind: the triangle a ab ac
    return np.concatenate([tris[count == 0], np.stack([ab, b, c], 1)[one], np.stack([ab, c, ac], 1)[one],
                           np.stack([a, ab, ac], 1)[two]])


def render_depth(mesh: trimesh.Trimesh, K: Float[np.ndarray, "3 3"], pose: Float[np.ndarray, "4 4"], width: int,
                 height: int, table_z: float | None = None, scene: trimesh.Trimesh | None = None
                 ) -> tuple[Float[np.ndarray, "H W"], Bool[np.ndarray, "H W"]]:
    """Exact depth of one view: pixel-centre rays against the mesh and, if given, the table plane z = table_z and
    the background `scene`.

    Args:
        mesh: the object, metres.
        K: (3, 3) intrinsics.
        pose: (4, 4) camera-to-world pose.
        width, height: image size in pixels.
        table_z: height of the (infinite) table plane, or None for no table.
        scene: background triangles (world frame, metres; anything but the object), or None.

    Returns:
        depth (H, W) float64 camera z in metres, 0 where the ray hits nothing; mask (H, W), True where the object
        is the first thing hit.
    """
    # world directions through the pixel centres; a point at parameter s along one has camera depth s
    dirs = transform(pose[:3, :3], pixel_rays(K, height, width)).reshape(-1, 3)
    eye = pose[:3, 3]
    cam = (np.asarray(mesh.vertices, np.float64) - eye) @ pose[:3, :3]
    obj = _cast(cam[np.asarray(mesh.faces)], K, width, height)
    table = np.full(len(dirs), np.inf)
    if table_z is not None:
        down = dirs[:, 2] < 0
        s = np.where(down, (table_z - eye[2]) / np.where(down, dirs[:, 2], -1.0), np.inf)
        table = np.where(s > 0, s, np.inf)
    if scene is not None and len(scene.faces):
        back = clip_near(((np.asarray(scene.vertices, np.float64) - eye) @ pose[:3, :3])[np.asarray(scene.faces)])
        if len(back):
            table = np.minimum(table, _cast(back, K, width, height))
    depth = np.minimum(obj, table)
    mask = obj <= table
    depth = np.where(np.isfinite(depth), depth, 0.0)
    return depth.reshape(height, width), (mask & np.isfinite(obj)).reshape(height, width)


def add_noise(depth: Float[np.ndarray, "*shape"], rng: np.random.Generator, a: float = NOISE_A,
              dropout: float = DROPOUT) -> Float[np.ndarray, "*shape"]:
    """Stereo-like depth noise (module docstring): Gaussian of sigma = a z^2 on every reading, then a `dropout`
    share of the readings set to 0. Pixels without reading stay 0; noisy readings stay >= 0."""
    if not (a >= 0 and 0 <= dropout <= 1):
        raise FfcgsError(f"noise needs a >= 0 and 0 <= dropout <= 1, got a = {a}, dropout = {dropout}")
    noisy = depth + a * depth**2 * rng.standard_normal(depth.shape)
    lost = rng.random(depth.shape) < dropout
    return np.where((depth > 0) & ~lost, np.maximum(noisy, 0.0), 0.0)


def render_views(mesh: trimesh.Trimesh, views: int = 5, width: int = 640, height: int = 480, noise: bool = False,
                 seed: int | np.random.Generator = 0, table: bool = True, elevation_deg: float = 35.0,
                 distance: float = 0.45, noise_a: float = NOISE_A, dropout: float = DROPOUT,
                 scene: trimesh.Trimesh | None = None) -> Frames:
    """Depth frames of `mesh` resting on a table, from `views` cameras around it (`view_poses` about the centre of
    its bounding box) with RealSense-like intrinsics (`camera_K`).

    Args:
        mesh: the object in metres; the table is the plane z = its lowest z.
        views: number of cameras, evenly spaced in azimuth.
        width, height: image size (80x60 renders ~60x faster than 640x480, for tests).
        noise: add `add_noise` noise (sigma = noise_a z^2, `dropout` share of readings lost).
        seed: seed or numpy Generator of the noise.
        table: render the table plane (False: only the object; pixels past it read 0).
        elevation_deg, distance: camera placement (degrees above the horizontal, metres to the centre).
        noise_a, dropout: the noise model's parameters.
        scene: background triangles around the object (`depth_scene.scene_mesh`: a finite table, floor, wall,
            other objects), or None.

    Returns:
        Frames with float32 depth and the object masks (True where the ray's first hit is the object).
    """
    if not (isinstance(width, int) and isinstance(height, int) and width > 0 and height > 0):
        raise FfcgsError(f"width and height must be positive integers, got {width}x{height}")
    K = camera_K(width, height)
    poses = view_poses(np.asarray(mesh.bounds, np.float64).mean(0), views, elevation_deg, distance)
    table_z = float(mesh.bounds[0, 2]) if table else None
    rendered = [render_depth(mesh, K, p, width, height, table_z, scene) for p in poses]
    depth = np.stack([d for d, _ in rendered])
    if noise:
        depth = add_noise(depth, np.random.default_rng(seed), noise_a, dropout)
    return Frames(depth.astype(np.float32), K, poses, np.stack([m for _, m in rendered]),
                  tuple(f"view_{i:03d}" for i in range(views)))
