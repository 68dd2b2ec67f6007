"""The data engine's unit of work: one object's candidates, every one labelled by the physics test.

`label` (a "keep all" build, `DatasetConfig.keep`) runs, for one object in its own frame:
    1. the Gradient-SDF on the device;
    2. `per_object` candidates: the device synthesis with `DatasetConfig.sampler` (any of the synthesis samplers,
       or "planner": the planner's annealing as the start poses, the best `per_object` of `planner.population`
       refined);
    3. the physics test of every candidate, valid or not, under each of `DatasetConfig.protocols`
       (`physics.runner.evaluate`, or for a group of objects `evaluate_many`: MuJoCo Warp where it costs less,
       every protocol as worlds of the same launches, CPU MuJoCo otherwise);
and returns an `Annotation` whose grasps carry the labels (`schema.LABEL_ARRAYS`). Nothing is filtered: a
learned predictor needs the failures, and the learned sampler's training set is the successes
(`schema.Record.holds`).

`label_many` does the same for a group of objects with one `physics.runner.evaluate_many`: on MuJoCo Warp every
object's grasps are worlds of the same launches, and each object is synthesised only when the physics asks for it,
on the physics' feeding thread, while the GPU simulates the objects before it.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable

import numpy as np
import trimesh

from ffcgs_jax.dataset.config import DatasetConfig
from ffcgs_jax.dataset.objects import object_seed
from ffcgs_jax.dataset.schema import LABEL_ARRAYS, PHYSICS_ARRAYS, holds

GRASP_KEYS = ("wrist_pose", "q", "epsilon", "E", "E_g", "E_c")


def candidates(hand, mesh: trimesh.Trimesh, cfg: DatasetConfig, name: str, grid):
    """The object's `per_object` candidates as a GraspSet (step 2), in the synthesis's own order."""
    import jax

    from ffcgs_jax.dataset import planner
    from ffcgs_jax.synthesis import grasp

    seed = object_seed(cfg.seed, name, 0, 1)
    if cfg.sampler == "planner":
        pcfg = dataclasses.replace(cfg.planner, refine=min(cfg.per_object, cfg.planner.population))
        return planner.plan(hand, mesh, pcfg, cfg.grasp, name, grid=grid, key=jax.random.PRNGKey(seed))
    # the candidates as drawn, the weak ones too: searching further (`synthesis.search`) would keep the best of
    # several batches, and the predictor learns from the failures
    gcfg = dataclasses.replace(cfg.grasp, sampler=cfg.sampler, n=cfg.per_object, seed=seed % (2**31),
                               search=dataclasses.replace(cfg.grasp.search, max_rounds=1))
    return grasp.synthesize(hand, mesh, gcfg, name, grid=grid)


def label(hand, spec, mesh: trimesh.Trimesh, cfg: DatasetConfig, name: str, grid=None):
    """Steps 1-3 of the module docstring: an `build.Annotation`-shaped (grasps, counts, seconds) triple."""
    from ffcgs_jax.physics import runner as physics_runner

    t0 = time.perf_counter()
    gs = candidates(hand, mesh, cfg, name, _grid(mesh, cfg, grid))
    t1 = time.perf_counter()
    phys = physics_runner.evaluate(spec, mesh, gs["wrist_pose"], gs["q"], cfg.physics, cfg.protocol_list(),
                                   squeeze_dir=gs["squeeze_dir"])
    t2 = time.perf_counter()
    return (*labelled(gs, phys), {"synthesis": t1 - t0, "physics": t2 - t1})


def label_many(hand, spec, objects, cfg: DatasetConfig, done: Callable | None = None) -> list[tuple]:
    """`label` of every (mesh, name) or (mesh, name, grid) of `objects`, their physics as one
    `evaluate_many` fed by a generator: each object is synthesised when the physics asks for the next one (on
    MuJoCo Warp, on its feeding thread while the GPU simulates the objects before).

    Returns `label`'s triple per object, in order. Seconds: "synthesis" is the object's own; "physics" is the
    group's `evaluate_many` wall time less the synthesis done inside it (what the synthesis did not hide),
    shared evenly, so a group's seconds add up to its wall time. An object whose synthesis fails ends the
    group: the objects before it are still simulated and handed to `done(index, triple)` (the caller keeps
    them), then its error is raised. `done` is called for every object labelled, in order."""
    from ffcgs_jax.physics import runner as physics_runner

    made, synthesis, failed = [], [], []

    def items():
        for mesh, name, *grid in objects:
            t0 = time.perf_counter()
            try:
                gs = candidates(hand, mesh, cfg, name, _grid(mesh, cfg, grid[0] if grid else None))
            except Exception as e:  # noqa: BLE001 - raised to the caller once the objects before it are labelled
                failed.append(e)
                return
            made.append(gs)
            synthesis.append(time.perf_counter() - t0)
            yield physics_runner.Item(mesh, gs["wrist_pose"], gs["q"], gs["squeeze_dir"])

    t0 = time.perf_counter()
    phys = physics_runner.evaluate_many(spec, items(), cfg.physics, cfg.protocol_list())
    share = max(0.0, time.perf_counter() - t0 - sum(synthesis)) / max(1, len(made))
    out = []
    for i, (gs, ph, s) in enumerate(zip(made, phys, synthesis, strict=True)):
        out.append((*labelled(gs, ph), {"synthesis": s, "physics": share}))
        if done is not None:
            done(i, out[-1])
    if failed:
        raise failed[0]
    return out


def _grid(mesh: trimesh.Trimesh, cfg: DatasetConfig, grid):
    """Step 1: the object's SDF, unless given."""
    from ffcgs_jax.geometry import sdf as sdf_mod

    return sdf_mod.build_sdf(mesh, cfg.grasp.sdf) if grid is None else grid


def labelled(gs, phys: dict) -> tuple[dict, dict]:
    """A candidate set and its physics results as (grasp arrays with labels, counts)."""
    grasps = {k: np.asarray(gs[k]) for k in GRASP_KEYS}
    for k, v in phys.items():
        if k in PHYSICS_ARRAYS or k in LABEL_ARRAYS:
            grasps[k] = np.asarray(v)
    grasps |= {k: np.asarray(gs[k]) for k in LABEL_ARRAYS if k in gs.arrays and k not in grasps}
    held = holds(grasps, len(grasps["q"]))  # every protocol asked for ran: at least one outcome each
    counts = {"candidates": len(grasps["q"]), "valid": int(np.sum(grasps["valid"])), "passed_all": int(held.sum())}
    counts |= {f"passed_{k.removesuffix('_success')}": int(np.sum(grasps[k])) for k in sorted(grasps)
               if k.endswith("_success")}
    return grasps, counts
