"""The grasp pipeline: sample wrist poses, optimise the fingers (Algorithm 1), filter, evaluate.

`synthesize` is what `ffcgs grasp` runs. The device part (sampling, descent, filters) is one jit-compiled
function, compiled ahead of time so its compile time is measured apart from the synthesis time; the evaluation
(contacts, force closure and Ferrari-Canny epsilon from the mesh itself, `evaluation.device_metrics`) is a second
compiled function on the same device, and both results come back to the host in one copy.
"""

import dataclasses
import functools
import json
import time
import warnings
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import trimesh
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from ffcgs_jax.core.config import check_all
from ffcgs_jax.core.config import from_dict as config_from_dict
from ffcgs_jax.core.errors import FfcgsError, check_grasp_set
from ffcgs_jax.evaluation import device_metrics, metrics, ranking
from ffcgs_jax.geometry import mesh_io
from ffcgs_jax.geometry import sdf as sdf_mod
from ffcgs_jax.hand import kinematics as K
from ffcgs_jax.hand.kinematics import Hand
from ffcgs_jax.hand.sites import palm_centre_root
from ffcgs_jax.runtime import compile_clock, compiled, progress, traced_store
from ffcgs_jax.runtime import fetch, memory, sharding
from ffcgs_jax.synthesis import grasp_io, prediction, samplers, search
from ffcgs_jax.synthesis import filters as F
from ffcgs_jax.synthesis.config import EnergyConfig, GraspConfig, OptimConfig
from ffcgs_jax.synthesis.energy import Target, Terms, chosen, fingertip_contacts, make_target
from ffcgs_jax.synthesis.grasp_set import GraspSet
from ffcgs_jax.synthesis.optimize import OptResult, Trace, descend


class DeviceOut(NamedTuple):
    poses: jax.Array
    opt: OptResult
    pose_collides: jax.Array
    palm_up: jax.Array
    tips_below_table: jax.Array
    penetration: jax.Array
    table_penetration: jax.Array
    tip_jac: jax.Array  # (B, C, 3, Q) d contacts / d q at the result: the squeeze direction's Jacobians


class DeviceConfig(NamedTuple):
    """The part of GraspConfig the compiled function depends on (the seed and the SDF settings are not)."""

    sampler: str
    sampling: samplers.SamplerConfig
    energy: EnergyConfig
    optim: OptimConfig
    filters: F.FilterConfig


def _device_part(hand: Hand, target: Target, key: jax.Array, given: jax.Array | None, cfg: DeviceConfig,
                 n: int, given_q: jax.Array | None = None, sampler_params: dict | None = None,
                 sampler_res: int | None = None, mesh: Mesh | None = None, palm_root: jax.Array | None = None
                 ) -> DeviceOut:
    """`palm_root`: `hand.sites.palm_centre_root`, from the host (where sampling; tracing MJX for it costs seconds)."""
    if given is None:
        poses = samplers.CORES[cfg.sampler](hand, palm_root, key, target.sdf, n, cfg.sampling, cfg.filters,
                                            params=sampler_params, res=sampler_res, mesh=mesh)
    else:
        poses = given
    # The trace is (T+1, B, ...): its pose axis is the second.
    specs = DeviceOut(*[P(sharding.AXIS)] * 8)._replace(
        opt=OptResult(*[P(sharding.AXIS)] * 6, trace=P(None, sharding.AXIS)))
    return sharding.split(functools.partial(_descend_and_filter, cfg=cfg), mesh, (hand, target), (poses, given_q),
                          specs)


def _descend_and_filter(hand: Hand, target: Target, poses: jax.Array, given_q: jax.Array | None,
                        cfg: DeviceConfig) -> DeviceOut:
    opt = descend(hand, target, poses, cfg.energy, cfg.optim, given_q)
    poses = opt.wrist_pose
    tips = jnp.moveaxis(opt.trace.tips, 1, 0)  # (B, T+1, C, 3)
    # one kinematics pass for the final filters: each pass is a large graph to trace and compile
    frames = jax.vmap(K.forward_kinematics, (None, 0, 0))(hand, poses, opt.q)
    pen = jax.vmap(lambda H, q, f: F.hand_penetration(hand, target.sdf, H, q, f)[0])(poses, opt.q, frames)
    tpen = jax.vmap(lambda H, q, f: F.hand_table_penetration(hand, target.sdf, H, q, f)[0])(poses, opt.q, frames)
    # the chosen sphere's centre moves along the normal as its skin point does (a rotation moves the skin point
    # tangentially relative to the centre), and only the normal part enters the squeeze direction
    choice = jax.vmap(lambda f: fingertip_contacts(hand, target.sdf, f).choice)(frames)
    jac = jax.vmap(lambda H, q, k: jax.jacfwd(
        lambda x: chosen(K.fingertip_spheres(hand, K.forward_kinematics(hand, H, x))[0], k))(q))(poses, opt.q, choice)
    return DeviceOut(
        poses=poses,
        opt=opt,
        pose_collides=F.pose_collides_batch(hand, target.sdf, poses, cfg.filters),
        palm_up=F.palm_up_batch(hand, poses, cfg.filters),
        tips_below_table=jax.vmap(lambda t: F.tips_below_table(target.sdf, t, cfg.filters.tip_table_margin))(tips),
        penetration=pen,
        table_penetration=tpen,
        tip_jac=jac,
    )


device_mesh = sharding.device_mesh
# key -> (executable, how it takes its arguments: `traced_store.lower`), kept in `runtime.compiled` under STAGE
STAGE = "device_part"
traced_store.register_outputs(DeviceOut, OptResult, Terms, Trace)


def compiled_executables() -> list:
    """The device part's executables this process holds, in the order compiled (`fj.clear_compiled` empties
    them)."""
    return [executable for executable, _ in compiled.held(STAGE)]


def compiled_device_part(hand: Hand, target: Target, key: jax.ShapeDtypeStruct, given, dcfg: DeviceConfig, n: int,
                         given_q=None, sampler_params=None, sampler_res=None, mesh=None):
    """Ahead-of-time compiled device part, cached like jit's own cache (AOT compiles bypass that cache), so that
    compile time can be reported apart and every later object reuses the executable: (compiled, call), run as
    `call(compiled, hand, target, key, given, given_q, sampler_params)`. A new executable is checked
    against the device's free memory once, when compiled (`memory.check_fits` reads its memory analysis, about
    0.1 s: too slow for every call). With the compilation cache on, the trace itself is kept on disk too
    (`traced_store`)."""
    shapes = jax.tree.map(lambda x: (x.shape, x.dtype), (target, key, given, given_q, sampler_params))
    k = (hand.spec, dcfg, n, str(shapes), sampler_res, jax.default_backend(), mesh)
    kept = compiled.get(STAGE, k)
    if kept is None:
        def part(hand, target, key, given, given_q, sampler_params, palm_root):
            return _device_part(hand, target, key, given, dcfg, n, given_q, sampler_params, sampler_res, mesh,
                                palm_root)

        # the sampler's palm centre from MuJoCo on the host, once per executable: an MJX pass for it in the program
        # cost seconds of tracing, and a host pass per call milliseconds of every call
        palm_root = None if given is not None else jnp.asarray(palm_centre_root(hand), hand.lower.dtype)
        if palm_root is not None and mesh.size > 1:
            palm_root = jax.device_put(palm_root, NamedSharding(mesh, P()))
        # host callbacks (the proxsuite LP) and programs over several devices cannot be stored
        storable = mesh.size == 1 and dcfg.energy.lp_solver != "proxsuite"
        with progress.compiling("the synthesis"):  # a minute or more on a CPU: the CLI says so while it runs
            lowered, call = traced_store.lower(STAGE, part, (hand, target, key, given, given_q, sampler_params,
                                                             palm_root), (dcfg, n, sampler_res), storable)
            executable = lowered.compile()
        # before anything is allocated: no out-of-memory traceback
        memory.check_fits(executable, n, mesh.devices.flat[0])
        kept = executable, lambda executable, *args: call(executable, *args, palm_root)
        compiled.put(STAGE, k, kept)
    return kept


# gs unannotated (here and in check_on_mesh): another type is refused with one FfcgsError line, not by a type checker
def save_grasps(gs, path) -> None:
    """Write `gs` to a grasp .npz file (its arrays, object name and config; not the per-iteration trace), as
    `ffcgs grasp --out` does: atomically, no pickle."""
    grasp_io.save_npz(gs, path)


def load_grasps(path) -> GraspSet:
    """A grasp .npz file (`save_grasps`, `ffcgs grasp --out`) as a GraspSet, its arrays checked (one line naming the
    file and the problem otherwise). The config comes back as written; a file from a version whose config no longer
    parses keeps GraspConfig's defaults, with a warning. The trace is not stored: `trace` is empty."""
    arrays = grasp_io.load_npz(path)
    name = str(arrays.pop("object_name", Path(path).stem))
    cfg = GraspConfig()
    if "config_json" in arrays:
        try:
            cfg = config_from_dict(GraspConfig, _as_made(json.loads(str(arrays.pop("config_json")))),
                                   say_renamed=False)
        except (FfcgsError, ValueError) as e:
            warnings.warn(f"{path}: its config does not parse here ({e}); GraspConfig's defaults stand in",
                          stacklevel=2)
    return GraspSet(arrays, {}, cfg, name)


def _as_made(stored: dict) -> dict:
    """A stored config from before a setting existed, with that setting at what the code that wrote it did: no
    final projection (`optim.project_steps` 0) and no further search (`search.max_rounds` 1); their defaults would
    misstate how the grasps were made."""
    if isinstance(stored, dict):
        optim = stored.get("optim")
        if isinstance(optim, dict) and "project_steps" not in optim:
            stored = {**stored, "optim": {**optim, "project_steps": 0}}
        if "search" not in stored:
            stored = {**stored, "search": {"max_rounds": 1}}
    return stored


def synthesize(hand: Hand, mesh: trimesh.Trimesh | sdf_mod.GradientSDF, cfg: GraspConfig = GraspConfig(),
               object_name: str = "object", grid: sdf_mod.GradientSDF | None = None, poses: np.ndarray | None = None,
               q: np.ndarray | None = None) -> GraspSet:
    """Sample `cfg.n` wrist poses on the object (or take `poses`, (B, 4, 4), object frame), optimise the fingers,
    filter and evaluate the grasps. `q` (B, Q), only with `poses`, starts the descent there instead of at the open
    hand (the annotation planner does not: see `dataset.planner.plan` for why).

    `mesh` is what the filters and epsilon read (`evaluation.device_metrics.evaluate`): the object's mesh, or for an
    object known only by its SDF (fused from depth frames) that `GradientSDF`, which is then also the grid planned
    on. `grid`: plan on this SDF instead of building one from the mesh."""
    check_all(cfg)  # nested configs too: an unknown optim.method must not silently fall back
    cfg = for_hand(cfg, hand)
    prediction.resolve(cfg.rank, hand, cfg.evaluator)  # a bad predictor file is one line before any compile
    if poses is None:
        samplers.sampler_params(cfg.sampler, hand, cfg.sampling)  # and so is a bad sampler weights file
    device_mesh(cfg.devices)  # and more devices than the machine has
    clock = compile_clock.compiling
    # The ahead-of-time compiles are timed where they happen; whatever else compiles during the call (a
    # process's first call: the SDF build, the target, the packing of the results) is counted by `clock` and moved
    # from the stage it happened in to compile_s, so sdf_s, synthesis_s, evaluation_s and total_s are call time.
    with clock() as every:
        start = time.perf_counter()
        with clock() as sdf_compile:
            if grid is None:
                with progress.compiling("the SDF build"):  # its kernels compile on a process's first call
                    grid = mesh if isinstance(mesh, sdf_mod.GradientSDF) else sdf_mod.build_sdf(mesh, cfg.sdf)
        sdf_s = time.perf_counter() - start - sdf_compile[0]
        target = make_target(grid)
        key = jax.random.PRNGKey(cfg.seed)
        given = None
        if poses is not None:
            given = jnp.asarray(K.check_wrist_poses(poses, "wrist poses").reshape(-1, 4, 4), target.sdf.grid.dtype)
        given_q = None
        if q is not None:
            if given is None:
                raise FfcgsError("start channels q need the wrist poses they belong to (poses=...)")
            qa = np.asarray(q)
            if qa.shape != (given.shape[0], hand.n_channels) or not np.isfinite(qa).all():
                raise FfcgsError(f"start channels q must be finite with shape ({given.shape[0]}, "
                                 f"{hand.n_channels}), got {qa.shape}")
            given_q = jnp.asarray(qa, target.sdf.grid.dtype)
        with clock() as aot_device:
            run, compile_s = compile_device(hand, target, cfg, given, given_q)
        t0 = time.perf_counter()
        with clock() as run_compile:
            out = run(key)
            surface = surface_of(mesh)  # the triangle table of a new mesh (host work) while the device part runs
            # An evaluation compiled before is queued behind the device part, so its host-side preparation and
            # launch overlap the device's work; a new one is compiled after the device part ends (a compile
            # overlapping it would hide in synthesis_s). Either way synthesis_s ends when the device part's results
            # are ready.
            queued, _ = prepare_evaluation(hand, surface, target, cfg, out, compile=False)
            ev = queued() if queued is not None else None
            out = jax.block_until_ready(out)
        synthesis_s = time.perf_counter() - t0 - run_compile[0]
        evaluate, eval_compile_s = (lambda: ev), 0.0
        with clock() as aot_eval:
            if queued is None:
                with progress.compiling("the evaluation"):
                    evaluate, eval_compile_s = prepare_evaluation(hand, surface, target, cfg, out)
        gs = finish(hand, target, cfg, out, evaluate, synthesis_s, object_name)
        # a weak first batch: more batches through the same executables, only the key changes (`search`)
        again = None if given is not None else \
            (lambda k: finish(hand, target, cfg, *_batch(hand, surface, target, cfg, run, k), object_name))
        gs = search.further(gs, cfg.search, cfg.seed, again)
    on_the_way = every[0] - aot_device[0] - aot_eval[0]
    compile_total = compile_s + eval_compile_s + on_the_way
    # where the object came from, when `load_mesh` read it and it is unchanged since: a file saved from Python is
    # then evaluated (`ffcgs eval`) without naming the object again
    return gs.with_arrays(compile_s=np.asarray(compile_total, np.float64), sdf_s=np.asarray(sdf_s, np.float64),
                          total_s=np.asarray(time.perf_counter() - start - compile_total, np.float64),
                          **mesh_io.source_of(mesh))


def _batch(hand, surface, target, cfg, run, key) -> tuple[DeviceOut, object, float]:
    """Another batch of a call whose executables are compiled: (device results, its evaluation, seconds)."""
    t0 = time.perf_counter()
    out = run(key)
    evaluate, _ = prepare_evaluation(hand, surface, target, cfg, out)
    ev = evaluate()
    out = jax.block_until_ready(out)
    return out, (lambda: ev), time.perf_counter() - t0


def compile_device(hand: Hand, target: Target, cfg: GraspConfig, given: jax.Array | None = None,
                   given_q: jax.Array | None = None):
    """The compiled device part (sampling or `given` poses, descent, filters) as `run(key) -> DeviceOut`, and the
    seconds its compilation took (0 when cached). For benchmarks: time `run` apart from host-side evaluation."""
    cfg = for_hand(cfg, hand)
    n = cfg.n if given is None else given.shape[0]
    dcfg = DeviceConfig(cfg.sampler if given is None else "given", cfg.sampling, cfg.energy, cfg.optim, cfg.filters)
    params, res = None, None
    if given is None:
        params, res = samplers.sampler_params(cfg.sampler, hand, cfg.sampling, target.sdf.grid.dtype)
    mesh = device_mesh(cfg.devices)
    if mesh.size > 1:  # inputs committed to one device (the hand's, the SDF's) must be on all of the mesh's
        hand, target, given, given_q, params = jax.device_put((hand, target, given, given_q, params),
                                                              NamedSharding(mesh, P()))
    key0 = jax.ShapeDtypeStruct((2,), jnp.uint32)  # `jax.random.PRNGKey`'s: no device call per lookup
    t0 = time.perf_counter()
    compiled, call = compiled_device_part(hand, target, key0, given, dcfg, n, given_q, params, res, mesh)
    return (lambda key: call(compiled, hand, target, key, given, given_q, params)), \
        time.perf_counter() - t0


def surface_of(mesh) -> device_metrics.MeshTable | sdf_mod.GradientSDF:
    """What the device evaluation measures against: the mesh's triangle table, or an SDF-only object's own grid."""
    return mesh if isinstance(mesh, sdf_mod.GradientSDF) else device_metrics.mesh_table(mesh)


def for_hand(cfg: GraspConfig, hand: Hand) -> GraspConfig:
    """`cfg` with the hand-dependent defaults (sampler "auto", standoff 0) made concrete (`samplers.for_hand`)."""
    name, sampling = samplers.for_hand(cfg.sampler, hand, cfg.sampling)
    return dataclasses.replace(cfg, sampler=name, sampling=sampling)


def prepare_evaluation(hand, surface, target, cfg, out: DeviceOut, compile: bool = True):
    """(`run()` of the device evaluation of `out`'s grasps on `surface` (`surface_of`), seconds spent compiling it);
    `compile` False: (None, 0.0) unless an earlier call compiled it (`device_metrics.compile_evaluate`)."""
    return device_metrics.compile_evaluate(surface, out.opt.final.contacts, out.opt.q, hand.lower, hand.upper,
                                           target.centre, target.radius, metrics_config(cfg), compile=compile)


def finish(hand, target, cfg, out: DeviceOut, evaluate, synthesis_s, object_name) -> GraspSet:
    """The grasps on the host, ranked fields and all; `synthesize` adds the call's compile_s, sdf_s and total_s."""
    t0 = time.perf_counter()
    with compile_clock.compiling() as packing:  # the packing's first call in a process compiles: not copy time
        out, ev = fetch.device_get((out, evaluate()))  # the one device-to-host copy of the call (one per dtype)
    opt = out.opt
    q = np.asarray(opt.q, np.float64)
    contacts = np.asarray(opt.final.contacts, np.float64)
    penetration = np.asarray(out.penetration, np.float64)
    E_c = np.asarray(opt.final.E_c, np.float64)
    # usable: collision-free, every filter passed, every fingertip touching and force closure with those contacts
    valid = (~np.asarray(out.pose_collides) & ~np.asarray(out.palm_up) & ~np.asarray(out.tips_below_table)
             & np.asarray(opt.lp_ok) & (penetration <= cfg.max_penetration) & (E_c <= cfg.max_contact_rms)
             & (ev["n_contacts"] == contacts.shape[1]) & ev["force_closure"])
    touching = np.abs(ev["contact_dist"]) <= cfg.contact_tol
    squeeze_dir = metrics.squeeze_direction(np.asarray(out.tip_jac), ev["normals"], touching)
    joint_names = _joint_names(hand.spec)
    arrays = {
        "wrist_pose": K.orthonormalize(np.asarray(out.poses, np.float64)),
        "q": q,
        "channel_names": np.array(hand.spec.channel_names),
        "joint_pos": q @ np.asarray(hand.coupling, np.float64).T,
        "joint_names": joint_names,
        "contacts": contacts,
        "E": np.asarray(opt.final.E, np.float64),
        "E_g": np.asarray(opt.final.E_g, np.float64),
        "E_c": E_c,
        "E_q": np.asarray(opt.final.E_q, np.float64),
        "E_m": np.asarray(opt.final.E_m, np.float64),
        "support_min": np.asarray(opt.final.support_min, np.float64),
        "epsilon": np.asarray(ev["epsilon"], np.float64),
        "force_closure": np.asarray(ev["force_closure"]),
        "E_g_mesh": np.asarray(ev["E_g"], np.float64),
        "E_c_mesh": np.asarray(ev["E_c"], np.float64),
        "contact_dist": np.asarray(ev["contact_dist"], np.float64),
        "n_contacts": np.asarray(ev["n_contacts"], np.int64),
        "squeeze_dir": squeeze_dir,
        "q_squeeze": np.clip(q + cfg.squeeze_angle * squeeze_dir, np.asarray(hand.lower), np.asarray(hand.upper)),
        "penetration": penetration,
        "table_penetration": np.asarray(out.table_penetration, np.float64),
        "pose_collides": np.asarray(out.pose_collides),
        "palm_up": np.asarray(out.palm_up),
        "tips_below_table": np.asarray(out.tips_below_table),
        "lp_ok": np.asarray(opt.lp_ok),
        "iters": np.asarray(opt.iters),
        "valid": valid,
        "synthesis_s": np.asarray(synthesis_s, np.float64),
    }
    rank, predictor = prediction.resolve(cfg.rank, hand, cfg.evaluator)
    with compile_clock.compiling() as predictor_compile:  # a process's first prediction compiles: not call time
        if predictor is not None:
            arrays |= prediction.predictions(*predictor, hand, target.sdf, arrays)
    arrays["rank_by"] = np.array(rank)
    arrays["evaluation_s"] = np.asarray(time.perf_counter() - t0 - packing[0] - predictor_compile[0],
                                        np.float64)  # the copy and the prediction included
    trace = {k: np.asarray(getattr(opt.trace, k), np.float64) for k in ("E", "E_g", "E_c")}
    return GraspSet(arrays, trace, cfg, object_name)


@functools.lru_cache(maxsize=8)
def _joint_names(spec) -> np.ndarray:
    m = spec.mj_model()  # parses the MJCF: once per hand, not per call
    return np.array([mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, j) for j in range(m.njnt)])


compiled.register("synthesis.grasp joint names", _joint_names)


def metrics_config(cfg: GraspConfig) -> metrics.MetricsConfig:
    """The evaluation's settings, derived from the synthesis's (`MetricsConfig.from_energy`)."""
    return metrics.MetricsConfig.from_energy(cfg.energy, cfg.contact_tol)


def check_on_mesh(hand: Hand, mesh: trimesh.Trimesh, gs, grid: sdf_mod.GradientSDF) -> dict[str, np.ndarray]:
    """The grasps' contact and force-closure figures measured on another surface than the one they were filtered
    on (grasps planned from depth frames, checked on the true mesh): `epsilon_true`, `force_closure_true`,
    `contact_dist_true` and `n_contacts_true`, as `epsilon` ... `n_contacts` (torque origin and scale from `grid`,
    as the synthesis); and where `mesh` came from when `load_mesh` read it (`object_source`, `object_scale`,
    `object_sha256`: the object `ffcgs eval` then simulates). Add them with `gs.with_arrays(**figures)`."""
    check_grasp_set(gs, "check_on_mesh")
    target = make_target(grid)
    dtype = target.sdf.grid.dtype
    ev = device_metrics.evaluate(surface_of(mesh), jnp.asarray(gs["contacts"], dtype), jnp.asarray(gs["q"], dtype),
                                 hand.lower, hand.upper, target.centre, target.radius, metrics_config(gs.config))
    ev = fetch.device_get(ev)
    return {f"{k}_true": np.asarray(ev[k]) for k in ("epsilon", "force_closure", "contact_dist", "n_contacts")} \
        | mesh_io.source_of(mesh)


def _first_prediction(gs: GraspSet) -> str:
    """The first offered grasp's predicted success; with no valid grasp the first offered is not a grasp to use,
    and a bare figure there read as a good grasp (0 of 32 valid showed "1.00")."""
    first = gs.order()[0]
    p = f"{float(gs['pred_success'][first]):.2f}"
    return p if gs["valid"][first] else f"none valid (the first offered, not valid: {p})"


def rejections(gs: GraspSet) -> str:
    """Why the grasps that are not valid were refused, as "reason count" pairs, the commonest first: with 0 of 32
    valid (Algorithm 1 as published, a large `d0`) the counts alone said nothing of what to change."""
    a, cfg = gs.arrays, gs.config
    tests = {  # the terms of `finish`'s `valid`, each on the arrays a grasp file keeps
        "hand in the object": ("penetration", lambda x: x > cfg.max_penetration),
        "tips not all touching": ("n_contacts", lambda x: x != a["contacts"].shape[1]),
        "no force closure": ("force_closure", lambda x: ~x.astype(bool)),
        "tips far (E_c)": ("E_c", lambda x: x > cfg.max_contact_rms),
        "open hand collides": ("pose_collides", lambda x: x.astype(bool)),
        "palm up": ("palm_up", lambda x: x.astype(bool)),
        "tips below the table": ("tips_below_table", lambda x: x.astype(bool)),
        "LP failed": ("lp_ok", lambda x: ~x.astype(bool)),
    }
    reasons = {name: test(np.asarray(a[key])) for name, (key, test) in tests.items() if key in a}
    bad = ~np.asarray(a["valid"], bool)
    counts = sorted(((int((m & bad).sum()), name) for name, m in reasons.items() if (m & bad).any()), reverse=True)
    return ", ".join(f"{name} {k}" for k, name in counts) or "-"


def summary_rows(gs: GraspSet) -> list[tuple[str, str]]:
    """The short table `ffcgs grasp` prints: counts and medians over the valid grasps."""
    v = gs["valid"]
    med = lambda k, s=1.0: f"{np.median(gs[k][v]) * s:.4g}" if v.any() else "-"  # noqa: E731
    return [
        ("grasps (valid / sampled)", f"{int(v.sum())} / {len(v)}"),
        ("force closure, touching tips (all)", f"{int(gs['force_closure'].sum())} / {len(v)}"),
        ("all tips touching (all)", f"{int((gs['n_contacts'] == gs['contacts'].shape[1]).sum())} / {len(v)}"
                                    f"  (within {1000 * gs.config.contact_tol:g} mm)"),
        ("median E", med("E")),
        ("median E_g", med("E_g")),
        ("median E_c (cm)", med("E_c", 100)),
        *([("not valid, by reason (a grasp may have several)", rejections(gs))] if not v.all() else []),
        ("median epsilon", med("epsilon")),
        ("median penetration (mm)", med("penetration", 1000)),
        *([("predicted success: first grasp / median valid", _first_prediction(gs) + f" / {med('pred_success')}")]
          if "pred_success" in gs.arrays and len(v) else []),
        ("ranked by", "predicted success (--rank energy: E)" if ranking.rank_by(gs.arrays) == "predicted"
         else "E, the analytic order"),
        ("synthesis time (s)", f"{float(gs['synthesis_s']):.3f}"),
        *([("whole call (s)", f"{float(gs['total_s']):.3f} (SDF {float(gs['sdf_s']):.3f}, device "
                              f"{float(gs['synthesis_s']):.3f}, evaluation {float(gs['evaluation_s']):.3f})")]
          if "total_s" in gs.arrays else []),
        ("compile time (s)", f"{float(gs['compile_s']):.2f}"),
    ]
