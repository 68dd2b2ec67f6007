"""The object's collision geometry for the physics test: convex parts by the method `PhysicsConfig.collision` names,
within `PhysicsConfig.collision_budget` seconds of wall clock.

MuJoCo collides a mesh geom through its convex hull, so the object is given as convex parts. Methods
(`COLLISIONS`; bench/RESULTS.md, "Collision geometry", compares them):

- "voxel-hulls" (default): `voxel_parts.voxel_hulls`, hulls of voxel clusters cut until each stays within
  `voxel_tol` of the solid. Its cost is set by the grid, not by the shape; past the budget it stops cutting.
- "coacd": CoACD with bounded search settings (`COACD_BOUNDED`), in a worker process killed at the budget (its C++
  loop cannot be interrupted from Python).
- "vhacd": V-HACD (`pip install vhacdx`), in a worker process the same way.
- "voxel-boxes", "patch-hulls": `voxel_parts.voxel_boxes`, `patch_hulls` (bench candidates).

Past the budget every method falls back to `voxel_hulls` on a coarse grid (`FALLBACK_CELLS`): coarser, still the
solid with its openings, and says so in one warning line.
"""

import multiprocessing
import time
import warnings

import numpy as np
import trimesh

from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.physics import voxel_parts
from ffcgs_jax.physics.config import PhysicsConfig
from ffcgs_jax.physics.voxel_parts import Part

CONVEX_RTOL = 0.01  # volume shortfall against the hull under which a mesh counts as convex
FALLBACK_CELLS = 24  # voxels along the longest side of the fallback's grid: well under a second on any mesh
# CoACD's search bounded: fewer MCTS iterations, nodes and depth and a coarser preprocessing grid than its defaults
# (150, 20, 3, 50); the worst of the YCB test split still needs minutes at its defaults
COACD_BOUNDED = dict(preprocess_resolution=30, mcts_iterations=60, mcts_nodes=10, mcts_max_depth=2)
MIN_EXTENT = 1e-4  # metres: a mesh thinner than this along an axis has no volume to collide with


class BudgetWarning(UserWarning):
    """The decomposition passed its budget and the object got the coarser fallback parts."""


def check_mesh(mesh: trimesh.Trimesh) -> None:
    """One line of FfcgsError for a mesh no decomposition can use: empty, non-finite or flat."""
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    if len(v) < 4 or len(f) < 4:
        raise FfcgsError(f"the object mesh is empty or degenerate ({len(v)} vertices, {len(f)} faces): "
                         "it needs a closed surface to collide with")
    if not np.isfinite(v).all():
        raise FfcgsError("the object mesh has NaN or inf vertices")
    if np.min(np.ptp(v, axis=0)) < MIN_EXTENT:
        raise FfcgsError(f"the object mesh is flat (extents {np.round(np.ptp(v, axis=0), 6).tolist()} m): "
                         "it has no volume to collide with")


def parts(mesh: trimesh.Trimesh, cfg: PhysicsConfig = PhysicsConfig()) -> list[Part]:
    """Convex parts of `mesh` by `cfg.collision` within `cfg.collision_budget` s, as (vertices (V, 3) float64,
    faces (F, 3) int32) in the mesh's frame. A convex mesh is its own (simplified) hull."""
    cfg.check()
    check_mesh(mesh)
    hull = mesh.convex_hull
    if mesh.is_volume and mesh.volume >= (1 - CONVEX_RTOL) * hull.volume:
        part = voxel_parts.simplified_hull(np.asarray(hull.vertices, np.float64), cfg.hull_vertices)
        if part is not None:
            return [part]
    deadline = time.monotonic() + cfg.collision_budget
    if cfg.collision == "voxel-hulls":
        out, complete = voxel_parts.voxel_hulls(mesh, cfg.voxel_cells, cfg.voxel_tol, cfg.max_hulls,
                                                cfg.hull_vertices, deadline)
        if not complete:
            warnings.warn(f"collision geometry: voxel-hulls stopped at its {cfg.collision_budget:g} s budget; "
                          f"the object has {len(out)} coarser convex parts", BudgetWarning, stacklevel=2)
    elif cfg.collision == "voxel-boxes":
        out = voxel_parts.voxel_boxes(mesh, max(8, cfg.voxel_cells // 2))
    elif cfg.collision == "patch-hulls":
        out = voxel_parts.patch_hulls(mesh, max_vertices=cfg.hull_vertices)
    else:
        out = in_worker(cfg.collision, mesh, _settings(cfg), cfg.collision_budget)
        if out is None:
            out = fallback(mesh, cfg)
            warnings.warn(f"collision geometry: {cfg.collision} passed its {cfg.collision_budget:g} s budget; "
                          f"the object has {len(out)} coarser voxel-hull parts instead", BudgetWarning, stacklevel=2)
    out = [p for p in out if len(p[0]) >= 4 and not flat(p[0])]
    if not out:
        raise FfcgsError(f"the {cfg.collision} decomposition of the object produced no solid part "
                         "(is the mesh degenerate?)")
    return out


def flat(vertices: np.ndarray) -> bool:
    """Whether a part's vertices lie in a plane (RMS distance from their best plane under `MIN_EXTENT` / 10): V-HACD
    and CoACD can return such a sliver, which has no volume to collide with and which MuJoCo refuses to compile
    ("coplanar vertices, cannot compute convex hull"), failing the whole object's scene."""
    v = np.asarray(vertices, np.float64)
    s = np.linalg.svd(v - v.mean(axis=0), compute_uv=False)
    return bool(s[-1] / np.sqrt(len(v)) < MIN_EXTENT / 10)


def fallback(mesh: trimesh.Trimesh, cfg: PhysicsConfig) -> list[Part]:
    """The coarse voxel-hull parts every method falls back to past its budget."""
    return voxel_parts.voxel_hulls(mesh, FALLBACK_CELLS, max(cfg.voxel_tol, 0.004), cfg.max_hulls,
                                   cfg.hull_vertices)[0]


def _settings(cfg: PhysicsConfig) -> dict:
    if cfg.collision == "coacd":
        return dict(threshold=cfg.coacd_threshold, max_convex_hull=cfg.max_hulls, max_ch_vertex=cfg.hull_vertices,
                    decimate=True, seed=0, **COACD_BOUNDED)
    return dict(maxConvexHulls=cfg.max_hulls, maxNumVerticesPerCH=cfg.hull_vertices, resolution=100_000,
                asyncACD=False)


def in_worker(method: str, mesh: trimesh.Trimesh, settings: dict, budget: float) -> list[Part] | None:
    """`method` ("coacd" or "vhacd" with its keyword `settings`) run in a fresh process, killed after `budget`
    seconds (None then). A fresh process ("spawn"): forking a process that runs JAX's threads can deadlock."""
    ctx = multiprocessing.get_context("spawn")
    receive, send = ctx.Pipe(duplex=False)
    verts, faces = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)
    worker = ctx.Process(target=_work, args=(send, method, verts, faces, settings), daemon=True)
    worker.start()
    send.close()
    try:
        if not receive.poll(budget):
            return None
        try:
            status, payload = receive.recv()
        except EOFError:
            worker.join()
            raise FfcgsError(f"the {method} decomposition of the object crashed (exit code "
                             f"{worker.exitcode})") from None
    finally:
        if worker.is_alive():
            worker.kill()
        worker.join()
        receive.close()
    if status != "ok":
        raise FfcgsError(payload)
    return payload


def _work(send, method: str, verts: np.ndarray, faces: np.ndarray, settings: dict) -> None:
    try:
        send.send(("ok", decompose_with(method, verts, faces, settings)))
    except Exception as e:  # noqa: BLE001 - sent back as the one line the caller raises
        send.send(("error", f"the {method} decomposition of the object failed: {type(e).__name__}: {e}"))
    finally:
        send.close()


def decompose_with(method: str, verts: np.ndarray, faces: np.ndarray, settings: dict) -> list[Part]:
    """CoACD ("coacd") or V-HACD ("vhacd") on the mesh, in this process (no time bound)."""
    if method == "coacd":
        try:
            import coacd
        except ImportError:
            raise FfcgsError("collision 'coacd' needs CoACD: pip install coacd") from None
        coacd.set_log_level("error")
        raw = coacd.run_coacd(coacd.Mesh(verts, faces.astype(np.int32)), **settings)
    elif method == "vhacd":
        try:
            import vhacdx
        except ImportError:
            raise FfcgsError("collision 'vhacd' needs V-HACD: pip install vhacdx") from None
        raw = vhacdx.compute_vhacd(verts, faces.astype(np.uint32), **settings)
    else:
        raise FfcgsError(f"no worker method {method!r}; methods: coacd, vhacd")
    return [(np.asarray(v, np.float64), np.asarray(f, np.int32)) for v, f in raw if len(v) >= 4]
