"""The data engine's unit of work: one object's candidates, every one labelled by the physics test.

`label` (a "keep all" build, `DatasetConfig.keep`) runs, for one object in its own frame:
    1. the Gradient-SDF on the device;
    2. `per_object` candidates: the device synthesis with `DatasetConfig.sampler` (any of the synthesis samplers,
       or "planner": the planner's annealing as the start poses, the best `per_object` of `planner.population`
       refined);
    3. the physics test of every candidate, valid or not, under each of `DatasetConfig.protocols`
       (`physics.runner.evaluate`: MuJoCo Warp for lift-shake and six-dir where it pays, CPU MuJoCo otherwise and
       always for DexGraspBench's protocol);
and returns an `Annotation` whose grasps carry the labels (`schema.LABEL_ARRAYS`). Nothing is filtered: a
learned predictor needs the failures, and the learned sampler's training set is the successes
(`schema.Record.holds`).
"""

from __future__ import annotations

import dataclasses
import time

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
    gcfg = dataclasses.replace(cfg.grasp, sampler=cfg.sampler, n=cfg.per_object, seed=seed % (2**31))
    return grasp.synthesize(hand, mesh, gcfg, name, grid=grid)


def label(hand, spec, mesh: trimesh.Trimesh, cfg: DatasetConfig, name: str, grid=None):
    """Steps 1-3 of the module docstring: an `build.Annotation`-shaped (grasps, counts, seconds) triple."""
    from ffcgs_jax.geometry import sdf as sdf_mod
    from ffcgs_jax.physics import runner as physics_runner

    t0 = time.perf_counter()
    if grid is None:
        grid = sdf_mod.build_sdf(mesh, cfg.grasp.sdf)
    gs = candidates(hand, mesh, cfg, name, grid)
    t1 = time.perf_counter()
    phys = physics_runner.evaluate(spec, mesh, gs["wrist_pose"], gs["q"], cfg.physics, cfg.protocol_list(),
                                   squeeze_dir=gs["squeeze_dir"])
    t2 = time.perf_counter()
    grasps = {k: np.asarray(gs[k]) for k in GRASP_KEYS}
    for k, v in phys.items():
        if k in PHYSICS_ARRAYS or k in LABEL_ARRAYS:
            grasps[k] = np.asarray(v)
    grasps |= {k: np.asarray(gs[k]) for k in LABEL_ARRAYS if k in gs.arrays and k not in grasps}
    held = holds(grasps, len(grasps["q"]))  # every protocol asked for ran: at least one outcome each
    counts = {"candidates": len(grasps["q"]), "valid": int(np.sum(grasps["valid"])), "passed_all": int(held.sum())}
    counts |= {f"passed_{k.removesuffix('_success')}": int(np.sum(grasps[k])) for k in sorted(grasps)
               if k.endswith("_success")}
    return grasps, counts, {"synthesis": t1 - t0, "physics": t2 - t1}
