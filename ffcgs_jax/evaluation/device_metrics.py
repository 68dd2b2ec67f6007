"""Grasp evaluation on the device: `metrics.evaluate`'s figures as one jit-compiled function over the whole batch.

`metrics.py` scores grasps from the mesh in float64 NumPy/SciPy, one grasp at a time (trimesh closest points, Qhull,
HiGHS): about 20 ms a grasp on two CPU cores, which made it most of a `synthesize` call. This module computes the
same figures for every grasp at once, on the device that ran the synthesis, and stays the path `synthesize` uses;
`metrics.evaluate` is kept as its independent reference in tests.

- Closest points: every fingertip point against every triangle, streamed in chunks of `FACE_CHUNK` triangles
  through one compiled step that keeps each point's nearest triangle and sums the solid angles (so one executable
  serves every mesh, and the cost grows linearly with its faces); the normal rule of `metrics.mesh_contacts` (face normal; (p - closest) / d off an
  edge or vertex; on the surface at an edge or vertex the mean of the faces that share it, from tables built once
  per mesh). The sign comes from the generalised winding number (inside where > 1/2), as the SDF's does, instead
  of trimesh's ray tests: the same on watertight meshes, and defined on open ones.
- E_g: the Q-distance LP of the touching contacts' wrenches in the in-graph simplex (`kernels.lp_jax`), the same
  LP `metrics.q_distance_reference` gives HiGHS. Fingertips that do not touch exert no force: their wrench rows
  are replaced by a touching fingertip's, which leaves the wrench hull, and so every figure, unchanged.
- Ferrari-Canny epsilon: the minimum over unit wrench directions u of the support h(u) = max_j u . w_j (for a hull
  holding the origin, the distance to its nearest facet), searched by facet walks (`search_epsilon`): from the
  `EPS_KEEP` lowest of `EPS_STARTS` spread directions, each step shoots a ray from the origin along the current
  direction (`ray_facet`, a 6-row LP) and moves to the normal of the facet the ray leaves through, which never
  increases the facet's distance; a walk ends in a facet holding the origin's foot point. The first ray of a walk is
  solved cold, each later one from the last ray's optimal basis by dual simplex pivots (`_dual_simplex`: the LP's
  duals do not depend on the ray, so that basis stays dual feasible). Every h(u) of a unit u
  bounds epsilon from above, so the result is never below Qhull's; bench/RESULTS.md gives how close it comes
  ("End-to-end speed"). Force closure: a full-rank wrench set (as `metrics.epsilon_q1` asks), the origin in the
  hull (E_g at most `eps_tol`'s bound) and the searched epsilon above its bound.
"""

import cachetools
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import trimesh

from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.evaluation.epsilon_search import EPS_STARTS, eps_tol, full_rank, search_epsilon
from ffcgs_jax.evaluation.metrics import MetricsConfig
from ffcgs_jax.geometry import mesh_io
from ffcgs_jax.geometry import sdf as sdf_mod
from ffcgs_jax.kernels import lp_host, lp_jax, quality
from ffcgs_jax.kernels.directions import sphere_basis
from ffcgs_jax.kernels.triangles import closest_offset, dist2, orientation, solid_angles, tri_table
from ffcgs_jax.runtime import compile_clock, compiled, traced_store
from ffcgs_jax.core.types import Array, Float

_POINT_CHUNK = 4096  # fingertip points per brute-force pass (bounds the (points, triangles) work in flight)
FACE_CHUNK = 2048  # triangles per streamed chunk: every mesh, of 10 or 200,000 faces, runs through one executable
_MIN_GRASPS = 32  # the smallest batch bucket: smaller batches are padded to it (see `_bucket`)
_WIDTH = 33  # columns of a chunk row: `tri_table`'s 12, face normal 3, edge normals 9, vertex normals 9
Host = Array | np.ndarray


class MeshTable(NamedTuple):
    """A triangle mesh as the device evaluation reads it (a pytree): its triangles in chunks of `FACE_CHUNK` rows,
    the last padded with degenerate triangles 1 km away, never the closest and of zero solid angle. The chunks are
    streamed through one compiled step (`_chunk_step`), so the executables do not depend on the face count.

    Attributes:
        chunks: per chunk a (FACE_CHUNK, 33) array, per triangle: a - centre, b - a, c - a, |b - a|^2,
            (b - a).(c - a), |c - a|^2 (`tri_table`: relative to `centre`, so float32 keeps about 1e-8 m
            on a 10 cm object); the outward unit face normal (3); per edge ab, bc, ca the normalised sum of the face
            normals sharing it (9); per vertex a, b, c the same over the faces sharing it (9).
        centre: (3,) the frame origin of the rows, metres.
        scale: () the mesh's scale (trimesh `scale`): "on the surface" means within 1e-9 of it, as in `metrics`.
        orient: () +1 for an outward mesh, -1 for an inside-out one (signed volume): winding numbers are multiplied.
    """

    chunks: tuple[Float[Array, "K 33"], ...]
    centre: Float[Array, " 3"]
    scale: Float[Array, ""]
    orient: Float[Array, ""]


_TABLES = cachetools.LRUCache(16)
compiled.register("evaluation.device_metrics triangle tables", _TABLES)
# the kernels' host-side memos, registered here: `kernels` sits beside `runtime`, and cannot import it
compiled.register("kernels.quality basis", quality.basis)
compiled.register("kernels.lp_jax basis", lp_jax.basis_from_key)
compiled.register("kernels.lp_host solver", lp_host.host_fn)


def mesh_table(mesh: trimesh.Trimesh, dtype=None) -> MeshTable:
    """The `MeshTable` of `mesh` on the default device, cached per `mesh_io.mesh_sha256` and dtype (16 meshes, least recently
    used dropped), so repeated calls on one object build it once."""
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise FfcgsError(f"device evaluation needs a triangle mesh with faces, got {type(mesh).__name__}")
    dtype = jnp.asarray(0.0).dtype if dtype is None else np.dtype(dtype)
    key = (mesh_io.mesh_sha256(mesh), str(dtype))
    if (table := _TABLES.get(key)) is None:
        table = _TABLES[key] = jax.device_put(_build_table(mesh, dtype))
    return table


def _bucket(n: int, least: int) -> int:
    """n padded up to a power of two >= `least` up to 1024, then to multiples of 1024: few batch sizes, so few
    executables (each costs hundreds of memory mappings on a CPU, and a process has 65,530: a test process ran out),
    and at most 1023 rows of padding past 1024."""
    return max(least, 1 << (n - 1).bit_length()) if n <= 1024 else -(-n // 1024) * 1024


def clear_cache() -> None:
    """Forget the cached triangle tables (`mesh_table` builds the next one anew)."""
    _TABLES.clear()


def _unit_rows(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.where(n > 0, v / np.where(n > 0, n, 1.0), 0.0)


def _build_table(mesh: trimesh.Trimesh, dtype) -> MeshTable:
    verts = np.asarray(mesh.vertices, np.float64)
    faces = np.asarray(mesh.faces, np.int64)
    if not np.isfinite(verts).all():
        raise FfcgsError("device evaluation: mesh vertices contain NaN or inf")
    tri = verts[faces]
    centre = 0.5 * (tri.reshape(-1, 3).min(0) + tri.reshape(-1, 3).max(0))
    fn = np.asarray(mesh.face_normals, np.float64)  # `metrics.mesh_contacts` reads trimesh's normals as they are
    fn3 = np.repeat(fn, 3, axis=0)  # each face's normal once per corner (and per edge)

    def sums(index, n):  # per index, the sum of the normals given it (np.add.at's result, 10x quicker)
        return np.stack([np.bincount(index, weights=fn3[:, j], minlength=n) for j in range(3)], axis=1)

    vsum = sums(faces.ravel(), len(verts))
    edges = np.sort(np.stack([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]], 1).reshape(-1, 2), axis=1)
    _, inv = np.unique(edges[:, 0] * len(verts) + edges[:, 1], return_inverse=True)  # one integer per edge: fast
    inv = inv.ravel()
    esum = sums(inv, inv.max() + 1)
    f = len(faces)
    table = np.concatenate([tri_table(tri - centre, np.float64)[:f], fn,  # padded below, not to its chunk size
                            _unit_rows(esum[inv.reshape(f, 3)]).reshape(f, 9), _unit_rows(vsum[faces]).reshape(f, 9)],
                           axis=1)
    pad = -f % FACE_CHUNK
    far = np.concatenate([tri_table(np.full((1, 3, 3), 1e3), np.float64)[:1], np.tile([0.0, 0.0, 1.0], (1, 7))], 1)
    table = np.concatenate([table, np.broadcast_to(far, (pad, _WIDTH))]).astype(dtype)
    return MeshTable(
        chunks=tuple(table[i:i + FACE_CHUNK] for i in range(0, len(table), FACE_CHUNK)),
        centre=centre.astype(dtype),
        scale=np.asarray(max(float(mesh.scale), 1e-12), dtype),
        orient=np.asarray(orientation(tri), dtype),
    )


# ------------------------------------------------------------------------------------------------ contacts


def _edge_tol(dtype) -> float:
    """Barycentric tolerance for "on an edge or vertex": the reference's 1e-9 in float64; float32 rounds at ~1e-7."""
    return 1e-9 if jnp.dtype(dtype) == jnp.float64 else 1e-5


def _barycentric(row, closest_rel):
    """(3,) barycentric coordinates of a point of the triangle `row` (relative to a), from the Gram system."""
    ab, ac = row[3:6], row[6:9]
    d00, d01, d11 = row[9], row[10], row[11]
    r0, r1 = ab @ closest_rel, ac @ closest_rel
    det = d00 * d11 - d01 * d01
    ok = det > 0
    det = jnp.where(ok, det, 1.0)
    v = jnp.where(ok, (d11 * r0 - d01 * r1) / det, 0.0)
    w = jnp.where(ok, (d00 * r1 - d01 * r0) / det, 0.0)
    return jnp.stack([1.0 - v - w, v, w])


class Nearest(NamedTuple):
    """Per fingertip point, what the chunks streamed so far give (`_chunk_step`): the squared distance to the
    nearest triangle, that triangle's chunk row (33,), and the sum of all triangles' solid angles."""

    d2: Float[Array, " P"]
    row: Float[Array, "P 33"]
    solid_angle: Float[Array, " P"]


def _chunk_step(state: Nearest, chunk: Float[Array, "K 33"], points: Float[Array, "P 3"], centre) -> Nearest:
    """`state` updated with one chunk of triangles. Only a strictly nearer triangle replaces the kept one, so ties go
    to the lower triangle index, as one argmin over the whole mesh would."""
    r = [chunk[:, i] for i in range(12)]
    ab, ac = chunk[:, 3:6], chunk[:, 6:9]
    recip = lambda x: jnp.where(x != 0, 1.0 / jnp.where(x != 0, x, 1.0), 0.0)  # noqa: E731
    cols = r + [recip(r[9]), recip(r[11]), recip(jnp.sum((ac - ab) ** 2, axis=1))]  # `triangles.search_table`'s
    corners = r[0:3] + [r[i] + r[3 + i] for i in range(3)] + [r[i] + r[6 + i] for i in range(3)]

    def one(p):
        # structure-of-arrays kernels over the chunk's triangles: XLA vectorises them, where a vmap over rows of
        # `closest_offset` ran 5x slower on a CPU; the kept row's closest point is recomputed exactly after
        d2 = dist2(p[0], p[1], p[2], cols)
        f = jnp.argmin(d2)
        return d2[f], chunk[f], jnp.sum(solid_angles(p[0], p[1], p[2], corners))

    d2, row, wind = jax.lax.map(one, points - centre[None, :], batch_size=_POINT_CHUNK)
    nearer = d2 < state.d2
    return Nearest(jnp.where(nearer, d2, state.d2), jnp.where(nearer[:, None], row, state.row),
                   state.solid_angle + wind)


def _mesh_point(centre, scale, orient, near_d2, r, solid_angle, p):
    """Closest point, outward normal and signed distance of one point p (3,) from its nearest triangle's chunk row
    `r` and the mesh's total solid angle there; `metrics.mesh_contacts`'s rules."""
    del near_d2  # the distance is recomputed from the row, as the search computed it
    p = p - centre
    row = r[:12]
    off = closest_offset(p, row)
    closest = p + off
    dist = jnp.sqrt(jnp.sum(off * off))
    tri0 = row[0:3]
    inside = orient * solid_angle / (4 * jnp.pi) > 0.5
    edge_tol = _edge_tol(p.dtype)
    bary = _barycentric(row, closest - tri0)
    on_edge = jnp.any(bary < edge_tol)
    on_surface = dist <= edge_tol * scale
    n = r[12:15]
    away = (p - closest) / jnp.where(dist > 0, dist, 1.0)
    n = jnp.where(on_edge & ~inside & ~on_surface, away, n)
    # on the surface at an edge or vertex: the shared normal of the feature the point lies on
    small = bary < edge_tol
    vertex = jnp.sum(small) >= 2
    which_vertex = jnp.argmax(~small)  # the one coordinate that is not 0
    which_edge = jnp.argmax(small)  # the edge opposite the 0 coordinate: 0 -> bc (edge 1), 1 -> ca (2), 2 -> ab (0)
    edge_normal, vertex_normal = r[15:24].reshape(3, 3), r[24:33].reshape(3, 3)
    shared = jnp.where(vertex, vertex_normal[which_vertex], edge_normal[jnp.array([1, 2, 0])[which_edge]])
    n = jnp.where(on_edge & on_surface, shared, n)
    return closest + centre, n, jnp.where(inside, -dist, dist)


def _start(points: Float[Array, "P 3"]) -> Nearest:
    """The state before any chunk: nothing near, no solid angle."""
    p, dt = points.shape[0], points.dtype
    return Nearest(jnp.full((p,), jnp.inf, dt), jnp.zeros((p, _WIDTH), dt), jnp.zeros((p,), dt))


def mesh_contacts(table: MeshTable, points: Float[Array, "P 3"]):
    """Closest points, normals and signed distances of `points` on the mesh, all chunks in one trace (for benchmarks
    that jit the contacts apart; `evaluate` streams the chunks through one compiled step instead)."""
    state = _start(points)
    for chunk in table.chunks:
        state = _chunk_step(state, chunk, points, table.centre)
    return _points_on_mesh(table.centre, table.scale, table.orient, state, points)


def _points_on_mesh(centre, scale, orient, state: Nearest, points):
    return jax.vmap(_mesh_point, (None, None, None, 0, 0, 0, 0))(centre, scale, orient, *state, points)


def _sdf_contacts(grid: sdf_mod.GradientSDF, points: Float[Array, "P 3"]):
    """`metrics.sdf_contacts` in JAX: the Gradient-SDF's own zero level (for objects fused from depth frames)."""
    d, n = sdf_mod.query(grid, points)
    n = n / jnp.linalg.norm(n, axis=1, keepdims=True)
    return points - d[:, None] * n, n, d


# ------------------------------------------------------------------------------------------------ quality


def _grasp(closest, normals, signed, q, lower, upper, centre, radius, starts, U, cfg: MetricsConfig):
    dt = closest.dtype
    touching = jnp.abs(signed) <= cfg.contact_tol
    any_touch = jnp.any(touching)
    src = jnp.where(touching, jnp.arange(len(signed)), jnp.argmax(touching))  # silent tips repeat a touching one
    W = quality.primitive_wrenches(closest[src], normals[src], centre, radius, cfg.lp_friction, cfg.cone_edges)
    e_g, lp_ok, _ = lp_jax.q_distance(W, U)
    spans = full_rank(W)
    eps = search_epsilon(W, starts)
    eps_min, g_tol = eps_tol(dt)
    closure = any_touch & lp_ok & spans & (e_g <= g_tol) & (eps > eps_min)
    e_g = jnp.where(any_touch, e_g, jnp.nan)
    e_c = jnp.sqrt(jnp.mean((signed + cfg.d0) ** 2))
    mid, half = 0.5 * (lower + upper), 0.5 * (upper - lower)
    e_q = jnp.mean(((q - mid) / (upper - lower)) ** 2)
    return dict(
        epsilon=jnp.where(closure, eps, 0.0),
        force_closure=closure,
        E_g=e_g,
        E=e_g + cfg.a_c * e_c + cfg.a_q * e_q,
        E_c=e_c,
        E_c_cm=100 * e_c,
        E_q=e_q,
        joint_limit_use=jnp.max(jnp.abs(q - mid) / half),
        contact_dist=signed,
        normals=normals,
        n_contacts=jnp.sum(touching).astype(jnp.int32),
        lp_ok=lp_ok,
    )


def _quality(closest, normals, signed, q, lower, upper, centre, radius, cfg: MetricsConfig):
    """Every grasp's figures from its fingertips' closest points, normals and signed distances, (B, C, ...)."""
    U = quality.basis(cfg.basis_size)  # a host array: the LP's basis is part of its compiled form
    starts = jnp.asarray(sphere_basis(EPS_STARTS).T, closest.dtype)
    grasp = functools.partial(_grasp, U=U, cfg=cfg)
    return jax.vmap(grasp, (0, 0, 0, 0, None, None, None, None, None))(
        closest, normals, signed, q, lower, upper, centre, radius, starts)


def _flat(contacts):
    return contacts.reshape(-1, 3)


def _start_mesh(contacts) -> Nearest:
    return _start(_flat(contacts))


def _step_mesh(state: Nearest, chunk, contacts, centre) -> Nearest:
    return _chunk_step(state, chunk, _flat(contacts), centre)


def _finish_mesh(state: Nearest, table_centre, scale, orient, contacts, q, lower, upper, centre, radius,
                 cfg: MetricsConfig):
    b, c = contacts.shape[:2]
    closest, normals, signed = _points_on_mesh(table_centre, scale, orient, state, _flat(contacts))
    return _quality(closest.reshape(b, c, 3), normals.reshape(b, c, 3), signed.reshape(b, c), q, lower, upper,
                    centre, radius, cfg)


def _evaluate_sdf(grid, contacts, q, lower, upper, centre, radius, cfg: MetricsConfig):
    b, c = contacts.shape[:2]
    closest, normals, signed = _sdf_contacts(grid, _flat(contacts))
    return _quality(closest.reshape(b, c, 3), normals.reshape(b, c, 3), signed.reshape(b, c), q, lower, upper,
                    centre, radius, cfg)


# One executable of each, whatever the mesh: the chunks stream through `_step_jit`, one call per chunk, queued on
# the device back to back (a 200,000-face mesh is about 100 calls of a few microseconds' dispatch each).
_start_jit = jax.jit(_start_mesh, keep_unused=True)  # committed where the contacts are, as a step's state
_step_jit = jax.jit(_step_mesh)
_sdf_jit = jax.jit(_evaluate_sdf, static_argnames=("cfg",))
# The argument signatures run once already, each with the mesh evaluation's last step compiled ahead (its trace
# is most of the evaluation's compile time, and `traced_store` keeps it on disk with the compilation cache), are
# kept in `runtime.compiled` under STAGE: key -> (executable, call), or None where a first run compiled by jit.
STAGE = "evaluate_mesh"


def _finish(key, cfg: MetricsConfig, *args):
    kept = compiled.get(STAGE, key)
    if kept is None:
        lowered, call = traced_store.lower(STAGE, functools.partial(_finish_mesh, cfg=cfg), args, cfg)
        kept = (lowered.compile(), call)
        compiled.put(STAGE, key, kept)
    executable, call = kept
    return call(executable, *args)


def _signature(x) -> tuple:
    return (x.shape, str(x.dtype), str(getattr(x, "sharding", None)))


def evaluate(surface: MeshTable | sdf_mod.GradientSDF, contacts: Float[Array, "B C 3"], q: Float[Array, "B Q"],
             lower: Float[Host, " Q"], upper: Float[Host, " Q"], centre: Float[Host, " 3"],
             radius: Float[Host, ""] | float, cfg: MetricsConfig = MetricsConfig()) -> dict[str, Array]:
    """`metrics.evaluate`'s figures for a batch of grasps, computed on the device; the results stay on the device
    (fetch them once with `jax.device_get`).

    Args:
        surface: the object: a `MeshTable` (`mesh_table(mesh)`), or a `GradientSDF` for an object known only by its
            SDF (its own zero level, as `metrics.sdf_contacts`).
        contacts: (B, C, 3) fingertip contact points, metres, in the surface's frame.
        q: (B, Q) channel positions; lower, upper: (Q,) their limits.
        centre: (3,) torque origin; radius: torque scale L > 0 (the synthesis's `Target`).
        cfg: friction, cone, basis, energy weights and the touching tolerance.

    Returns:
        dict of device arrays: epsilon, force_closure, E_g (NaN without a touching fingertip), E, E_c, E_c_cm, E_q,
        joint_limit_use, n_contacts, lp_ok (B,); contact_dist (B, C); normals (B, C, 3).
    """
    run, _ = compile_evaluate(surface, contacts, q, lower, upper, centre, radius, cfg)
    return run()


def compile_evaluate(surface, contacts, q, lower, upper, centre, radius, cfg: MetricsConfig = MetricsConfig(),
                     compile: bool = True):
    """`evaluate`'s arguments checked and its executables compiled: `run()` gives its result, and the seconds the
    compilation took (0 when an earlier call of the same batch compiled it, whatever its mesh), so callers report
    compile apart. `compile` False: (None, 0.0) where nothing compiled yet fits, for callers that must not compile
    now. A first call runs the evaluation once to compile it; its `run()` then returns that result."""
    cfg.check()
    if contacts.ndim != 3 or contacts.shape[-1] != 3 or q.ndim != 2 or q.shape[0] != contacts.shape[0]:
        raise FfcgsError(f"device evaluation needs contacts (B, C, 3) and q (B, Q), got {contacts.shape} and "
                         f"{q.shape}")
    dt = contacts.dtype
    cast = lambda x: jnp.asarray(x, dt)  # noqa: E731
    b = contacts.shape[0]
    pad = _bucket(b, _MIN_GRASPS) - b  # rows repeating the last grasp, dropped from the results
    rows = lambda x: jnp.concatenate([x, jnp.repeat(x[-1:], pad, axis=0)]) if pad else x  # noqa: E731
    surface = jax.tree.map(cast, surface)
    args = (rows(contacts), rows(cast(q)), cast(lower), cast(upper), cast(centre), cast(radius))
    mesh = isinstance(surface, MeshTable)
    shapes = (surface.chunks[0], surface.centre) if mesh else surface
    key = (str(jax.tree.map(_signature, (shapes, args))), type(surface).__name__, cfg, jax.default_backend())

    def run():
        if mesh:
            state = _start_jit(args[0])
            for chunk in surface.chunks:
                state = _step_jit(state, chunk, args[0], surface.centre)
            out = _finish(key, cfg, state, surface.centre, surface.scale, surface.orient, *args)
        else:
            out = _sdf_jit(surface, *args, cfg=cfg)
        return {k: v[:b] for k, v in out.items()} if pad else out

    if compiled.has(STAGE, key):
        return run, 0.0
    if not compile:
        return None, 0.0
    with compile_clock.compiling() as seconds:
        first = run()
        if mesh and len(surface.chunks) == 1:  # a step's own state, as a later mesh's second chunk will pass it
            _step_jit(_step_jit(_start_jit(args[0]), surface.chunks[0], args[0], surface.centre), surface.chunks[0],
                      args[0], surface.centre)
    if not compiled.has(STAGE, key):
        compiled.put(STAGE, key, None)
    return (lambda: first), seconds[0]
