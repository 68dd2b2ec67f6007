"""`ffcgs dataset build`: annotate objects with the planner and the physics test, write rotated records to MCAP.

Per object (in its own frame, resting on the table as the file has it):
    1. the Gradient-SDF;
    2. `planner.plan`: simulated annealing of `planner.population` candidates, the best `planner.refine` refined by
       the Q-distance optimiser, ranked valid first and then by epsilon;
    3. the valid ones, near-duplicate wrists dropped (`planner.dedupe`);
    4. `planner.physics_select`: six-dir then lift-shake, in ranking order, until `per_object` pass both;
    (the kept grasps and counts are saved to OUT.parts/annotations/<object>.npz, so an interrupted build, or one
    finished elsewhere from annotations copied in, never annotates an object twice)
    5. for each of `rotations` random rotations R: the mesh is rotated, its SDF rebuilt (never the voxel grid
       rotated), the kept wrist poses pre-multiplied by R, a noisy copy drawn, and the record written.

A labelled build ("keep all") whose physics runs on MuJoCo Warp takes the objects `group` at a time
(`build_group`): their candidates are labelled by one physics run, each object still annotated and written as
alone (same files, same resume).

The annotation happens once per object, before the rotations. With the default yaw rotations (about the vertical
axis through the object's origin) gravity and the table are unchanged relative to object and hand, so the physics
results hold for every rotated copy exactly; "so3" rotations are a shape-only augmentation.

Determinism: every random draw comes from (seed, object name[, rotation]), so a record does not depend on which
other objects are built, in what order, or whether the build was interrupted. Parts are bit-identical on one
machine and JAX backend. A GPU build and a CPU build of the same config differ in the last float bits (and so,
through the ranking, in which grasps are kept); their parts can still be merged, since each record is complete
in itself, and `timing.jsonl` in the parts directory says which backend built which object.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from ffcgs_jax.core import files
from ffcgs_jax.core.config import check_all
from ffcgs_jax.dataset import engine, schema
from ffcgs_jax.dataset import mcap_io as dataset_io
from ffcgs_jax.dataset.config import DatasetConfig
from ffcgs_jax.dataset.objects import Source, object_seed, objects_sha256, sources
from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.runtime import compiled


def rotation(cfg: DatasetConfig, name: str, index: int) -> np.ndarray:
    """The 3x3 rotation of record `index` of object `name`: a uniform yaw, or uniform over SO(3). In a labelled
    build ("keep all") record 0 is the object as simulated (the identity), so its labels are the physics test's
    outcomes for exactly its numbers; the others are augmented copies."""
    from scipy.spatial.transform import Rotation

    if cfg.keep == "all" and index == 0:
        return np.eye(3)
    rng = np.random.default_rng(object_seed(cfg.seed, name, index, 0))
    if cfg.rotation_mode == "yaw":
        return Rotation.from_rotvec([0.0, 0.0, rng.uniform(-np.pi, np.pi)]).as_matrix()
    return Rotation.random(random_state=rng).as_matrix()


def noisy(poses: np.ndarray, sigma_t: float, sigma_r: float, rng: np.random.Generator) -> np.ndarray:
    """Wrist poses (G, 4, 4) with Gaussian noise: translation N(0, sigma_t^2 I) in the object frame, rotation
    exp(N(0, sigma_r^2 I)) applied in the wrist frame."""
    from scipy.spatial.transform import Rotation

    out = np.array(poses, np.float64, copy=True)
    g = len(out)
    if g == 0:
        return out
    dt = rng.normal(0.0, sigma_t, (g, 3))
    dr = Rotation.from_rotvec(rng.normal(0.0, sigma_r, (g, 3))).as_matrix()
    out[:, :3, :3] = out[:, :3, :3] @ dr
    out[:, :3, 3] += dt
    return out


def _homogeneous(R: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    return T


def rotate_mesh(mesh: trimesh.Trimesh, R: np.ndarray) -> trimesh.Trimesh:
    return mesh.copy().apply_transform(_homogeneous(R))


def record_config(cfg: DatasetConfig) -> dict:
    """The config stored in the dataset and checked on resume: everything but where the files are."""
    d = dataclasses.asdict(cfg)
    for k in ("objects", "out", "shard", "annotate", "engine", "address", "task_cpus", "ray_from", "allow_test", "cpus",
              "gpus", "group"):
        d.pop(k)
    for k in ("workers", "backend"):  # where the physics runs (the backends' outcomes agree: bench/RESULTS.md)
        d["physics"].pop(k)
    d["grasp"].pop("devices")  # where it runs, not what it computes
    for k in ("rank", "evaluator"):  # the order grasps are offered in: records keep every candidate, unranked
        d["grasp"].pop(k)
    if cfg.sampler != "cvae":  # the planner samples geometric poses: cvae settings do not matter
        for k in ("cvae_oversample", "weights"):
            d["grasp"]["sampling"].pop(k)
    for k in ("lp_solver", "lp_pivots"):  # like the backend: the LP paths agree to their tolerance
        d["grasp"]["energy"].pop(k)
    return json.loads(json.dumps(d))  # as stored (lists for tuples), so a resumed build compares like with like


@dataclass
class Annotation:
    """The kept grasps of one object in its own frame, and what it took to find them."""

    grasps: dict[str, np.ndarray]
    counts: dict[str, int]
    seconds: dict[str, float]

    def save(self, path: Path) -> None:
        """Atomically, as an npz (no pickle): the grasp arrays and the counts as JSON. Seconds are not saved: the
        file must not depend on how fast the machine was."""
        arrays = dict(self.grasps) | {"counts_json": np.array(json.dumps(self.counts, sort_keys=True))}
        files.atomic_write(path, lambda f: np.savez(f, **arrays))

    @classmethod
    def load(cls, path: Path) -> Annotation:
        try:
            with np.load(path, allow_pickle=False) as z:
                grasps = {k: z[k] for k in z.files if k != "counts_json"}
                counts = json.loads(str(z["counts_json"]))
        except Exception as e:  # noqa: BLE001 - any unreadable cache file names itself
            raise FfcgsError(f"annotation file {path} is unreadable ({type(e).__name__}: {e}); delete it to "
                             f"annotate that object again") from None
        return cls(grasps, counts, {})


def annotation_path(parts_dir: Path, name: str) -> Path:
    return parts_dir / "annotations" / (schema.record_id(name, 0).rsplit(".", 1)[0] + ".npz")


def annotate(hand, spec, mesh: trimesh.Trimesh, cfg: DatasetConfig, name: str, grid=None,
             progress=None) -> Annotation:
    """Plan, dedupe, physics-select (module docstring, steps 1-4); for a "keep all" build, `label.label`."""
    import jax

    if cfg.keep == "all":
        from ffcgs_jax.dataset import label

        return Annotation(*label.label(hand, spec, mesh, cfg, name, grid))

    from ffcgs_jax.dataset import planner
    from ffcgs_jax.geometry import sdf as sdf_mod

    t0 = time.perf_counter()
    if grid is None:
        grid = sdf_mod.build_sdf(mesh, cfg.grasp.sdf)
    key = jax.random.PRNGKey(object_seed(cfg.seed, name, 0, 1))
    gs = planner.plan(hand, mesh, cfg.planner, cfg.grasp, name, grid=grid, key=key)
    t1 = time.perf_counter()
    valid = np.flatnonzero(gs["valid"])  # ranked: valid first, by epsilon
    cand = gs.select(valid[planner.dedupe(gs["wrist_pose"][valid], cfg.dedupe_trans, cfg.dedupe_rot)])
    counts = {"annealed": cfg.planner.population, "refined": len(gs["valid"]), "valid": len(valid),
              "valid_epsilon_pos": int((gs["epsilon"][valid] > 0).sum()), "distinct": len(cand["valid"])}
    if cfg.physics_test == "both":
        keep, phys = planner.physics_select(cand, spec, mesh, cfg.per_object, cfg.physics, cfg.physics_chunk,
                                            progress)
        counts |= {"tested_six_dir": int(phys["tested_six_dir"].sum()),
                   "passed_six_dir": int(phys["six_dir_success"].sum()),
                   "tested_lift_shake": int(phys["tested_lift_shake"].sum()),
                   "passed_both": int((phys["six_dir_success"] & phys["lift_shake_success"]).sum())}
    else:
        keep, phys = np.arange(min(cfg.per_object, len(cand["valid"]))), None
    t2 = time.perf_counter()
    kept = cand.select(keep)
    grasps = {k: np.asarray(kept[k]) for k in ("wrist_pose", "q", "epsilon", "E", "E_g", "E_c")}
    if phys is not None:
        grasps |= {k: phys[k][keep] for k in ("lift_shake_success", "six_dir_success")}
    counts["kept"] = len(keep)
    return Annotation(grasps, counts, {"plan": t1 - t0, "physics": t2 - t1})


def records(source: Source, mesh: trimesh.Trimesh, ann: Annotation, cfg: DatasetConfig, todo: set[int]):
    """The rotated records (step 5) of the rotation indices in `todo`."""
    from ffcgs_jax.geometry import sdf as sdf_mod

    for r in sorted(todo):
        R = rotation(cfg, source.name, r)
        grid = sdf_mod.build_sdf(rotate_mesh(mesh, R), cfg.grasp.sdf)
        poses = _homogeneous(R)[None] @ ann.grasps["wrist_pose"]
        rng = np.random.default_rng(object_seed(cfg.seed, source.name, r, 2))
        yield schema.Record.create(
            object_name=source.name, mesh_sha256=source.sha256, rotation_index=r, rotation=R, split=source.split,
            category=source.category, info=ann.counts | ({"scale": source.scale} if source.scale != 1 else {}),
            sdf=grid,
            **(ann.grasps | {"wrist_pose": poses}),
            wrist_pose_noisy=noisy(poses, cfg.noise_trans, cfg.noise_rot, rng))


@functools.lru_cache(maxsize=4)
def _hand(name: str):
    from ffcgs_jax.hand import kinematics as K
    from ffcgs_jax.hand import spec as hand_spec

    return K.load_hand(name), hand_spec.load_spec(name)


compiled.register("dataset.build hands", _hand)


def build_object(cfg: DatasetConfig, src: Source, parts_dir: Path, progress=None) -> dict | None:
    """One object, the unit of work (a Ray task's, or the plain loop's): annotate it (or reuse its annotation file)
    and write the parts of its rotations not yet finished. Returns its timing row, None when there was nothing
    to do. Writes are atomic and a finished part is never rewritten, so running an object twice (a retried task,
    two machines on one shared folder) gives the same files."""
    todo = _todo(cfg, src, parts_dir)
    if not todo:
        return None
    t0 = time.perf_counter()
    hand, spec = _hand(cfg.hand)
    mesh = src.load()
    cached = annotation_path(parts_dir, src.name)
    if cached.is_file():  # annotated before (this run was interrupted, or another machine did it)
        ann = Annotation.load(cached)
    elif not cfg.annotate:
        return None
    else:
        ann = annotate(hand, spec, mesh, cfg, src.name, progress=progress)
        _keep(parts_dir, src, ann)
    return _write(cfg, src, mesh, ann, todo, parts_dir, time.perf_counter() - t0)


def build_group(cfg: DatasetConfig, srcs: list[Source], parts_dir: Path, progress=None) -> list[dict | None]:
    """Several objects of a labelled build as one unit of work (`DatasetConfig.group`): as `build_object` for
    each, but the objects to annotate are labelled together (`label.label_many`: on MuJoCo Warp their grasps
    are worlds of the same launches, the next object synthesised while the GPU simulates). Returns a timing row
    per object, in order, None where there was nothing to do; its seconds are the object's own plus an even
    share of the group's physics. Objects of any other build, or a group of one, go through `build_object`."""
    from ffcgs_jax.dataset import label

    if cfg.keep != "all" or len(srcs) == 1:
        return [build_object(cfg, src, parts_dir, progress) for src in srcs]
    todo = [_todo(cfg, src, parts_dir) for src in srcs]
    meshes, anns, spent, fresh = {}, {}, {}, []
    for i, src in enumerate(srcs):
        cached = annotation_path(parts_dir, src.name)
        if not todo[i] or not (cfg.annotate or cached.is_file()):
            continue
        t0 = time.perf_counter()
        meshes[i] = src.load()
        if cached.is_file():
            anns[i] = Annotation.load(cached)
        else:
            fresh.append(i)
        spent[i] = time.perf_counter() - t0
    if fresh:
        hand, spec = _hand(cfg.hand)

        def done(k: int, triple: tuple) -> None:  # kept as it comes: a later object's failure loses none
            i = fresh[k]
            anns[i] = Annotation(*triple)
            _keep(parts_dir, srcs[i], anns[i])
            spent[i] += sum(anns[i].seconds.values())

        label.label_many(hand, spec, [(meshes[i], srcs[i].name) for i in fresh], cfg, done)
    return [_write(cfg, src, meshes[i], anns[i], todo[i], parts_dir, spent[i]) if i in anns else None
            for i, src in enumerate(srcs)]


def _todo(cfg: DatasetConfig, src: Source, parts_dir: Path) -> set[int]:
    """The rotation indices of `src` whose parts are not written yet."""
    # this object's parts only: listing the folder per object would read every part of a build of thousands
    return {r for r in range(cfg.rotations) if not dataset_io.part_done(parts_dir, schema.record_id(src.name, r))}


def _keep(parts_dir: Path, src: Source, ann: Annotation) -> None:
    cached = annotation_path(parts_dir, src.name)
    cached.parent.mkdir(exist_ok=True)
    ann.save(cached)


def _write(cfg: DatasetConfig, src: Source, mesh: trimesh.Trimesh, ann: Annotation, todo: set[int],
           parts_dir: Path, spent: float) -> dict:
    """Write the records of `todo`; the object's timing row, `spent` the seconds it took before writing."""
    import jax

    t1 = time.perf_counter()
    for rec in records(src, mesh, ann, cfg, todo):
        dataset_io.write_part(parts_dir, rec)
    write = time.perf_counter() - t1
    return {"object": src.name, "backend": jax.default_backend(), "physics_backend": cfg.physics.backend,
            "cached": not ann.seconds, "records": len(todo), "grasps": len(todo) * len(ann.grasps["q"]),
            **ann.counts, **{f"{k}_s": round(v, 3) for k, v in ann.seconds.items()},
            "write_s": round(write, 3), "total_s": round(spent + write, 3)}


def build(cfg: DatasetConfig, show_progress: bool = True) -> dict:
    """Run (or resume) the build; returns {"out", "built", "skipped", "seconds", "timing", "missing", "engine"}:
    "out" is None when this shard finished but other shards' records are still missing (then "missing" counts
    them)."""
    import jax
    from tqdm.auto import tqdm

    from ffcgs_jax.physics import runner as physics_runner

    # `fj.build_dataset` lands here with no CLI parsing before it: nested configs are checked too
    if not isinstance(cfg, DatasetConfig):
        raise FfcgsError(f"build takes a DatasetConfig, got {type(cfg).__name__}")
    check_all(cfg)
    engine.reachable(cfg.address)  # before anything is written or said
    srcs = sources(cfg)
    parts = dataset_io.parts_dir_for(cfg.out)
    if not cfg.annotate and not dataset_io.done_records(parts) \
            and not any(annotation_path(parts, s.name).is_file() for s in srcs):
        raise FfcgsError(f"--no-annotate found no annotated object in {parts / 'annotations'}, so the dataset "
                         "would be empty; copy the annotations there, or build without --no-annotate")
    _hand(cfg.hand)  # a bad hand is one line here, not in every task
    extra = {"objects": [s.describe() for s in srcs], "objects_sha256": objects_sha256(srcs),
             "x64": bool(jax.config.jax_enable_x64)}
    writer = dataset_io.DatasetWriter(cfg.out, record_config(cfg), extra)
    # after the checks: a refused build says one line
    labelled = cfg.keep == "all"
    if labelled:  # a group of objects is one physics run: `auto` weighs the group's grasps
        backend, note = physics_runner.resolve_backend(cfg.physics.backend, cfg.per_object * cfg.group,
                                                       cfg.protocol_list(), cfg.physics)
    else:
        backend, note = physics_runner.resolve_backend(cfg.physics.backend, cfg.physics_chunk)
    if note and show_progress:
        print(f"ffcgs: {note}", file=sys.stderr)
    if not labelled:  # a labelled build keeps "auto": its groups then run where they cost least
        cfg = dataclasses.replace(cfg, physics=dataclasses.replace(cfg.physics, backend=backend))
    expected = [schema.record_id(s.name, r) for s in srcs for r in range(cfg.rotations)]
    timing_log = writer.parts_dir / "timing.jsonl"
    k, n = cfg.shard_of()
    mine = srcs[k::n]
    todo = [s for s in mine if any(schema.record_id(s.name, r) not in writer.done for r in range(cfg.rotations))]
    # groups share MuJoCo Warp's launches; on the CPU the objects' physics would only run one after another
    size = cfg.group if labelled and backend == "warp" else 1
    groups = [todo[i: i + size] for i in range(0, len(todo), size)]
    how, why = engine.choose(cfg, len(todo))
    if why and show_progress:
        print(f"ffcgs: {why}", file=sys.stderr)
    t_start = time.perf_counter()
    bar = tqdm(total=len(todo), desc="objects", unit="obj", disable=not show_progress, dynamic_ncols=True)
    built = 0

    def finished(src: Source, row: dict | None) -> None:
        nonlocal built
        bar.update(1)
        if row is None:
            return
        built += 1
        with open(timing_log, "a") as f:
            f.write(json.dumps(row) + "\n")
        if show_progress:
            c = row
            if cfg.keep == "all":
                tqdm.write(f"{src.name}: {c['candidates']} candidates, {c['passed_all']} pass all, "
                           f"{row['total_s']:.1f} s")
            else:
                tqdm.write(f"{src.name}: kept {c['kept']} of {c['valid']} valid "
                           f"({c.get('tested_six_dir', 0)} physics-tested) in {row['total_s']:.0f} s")

    try:
        engine.run(how, cfg, groups, writer.parts_dir, finished, bar, work=build_group)
    finally:
        bar.close()
    missing = len(set(expected) - set(dataset_io.done_records(writer.parts_dir)))
    result = {"built": built, "skipped": len(mine) - len(todo), "missing": missing, "engine": how,
              "seconds": time.perf_counter() - t_start, "timing": str(timing_log)}
    if not missing:
        writer.finish(expected)
    elif not cfg.annotate and cfg.shard_of() == (0, 1):
        writer.finish()  # a partial dataset, asked for: what is annotated so far
        return {"out": cfg.out, "partial": True, **result}
    return {"out": None if missing else cfg.out, **result}


def merge(out: str | Path) -> dict:
    """`ffcgs dataset merge OUT`: the dataset file from the parts in OUT.parts/ (written by builds on any number
    of machines into one shared folder), once every object's records are there; else one line saying how many
    are missing."""
    parts = dataset_io.parts_dir_for(out)
    config = parts / dataset_io.CONFIG_NAME
    if not config.is_file():
        raise FfcgsError(f"{parts} is not a build's parts folder (no {dataset_io.CONFIG_NAME}): run `ffcgs "
                         f"dataset build --out {out}` first")
    try:
        stored = json.loads(config.read_text())
        names = [o["name"] for o in stored["extra"]["objects"]]
        rotations = int(stored["config"]["rotations"])
    except (ValueError, KeyError, TypeError) as e:
        raise FfcgsError(f"{config} does not describe a build ({type(e).__name__}: {e})") from None
    expected = [schema.record_id(n, r) for n in names for r in range(rotations)]
    missing = sorted(set(expected) - set(dataset_io.done_records(parts)))
    if missing:
        raise FfcgsError(f"{len(missing)} of {len(expected)} records are not built yet (first: {missing[0]}); "
                         f"finish the build (rerun the same command), then merge")
    dataset_io.merge(parts, out, expected)
    return {"out": str(out), "records": len(expected), "objects": len(names)}
