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
