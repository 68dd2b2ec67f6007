"""The object's convex parts for MuJoCo's collisions (`collision.parts`), cached on disk.

The parts depend only on the mesh and the collision settings (`PhysicsConfig.collision`, its budget, the voxel and
CoACD settings, the part limits), and the slower methods take seconds, so they are cached as an .npz named by a
SHA-256 of both, in `$FFCGS_CACHE_DIR/convex` (default `~/.cache/ffcgs-jax/convex`). A result that fell back to
the coarse geometry at its budget is not cached: the next run tries the asked-for method again.
"""

import hashlib
import json
import os
import warnings
from pathlib import Path

import numpy as np
import trimesh

from ffcgs_jax.core import files
from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.geometry import mesh_io
from ffcgs_jax.physics import collision
from ffcgs_jax.physics.config import PhysicsConfig

_VERSION = 3  # bump when the decomposition's meaning changes, so old cache entries are not reused


def cache_dir() -> Path:
    root = os.environ.get("FFCGS_CACHE_DIR")
    return (Path(root) if root else Path.home() / ".cache" / "ffcgs-jax") / "convex"


def _key(mesh: trimesh.Trimesh, cfg: PhysicsConfig) -> str:
    h = hashlib.sha256(mesh_io.mesh_sha256(mesh).encode())
    settings = dict(v=_VERSION, t=cfg.coacd_threshold, n=cfg.max_hulls, k=cfg.hull_vertices, c=cfg.collision,
                    cells=cfg.voxel_cells, tol=cfg.voxel_tol)  # not the budget: only finished parts are cached
    h.update(json.dumps(settings, sort_keys=True).encode())
    return h.hexdigest()[:32]


def decompose(mesh: trimesh.Trimesh, cfg: PhysicsConfig = PhysicsConfig(), use_cache: bool = True
              ) -> list[tuple[np.ndarray, np.ndarray]]:
    """Convex parts of `mesh` as (vertices (V, 3) float64, faces (F, 3) int32), in the mesh's frame, by
    `cfg.collision` (`collision.parts`)."""
    path = cache_dir() / f"{_key(mesh, cfg)}.npz"
    if use_cache and path.is_file():
        try:
            return _read(path)
        except Exception:  # noqa: BLE001 - a truncated cache file is rebuilt, not fatal
            pass
    parts, final = compute_parts(mesh, cfg)
    if use_cache and final:
        try:
            _write(path, parts)
        except FfcgsError as e:  # an unusable cache folder costs time on the next run, not this result
            warnings.warn(f"convex parts not cached ({e}); set FFCGS_CACHE_DIR to a writable folder", stacklevel=2)
    return parts


def compute_parts(mesh: trimesh.Trimesh, cfg: PhysicsConfig) -> tuple[list[tuple[np.ndarray, np.ndarray]], bool]:
    """The parts and whether they may be cached (False when the method fell back at its budget)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        parts = collision.parts(mesh, cfg)
    for w in caught:  # passed on to the caller's handlers (the CLI prints each as one line)
        warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    return parts, not any(issubclass(w.category, collision.BudgetWarning) for w in caught)


def _write(path: Path, parts) -> None:
    arrays = {}
    for i, (v, f) in enumerate(parts):
        arrays[f"v{i}"], arrays[f"f{i}"] = v, f
    # atomic, so parallel workers never read half a file
    files.atomic_write(files.check_output(path, "convex cache"), lambda f: np.savez(f, n=len(parts), **arrays))


def _read(path: Path) -> list[tuple[np.ndarray, np.ndarray]]:
    with np.load(path) as z:
        return [(z[f"v{i}"], z[f"f{i}"]) for i in range(int(z["n"]))]
