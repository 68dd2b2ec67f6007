"""The GPU world engine (`worlds`, `world_kernels`, `world_model`) and what `auto` weighs (`cost`).

The engine's outcomes are the CPU backend's on the same grasps (one object alone or among others, compacted or
not), each world's hand meets only its own object, the device programs are the protocols' own segments and check
where the CPU checks, the mesh pool reproduces an object's meshes, and bad input falls back to the CPU with one
line. Warp runs on the CPU here (slowly: worlds of 8-16, the FAST config, four grasps; the expensive runs are
module fixtures shared by several tests); a variant of the comparison runs on CUDA where there is a device. The
tests of `world_model` and `cost` need no Warp."""

import ctypes
import dataclasses
import json
import types
import warnings

import mujoco
import numpy as np
import pytest
import trimesh

from ffcgs_jax.physics import backend_warp, convex, cost, world_model, worlds
from ffcgs_jax.physics import dexgraspbench as dgb
from ffcgs_jax.physics import protocols as P
from ffcgs_jax.physics import runner
from ffcgs_jax.physics import world_kernels as K
from ffcgs_jax.physics.backend_cpu import CpuSim
from ffcgs_jax.physics.config import PROTOCOLS, PhysicsConfig
from physics_trials import ONE_TRIAL

from test_runner import BALL, SPEC, enveloping_ball_grasp
from worlds_cases import FAST, StepCounter, at, four_grasps, make_jobs

needs_warp = pytest.mark.skipif(backend_warp.unavailable() is not None, reason="warp-lang / mujoco-warp missing")
NWORLD = 16


def _outcomes_equal(got: dict, ref: dict, what: str, move_atol: float | None = None) -> None:
    """Same success and reason; with `move_atol`, the grasps that hold moved and turned alike (m; 1e-3 degrees).
    A failing grasp's reading is not compared: a dropped ball's fall grows differences of float rounding (about
    1e-6 m) into 0.5 mm and 2.6 degrees (measured)."""
    np.testing.assert_array_equal(got["success"], ref["success"], err_msg=what)
    np.testing.assert_array_equal(got["reason"], ref["reason"], err_msg=what)
    if move_atol is not None:
        held = ref["success"]
        for k in ("move", "rot", "move_dir", "rot_dir"):
            if k in ref:
                np.testing.assert_allclose(got[k][held], ref[k][held], atol=move_atol if "move" in k else 1e-3,
                                           err_msg=f"{what} {k}")


def _run(jobs, device="cpu", **kw):
    """`worlds.run_jobs` of `jobs` on NWORLD worlds, with the world counts it resized to and its `Stats`."""
    sizes, stats = [], {}
    real = worlds.Engine.resize

    def spy(self, size):
        sizes.append((self.kind, size))
        return real(self, size)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(worlds.Engine, "resize", spy)
        for name, value in kw.items():
            mp.setattr(worlds, name, value)
        results = worlds.run_jobs(SPEC, jobs, nworld=NWORLD, device=device, stats=stats)
    return types.SimpleNamespace(results=results, sizes=sizes, stats=stats)


@pytest.fixture(scope="module")
def ball_jobs():
    Ts, qs = four_grasps()
    return make_jobs(BALL, "ball", Ts, qs)


@pytest.fixture(scope="module")
def cpu_ref(ball_jobs):
    return [P.run_protocol(CpuSim(j.scene, 1), j.batch, j.depth, j.cfg, j.protocol) for j in ball_jobs]


@pytest.fixture(scope="module")
def compacted(ball_jobs):
    """The ball's jobs on Warp-CPU, survivors moving down to a single world at the tail."""
    return _run(ball_jobs, MIN_WORLDS_CPU=1)


# --- outcomes: the CPU backend's ----------------------------------------------------------------------------


@needs_warp
@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(
    backend_warp.unavailable() is not None or backend_warp.no_cuda() is not None, reason="no CUDA device"))])
def test_engine_gives_the_cpu_backends_outcomes(device, request, ball_jobs, cpu_ref):
    run = request.getfixturevalue("compacted") if device == "cpu" else _run(ball_jobs, device="cuda")
    for job, got, ref in zip(ball_jobs, run.results, cpu_ref):
        assert ref["success"].any() and not ref["success"].all(), job.protocol  # both outcomes compared
        _outcomes_equal(got, ref, job.protocol)
        assert not got["flagged"].any(), job.protocol
        if "move_dir" in ref:  # the directions the CPU did not push after a failing one are NaN here too
            np.testing.assert_array_equal(np.isnan(got["move_dir"]), np.isnan(ref["move_dir"]), job.protocol)
    lift, ok = run.results[0], cpu_ref[0]["success"]
    np.testing.assert_allclose(lift["move"][ok], cpu_ref[0]["move"][ok], atol=2e-3)


@needs_warp
def test_an_object_among_others_gives_its_outcomes_alone(ball_jobs, compacted):
    """The ball after another object (the ball scaled 1.15: other parts, mass, inertia) in the same launches, on
    other worlds (default world counts), gives the ball's outcomes alone."""
    big = BALL.copy()
    big.apply_scale(1.15)
    Ts, qs = four_grasps()
    many = _run(make_jobs(big, "big", Ts, qs) + ball_jobs)
    assert many.stats["ours"].objects == 2 and many.stats["dexgraspbench"].objects == 2
    for job, got, alone in zip(ball_jobs, many.results[3:], compacted.results):
        _outcomes_equal(got, alone, job.protocol, move_atol=1e-5)


@needs_warp
def test_compaction_changes_no_outcome(ball_jobs, compacted):
    whole = _run(ball_jobs, MIN_WORLDS_CPU=1, COMPACT=False)
    for job, got, ref in zip(ball_jobs, compacted.results, whole.results):
        _outcomes_equal(got, ref, job.protocol, move_atol=1e-5)
    for kind in ("ours", "dexgraspbench"):
        small = [s for k, s in compacted.sizes if k == kind]
        full = [s for k, s in whole.sizes if k == kind]
        assert any(b < a for a, b in zip(small, small[1:])), small  # survivors moved to fewer worlds
        assert full == sorted(full), full  # uncompacted: it only grows
        assert compacted.stats[kind].world_steps < whole.stats[kind].world_steps, kind


@needs_warp
def test_friction_and_mass_are_per_world(ball_jobs, cpu_ref):
    """Robust trials vary the object's friction and mass per world: the ball at friction 0.05 and 0.3 kg in the
    launches of the ball at friction 1 gives the CPU's outcomes of that scene, which drop grasps the ball at
    friction 1 holds (so a friction left at the engine's value would fail this)."""
    slick = dataclasses.replace(FAST, sim_friction=0.05, mass=0.3)
    Ts, qs = four_grasps()
    jobs = make_jobs(BALL, "slick", Ts, qs, protocols=("lift-shake",), cfg=slick)
    ref = P.run_protocol(CpuSim(jobs[0].scene, 1), jobs[0].batch, jobs[0].depth, jobs[0].cfg, "lift-shake")
    assert ref["success"].sum() < cpu_ref[0]["success"].sum()
    run = _run(ball_jobs[:1] + jobs)
    _outcomes_equal(run.results[1], ref, "lift-shake")
    _outcomes_equal(run.results[0], cpu_ref[0], "lift-shake")
    assert world_model.engine_config(slick) == world_model.engine_config(FAST)


# --- one model, many objects: a world's hand meets only its own object -------------------------------------


@pytest.fixture(scope="module")
def ours_engine():
    return worlds.Engine(SPEC, FAST, "ours", FAST.max_hulls, nworld=8, device="cpu")


def _contacts(pairs_geoms, dists, label) -> dict:
    """{(label, label) sorted: the smallest distance of the contacts of that pair}."""
    out: dict = {}
    for (g1, g2), dist in zip(pairs_geoms, dists):
        key = tuple(sorted((label(int(g1)), label(int(g2)))))
        out[key] = min(out.get(key, np.inf), float(dist))
    return out


def _labeller(scene):
    """A geom of `scene` as (what, index): a hand geom by its place in `hand_geoms` (ids differ between a scene
    with a table and one without), an object part by its slot, the table."""
    names = {int(g): ("hand", i) for i, g in enumerate(scene.hand_geoms)}
    names |= {int(g): ("part", i) for i, g in enumerate(scene.obj_geoms)}
    return lambda g: names.get(g, ("table", 0) if g == scene.table_geom else ("geom", g))


@needs_warp
def test_a_worlds_hand_meets_only_its_own_object(ours_engine):
    """The ball and a 14 cm box around it in two worlds of one engine, the hand 1 cm into the ball at the same
    pose in both: the ball's world has the contacts CPU MuJoCo finds on the ball's own scene, none of the box's."""
    e = ours_engine
    six = runner.scenes(SPEC, BALL, FAST, ("six-dir",))["six-dir"]
    box = trimesh.creation.box((0.14, 0.14, 0.14))
    box.apply_translation(BALL.bounds.mean(0))
    box_six = runner.scenes(SPEC, box, FAST, ("six-dir",), parts=[(box.vertices, box.faces)])["six-dir"]
    T, q = enveloping_ball_grasp(shift=-0.01)
    batch, depth, _ = runner.prepare(six, BALL, T[None], q[None], FAST)
    job = worlds.Job(six, batch, depth, FAST, "six-dir")
    ball_obj, box_obj = e.add_object("ball-six", six), e.add_object("box-six", box_six)
    e._upload_pool()
    e.resize(e.nworld)
    blocks = [e.fresh(0, job, ball_obj, np.array([0])), e.fresh(1, job, box_obj, np.array([0]))]
    for b in blocks:
        b.qpos[:, six.hand_qpos] = q @ six.coupling.T  # the grasp's fingers closed on the ball, not the open hand
        assert len(e.place(b).ip) == 0
    e.advance(1)  # the step's contacts are those of the placed state
    d = e._data[e.size][0]
    n = int(d.nacon.numpy()[0])
    wid, geom, dist = d.contact.worldid.numpy()[:n], d.contact.geom.numpy()[:n], d.contact.dist.numpy()[:n]
    label = _labeller(e.scene)
    ball_w, box_w = (int(np.flatnonzero(e.tag[: e.size, 0] == j)[0]) for j in (0, 1))
    on_ball = _contacts(geom[wid == ball_w], dist[wid == ball_w], label)
    on_box = _contacts(geom[wid == box_w], dist[wid == box_w], label)

    m = six.model
    cd = mujoco.MjData(m)
    cd.qpos[:] = blocks[0].qpos[0].astype(np.float32)  # the state as the worlds hold it
    mujoco.mj_forward(m, cd)
    cpu = _contacts([c.geom for c in cd.contact[: cd.ncon]], [c.dist for c in cd.contact[: cd.ncon]],
                    _labeller(six))
    assert len(cpu) >= 4 and min(cpu.values()) < -0.005, cpu  # the hand is well into the ball
    assert set(on_ball) == set(cpu), (on_ball, cpu)
    for k in cpu:
        assert abs(on_ball[k] - cpu[k]) < 1e-4, (k, on_ball[k], cpu[k])
    assert set(on_box) - set(on_ball), on_box  # the box is there, in its own world only


# --- the device programs: the protocols' segments, checked where the CPU checks -------------------------------


def _control(e) -> tuple[np.ndarray, ...]:
    """Launch only the `control` kernel over the engine's worlds (as `Engine._one_step` does); returns the servo
    targets, wrist target position and orientation, weld switches and the object's force it wrote."""
    wp, d = e.wp, e._data[e.size][0]
    with wp.ScopedDevice(e.device):
        wp.launch(e.k["control"], dim=e.size, inputs=[
            e.ip, e.fp, e.col, e.sched_i, e.sched_f, e.ev_t, e.ev_code, int(e.scene.obj_body),
            int(e.scene.hold_eq), d.qpos, d.qvel, d.qacc_warmstart, d.ctrl, d.mocap_pos, d.mocap_quat, d.eq_active,
            d.xfrc_applied, *e.snap])
    return (d.ctrl.numpy(), d.mocap_pos.numpy(), d.mocap_quat.numpy()[:, 0], d.eq_active.numpy(),
            d.xfrc_applied.numpy()[:, e.scene.obj_body, :3])


def _check_programs(e, programs: list) -> set[int]:
    """`programs`: per world (its first worlds in order) (segments, grasp, batch, weld as the CPU scene holds
    it, the table's height there). Sets each world's step counter to steps across its program and compares what
    `control` writes with the segments' own values at that step; returns the program kinds seen."""
    L = e.lay
    ip = e.ip.numpy()
    kinds = {int(k) for k in ip[: len(programs), L.KIND]}
    lengths = np.array([sum(s.n for s in segs) for segs, *_ in programs])
    ends = {int(x) for segs, *_ in programs for x in np.cumsum([s.n for s in segs])}
    samples = sorted(set(range(0, int(lengths.max()), 5)) | {x + d for x in ends for d in (-1, 0, 1)} | {0})
    for s in samples:
        t = np.minimum(s, lengths - 1)
        ip = e.ip.numpy()
        ip[: len(programs), L.T] = t
        e.ip.assign(ip)
        ctrl, mpos, mquat, active, force = _control(e)
        for w, (segs, g, batch, weld, table) in enumerate(programs):
            c, off, f, hold = at(segs, int(t[w]))
            what = f"world {w} (kind {int(ip[w, L.KIND])}) step {t[w]}"
            np.testing.assert_allclose(ctrl[w], c[g], atol=1e-5, err_msg=what)
            np.testing.assert_allclose(mpos[w, 0], batch.wrist_pos[g] + off, atol=1e-5, err_msg=what)
            if e.scene.table_geom >= 0:  # the table's mount (a mocap body): the CPU scene's table, or none
                np.testing.assert_allclose(mpos[w, 1], [0, 0, -1000.0 if table is None else table], err_msg=what)
            np.testing.assert_allclose(mquat[w], batch.wrist_quat[g], atol=1e-6, err_msg=what)
            np.testing.assert_allclose(force[w], f, rtol=1e-6, atol=1e-6, err_msg=what)
            if e.scene.hold_eq >= 0:
                assert bool(active[w, e.scene.hold_eq]) == (hold and weld), what
    return kinds


@needs_warp
def test_the_device_programs_are_the_protocols_segments(ours_engine, ball_jobs):
    lift, six, bench = ball_jobs
    e = ours_engine
    obj = e.add_object("ball-lift", lift.scene)
    e._upload_pool()
    e.resize(e.nworld)
    closing = e.fresh(1, six, obj, np.array([1]))
    blocks = [e.fresh(0, lift, obj, np.array([0])), closing,
              e.pushes(closing.ip, closing.fp, [closing.qpos, closing.qvel, closing.warm], closing.tag, FAST.accel)]
    for b in blocks:
        assert len(e.place(b).ip) == 0
    lb, sb = lift.batch, six.batch
    has_weld = lambda job: job.scene.hold_eq >= 0  # noqa: E731 - lift-shake's scene has none: the table holds it
    table = float(lift.scene.model.geom_pos[lift.scene.table_geom, 2])
    assert six.scene.table_geom < 0
    programs = [(P.closing(lb, FAST) + P.lift_shake(lb, FAST), 0, lb, has_weld(lift), table),
                (P.closing(sb, FAST), 1, sb, has_weld(six), None)]
    programs += [([P.push(sb, FAST, d, six.scene.mass)], 1, sb, has_weld(six), None) for d in P.DIRECTIONS]
    seen = _check_programs(e, programs)

    be = worlds.Engine(SPEC, bench.cfg, "dexgraspbench", FAST.max_hulls, nworld=8, device="cpu")
    obj = be.add_object("ball", bench.scene)
    be._upload_pool()
    be.resize(be.nworld)
    squeeze = be.fresh(0, bench, obj, np.array([1]))
    for b in (squeeze, be.pushes(squeeze.ip, squeeze.fp, [squeeze.qpos, squeeze.qvel, squeeze.warm], squeeze.tag,
                                 bench.cfg.accel)):
        assert len(be.place(b).ip) == 0
    bb = bench.batch
    programs = [(P.grasp_and_squeeze(bb, bench.cfg), 1, bb, False, None)]
    programs += [([P.bench_push(bb, bench.cfg, d, bench.scene.mass)], 1, bb, False, None) for d in P.DIRECTIONS]
    seen |= _check_programs(be, programs)
    assert seen == {K.LIFT, K.SIX_CLOSE, K.SIX_PUSH, K.BENCH_SQUEEZE, K.BENCH_PUSH}


LONG = PhysicsConfig(robust=ONE_TRIAL, close_time=1.1, settle_time=0.3, lift_height=0.13, shake_cycles=1, push_time=1.3)


@pytest.mark.parametrize("cfg", [FAST, LONG], ids=["fast", "long"])
def test_the_schedule_checks_where_the_cpu_protocols_look(cfg):
    """A simulator that only counts steps (`StepCounter`) records where `run_protocol` reads the object: after
    closing (the reference; six-dir's pushes and DexGraspBench's branch there), after each `CHUNK` of a segment
    and at its end, DexGraspBench's every `CHECK_TIME`. `Schedule` puts its events at the same steps."""
    nu = 3
    sched = worlds.Schedule(cfg, nu)
    z = np.zeros((1, nu))
    batch = P.Batch(np.zeros((1, 3)), np.array([[1.0, 0, 0, 0]]), z, z + 0.1, z + 0.05)

    def events(kind, sched=sched):
        a = sched.adr[kind]
        return [(int(t), int(c)) for t, c in zip(sched.ev_t[a: a + sched.num[kind]],
                                                 sched.ev_code[a: a + sched.num[kind]])]

    def looks(protocol, pcfg):
        sim = StepCounter()
        P.run_protocol(sim, batch, np.zeros(1), pcfg, protocol)
        return sim.times()

    close = P.steps(cfg.close_time, cfg.timestep) + P.steps(cfg.settle_time, cfg.timestep)
    lift = events(K.LIFT)
    assert [t for t, _ in lift] == looks("lift-shake", cfg) and close == lift[0][0]
    assert [c for _, c in lift] == [K.REF] + [K.CHECK] * (len(lift) - 2) + [K.FINAL]
    assert len(lift) > 3  # more than one check per segment on the long config, one each on the fast
    six = looks("six-dir", cfg)
    assert events(K.SIX_CLOSE) == [(close, K.BRANCH)] and six[0] == close
    push = events(K.SIX_PUSH)
    assert [t for t, _ in push] == [t - close for t in six[1:]]
    assert [c for _, c in push] == [K.CHECK] * (len(push) - 1) + [K.FINAL]
    bcfg = P.get("dexgraspbench").settings(cfg)  # DexGraspBench's engine is built with its own config
    bsched = worlds.Schedule(bcfg, nu)
    bench = looks("dexgraspbench", bcfg)
    squeeze = 2 * P.steps(dgb.STAGE_TIME, bcfg.timestep)
    assert events(K.BENCH_SQUEEZE, bsched) == [(0, K.REF), (squeeze, K.BRANCH)] and bench[:2] == [0, squeeze]
    bpush = events(K.BENCH_PUSH, bsched)
    assert [t for t, _ in bpush] == [t - squeeze for t in bench[2:]]
    every = P.steps(dgb.CHECK_TIME, bcfg.timestep)
    assert [t for t, _ in bpush] == list(range(every, P.steps(dgb.PUSH_TIME, bcfg.timestep) + 1, every))
    assert [c for _, c in bpush] == [K.CHECK] * (len(bpush) - 1) + [K.FINAL]
    for s, kind, evs in ((sched, K.LIFT, lift), (sched, K.SIX_PUSH, push), (bsched, K.BENCH_PUSH, bpush)):
        assert s.length[kind] == evs[-1][0] + 1


# --- world_model: the mesh pool --------------------------------------------------------------------------------


def _flat(m, flat: str, adr: np.ndarray, i: int, n: int) -> np.ndarray:
    return np.asarray(m[flat])[adr[i]: adr[i] + n] if adr[i] >= 0 else np.zeros(0)


def test_the_mesh_pool_reproduces_an_objects_meshes():
    """The mug's meshes appended to a template's pool: every mesh field reads the same through the pool's
    addresses as through the mug scene's own, the addresses shifted by what lies before, the template's meshes
    untouched."""
    import ffcgs_jax as fj

    mug = fj.load_mesh("mug")
    scene = runner.scenes(SPEC, mug, FAST, ("six-dir",))["six-dir"]
    rows = world_model.object_rows(scene)
    assert rows.parts > 1
    template = world_model.template(SPEC, FAST, "ours", rows.parts).model
    pool = world_model.MeshPool(template)
    first = pool.add(rows.meshes)
    assert first == template.nmesh and pool.nmesh == template.nmesh + rows.parts
    got = pool.arrays()
    m = scene.model
    own = {f: np.asarray(getattr(m, f"mesh_{f}")) for f in worlds.MESH_FIELDS}
    tpl = {f: np.asarray(getattr(template, f"mesh_{f}")) for f in worlds.MESH_FIELDS}
    mfirst = int(m.geom_dataid[scene.obj_geoms].min())
    for f in worlds.MESH_FIELDS:  # the template's meshes come first, as they were
        n = len(tpl[f])
        np.testing.assert_array_equal(got[f][:n], tpl[f].reshape(got[f][:n].shape), err_msg=f)
    for adr, flat in world_model.ADDRESSES.items():  # object addresses: its own, moved past the template's
        mine, theirs = got[adr][first:], own[adr][mfirst: mfirst + rows.parts]
        assert np.array_equal(mine >= 0, theirs >= 0), adr
        if (theirs >= 0).any():
            start = int(theirs[theirs >= 0].min())
            assert set((mine - theirs)[mine >= 0].tolist()) == {len(tpl[flat]) - start}, adr
    facenum = np.asarray(m.mesh_facenum)
    graph_end = np.append(own["graphadr"][1:], len(own["graph"]))
    for i in range(rows.parts):
        a, b = first + i, mfirst + i
        for f in ("vertnum", "normalnum", "pos", "quat", "polynum"):
            np.testing.assert_array_equal(got[f][a], own[f][b], err_msg=f)
        nv = own["vertnum"][b]
        np.testing.assert_array_equal(_flat(got, "vert", got["vertadr"], a, nv), _flat(own, "vert", own["vertadr"],
                                                                                        b, nv))
        np.testing.assert_array_equal(_flat(got, "normal", got["normaladr"], a, own["normalnum"][b]),
                                      _flat(own, "normal", own["normaladr"], b, own["normalnum"][b]))
        np.testing.assert_array_equal(_flat(got, "face", got["faceadr"], a, facenum[b]),
                                      _flat(own, "face", own["faceadr"], b, facenum[b]))
        ng = graph_end[b] - own["graphadr"][b] if own["graphadr"][b] >= 0 else 0
        np.testing.assert_array_equal(_flat(got, "graph", got["graphadr"], a, ng),
                                      _flat(own, "graph", own["graphadr"], b, ng))
        npoly = own["polynum"][b]
        pa, pb = got["polyadr"][a], own["polyadr"][b]
        np.testing.assert_array_equal(got["polynormal"][pa: pa + npoly], own["polynormal"][pb: pb + npoly])
        for j in range(npoly):
            k, n = got["polyvertadr"][pa + j], own["polyvertnum"][pb + j]
            assert got["polyvertnum"][pa + j] == n
            np.testing.assert_array_equal(got["polyvert"][k: k + n],
                                          own["polyvert"][own["polyvertadr"][pb + j]: own["polyvertadr"][pb + j] + n])
        va, vb = got["vertadr"][a], own["vertadr"][b]
        for v in range(nv):
            k, n = got["polymapadr"][va + v], own["polymapnum"][vb + v]
            assert got["polymapnum"][va + v] == n
            np.testing.assert_array_equal(got["polymap"][k: k + n],
                                          own["polymap"][own["polymapadr"][vb + v]: own["polymapadr"][vb + v] + n])


# --- bad input: the CPU answers, with one line --------------------------------------------------------------


@pytest.fixture
def no_engines():
    """No engine kept from before (its buffers would be reused) nor left behind (a test's odd buffers)."""
    worlds.clear()
    yield
    worlds.clear()


def _two():
    Ts, qs = four_grasps()
    return Ts[:2], qs[:2]


def _same_results(got: dict, ref: dict, prefix: str) -> None:
    keys = [k for k in ref if k.startswith(prefix)]
    assert keys
    for k in keys:
        np.testing.assert_array_equal(got[k], ref[k], err_msg=k)


@needs_warp
def test_overflowed_buffers_are_flagged_and_rerun_on_the_cpu(monkeypatch, no_engines, capfd):
    """One warning line for the call, none of MuJoCo Warp's printf lines (one per world and step, hundreds in a
    labelled build of an object that overflows)."""
    Ts, qs = _two()
    monkeypatch.setattr(worlds, "buffer_sizes", lambda scene: (2, 60))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        warp = runner.evaluate(SPEC, BALL, Ts, qs, FAST, ("six-dir",), backend="warp")
    cpu = runner.evaluate(SPEC, BALL, Ts, qs, FAST, ("six-dir",), backend="cpu")
    assert warp["physics_rerun_cpu"].all()
    _same_results(warp, cpu, "six_dir_")
    said = [str(w.message) for w in caught if "overflowed" in str(w.message)]
    assert len(said) == 1 and "2 grasp trials" in said[0] and "\n" not in said[0], said
    ctypes.CDLL(None).fflush(None)  # the kernels' printf goes through the C library's buffered stdout
    printed = capfd.readouterr()
    assert "overflow" not in printed.out + printed.err


@needs_warp
def test_object_keys_name_the_objects_of_one_run_only(no_engines):
    """`runner` keys a call's objects by their index (0, 1, ...): a later call's object 0 is another object, not
    the kept engine's object 0 of the call before. Told apart cheaply: the second object has more parts than the
    slots (a grasp starting in penetration: nothing is simulated)."""
    deep, q = enveloping_ball_grasp(shift=-0.03)
    part = convex.decompose(BALL, FAST)[0]
    one, = make_jobs(BALL, 0, deep[None], q[None], ("six-dir",))
    three, = make_jobs(BALL, 0, deep[None], q[None], ("six-dir",), parts=[part] * 3)
    first, = worlds.run_jobs(SPEC, [one], nworld=8, device="cpu", slots=2)
    assert first["reason"].tolist() == [P.REASONS.index("penetration")]
    with pytest.warns(UserWarning, match="an object of 3 convex parts does not fit the 2 slots"):
        assert worlds.run_jobs(SPEC, [three], nworld=8, device="cpu", slots=2) == [None]


@needs_warp
def test_an_object_of_more_parts_than_slots_runs_on_the_cpu(no_engines):
    Ts, qs = _two()
    part = convex.decompose(BALL, FAST)[0]
    three = [part] * 3  # three parts for two slots
    job, = make_jobs(BALL, None, Ts, qs, ("six-dir",), parts=three)
    with pytest.warns(UserWarning, match="six-dir of an object runs on the CPU: an object of 3 convex parts does "
                                         "not fit the 2 slots") as caught:
        assert worlds.run_jobs(SPEC, [job], nworld=8, device="cpu", slots=2) == [None]
    assert all("\n" not in str(w.message) for w in caught)
    cfg = dataclasses.replace(FAST, max_hulls=2)
    with pytest.warns(UserWarning, match="does not fit the 2 slots"):
        warp = runner.evaluate(SPEC, BALL, Ts, qs, cfg, ("six-dir",), backend="warp", parts=three)
    cpu = runner.evaluate(SPEC, BALL, Ts, qs, cfg, ("six-dir",), backend="cpu", parts=three)
    assert warp["physics_rerun_cpu"].all()
    _same_results(warp, cpu, "six_dir_")


def test_a_gpu_failure_gives_the_cpu_results_with_one_line(monkeypatch):
    Ts, qs = _two()

    def fail(*a, **k):
        raise RuntimeError("CUDA out of memory\nmore detail the user need not see")

    monkeypatch.setattr(worlds, "run_jobs", fail)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        warp = runner.evaluate(SPEC, BALL, Ts, qs, FAST, ("six-dir",), backend="warp")
    said = [str(w.message) for w in caught if "physics" in str(w.message)]
    assert said == ["physics: MuJoCo Warp failed (RuntimeError: CUDA out of memory); these grasps run on the CPU"]
    cpu = runner.evaluate(SPEC, BALL, Ts, qs, FAST, ("six-dir",), backend="cpu")
    _same_results(warp, cpu, "six_dir_")


# --- cost: where `auto` runs a batch ------------------------------------------------------------------------


@pytest.fixture
def record(tmp_path, monkeypatch):
    path = tmp_path / "cost.json"
    monkeypatch.setattr(cost, "record_path", lambda: path)
    return path


def test_auto_takes_the_cpu_for_a_few_grasps_and_warp_for_many(record):
    where, why = cost.choose(8, PROTOCOLS, FAST, cores=64, warm=False)
    assert where == "cpu" and "\n" not in why and why.startswith("physics on the CPU: 8 grasps") and \
        "default figures" in why, why
    assert cost.choose(20000, PROTOCOLS, PhysicsConfig(), cores=64, warm=False) == ("warp", None)
    # a warm engine pays no start-up: 8 grasps on a 2-core machine go to the GPU then
    assert cost.choose(8, PROTOCOLS, FAST, cores=2, warm=True)[0] == "warp"


def test_cost_records_round_trip(record):
    cost.remember_cpu("six-dir", 2.0)
    cost.remember_cpu("six-dir", 4.0)  # blended with what was there
    cost.remember_warp(512, 1e-3)
    cost.remember_setup(7.0)
    data = json.loads(record.read_text())
    assert data == {"cpu": {"six-dir": 3.0}, "step_s": {"512": 1e-3}, "setup_s": 7.0}
    cpu, _ = cost.estimate(10, ("six-dir",), FAST, cores=5, warm=True)
    assert cpu == pytest.approx(10 * 3.0 / 5)
    where, why = cost.choose(1, ("six-dir",), FAST, cores=64, warm=False)
    assert where == "cpu" and "as measured on this machine" in why
    record.write_text("{not json")  # a damaged record costs only the measured figures
    assert cost.estimate(10, ("six-dir",), FAST, cores=5, warm=True)[0] == pytest.approx(
        10 * cost.PRIOR["cpu"]["six-dir"] / 5)
