"""Convex decomposition of object meshes for MuJoCo's collisions, cached on disk.

MuJoCo collides a mesh geom through its convex hull, so a mug would be a solid lump with no handle opening. The
object is therefore split into convex parts by CoACD (approximate convex decomposition, `pip install coacd`).
Settings (`PhysicsConfig`): concavity threshold 0.05, at most 32 parts of at most 64 vertices each (few vertices
keep MuJoCo's convex collision cheap). CoACD's preprocessing remeshes open or non-manifold inputs. A mesh that is
already convex (volume within 1 % of its hull's) skips CoACD and becomes its own hull.

The result depends only on the mesh and those settings, and CoACD takes seconds to tens of seconds on a
few-thousand-face mesh, so it is cached as an .npz named by a SHA-256 of both, in `$FFCGS_CACHE_DIR/convex`
(default `~/.cache/ffcgs-jax/convex`).
"""

import hashlib
import json
import os
import warnings
from pathlib import Path

import numpy as np
import trimesh

from ffcgs_jax import files
from ffcgs_jax.errors import FfcgsError
from ffcgs_jax.physics.config import PhysicsConfig

CONVEX_RTOL = 0.01  # volume shortfall against the hull under which a mesh counts as convex
_VERSION = 1  # bump when the decomposition's meaning changes, so old cache entries are not reused


def cache_dir() -> Path:
    root = os.environ.get("FFCGS_CACHE_DIR")
    return (Path(root) if root else Path.home() / ".cache" / "ffcgs-jax") / "convex"


def _key(mesh: trimesh.Trimesh, cfg: PhysicsConfig) -> str:
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(mesh.vertices, np.float64).tobytes())
    h.update(np.ascontiguousarray(mesh.faces, np.int64).tobytes())
    settings = dict(v=_VERSION, t=cfg.coacd_threshold, n=cfg.max_hulls, k=cfg.hull_vertices)
    h.update(json.dumps(settings, sort_keys=True).encode())
    return h.hexdigest()[:32]


def decompose(mesh: trimesh.Trimesh, cfg: PhysicsConfig = PhysicsConfig(), use_cache: bool = True
              ) -> list[tuple[np.ndarray, np.ndarray]]:
    """Convex parts of `mesh` as (vertices (V, 3) float64, faces (F, 3) int32), in the mesh's frame."""
    path = cache_dir() / f"{_key(mesh, cfg)}.npz"
    if use_cache and path.is_file():
        try:
            return _read(path)
        except Exception:  # noqa: BLE001 - a truncated cache file is rebuilt, not fatal
            pass
    parts = _compute(mesh, cfg)
    if use_cache:
        try:
            _write(path, parts)
        except FfcgsError as e:  # an unusable cache folder costs time on the next run, not this result
            warnings.warn(f"convex parts not cached ({e}); set FFCGS_CACHE_DIR to a writable folder", stacklevel=2)
    return parts


def _compute(mesh: trimesh.Trimesh, cfg: PhysicsConfig) -> list[tuple[np.ndarray, np.ndarray]]:
    hull = mesh.convex_hull
    if mesh.is_volume and mesh.volume >= (1 - CONVEX_RTOL) * hull.volume:
        return [_simplified_hull(hull, cfg.hull_vertices)]
    try:
        import coacd
    except ImportError:
        raise FfcgsError("the physics test needs CoACD for non-convex objects: pip install coacd") from None
    coacd.set_log_level("error")
    raw = coacd.run_coacd(
        coacd.Mesh(np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int32)),
        threshold=cfg.coacd_threshold, max_convex_hull=cfg.max_hulls, max_ch_vertex=cfg.hull_vertices,
        decimate=True, seed=0,
    )
    parts = [(np.asarray(v, np.float64), np.asarray(f, np.int32)) for v, f in raw if len(v) >= 4]
    if not parts:
        raise FfcgsError("convex decomposition of the object produced no solid part (is the mesh degenerate?)")
    return parts


def _simplified_hull(hull: trimesh.Trimesh, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The hull of at most k of its vertices, chosen by farthest-point sampling (keeps the extremes)."""
    v = np.asarray(hull.vertices, np.float64)
    if len(v) > k:
        chosen = [int(np.argmax(np.linalg.norm(v - v.mean(0), axis=1)))]
        d = np.linalg.norm(v - v[chosen[0]], axis=1)
        while len(chosen) < k:
            i = int(np.argmax(d))
            chosen.append(i)
            d = np.minimum(d, np.linalg.norm(v - v[i], axis=1))
        small = trimesh.convex.convex_hull(v[chosen])
        return np.asarray(small.vertices, np.float64), np.asarray(small.faces, np.int32)
    return v, np.asarray(hull.faces, np.int32)


def _write(path: Path, parts) -> None:
    arrays = {}
    for i, (v, f) in enumerate(parts):
        arrays[f"v{i}"], arrays[f"f{i}"] = v, f
    # atomic, so parallel workers never read half a file
    files.atomic_write(files.check_output(path, "convex cache"), lambda f: np.savez(f, n=len(parts), **arrays))


def _read(path: Path) -> list[tuple[np.ndarray, np.ndarray]]:
    with np.load(path) as z:
        return [(z[f"v{i}"], z[f"f{i}"]) for i in range(int(z["n"]))]
