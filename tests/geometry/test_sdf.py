"""Gradient-SDF: exact grid values, sign with holes, interpolation, derivatives, extension outside the grid, files."""


import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh
from scipy.interpolate import RegularGridInterpolator

from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.geometry import sdf
from ffcgs_jax.geometry.config import SDFConfig

from paths import SHARED

EXACT_TOL = 1e-7  # m: grid values vs closed form on a mesh that is the exact shape (float32 search, float64 result)
FP64_TOL = 1e-12  # float64 agreement of two evaluations of the same formula
GRAD_FD_TOL = 1e-6  # relative: autodiff vs central differences inside one cell
SPHERE_R = 0.04
BOX_HALF = np.array([0.025, 0.04, 0.07])
YCB = SHARED / "objects" / "ycb"


def _centres(s: sdf.GradientSDF) -> np.ndarray:
    res = s.grid.shape[0]
    axes = [float(s.origin[i]) + float(s.voxel_size) * np.arange(res) for i in range(3)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1)


def _box_sdf(p: np.ndarray) -> np.ndarray:
    q = np.abs(p) - BOX_HALF
    return np.linalg.norm(np.maximum(q, 0), axis=-1) + np.minimum(q.max(-1), 0)


def _box_grad(p: np.ndarray) -> np.ndarray:
    q = np.abs(p) - BOX_HALF
    out = np.maximum(q, 0)
    inside = (q <= 0).all(-1)
    k = q.argmax(-1)
    out[inside] = 0.0
    out[inside, k[inside]] = 1.0
    out *= np.sign(p)
    return out / np.linalg.norm(out, axis=-1, keepdims=True)


def _hollow(mesh: trimesh.Trimesh, z_cut: float) -> trimesh.Trimesh:
    """The mesh with the faces whose centre lies above z_cut deleted: a hole at the top."""
    keep = mesh.triangles_center[:, 2] <= z_cut
    out = trimesh.Trimesh(mesh.vertices, mesh.faces[keep], process=False)
    assert not out.is_watertight
    return out


@pytest.fixture(scope="module")
def sphere_mesh():
    return trimesh.creation.icosphere(subdivisions=4, radius=SPHERE_R)


@pytest.fixture(scope="module")
def sphere(sphere_mesh):
    return sdf.build_sdf(sphere_mesh, SDFConfig(res=32))


@pytest.fixture(scope="module")
def box():
    return sdf.build_sdf(trimesh.creation.box(extents=2 * BOX_HALF), SDFConfig(res=32))


def test_grid_frame_is_cube_with_margin(box):
    """Cube centred on the bounding box; side = L + 2 * max(margin * L, min_margin)."""
    cfg = SDFConfig(res=32)
    side = 2 * BOX_HALF.max() * (1 + 2 * cfg.margin)
    np.testing.assert_allclose(float(box.voxel_size), side / 31, rtol=1e-12)
    np.testing.assert_allclose(np.asarray(box.origin), -side / 2 * np.ones(3), rtol=1e-12)
    tiny = sdf.build_sdf(trimesh.creation.box(extents=(0.01, 0.01, 0.01)), SDFConfig(res=16, min_margin=0.02))
    np.testing.assert_allclose(float(tiny.voxel_size), (0.01 + 2 * 0.02) / 15, rtol=1e-12)


def test_box_grid_matches_closed_form(box):
    p = _centres(box).reshape(-1, 3)
    grid = np.asarray(box.grid).reshape(-1, 4)
    np.testing.assert_allclose(grid[:, 0], _box_sdf(p), atol=EXACT_TOL)
    # The gradient is ambiguous on the medial planes inside (two faces equally near): skip those voxels.
    q = np.sort(np.abs(p) - BOX_HALF, axis=1)
    clear = (q[:, 2] - q[:, 1] > 1e-6) | (q[:, 2] > 0)
    np.testing.assert_allclose(grid[clear, 1:], _box_grad(p[clear]), atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(grid[:, 1:], axis=1), 1.0, atol=1e-12)


def test_sphere_grid_matches_closed_form(sphere, sphere_mesh):
    p = _centres(sphere).reshape(-1, 3)
    grid = np.asarray(sphere.grid).reshape(-1, 4)
    facet = SPHERE_R - np.linalg.norm(sphere_mesh.triangles_center, axis=1).min()  # mesh vs true sphere
    r = np.linalg.norm(p, axis=1)
    np.testing.assert_array_less(np.abs(grid[:, 0] - (r - SPHERE_R)), facet + EXACT_TOL)
    far = np.abs(r - SPHERE_R) > 0.005  # the faceted mesh's normals deviate from radial near the surface
    cos = np.einsum("ij,ij->i", grid[far, 1:], p[far] / r[far, None])
    assert cos.min() > 0.999


@pytest.mark.parametrize("shape", ["box", "sphere"])
def test_query_at_random_points(shape, box, sphere):
    s, f = (box, _box_sdf) if shape == "box" else (sphere, lambda p: np.linalg.norm(p, axis=-1) - SPHERE_R)
    h = float(s.voxel_size)
    lo = np.asarray(s.origin)
    p = lo + np.random.default_rng(0).uniform(0, 31 * h, (2000, 3))
    d, g = jax.jit(sdf.query)(s, jnp.asarray(p))
    d, g = np.asarray(d), np.asarray(g)
    # Trilinear interpolation of a 1-Lipschitz function is off by at most the mean corner distance (sqrt(3)/2 h);
    # where the field is smooth (away from the box's edges and medial planes, the sphere's centre) far less.
    err = np.abs(d - f(p))
    assert err.max() < np.sqrt(3) / 2 * h
    if shape == "box":
        # One face nearest over the whole cell (and the cell not across the centre plane of that axis).
        q = np.abs(p) - BOX_HALF
        k = q.argmax(1)
        qs = np.sort(q, axis=1)
        one_face = (qs[:, 2] > 0.05 * h) & (qs[:, 1] < -2 * h) | (qs[:, 2] < 0) & (qs[:, 2] - qs[:, 1] > 2 * h)
        smooth = one_face & (np.abs(p[np.arange(len(p)), k]) > 2 * h)
        np.testing.assert_allclose(d[smooth], f(p[smooth]), atol=1e-9)  # linear field: interpolation is exact
        np.testing.assert_allclose(g[smooth], _box_grad(p[smooth]), atol=1e-9)
    else:
        smooth = np.linalg.norm(p, axis=1) > 0.5 * SPHERE_R
        facet = SPHERE_R - np.linalg.norm(trimesh.creation.icosphere(4, SPHERE_R).triangles_center, axis=1).min()
        curvature = 3 * h**2 / 8 / (0.5 * SPHERE_R)  # trilinear error bound: h^2/8 * trace|Hessian|, |H| = 1/|p|
        assert err[smooth].max() < facet + curvature
        cos = np.einsum("ij,ij->i", g[smooth], p[smooth] / np.linalg.norm(p[smooth], axis=1, keepdims=True))
        assert cos.min() > 0.995
    np.testing.assert_allclose(np.linalg.norm(g, axis=1), 1.0, atol=1e-12)


def test_query_matches_float64_reference_and_loop(sphere):
    """vmap/jit equal a per-point loop and a float64 NumPy reference: trilinear weights (scipy's) applied to each
    corner's first-order estimate d_i + g_i . (p - v_i) for the distance and to the gradient channels."""
    h = float(sphere.voxel_size)
    p = np.asarray(sphere.origin) + np.random.default_rng(1).uniform(0, 31 * h, (50, 3))
    d, g = jax.jit(sdf.query)(sphere, jnp.asarray(p))
    assert d.dtype == jnp.float64
    axes = [float(sphere.origin[i]) + h * np.arange(32) for i in range(3)]
    ref = RegularGridInterpolator(axes, np.asarray(sphere.grid), method="linear")(p)
    grid, origin = np.asarray(sphere.grid), np.asarray(sphere.origin)
    d_ref = np.zeros(len(p))
    for n, x in enumerate(p):
        i0 = np.floor((x - origin) / h).astype(int)
        for c in np.ndindex(2, 2, 2):
            v = i0 + np.array(c)
            t = (x - origin) / h - i0
            w = np.prod(np.where(np.array(c) == 1, t, 1 - t))
            d_ref[n] += w * (grid[tuple(v)][0] + grid[tuple(v)][1:] @ (x - (origin + h * v)))
    np.testing.assert_allclose(d, d_ref, atol=FP64_TOL)
    np.testing.assert_allclose(g, ref[:, 1:] / np.linalg.norm(ref[:, 1:], axis=1, keepdims=True), atol=FP64_TOL)
    for i in range(0, 50, 7):
        di, gi = sdf.query(sphere, jnp.asarray(p[i : i + 1]))
        np.testing.assert_allclose(di[0], d[i], atol=FP64_TOL)
        np.testing.assert_allclose(gi[0], g[i], atol=FP64_TOL)


def test_cell_table_gives_the_same_queries(sphere):
    """`with_cells` (one gather per point) against the 8-voxel path, in float64: values and gradients inside the grid
    and outside it, `distance`'s derivative wrt the points, and its derivative wrt the grid values when the table is
    derived inside the differentiated function."""
    fast = sdf.with_cells(sphere)
    res = sphere.grid.shape[0]
    assert sphere.cells is None and fast.cells.shape == ((res - 1) ** 3, 2, 2, 2, 4)
    h = float(sphere.voxel_size)
    p = jnp.asarray(np.asarray(sphere.origin) + np.random.default_rng(7).uniform(-3 * h, 34 * h, (300, 3)))
    for a, b in zip(jax.jit(sdf.query)(sphere, p), jax.jit(sdf.query)(fast, p)):
        np.testing.assert_allclose(b, a, atol=FP64_TOL)
    grad = lambda s: jax.grad(lambda x: jnp.sum(sdf.distance(s, x) ** 2))(p)  # noqa: E731
    np.testing.assert_allclose(grad(fast), grad(sphere), atol=FP64_TOL)
    wrt_grid = lambda cells: jax.grad(lambda g: jnp.sum(sdf.distance(  # noqa: E731
        sdf.with_cells(sphere._replace(grid=g)) if cells else sphere._replace(grid=g), p) ** 2))(sphere.grid)
    np.testing.assert_allclose(wrt_grid(True), wrt_grid(False), atol=FP64_TOL)
    assert float(jnp.abs(wrt_grid(True)).max()) > 0


def test_gradients_match_finite_differences(sphere):
    h = float(sphere.voxel_size)
    rng = np.random.default_rng(2)
    cells = rng.integers(3, 28, (20, 3))
    p = np.asarray(sphere.origin) + h * (cells + rng.uniform(0.2, 0.8, (20, 3)))  # inside cells: a polynomial
    pj = jnp.asarray(p)

    @jax.jit
    def dist(x):
        return sdf.query(sphere, x)[0]

    grad = np.asarray(jax.grad(lambda x: dist(x).sum())(pj))  # points are independent: row i is d(d_i)/dp_i
    eps = 1e-4 * h
    fd = np.stack([(dist(pj + eps * e[None]) - dist(pj - eps * e[None])) / (2 * eps) for e in np.eye(3)], axis=1)
    np.testing.assert_allclose(grad, fd, rtol=GRAD_FD_TOL, atol=GRAD_FD_TOL)

    # `distance`: same value, but its derivative is the interpolated (normalised) gradient channel.
    d, g = jax.jit(sdf.query)(sphere, pj)
    v = jnp.asarray(rng.normal(size=(20, 3)))
    value, tangent = jax.jit(lambda x, t: jax.jvp(lambda y: sdf.distance(sphere, y), (x,), (t,)))(pj, v)
    np.testing.assert_allclose(value, d, atol=FP64_TOL)
    np.testing.assert_allclose(tangent, (g * v).sum(1), atol=FP64_TOL)
    np.testing.assert_allclose(jax.jit(jax.grad(lambda x: sdf.distance(sphere, x).sum()))(pj), g, atol=FP64_TOL)
    # Gradient-SDF semantics: the normal field agrees with the distance's slope (to the interpolation error).
    assert np.einsum("ij,ij->i", grad / np.linalg.norm(grad, axis=1, keepdims=True), np.asarray(g)).min() > 0.99


def test_outside_the_grid(sphere):
    h = float(sphere.voxel_size)
    lo = np.asarray(sphere.origin)
    hi = lo + 31 * h
    rng = np.random.default_rng(3)
    dirs = rng.normal(size=(30, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    t = np.array([0.06, 0.1, 0.3, 1.0, 10.0])  # from inside the box (0.06 m) to far outside it
    p = (dirs[:, None, :] * t[None, :, None]).reshape(-1, 3)
    d, g = jax.jit(sdf.query)(sphere, jnp.asarray(p))
    d = np.asarray(d).reshape(30, 5)
    assert (np.diff(d, axis=1) > 0).all()  # grows along each ray
    np.testing.assert_allclose(d[:, -1], 10.0 - SPHERE_R, rtol=0.05)  # roughly the distance at 10 m
    cos = np.einsum("ij,ij->i", np.asarray(g).reshape(30, 5, 3)[:, -1], -dirs)
    assert cos.max() < -0.99  # -g points back to the object

    # Continuous at the grid box, and finite derivatives of both outputs everywhere, the box face included.
    face = np.array([hi[0], 0.003, -0.002])
    dd, gg = sdf.query(sphere, jnp.asarray([face - [1e-9, 0, 0], face + [1e-9, 0, 0]]))
    np.testing.assert_allclose(dd[0], dd[1], atol=1e-8)
    np.testing.assert_allclose(gg[0], gg[1], atol=1e-6)
    edge = np.concatenate([p, [face, lo, hi, hi + [0, 0, 1e-12]]])

    def jacobians(x):
        return (
            jax.jacfwd(lambda y: sdf.query(sphere, y[None])[0][0])(x),
            jax.jacfwd(lambda y: sdf.query(sphere, y[None])[1][0])(x),
            jax.grad(lambda y: sdf.distance(sphere, y[None])[0])(x),
        )

    for jac in jax.jit(jax.vmap(jacobians))(jnp.asarray(edge)):
        assert np.isfinite(jac).all()


def test_query_scene_prefers_table_below_object(sphere):
    assert float(sphere.table_z) == pytest.approx(-SPHERE_R, abs=1e-12)  # default: the mesh's lowest z
    p = jnp.asarray([[0.03, 0.0, -0.039], [0.0, 0.0, 0.05], [0.0, 0.0, -0.05]])
    d, g = sdf.query_scene(sphere, p)
    d_obj, g_obj = sdf.query(sphere, p)
    np.testing.assert_allclose(d[0], 0.001, atol=1e-12)
    np.testing.assert_allclose(g[0], [0, 0, 1])
    np.testing.assert_allclose(d[1], d_obj[1])  # above the object: the object is nearer
    np.testing.assert_allclose(g[1], g_obj[1])
    np.testing.assert_allclose(d[2], -0.01, atol=1e-12)  # under the table: negative
    raised = sdf.build_sdf(trimesh.creation.box(extents=2 * BOX_HALF), SDFConfig(res=16), table_z=-0.5)
    assert float(raised.table_z) == -0.5


@pytest.mark.parametrize("z_cut", [0.036, 0.0])  # a small hole; half the sphere gone (a bowl)
def test_open_mesh_keeps_inside_and_outside(z_cut):
    """A sphere with the faces above z_cut deleted: no ray parity, the winding number decides; also along the z
    axis through the hole (inside below the hole's film at z_cut, outside above it)."""
    s = sdf.build_sdf(_hollow(trimesh.creation.icosphere(3, SPHERE_R), z_cut), SDFConfig(res=32))
    h = float(s.voxel_size)
    p = _centres(s).reshape(-1, 3)
    r = np.linalg.norm(p, axis=1)
    d = np.asarray(s.grid).reshape(-1, 4)[:, 0]
    z = p[:, 2]
    assert (d[(r < SPHERE_R - 2 * h) & (z < z_cut - 2 * h)] < 0).all()
    assert (d[(r > SPHERE_R + 2 * h) | (z > z_cut + 2 * h)] > 0).all()
    z = np.linspace(-0.06, 0.06, 241)
    z = z[(np.abs(z - z_cut) > 2 * h) & (np.abs(z + SPHERE_R) > 2 * h)]  # away from the surface and the film
    dz, _ = sdf.query(s, jnp.asarray(np.stack([0 * z, 0 * z, z], 1)))
    np.testing.assert_array_equal(np.asarray(dz) < 0, (z > -SPHERE_R) & (z < z_cut))


def test_inverted_faces_give_the_same_field(box):
    flipped = trimesh.creation.box(extents=2 * BOX_HALF)
    flipped.invert()
    s = sdf.build_sdf(flipped, SDFConfig(res=32))
    np.testing.assert_allclose(np.asarray(s.grid)[..., 0], np.asarray(box.grid)[..., 0], atol=EXACT_TOL)


def test_bad_points_raise(sphere):
    with pytest.raises(FfcgsError, match="NaN or inf"):
        sdf.query(sphere, jnp.asarray([[0.0, jnp.nan, 0.0]]))


@pytest.mark.parametrize("name", ["025_mug", "011_banana"])
def test_ycb_matches_trimesh(name):
    """At 64^3: voxel values equal trimesh's exact signed distance; queries within 2 cm of the surface are below
    half a voxel off except within thin walls (the mug's wall is under 2 voxels thick), never above 0.6 voxel."""
    file = YCB / f"{name}.stl"
    if not file.is_file():
        pytest.skip(f"YCB meshes not found at {YCB}")
    mesh = trimesh.load(file)
    s = sdf.build_sdf(mesh, SDFConfig(res=64))
    h = float(s.voxel_size)
    rng = np.random.default_rng(4)

    vox = _centres(s).reshape(-1, 3)[rng.choice(64**3, 400, replace=False)]
    ref = -trimesh.proximity.signed_distance(mesh, vox)  # trimesh: positive inside
    grid_d = np.asarray(s.grid).reshape(-1, 4)[:, 0]
    idx = np.round((vox - np.asarray(s.origin)) / h).astype(int)
    np.testing.assert_allclose(grid_d[np.ravel_multi_index(tuple(idx.T), (64,) * 3)], ref, atol=1e-5)

    pts, face = trimesh.sample.sample_surface(mesh, 1500, seed=4)
    pts = pts + mesh.face_normals[face] * rng.uniform(-0.02, 0.02, (1500, 1))
    lo, hi = np.asarray(s.origin), np.asarray(s.origin) + 63 * h
    pts = pts[((pts > lo) & (pts < hi)).all(1)]  # outside the box the field is an extension, tested elsewhere
    ref = -trimesh.proximity.signed_distance(mesh, pts)
    d, _ = jax.jit(sdf.query)(s, jnp.asarray(pts))
    err = np.abs(np.asarray(d) - ref) / h
    assert np.mean(err < 0.5) >= 0.995, np.sort(err)[-10:]
    assert err.max() < 0.6


def test_taylor_blend_is_exact_across_a_medial_plane():
    """Inside a slab thinner than two voxels, plain trilinear interpolation is half a voxel off at the mid-plane;
    blending each corner's first-order estimate d_i + g_i . (p - v_i) is exact there."""
    box = trimesh.creation.box((0.2, 0.2, 0.012))
    s = sdf.build_sdf(box, SDFConfig(res=32, margin=0.0, min_margin=0.01))
    rng = np.random.default_rng(0)
    p = np.stack([rng.uniform(-0.05, 0.05, 200), rng.uniform(-0.05, 0.05, 200), np.zeros(200)], 1)
    d, _ = sdf.query(s, jnp.asarray(p))
    np.testing.assert_allclose(np.asarray(d), -0.006, atol=1e-9)


def test_save_load_round_trip(sphere, tmp_path):
    file = tmp_path / "sphere.npz"
    sdf.save(sdf.with_cells(sphere), file)  # the cell table is derived: not written
    back = sdf.load(file)
    assert back.cells is None
    for a, b in zip(sphere, back):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_load_rejects_bad_files(sphere, tmp_path):
    with pytest.raises(FfcgsError, match="not found"):
        sdf.load(tmp_path / "missing.npz")
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a zip file at all")
    with pytest.raises(FfcgsError, match="not a readable .npz"):
        sdf.load(junk)
    fields = {k: np.asarray(v) for k, v in sphere._asdict().items() if v is not None}
    bad = tmp_path / "bad.npz"
    np.savez(bad, version=1, **{k: v for k, v in fields.items() if k != "origin"})
    with pytest.raises(FfcgsError, match="lacks key.*origin"):
        sdf.load(bad)
    np.savez(bad, version=1, **{**fields, "grid": fields["grid"][..., :3]})
    with pytest.raises(FfcgsError, match=r"grid must have shape \(R, R, R, 4\)"):
        sdf.load(bad)
    nan_grid = fields["grid"].copy()
    nan_grid[3, 4, 5, 0] = np.nan
    np.savez(bad, version=1, **{**fields, "grid": nan_grid})
    with pytest.raises(FfcgsError, match="grid must be finite"):
        sdf.load(bad)


@pytest.mark.slow
def test_res_128_builds():
    mesh = trimesh.creation.icosphere(subdivisions=4, radius=SPHERE_R)
    s = sdf.build_sdf(mesh, SDFConfig(res=128))
    p = _centres(s).reshape(-1, 3)
    err = np.abs(np.asarray(s.grid).reshape(-1, 4)[:, 0] - (np.linalg.norm(p, axis=1) - SPHERE_R))
    assert err.max() < 1e-4
