"""Loading object meshes from files or built-in names, with the checks that keep broken input out of the SDF.

Host only (NumPy and trimesh). Every problem with the caller's file raises `FfcgsError` naming the file.
"""

import hashlib
import pathlib
import warnings

import numpy as np
import trimesh

from ffcgs_jax.core import files
from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.geometry import objects
from ffcgs_jax.core.files import check_file

FORMATS = ("obj", "stl", "ply", "off", "glb", "gltf")  # mesh formats trimesh reads that we accept
MM_EXTENT = 2.0  # metres: a larger object is most likely in millimetres
TINY_EXTENT = 0.005  # metres: a smaller object is most likely scaled wrongly (no SVH fingertip grasps a 5 mm object)
SCALED_EXTENT = (1e-6, 1e6)  # metres: a scale that makes a mesh smaller or larger than this is refused
_FLAT = 1e-6  # a mesh thinner than this fraction of its size in some direction has no volume


def load_mesh(source: str | pathlib.Path, scale: float = 1.0) -> trimesh.Trimesh:
    """Read a triangle mesh in metres from a built-in object name or a file.

    A glb/gltf scene is flattened into one mesh (node transforms applied). Meshes that are not watertight are
    accepted with a warning: the SDF's winding-number sign handles holes. A watertight mesh whose faces wind
    inward is flipped. An object larger than 2 m warns that it looks like millimetres.

    Args:
        source: a built-in name (see `objects.names()`) or a path to an obj, stl, ply, off, glb or gltf file.
        scale: factor applied to the coordinates (0.001 turns millimetres into metres); must be > 0.

    Returns:
        The mesh, vertices merged, scaled. Its `metadata["ffcgs_source"]` records where it came from (`source_of`).

    Raises:
        FfcgsError: missing file, unsupported or unreadable format, no triangles (point cloud, path, empty file),
            NaN or inf coordinates, degenerate geometry (all faces of zero area, or flat), scale <= 0, or a scale
            that makes the mesh smaller than a micrometre or larger than 1000 km (`SCALED_EXTENT`).
    """
    if not (isinstance(scale, (int, float)) and np.isfinite(scale) and scale > 0):
        raise FfcgsError(f"scale must be a finite number > 0, got {scale!r}")
    path = _resolve(source)
    mesh = _read(path)
    name = str(path)

    verts = np.asarray(mesh.vertices, np.float64)
    faces = np.asarray(mesh.faces, np.int64).reshape(-1, 3)
    if len(faces) == 0 or len(verts) == 0:
        raise FfcgsError(f"mesh {name} is empty: it has no triangles")
    if not np.isfinite(verts).all():
        bad = int((~np.isfinite(verts).all(axis=1)).sum())
        raise FfcgsError(f"mesh {name} has {bad} vertices with NaN or inf coordinates")
    if faces.min() < 0 or faces.max() >= len(verts):
        raise FfcgsError(f"mesh {name} has faces that index missing vertices")
    raw = float(np.ptp(verts[np.unique(faces)], axis=0).max())
    if scale != 1 and raw > 0 and not SCALED_EXTENT[0] <= raw * scale <= SCALED_EXTENT[1]:
        # the scale, not the file, is wrong: past these sizes areas and volumes under- or overflow, and the mesh
        # would be refused as degenerate
        raise FfcgsError(f"scale {scale:g} (--scale) makes mesh {name} {raw * scale:.3g} m across ({raw:.3g} "
                         f"unscaled); a mesh in metres needs scale 1, one in millimetres 0.001")

    mesh = trimesh.Trimesh(vertices=verts * float(scale), faces=faces, process=True)
    used = mesh.vertices[np.unique(mesh.faces)]
    size = float(np.ptp(used, axis=0).max())
    if not mesh.area_faces.max() > 0 or size == 0:
        raise FfcgsError(f"mesh {name} is degenerate: all its faces have zero area")
    thickness = np.linalg.svd(used - used.mean(0), compute_uv=False)
    if thickness[-1] <= _FLAT * thickness[0]:
        raise FfcgsError(f"mesh {name} is flat (all vertices on one plane), so it encloses no volume")
    if mesh.is_watertight:
        if abs(mesh.volume) <= _FLAT * size**3:
            raise FfcgsError(f"mesh {name} encloses zero volume")
        if mesh.volume < 0:
            mesh.invert()
    else:
        warnings.warn(
            f"mesh {name} is not watertight (it has holes or open edges); the SDF's inside/outside comes from "
            "winding numbers and stays usable, but check the object",
            stacklevel=2,
        )
    if size > MM_EXTENT:
        warnings.warn(
            f"mesh {name} is {size:.3g} m across, which looks like millimetres; pass --scale 0.001 "
            "(load_mesh(..., scale=0.001)) to load it in metres",
            stacklevel=2,
        )
    if size < TINY_EXTENT:
        warnings.warn(
            f"mesh {name} is {size * 1000:.3g} mm across, which looks like a wrong scale (scale {scale:g} was "
            f"applied); a mesh in metres needs --scale 1, one in millimetres --scale 0.001",
            stacklevel=2,
        )
    # trimesh's hash of the geometry, kept until the mesh changes: `source_of` tells an edited mesh by it
    mesh.metadata[SOURCE_KEY] = (identity(source, scale, mesh), hash(mesh))
    return mesh


SOURCE_KEY = "ffcgs_source"


def source_of(mesh) -> dict[str, np.ndarray]:
    """Where `mesh` came from, as `identity`'s arrays, when `load_mesh` read it and it is unchanged since (moved,
    scaled or edited, it is no longer what the file holds); else {}. Cheap: trimesh keeps its geometry hash until
    the mesh changes, so this adds no work to a synthesis call."""
    recorded = mesh.metadata.get(SOURCE_KEY) if isinstance(mesh, trimesh.Trimesh) else None
    if recorded is None or recorded[1] != hash(mesh):
        return {}
    return dict(recorded[0])


def _resolve(source: str | pathlib.Path) -> pathlib.Path:
    """Path of a built-in object (a bare name) or of a file, checked to exist and to have a mesh format."""
    if isinstance(source, str) and source in objects.names():
        return objects.path(source)
    path = pathlib.Path(source)
    if not path.exists():
        hint = "" if path.suffix else f" (built-in objects: {', '.join(objects.names())})"
        raise FfcgsError(f"mesh file not found: {path}{hint}")
    check_file(path, "mesh file")
    if path.suffix.lower().lstrip(".") not in FORMATS:
        raise FfcgsError(f"mesh file {path} has unsupported format {path.suffix!r}; use one of {', '.join(FORMATS)}")
    _check_content(path)
    return path


_FORMAT_NAMES = {"obj": "a Wavefront OBJ", "stl": "an STL", "ply": "a PLY mesh"}
_MESH_CONTENT = ("a binary STL", "an ASCII STL", "a PLY mesh", "a binary glTF (.glb)", "an OFF mesh",
                 "a Wavefront OBJ")


def _content(path: pathlib.Path) -> str:
    """What the file's first bytes say it is: a mesh format's words ("a binary STL") or `files.kind_of`'s."""
    size = path.stat().st_size
    with open(path, "rb") as f:
        head = f.read(1024)
    if size >= 84 and size == 84 + 50 * int.from_bytes(head[80:84], "little"):
        return "a binary STL"
    kind = files.kind_of(head)
    if kind != "a text file":
        return kind
    words = head.lstrip().split(maxsplit=1)
    first = words[0].lower() if words else b""
    if first == b"solid":
        return "an ASCII STL"
    if first in (b"off", b"coff", b"noff"):
        return "an OFF mesh"
    if any(line.split()[:1] in ([b"v"], [b"f"], [b"vn"], [b"vt"]) for line in head.splitlines()):
        return "a Wavefront OBJ"
    return kind


def _check_content(path: pathlib.Path) -> None:
    """Refuse an obj, stl or ply file whose content is of another kind (a binary STL saved as .obj), naming both:
    the format readers would otherwise fail on it with their own, less helpful, words."""
    ext = path.suffix.lower().lstrip(".")
    content = _content(path)
    ok = {"obj": ("a Wavefront OBJ", "a text file"), "stl": ("a binary STL", "an ASCII STL"),
          "ply": ("a PLY mesh",)}.get(ext)
    if content == "an empty file":
        raise FfcgsError(f"mesh file {path} is empty (0 bytes)")
    if ok is not None and content not in ok:
        looks = "it looks like" if content in _MESH_CONTENT else "it is"
        if ext == "stl" and content == "a file of another format":
            looks, content = "it is", "binary, but its size does not fit the triangle count of a binary STL's " \
                                      "header (a truncated STL or a file of another format)"
        raise FfcgsError(f"{path} is not {_FORMAT_NAMES[ext]}: {looks} {content}")


def _read(path: pathlib.Path) -> trimesh.Trimesh:
    """Load with trimesh; a scene becomes one mesh; anything without triangles is refused."""
    try:
        loaded = trimesh.load(path, process=False)
    except Exception as e:  # noqa: BLE001 - trimesh raises many types for a broken file
        raise FfcgsError(f"cannot read mesh file {path}: {type(e).__name__}: {e}") from None
    if isinstance(loaded, trimesh.Scene):
        if not any(isinstance(g, trimesh.Trimesh) and len(g.faces) for g in loaded.geometry.values()):
            kinds = ", ".join(sorted({type(g).__name__ for g in loaded.geometry.values()})) or "nothing"
            raise FfcgsError(f"mesh file {path} holds no triangles (empty file or a scene of {kinds})")
        loaded = loaded.to_mesh()
    if not isinstance(loaded, trimesh.Trimesh):
        raise FfcgsError(f"mesh file {path} is not a triangle mesh but a {type(loaded).__name__} (no faces)")
    return loaded


def mesh_sha256(mesh: trimesh.Trimesh) -> str:
    """The package's one identity of a geometry: SHA-256 of the mesh as loaded (little-endian float64 vertices, then
    int64 faces). Two files give the same hash exactly when they load to the same geometry. It keys the in-process
    grid and triangle-table caches and the convex parts' disk cache, and grasp files and dataset records carry it."""
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(mesh.vertices, "<f8").tobytes())
    h.update(np.ascontiguousarray(mesh.faces, "<i8").tobytes())
    return h.hexdigest()


def identity(source: str | pathlib.Path, scale: float, mesh: trimesh.Trimesh) -> dict[str, np.ndarray]:
    """What a result was computed on, as npz arrays: `object_source` (a built-in name or the mesh file's absolute
    path), `object_scale` and `object_sha256` (`mesh_sha256`)."""
    src = str(source) if str(source) in objects.names() else str(pathlib.Path(source).expanduser().resolve())
    return {"object_source": np.array(src), "object_scale": np.float64(scale),
            "object_sha256": np.array(mesh_sha256(mesh))}
