"""The grasp pipeline `synthesize` end to end on the SVH: output fields, their consistency, determinism, presets.

Each SVH compile of the device part costs ~30 s on a 2-core CPU, so the module holds three: the box with this
project's method (geometric sampler, adam + wrist + penalty) and the ball with the random sampler under the
paper's preset; given poses (which skip the sampler: a third function) are marked slow. Everything else reuses them.
"""

import dataclasses

import jax
import mujoco
import numpy as np
import pytest

from bad_configs import with_bad
from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.geometry import mesh_io
from ffcgs_jax.geometry import sdf as sdf_mod
from ffcgs_jax.geometry.config import SDFConfig
from ffcgs_jax.hand import kinematics as K
from ffcgs_jax.synthesis import grasp as G
from ffcgs_jax.synthesis import samplers
from ffcgs_jax.synthesis.config import EnergyConfig, OptimConfig, SearchConfig
from ffcgs_jax.viz import scene

pytestmark = pytest.mark.e2e  # the SVH pipeline compiled in several configurations

N, ITERS = 4, 5
BOX = G.GraspConfig(n=N, sdf=SDFConfig(res=16), optim=OptimConfig(iters=ITERS))
# as configs/paper.toml: the paper's algorithm as published (no final projection, no further search)
PAPER = dataclasses.replace(BOX, sampler="random", energy=EnergyConfig(a_pen=0.0, a_m=0.0, normal_grad=False),
                            optim=OptimConfig(iters=ITERS, method="gd", wrist=False, project_steps=0),
                            search=SearchConfig(max_rounds=1))
ATOL_FK = 1e-9  # MJX (saved contacts) vs MuJoCo C forward kinematics, float64, metres
FIELDS = {  # name: (shape with G for the grasp count, dtype kind)
    "wrist_pose": (("G", 4, 4), "f"), "q": (("G", 9), "f"), "joint_pos": (("G", 20), "f"), "joint_names": ((20,), "U"),
    "contacts": (("G", 5, 3), "f"), "E": (("G",), "f"), "E_g": (("G",), "f"), "E_c": (("G",), "f"),
    "E_q": (("G",), "f"), "epsilon": (("G",), "f"), "penetration": (("G",), "f"), "valid": (("G",), "b"),
    "pose_collides": (("G",), "b"), "palm_up": (("G",), "b"), "tips_below_table": (("G",), "b"),
    "lp_ok": (("G",), "b"), "synthesis_s": ((), "f"), "compile_s": ((), "f"), "E_m": (("G",), "f"),
    "squeeze_dir": (("G", 9), "f"), "q_squeeze": (("G", 9), "f"), "n_contacts": (("G",), "i"),
}


def synth(hand, mesh, cfg, name, **kw):
    return G.synthesize(hand, mesh, cfg, name, **kw)


@pytest.fixture(scope="module")
def meshes():
    return {"box": mesh_io.load_mesh("box"), "ball": mesh_io.load_mesh("ball")}


@pytest.fixture(scope="module")
def box_run(svh, meshes):
    return synth(svh, meshes["box"], BOX, "box")


@pytest.fixture(scope="module")
def ball_paper_run(svh, meshes):
    return synth(svh, meshes["ball"], PAPER, "ball")


@pytest.fixture(params=["box_run", "ball_paper_run"])
def run(request):
    return request.getfixturevalue(request.param)


def test_compiles_on_the_way_are_compile_time_not_call_time(svh, meshes, box_run):
    """A process's first call also compiles the SDF build, the target and the results' packing (jit, not AOT): those
    seconds belong in compile_s, not in sdf_s or total_s. Cleared jit caches make this call such a first call (the
    device part's AOT executable is kept); the call after it compiles nothing."""
    sdf_mod.clear_cache()
    jax.clear_caches()
    first = synth(svh, meshes["box"], BOX, "box")
    sdf_mod.clear_cache()
    second = synth(svh, meshes["box"], BOX, "box")
    assert float(first["compile_s"]) > 0.3  # the SDF builder alone takes seconds to compile on a CPU
    # A compile counted as call time would add its seconds (the SDF builder's: about 2 s on the 2-core CPU). The
    # margin stays under that but above what a loaded 2-core machine stalls one call (0.63 s in CI's suite,
    # 2026-11-29, when the margin was 0.3 s).
    assert float(first["sdf_s"]) <= float(second["sdf_s"]) + 1.0
    assert float(first["total_s"]) <= float(second["total_s"]) + 1.2
    for a in (first, second):
        assert float(a["sdf_s"]) + float(a["synthesis_s"]) + float(a["evaluation_s"]) <= float(a["total_s"]) + 1e-3


def test_fields_shapes_and_dtypes(run):
    a = run.arrays
    G_ = len(a["valid"])
    assert G_ == N
    for name, (shape, kind) in FIELDS.items():
        assert name in a, name
        assert a[name].shape == tuple(G_ if s == "G" else s for s in shape), (name, a[name].shape)
        assert a[name].dtype.kind == kind, (name, a[name].dtype)
    for name in ("wrist_pose", "q", "contacts", "E", "E_g", "E_c", "E_q", "penetration"):
        assert np.isfinite(a[name]).all(), name
    assert a["compile_s"] >= 0 and a["synthesis_s"] > 0
    assert {k: v.shape for k, v in run.trace.items()} == {k: (ITERS + 1, N) for k in ("E", "E_g", "E_c")}
    np.testing.assert_allclose(run.trace["E"][-1], a["E"], rtol=1e-12)


def test_channels_within_limits_and_joints_follow_the_coupling(run, svh):
    q = run["q"]
    assert (q >= np.asarray(svh.lower) - 1e-12).all() and (q <= np.asarray(svh.upper) + 1e-12).all()
    np.testing.assert_allclose(run["joint_pos"], q @ np.asarray(svh.coupling).T, atol=1e-15)
    m = svh.spec.mj_model()
    assert run["joint_names"].tolist() == [m.joint(j).name for j in range(m.njnt)]
    assert (run["iters"] <= ITERS).all() and (run["iters"] >= 0).all()


def test_contacts_are_the_forward_kinematics_of_the_saved_grasp(run, svh):
    """Checked with MuJoCo C: the hand placed at the saved wrist pose with the saved channels; each contact lies on
    the skin of one of its fingertip's candidate spheres (a sphere of the fingertip link, or the site, radius 0)."""
    pos, rad, body = np.asarray(svh.tip_pos), np.asarray(svh.tip_radius), np.asarray(svh.tip_body)
    for i in range(N):
        m, d = scene.build_scene(svh.spec, run["wrist_pose"][i])
        scene.set_channels(m, d, np.asarray(svh.coupling), run["q"][i])
        # tip bodies by name: the scene's model holds more bodies than the hand's
        ids = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, mujoco.mj_id2name(svh.spec.mj_model(),
                                                                               mujoco.mjtObj.mjOBJ_BODY, int(b)))
               for b in body]
        centres = np.einsum("cij,ctj->cti", d.xmat[ids].reshape(-1, 3, 3), pos) + d.xpos[ids][:, None]
        off_skin = np.abs(np.linalg.norm(run["contacts"][i][:, None] - centres, axis=-1) - rad).min(axis=1)
        assert off_skin.max() <= ATOL_FK
    R = run["wrist_pose"][:, :3, :3]
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-9)
    np.testing.assert_allclose(run["wrist_pose"][:, 3], np.tile([0, 0, 0, 1.0], (N, 1)), atol=0)


def test_valid_is_the_and_of_the_filters(run):
    a, cfg = run.arrays, run.config
    expected = (~a["pose_collides"] & ~a["palm_up"] & ~a["tips_below_table"] & a["lp_ok"]
                & (a["penetration"] <= cfg.max_penetration))
    expected &= a["E_c"] <= cfg.max_contact_rms  # fingertips must touch
    np.testing.assert_array_equal(a["valid"], expected)
    order = run.order()
    assert sorted(order.tolist()) == list(range(N))
    v = a["valid"][order]
    # each group by decreasing predicted success where a predictor ranks, else by increasing E
    key = -a["pred_success"][order] if str(a.get("rank_by")) == "predicted" else a["E"][order]
    assert (np.diff(v.astype(int)) <= 0).all()  # valid ones first
    for group in (v, ~v):
        assert (np.diff(key[group]) >= 0).all()
    rows = dict(G.summary_rows(run))
    assert rows["grasps (valid / sampled)"] == f"{int(a['valid'].sum())} / {N}"


def test_energy_is_at_least_its_saved_parts(run):
    a, e = run.arrays, run.config.energy
    parts = a["E_g"] + e.a_c * a["E_c"] + e.a_q * a["E_q"] + e.a_m * a["E_m"]
    assert (a["E"] >= parts - 1e-9).all()
    if e.a_pen == 0:  # no penalty: E is exactly its parts
        np.testing.assert_allclose(a["E"], parts, rtol=1e-12)


def test_deterministic_for_a_seed_and_the_executable_is_reused(svh, meshes, box_run):
    again = synth(svh, meshes["box"], BOX, "box")
    for k, v in box_run.arrays.items():
        if not k.endswith("_s"):  # timings
            np.testing.assert_array_equal(again[k], v, err_msg=k)
    assert again.arrays["compile_s"] < 0.5  # reused (a fresh compile of the SVH pipeline takes tens of seconds)
    other = synth(svh, meshes["box"], dataclasses.replace(BOX, seed=1), "box")
    assert other.arrays["compile_s"] < 0.5  # the seed is not compiled in
    assert np.abs(other["wrist_pose"] - box_run["wrist_pose"]).max() > 1e-3


def test_a_mesh_of_any_size_runs_through_the_compiled_executables(svh, meshes, box_run):
    """A mesh of 15,000 faces after the 12-face box: no executable compiles (counted by JAX's own compile events),
    compile_s says so, and the result is the same as for the same surface in few faces."""
    from ffcgs_jax.runtime import compile_clock

    box = meshes["box"]
    fine = box.subdivide_to_size(0.004)  # the same surface, many faces
    assert len(fine.faces) > 10_000
    with compile_clock.compiling() as seconds:
        gs = synth(svh, fine, BOX, "fine box")
    assert seconds[0] == 0.0 and float(gs["compile_s"]) < 0.01  # the cached executables looked up
    np.testing.assert_allclose(gs["wrist_pose"], box_run["wrist_pose"], atol=1e-6)
    np.testing.assert_array_equal(gs["valid"], box_run["valid"])


def test_paper_preset_keeps_the_sampled_wrist_poses(svh, meshes, ball_paper_run):
    grid = sdf_mod.build_sdf(meshes["ball"], PAPER.sdf)
    sample = samplers.make_sampler("random", svh, PAPER.sampling, PAPER.filters)
    sampled = np.asarray(sample(jax.random.PRNGKey(PAPER.seed), grid, N))
    np.testing.assert_allclose(ball_paper_run["wrist_pose"], sampled, atol=1e-12)


@pytest.mark.slow  # a third SVH compile (~13 s): `poses=` is its own device function
def test_given_poses_skip_sampling(svh, meshes, box_run):
    """Three given poses with the paper preset (fixed wrist): three grasps, at exactly those poses."""
    given = box_run["wrist_pose"][:3]
    cfg = dataclasses.replace(PAPER, sampler="geometric")
    gs = synth(svh, meshes["box"], cfg, "box", poses=given)
    assert len(gs["valid"]) == 3 and gs["q"].shape == (3, 9) and gs.trace["E"].shape == (ITERS + 1, 3)
    np.testing.assert_array_equal(gs["wrist_pose"], given)
    np.testing.assert_allclose(gs["E"], gs["E_g"] + 5.0 * gs["E_c"] + 0.5 * gs["E_q"], rtol=1e-12)


@pytest.mark.parametrize("cfg, message", [
    (G.GraspConfig(n=0), r"n must be an integer in \[1, 1000000\]"),
    (with_bad(G.GraspConfig(), sampler="learned"), "unknown sampler 'learned'"),
    (G.GraspConfig(max_penetration=-0.1), "max_penetration"),
])
def test_bad_config_raises(svh, meshes, cfg, message):
    with pytest.raises(FfcgsError, match=message):
        G.synthesize(svh, meshes["box"], cfg)


def test_bad_given_poses_raise(svh, meshes):
    bad = np.tile(np.eye(4), (2, 1, 1))
    bad[1, 0, 0] = np.nan
    with pytest.raises(FfcgsError, match="NaN"):
        G.synthesize(svh, meshes["box"], BOX, poses=bad)
    with pytest.raises(FfcgsError, match=r"shape \(4, 4\) or \(B, 4, 4\)"):
        G.synthesize(svh, meshes["box"], BOX, poses=np.zeros((2, 3, 4)))


def test_nested_config_is_validated_before_compiling(svh, meshes, monkeypatch):
    def no_compile(*a, **k):
        raise AssertionError("reached compilation with an invalid config")

    monkeypatch.setattr(G, "compiled_device_part", no_compile)
    with pytest.raises(FfcgsError, match="optim.method"):
        G.synthesize(svh, meshes["box"], dataclasses.replace(BOX, optim=with_bad(OptimConfig(iters=ITERS), method="sgd")))


def test_lowering_a_function_of_a_hand():
    hand = K.load_hand("tests/data/toy_hand/toy.toml")
    jax.jit(lambda h: h.lower).lower(hand)


def test_summary_rows_type_checks(box_run):
    assert G.summary_rows(box_run)[-1][0] == "compile time (s)"


def test_squeeze_direction_is_sum_of_jacobian_transposed_normals(svh, meshes):
    """squeeze_dir (JAX Jacobians of the touching fingertips' chosen spheres) against MuJoCo C: sum over touching
    fingertips of J_i^T (-n_i), J_i the Jacobian of the contact point held on its fingertip link (mj_jac), n_i the
    mesh normal there; scaled to a largest channel of 1. The two Jacobians differ by a rotation times the skin offset,
    which is tangential up to the angle between the SDF's and the mesh's normals: agreement 0.05."""
    from ffcgs_jax.evaluation.metrics import mesh_contacts, squeeze_direction

    # 5 descent steps leave the fingertips short of the box: a 5 cm tolerance makes most of them "touching" (the
    # device part does not depend on the tolerance: no new compile)
    box_run = synth(svh, meshes["box"], dataclasses.replace(BOX, contact_tol=0.05), "box")
    a = box_run.arrays
    touching = np.abs(a["contact_dist"]) <= box_run.config.contact_tol
    some = touching.any(axis=1)
    assert some.sum() >= 2
    assert np.abs(a["squeeze_dir"]).max(axis=1)[some] == pytest.approx(1.0)
    assert (a["squeeze_dir"][~some] == 0).all()
    np.testing.assert_allclose(a["q_squeeze"], np.clip(a["q"] + box_run.config.squeeze_angle * a["squeeze_dir"],
                                                       np.asarray(svh.lower), np.asarray(svh.upper)), atol=1e-12)
    body = np.asarray(svh.tip_body)
    names = [mujoco.mj_id2name(svh.spec.mj_model(), mujoco.mjtObj.mjOBJ_BODY, int(b)) for b in body]
    jac = np.zeros((N, len(body), 3, svh.n_channels))
    for i in range(N):
        m, d = scene.build_scene(svh.spec, a["wrist_pose"][i])
        scene.set_channels(m, d, np.asarray(svh.coupling), a["q"][i])
        mujoco.mj_forward(m, d)  # mj_jac needs the motion subspaces (cdof) too
        cols = [m.jnt_dofadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, str(j))] for j in a["joint_names"]]
        for k, name in enumerate(names):
            jp = np.zeros((3, m.nv))
            mujoco.mj_jac(m, d, jp, None, a["contacts"][i, k], mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, name))
            jac[i, k] = jp[:, cols] @ np.asarray(svh.coupling)
    _, normals, _ = mesh_contacts(meshes["box"], a["contacts"])
    expected = squeeze_direction(jac, normals, touching)
    np.testing.assert_allclose(a["squeeze_dir"][some], expected[some], atol=0.05)


def test_grasps_are_ranked_by_the_shipped_predictor(svh, meshes, box_run):
    """`pred_success` is the predictor on the call's own SDF (the same numbers from the host path), in [0, 1];
    the order puts valid grasps first, each by decreasing prediction; --rank energy keeps E's order."""
    from ffcgs_jax.evaluation import ranking
    from ffcgs_jax.synthesis import prediction

    found = prediction.weights_for(svh)
    if found is None:
        pytest.skip("no predictor ships for the SVH")
    a = box_run.arrays
    assert str(a["rank_by"]) == "predicted"
    p = a["pred_success"]
    assert p.shape == (N,) and ((p >= 0) & (p <= 1)).all()
    assert {"pred_lift_shake", "pred_six_dir"} <= set(a)
    grid = sdf_mod.build_sdf(meshes["box"], BOX.sdf)
    again = prediction.predictions(*found, svh, grid, a)
    np.testing.assert_allclose(again["pred_success"], p, atol=1e-6)
    order = box_run.order()
    v = a["valid"][order]
    assert not (v[1:] & ~v[:-1]).any()  # valid ones first
    for group in (order[v], order[~v]):
        assert (np.diff(p[group]) <= 0).all()
    energy = ranking.ranked({**a, "rank_by": np.array("energy")})
    assert energy.tolist() == np.lexsort((np.arange(N), a["E"], ~a["valid"])).tolist()
    assert any(r[0].startswith("predicted success") for r in G.summary_rows(box_run))


def test_a_bad_evaluator_file_is_one_line_before_compiling(svh, meshes, tmp_path):
    bad = tmp_path / "bad.npz"
    np.savez(bad, x=np.zeros(3))
    with pytest.raises(FfcgsError, match="bad.npz") as e:
        G.synthesize(svh, meshes["box"], dataclasses.replace(BOX, evaluator=str(bad)))
    assert "\n" not in str(e.value)
