"""Generate the built-in objects in ffcgs_jax/geometry/assets/objects/<name>.ply.

Run once from the repository root (needs `pip install manifold3d`, a dev-only tool used for the mug's boolean
union; the package itself never imports it):

    python data/make_builtin_objects.py

Every object is written as binary PLY in metres, watertight with outward normals, resting on z = 0 and centred in
x/y (bounding box), sized for a human-size hand (Schunk SVH).
"""

import pathlib

import manifold3d
import numpy as np
import trimesh

OUT = pathlib.Path(__file__).resolve().parent.parent / "ffcgs_jax" / "geometry" / "assets" / "objects"


def revolve(profile: list[tuple[float, float]], segments: int) -> manifold3d.Manifold:
    """Solid of revolution about z of a closed (r, z) polygon (counter-clockwise, r >= 0)."""
    return manifold3d.CrossSection([profile]).revolve(circular_segments=segments)


def to_trimesh(solid: manifold3d.Manifold) -> trimesh.Trimesh:
    m = solid.to_mesh()
    return trimesh.Trimesh(np.asarray(m.vert_properties)[:, :3], np.asarray(m.tri_verts), process=True)


def mug() -> trimesh.Trimesh:
    """8.2 cm wide, 9.5 cm tall cup (4 mm wall, 7 mm bottom) with a D handle of 6.5 mm thick bar."""
    r_out, r_in, height, bottom = 0.041, 0.037, 0.095, 0.007
    body = revolve([(0.0, 0.0), (r_out - 0.003, 0.0), (r_out, 0.003), (r_out, height), (r_in, height),
                    (r_in, bottom), (0.0, bottom)], 40)
    bar, reach = 0.0065, 0.032  # handle tube radius, radius of its centre line
    handle = manifold3d.CrossSection.circle(bar, 12).translate((reach, 0.0)).revolve(circular_segments=24,
                                                                                      revolve_degrees=180.0)
    # The half ring lies in the x-y plane from +x to -x through +y; turn it upright, bulging towards +x.
    handle = handle.rotate((90.0, 0.0, 0.0)).rotate((0.0, 90.0, 0.0)).translate((r_in + 0.001, 0.0, 0.05))
    return to_trimesh(body + handle)


def bottle() -> trimesh.Trimesh:
    """7 cm diameter, 20 cm tall bottle: body, rounded shoulder, neck and cap (solid)."""
    shoulder = [(0.035 - 0.022 * (1 - np.cos(a)), 0.13 + 0.04 * np.sin(a)) for a in np.linspace(0, np.pi / 2, 7)[1:]]
    profile = [(0.0, 0.0), (0.032, 0.0), (0.035, 0.004), (0.035, 0.13), *shoulder, (0.013, 0.185), (0.015, 0.186),
               (0.015, 0.2), (0.0, 0.2)]
    return to_trimesh(revolve(profile, 32))


def banana() -> trimesh.Trimesh:
    """18 cm long tapered tube swept along a 15 cm-radius arc lying on the table, ends closed."""
    n_len, n_around, bend, arc = 24, 14, 0.15, 1.2  # rings, sides, arc radius (m), arc angle (rad)
    u = np.linspace(0.0, 1.0, n_len)
    ang = (u - 0.5) * arc
    centre = np.stack([bend * np.sin(ang), bend * (1 - np.cos(ang)), np.zeros_like(u)], 1)
    tangent = np.stack([np.cos(ang), np.sin(ang), np.zeros_like(u)], 1)
    side = np.cross(np.array([0.0, 0.0, 1.0]), tangent)
    radius = 0.004 + 0.014 * np.sin(np.pi * u) ** 0.6
    phi = np.linspace(0.0, 2 * np.pi, n_around, endpoint=False)
    ring = (np.cos(phi)[None, :, None] * side[:, None] + np.sin(phi)[None, :, None] * np.array([0.0, 0.0, 1.0]))
    verts = (centre[:, None] + radius[:, None, None] * ring).reshape(-1, 3)
    ends = np.stack([centre[0] - 0.004 * tangent[0], centre[-1] + 0.004 * tangent[-1]])
    verts = np.concatenate([verts, ends])
    faces = []
    for i in range(n_len - 1):
        for j in range(n_around):
            a, b = i * n_around + j, i * n_around + (j + 1) % n_around
            faces += [(a, b, b + n_around), (a, b + n_around, a + n_around)]
    first, last = n_len * n_around, n_len * n_around + 1
    for j in range(n_around):
        faces.append((first, (j + 1) % n_around, j))
        k = (n_len - 1) * n_around
        faces.append((last, k + j, k + (j + 1) % n_around))
    return trimesh.Trimesh(verts, np.array(faces), process=True)


def build() -> dict[str, trimesh.Trimesh]:
    return {
        "mug": mug(),
        "bottle": bottle(),
        "box": trimesh.creation.box(extents=(0.05, 0.08, 0.14)),
        "ball": trimesh.creation.icosphere(subdivisions=3, radius=0.035),
        "can": trimesh.creation.cylinder(radius=0.033, height=0.12, sections=40),
        "banana": banana(),
    }


def finish(mesh: trimesh.Trimesh, name: str) -> trimesh.Trimesh:
    """Outward normals, rest on z = 0, centre the bounding box in x/y; refuse anything not watertight."""
    if mesh.volume < 0:
        mesh.invert()
    lo, hi = mesh.bounds
    mesh.apply_translation([-(lo[0] + hi[0]) / 2, -(lo[1] + hi[1]) / 2, -lo[2]])
    if not (mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0):
        raise SystemExit(f"{name}: not a closed outward mesh")
    return mesh


def ply_bytes(mesh: trimesh.Trimesh) -> bytes:
    """Binary little-endian PLY: float32 vertices, faces as uint8 count + uint16 indices (half the size of
    trimesh's int32 export; trimesh and other readers load it)."""
    assert len(mesh.vertices) < 2**16
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(mesh.vertices)}\nproperty float x\nproperty float y\nproperty float z\n"
        f"element face {len(mesh.faces)}\nproperty list uchar ushort vertex_indices\nend_header\n"
    )
    faces = np.zeros(len(mesh.faces), dtype=[("n", "u1"), ("i", "<u2", (3,))])
    faces["n"], faces["i"] = 3, mesh.faces
    return header.encode() + np.asarray(mesh.vertices, "<f4").tobytes() + faces.tobytes()


def main() -> None:
    OUT.mkdir(parents=True, exist_ok=True)
    for name, mesh in build().items():
        mesh = finish(mesh, name)
        file = OUT / f"{name}.ply"
        file.write_bytes(ply_bytes(mesh))
        back = trimesh.load(file, force="mesh")
        if not (back.is_watertight and back.volume > 0 and np.allclose(back.vertices, mesh.vertices, atol=1e-6)):
            raise SystemExit(f"{name}: the written file does not read back as the same closed mesh")
        ext = ", ".join(f"{x * 100:.1f}" for x in mesh.extents)
        print(f"{file.name:12s} {len(mesh.faces):5d} faces  {file.stat().st_size / 1024:5.1f} KB  extents {ext} cm  "
              f"volume {mesh.volume * 1e6:.0f} cm^3")


if __name__ == "__main__":
    main()
