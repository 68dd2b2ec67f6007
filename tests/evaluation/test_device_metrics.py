"""The device evaluation against its float64 NumPy/SciPy reference (`metrics.evaluate`: trimesh, Qhull, HiGHS)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.spatial
import trimesh

from ffcgs_jax.evaluation import device_metrics as dm
from ffcgs_jax.evaluation import epsilon_search, metrics
from ffcgs_jax.evaluation.metrics import MetricsConfig
from ffcgs_jax.geometry import mesh_io, sdf
from ffcgs_jax.kernels.directions import sphere_basis

CFG = MetricsConfig(contact_tol=0.002)
N = 48  # grasps per call everywhere, so tests on one mesh share the compiled evaluation
LO, HI = -np.ones(9), np.ones(9)


def _grasps(mesh, n, seed, spread=(-0.0015, 0.003)):
    """n five-finger 'grasps': surface points pushed along their normals, and channel values."""
    rng = np.random.default_rng(seed)
    pts, fid = trimesh.sample.sample_surface(mesh, 5 * n, seed=seed)
    pts = pts + mesh.face_normals[fid] * rng.uniform(*spread, (5 * n, 1))
    return pts.reshape(n, 5, 3), rng.uniform(-0.9, 0.9, (n, 9))


def _brute_distance(mesh, contacts):
    """(B, C) signed distances by trimesh's point-triangle routine against every face, sign from `mesh.contains`."""
    flat = contacts.reshape(-1, 3)
    d = np.array([np.linalg.norm(trimesh.triangles.closest_point(mesh.triangles, np.repeat(p[None], len(mesh.faces),
                                                                                           0)) - p, axis=1).min()
                  for p in flat])
    return np.where(mesh.contains(flat), -d, d).reshape(contacts.shape[:2])


def _unambiguous(mesh, contacts, ref):
    """(B, C) mask of points where the reference is the exact answer: trimesh's closest-point search misses the
    nearest face by up to ~4e-6 m on some points (brute force over every face agrees with the device path to
    1e-15 there), and inside points closest to an edge or vertex get the normal of whichever face trimesh
    returns, a choice the device path may make differently."""
    flat = contacts.reshape(-1, 3)
    closest, _, tri = trimesh.proximity.closest_point(mesh, flat)
    bary = trimesh.triangles.points_to_barycentric(mesh.triangles[tri], closest)
    on_edge = (bary < 1e-9).any(axis=1)
    exact = np.abs(ref["contact_dist"] - _brute_distance(mesh, contacts)) <= 1e-12
    return ~(on_edge & mesh.contains(flat)).reshape(contacts.shape[:2]) & exact


def _both(mesh, contacts, q, cfg=CFG):
    centre, radius = metrics.default_centre_radius(mesh)
    ref = metrics.evaluate(mesh, contacts, q, LO, HI, cfg, centre=centre, radius=radius)
    surface = mesh if isinstance(mesh, sdf.GradientSDF) else dm.mesh_table(mesh)
    dev = jax.device_get(dm.evaluate(surface, jnp.asarray(contacts), jnp.asarray(q), LO, HI, centre, radius, cfg))
    return ref, dev


@pytest.mark.parametrize("name", ["mug", "box"])
def test_matches_the_reference_in_float64(name):
    mesh = mesh_io.load_mesh(name)
    contacts, q = _grasps(mesh, N, seed=3)
    ref, dev = _both(mesh, contacts, q)
    ok = _unambiguous(mesh, contacts, ref)
    np.testing.assert_allclose(dev["contact_dist"], _brute_distance(mesh, contacts), atol=1e-12)
    np.testing.assert_allclose(dev["contact_dist"], ref["contact_dist"], atol=1e-5)  # trimesh's search, see above
    np.testing.assert_allclose(dev["normals"][ok], ref["normals"][ok], atol=1e-6)
    np.testing.assert_array_equal(dev["n_contacts"], ref["n_contacts"])
    same = ok.all(axis=1)  # grasps whose wrenches are the reference's
    assert same.sum() >= 30
    for k in ("E_g", "E", "E_c", "E_q", "joint_limit_use"):
        np.testing.assert_allclose(dev[k][same], ref[k][same], atol=1e-6, err_msg=k)
    np.testing.assert_array_equal(dev["force_closure"][same], ref["force_closure"][same])
    fc = same & ref["force_closure"]
    assert fc.sum() >= 5
    # the searched epsilon bounds Qhull's from above and reaches it on most grasps
    assert (dev["epsilon"][fc] >= ref["epsilon"][fc] - 1e-12).all()
    assert np.mean(np.abs(dev["epsilon"][fc] - ref["epsilon"][fc]) <= 1e-9) >= 0.8


def test_epsilon_search_reaches_qhull_on_random_wrench_sets():
    mesh = mesh_io.load_mesh("mug")
    centre, radius = metrics.default_centre_radius(mesh)
    rng = np.random.default_rng(7)
    Ws, refs = [], []
    while len(Ws) < 60:
        pts, fid = trimesh.sample.sample_surface(mesh, 5, seed=int(rng.integers(1 << 30)))
        w = metrics.primitive_wrenches(pts, mesh.face_normals[fid], centre, radius, 0.3, 8)
        if (e := metrics.epsilon_q1(w)) > 0:
            Ws.append(w.T)
            refs.append(e)
    starts = jnp.asarray(sphere_basis(epsilon_search.EPS_STARTS).T)
    eps = np.asarray(jax.jit(jax.vmap(lambda w: epsilon_search.search_epsilon(w, starts)))(jnp.asarray(np.stack(Ws))))
    refs = np.asarray(refs)
    assert (eps >= refs - 1e-12).all()
    assert np.mean(np.abs(eps - refs) <= 1e-9 * np.maximum(refs, 1)) >= 0.9
    assert np.median(eps / refs) < 1 + 1e-9


def test_ray_facet_returns_the_facet_the_ray_leaves_through():
    rng = np.random.default_rng(1)
    w = rng.standard_normal((40, 6))
    hull = scipy.spatial.ConvexHull(w)
    ds = rng.standard_normal((10, 6))
    ds /= np.linalg.norm(ds, axis=1, keepdims=True)
    cold = jax.jit(jax.vmap(epsilon_search.ray_facet, (None, 0)))
    normals, bases = cold(jnp.asarray(w.T), jnp.asarray(ds))
    # warm: each ray finished by dual pivots from the optimal basis of another ray (the walks' later steps)
    warm, _ = jax.jit(jax.vmap(epsilon_search.ray_facet, (None, 0, 0)))(jnp.asarray(w.T), jnp.asarray(ds[::-1]), bases)
    np.testing.assert_allclose(np.asarray(warm)[::-1], np.asarray(normals), atol=1e-9)
    for d, n in zip(ds, np.asarray(normals)):
        # a facet normal of the hull, and the ray's exit point lies on that facet's plane
        dots = hull.equations[:, :6] @ n
        f = int(np.argmax(dots))
        assert dots[f] == pytest.approx(1.0, abs=1e-9)
        b = -hull.equations[f, 6]
        exit_t = np.min(-hull.equations[:, 6] / np.maximum(hull.equations[:, :6] @ d, 1e-300))
        assert n @ (exit_t * d) == pytest.approx(b, abs=1e-9)


def test_silent_fingertips_change_nothing():
    mesh = mesh_io.load_mesh("box")
    contacts, q = _grasps(mesh, N, seed=5, spread=(0.0, 0.0005))
    far = contacts.copy()
    far[:, 4] += 0.05 * mesh.face_normals[mesh.nearest.on_surface(far[:, 4])[2]]  # 5 cm off the surface
    centre, radius = metrics.default_centre_radius(mesh)
    ref4 = metrics.evaluate(mesh, contacts[:, :4], q, LO, HI, CFG, centre=centre, radius=radius)
    dev = jax.device_get(dm.evaluate(dm.mesh_table(mesh), jnp.asarray(far), jnp.asarray(q), LO, HI, centre, radius,
                                     CFG))
    np.testing.assert_array_equal(dev["n_contacts"], ref4["n_contacts"])
    np.testing.assert_allclose(dev["E_g"], ref4["E_g"], atol=1e-9)
    np.testing.assert_array_equal(dev["force_closure"], ref4["force_closure"])


@pytest.mark.e2e  # over 20 s on the 2-core CPU: kept out of plain `pytest` (README)
def test_an_sdf_surface_matches_the_reference_sdf_path():
    mesh = mesh_io.load_mesh("ball")
    grid = sdf.build_sdf(mesh)
    contacts, q = _grasps(mesh, N, seed=2)
    ref, dev = _both(grid, contacts, q)
    for k in ("contact_dist", "normals", "E_g", "E_c"):
        np.testing.assert_allclose(dev[k], ref[k], atol=1e-9, err_msg=k)
    np.testing.assert_array_equal(dev["force_closure"], ref["force_closure"])


def test_the_same_surface_in_16_times_the_faces_gives_the_same_figures_without_compiling():
    """The mug and its twice-subdivided copy (the same surface in 16 times the faces, many chunks): the same
    figures, and the large mesh runs through the executables the small one compiled."""
    from ffcgs_jax.runtime import compile_clock

    mesh = mesh_io.load_mesh("mug")
    fine = mesh.subdivide().subdivide()
    assert len(fine.faces) == 16 * len(mesh.faces) > 4 * dm.FACE_CHUNK
    contacts, q = _grasps(mesh, N, seed=3)
    centre, radius = metrics.default_centre_radius(mesh)
    run = lambda m: jax.device_get(dm.evaluate(dm.mesh_table(m), jnp.asarray(contacts), jnp.asarray(q), LO, HI,  # noqa: E731
                                               centre, radius, CFG))
    coarse = run(mesh)
    with compile_clock.compiling() as seconds:
        same = run(fine)
    assert seconds[0] == 0.0
    np.testing.assert_allclose(same["contact_dist"], coarse["contact_dist"], atol=1e-12)
    np.testing.assert_array_equal(same["n_contacts"], coarse["n_contacts"])
    np.testing.assert_array_equal(same["force_closure"], coarse["force_closure"])
    for k in ("normals", "E_g", "epsilon"):
        np.testing.assert_allclose(same[k], coarse[k], atol=1e-9, err_msg=k)


def test_batched_equals_one_at_a_time():
    mesh = mesh_io.load_mesh("box")  # the batch size and triangle bucket of the tests above: one more compile only
    contacts, q = _grasps(mesh, N, seed=4)
    table = dm.mesh_table(mesh)
    centre, radius = metrics.default_centre_radius(mesh)
    run = lambda c, qq: jax.device_get(dm.evaluate(table, jnp.asarray(c), jnp.asarray(qq), LO, HI, centre,  # noqa: E731
                                                   radius, CFG))
    whole = run(contacts, q)
    for i in range(0, N, 12):
        one = run(contacts[i:i + 1], q[i:i + 1])
        for k, v in whole.items():
            np.testing.assert_allclose(one[k][0], v[i], rtol=1e-12, atol=1e-12, err_msg=k)


def test_mesh_tables_are_cached_by_content():
    mesh = mesh_io.load_mesh("box")
    assert dm.mesh_table(mesh) is dm.mesh_table(mesh.copy())
    moved = mesh.copy()
    moved.vertices[0] += 1e-4
    assert dm.mesh_table(moved) is not dm.mesh_table(mesh)


def test_bad_shapes_are_refused():
    mesh = mesh_io.load_mesh("box")
    with pytest.raises(Exception, match="contacts"):
        dm.evaluate(dm.mesh_table(mesh), jnp.zeros((2, 3)), jnp.zeros((2, 9)), LO, HI, np.zeros(3), 0.1, CFG)


@pytest.mark.skipif(jax.default_backend() != "gpu", reason="needs a GPU (runs on the device machine)")
def test_gpu_float32_agrees_with_cpu_float64(monkeypatch):
    mesh = mesh_io.load_mesh("mug")
    contacts, q = _grasps(mesh, N, seed=3)
    centre, radius = metrics.default_centre_radius(mesh)
    cpu = jax.devices("cpu")[0]
    with jax.default_device(cpu), monkeypatch.context() as m:
        m.setenv("FFCGS_LP_KERNEL", "xla")  # the LP kernel is picked by the default backend, the GPU's
        ref = jax.device_get(dm.evaluate(dm.mesh_table(mesh), jnp.asarray(contacts), jnp.asarray(q), LO, HI, centre,
                                         radius, CFG))
    f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
    gpu = jax.device_get(dm.evaluate(dm.mesh_table(mesh, jnp.float32), f32(contacts), f32(q), f32(LO), f32(HI),
                                     f32(centre), f32(radius), CFG))
    np.testing.assert_allclose(gpu["contact_dist"], ref["contact_dist"], atol=1e-6)
    far = np.abs(np.abs(ref["contact_dist"]) - CFG.contact_tol) > 1e-5  # not at the touching threshold
    np.testing.assert_array_equal(gpu["n_contacts"][far.all(1)], ref["n_contacts"][far.all(1)])
    same = far.all(1) & (np.abs(ref["E_g"]) > 1e-4) | (ref["E_g"] == 0)
    np.testing.assert_allclose(gpu["E_g"][same], ref["E_g"][same], atol=1e-4)
    fc = ref["force_closure"] & gpu["force_closure"]
    assert np.mean(gpu["force_closure"] == ref["force_closure"]) >= 0.95
    # a walk may end on another local minimum in float32: most agree
    rel = (gpu["epsilon"][fc] - ref["epsilon"][fc]) / ref["epsilon"][fc]
    assert np.median(np.abs(rel)) < 1e-3
