"""Generated training shapes: boxes, cylinders, ellipsoids and capsules of graspable sizes.

The YCB training split has 36 objects; these add shape variety for the sampler (`ffcgs dataset build
--procedural N`). Shape i depends only on (seed, i), so adding shapes never changes the earlier ones. Sizes are
drawn so that the hand can close around some part: the smallest extent is 2-9 cm and the largest at most 21 cm
(round shapes get 5 mm added to their radii).
Each mesh rests on z = 0 and is centred in x and y, like the built-in objects.
"""

import hashlib

import numpy as np
import trimesh

KINDS = ("box", "cylinder", "ellipsoid", "capsule")

HELD_OUT_SEEDS = {1000: "bench/quality.py's unseen procedural shapes",
                  2000: "the complex family of bench/quality.py and bench/validated_call.py",
                  3200: "bench/diverse_objects.py's set",
                  4500: "bench/robust_verdict.py's complex shapes and the robust predictor's held-out labels",
                  4600: "the held-out complex shapes of every `ffcgs learn` report"}
"""Seeds whose shapes the benchmarks report on: never training data (`dataset.objects.sources` refuses them)."""


def _rng(seed: int, index: int) -> np.random.Generator:
    digest = hashlib.sha256(f"ffcgs-procedural:{seed}:{index}".encode()).digest()
    return np.random.default_rng(int.from_bytes(digest[:8], "little"))


def shape(seed: int, index: int) -> tuple[str, trimesh.Trimesh]:
    """(name "proc_NNNN_kind", watertight mesh in metres) of procedural shape `index`."""
    rng = _rng(seed, index)
    kind = KINDS[index % len(KINDS)]
    small = rng.uniform(0.02, 0.08)
    large = rng.uniform(max(small, 0.04), 0.20)
    mid = rng.uniform(small, large)
    if kind == "box":
        mesh = trimesh.creation.box(extents=rng.permutation([small, mid, large]))
    elif kind == "cylinder":
        # upright or lying: a can or a rolling pin
        mesh = trimesh.creation.cylinder(radius=small / 2 + 0.005, height=large, sections=48)
        if rng.random() < 0.5:
            mesh.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    elif kind == "ellipsoid":
        mesh = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
        mesh.apply_scale(np.array([small, mid, min(large, 0.12)]) / 2 + 0.005)
    else:
        mesh = trimesh.creation.capsule(height=large - small, radius=small / 2 + 0.005, count=[24, 24])
        if rng.random() < 0.5:
            mesh.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
    mesh.apply_transform(trimesh.transformations.rotation_matrix(rng.uniform(0, 2 * np.pi), [0, 0, 1]))
    lo, hi = mesh.bounds
    mesh.apply_translation([-(lo[0] + hi[0]) / 2, -(lo[1] + hi[1]) / 2, -lo[2]])
    return f"proc_{index:04d}_{kind}", mesh


# Geometrically complex shapes: what makes a convex decomposition slow or wrong (many lobes, thin plates, holes that
# must stay open, deep concavities). Built as exact booleans of primitives by manifold3d, so every mesh is a closed,
# oriented 2-manifold; `complex_shape` keeps them near `COMPLEX_FACES` faces, like the simplified YCB meshes.
COMPLEX_KINDS = ("blob", "fins", "torus", "cup", "bowl", "c_shape", "plate")
COMPLEX_FACES = 3000
_MAX_FACES = int(1.2 * COMPLEX_FACES)


def complex_shape(seed: int, index: int) -> tuple[str, trimesh.Trimesh]:
    """(name "cplx_NNNN_kind", watertight mesh in metres) of complex procedural shape `index`: kind
    `COMPLEX_KINDS[index % 7]`, largest extent 5-15 cm, thin parts 3-8 mm, about `COMPLEX_FACES` faces, resting on
    z = 0 and centred in x and y. Depends only on (seed, index), and differs from `shape(seed, index)`."""
    import manifold3d as mf

    rng = _rng(seed + 0x5EED, index)
    kind = COMPLEX_KINDS[index % len(COMPLEX_KINDS)]
    solid = _BUILDERS[kind](mf, rng)
    if solid.num_tri() < COMPLEX_FACES:  # split long edges: equilateral triangles of the target count cover the area
        edge = float(np.sqrt(solid.surface_area() / (0.433 * COMPLEX_FACES)))
        for scale in (1.0, 1.2, 1.5, 2.0):  # splitting overshoots on long thin faces: lengthen until within bounds
            finer = solid.refine_to_length(edge * scale)
            if finer.num_tri() <= _MAX_FACES:
                solid = finer
                break
    for tol in (0.0002, 0.0005, 0.001, 0.002):  # coarsen until near the target face count
        if solid.num_tri() <= _MAX_FACES:
            break
        solid = solid.simplify(tol)
    m = solid.to_mesh()
    mesh = trimesh.Trimesh(np.asarray(m.vert_properties, np.float64)[:, :3], np.asarray(m.tri_verts, np.int64))
    mesh.apply_transform(trimesh.transformations.rotation_matrix(rng.uniform(0, 2 * np.pi), [0, 0, 1]))
    lo, hi = mesh.bounds
    mesh.apply_translation([-(lo[0] + hi[0]) / 2, -(lo[1] + hi[1]) / 2, -lo[2]])
    return f"cplx_{index:04d}_{kind}", mesh


def _ellipsoid(mf, radii, centre, segments: int):
    return mf.Manifold.sphere(1.0, segments).scale(tuple(radii)).translate(tuple(centre))


def _blob(mf, rng):
    """A union of 5-9 overlapping ellipsoids: many lobes and the creases between them."""
    n = int(rng.integers(5, 10))
    core = rng.uniform(0.02, 0.03, 3)
    parts = [_ellipsoid(mf, core, (0, 0, 0), 24)]
    for _ in range(n - 1):
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        radii = rng.uniform(0.008, 0.02, 3)
        parts.append(_ellipsoid(mf, radii, direction * rng.uniform(0.025, 0.04), 16))
    return mf.Manifold.batch_boolean(parts, mf.OpType.Add)


def _fins(mf, rng):
    """A rounded body with 2-4 thin plates (3-8 mm) standing out of it: thin parts a hull would swallow."""
    body = _ellipsoid(mf, rng.uniform([0.02, 0.02, 0.03], [0.03, 0.03, 0.05]), (0, 0, 0), 40)
    fins = [body]
    n = int(rng.integers(2, 5))
    for k in range(n):
        t = rng.uniform(0.003, 0.008)
        span = rng.uniform(0.035, 0.06)
        fin = mf.Manifold.cube((span, t, rng.uniform(0.03, 0.06)), True).translate((span / 2, 0, 0))
        fins.append(fin.rotate((0, 0, 360.0 * k / n + rng.uniform(-15, 15))))
    return mf.Manifold.batch_boolean(fins, mf.OpType.Add)


def _torus(mf, rng):
    """A ring lying or standing: a hole through the middle."""
    major, minor = rng.uniform(0.03, 0.055), rng.uniform(0.008, 0.016)
    ring = mf.Manifold.revolve(mf.CrossSection.circle(minor, 24).translate((major, 0)), 64)
    return ring.rotate((90, 0, 0)) if rng.random() < 0.5 else ring


def _cup(mf, rng):
    """A mug: an open cylinder with walls 3-8 mm thick and a ring handle whose opening stays open."""
    r, h, wall = rng.uniform(0.03, 0.045), rng.uniform(0.06, 0.12), rng.uniform(0.003, 0.008)
    outer = mf.Manifold.cylinder(h, r, r, 96)
    inner = mf.Manifold.cylinder(h, r - wall, r - wall, 96).translate((0, 0, wall))
    hole, thick = rng.uniform(0.012, 0.02), rng.uniform(0.004, 0.008)
    handle = mf.Manifold.revolve(mf.CrossSection.circle(thick, 16).translate((hole + thick, 0)), 48)
    handle = handle.rotate((90, 0, 0)).translate((r + hole * 0.6, 0, h / 2))
    return (outer - inner) + (handle - mf.Manifold.cylinder(h, r - wall, r - wall, 96).translate((0, 0, wall)))


def _bowl(mf, rng):
    """A hemispherical shell 3-8 mm thick: a deep concavity open on top."""
    r, wall = rng.uniform(0.04, 0.07), rng.uniform(0.003, 0.008)
    shell = mf.Manifold.sphere(r, 64) - mf.Manifold.sphere(r - wall, 64)
    return shell - mf.Manifold.cube((3 * r, 3 * r, 2 * r), True).translate((0, 0, r * rng.uniform(0.0, 0.5) + r))


def _c_shape(mf, rng):
    """Three quarters of a thick ring of rectangular section: a C whose mouth a hull would close."""
    major = rng.uniform(0.03, 0.05)
    w, t = rng.uniform(0.01, 0.02), rng.uniform(0.02, 0.05)
    section = mf.CrossSection.square((w, t), True).translate((major, 0))
    return mf.Manifold.revolve(section, 64, rng.uniform(220, 300))


def _plate(mf, rng):
    """A plate 3-8 mm thick with 2-3 round holes through it, standing on edge or lying."""
    a, b, t = rng.uniform(0.08, 0.14), rng.uniform(0.05, 0.09), rng.uniform(0.003, 0.008)
    plate = mf.Manifold.cube((a, b, t), True)
    n = int(rng.integers(2, 4))
    for k in range(n):
        radius = rng.uniform(0.008, min(0.018, b / 4))
        x = (k + 0.5) / n * a - a / 2
        plate = plate - mf.Manifold.cylinder(4 * t, radius, radius, 40, True).translate((x, 0, 0))
    return plate.rotate((90, 0, 0)) if rng.random() < 0.5 else plate


_BUILDERS = {"blob": _blob, "fins": _fins, "torus": _torus, "cup": _cup, "bowl": _bowl, "c_shape": _c_shape,
             "plate": _plate}
