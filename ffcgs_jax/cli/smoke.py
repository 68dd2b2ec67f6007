"""`FFCGS_SMOKE=1`: every command exactly as typed, the long ones cut to a small slice of their work.

README's command blocks run in CI as written (`tests/test_readme_commands.py`), and a user can try a command line
before committing hours to it. A dataset build of 2,000 objects, 100 training epochs or a 65,536-grasp benchmark
would take hours on a 2-core CPU; under `FFCGS_SMOKE` they keep every option that shapes the work (sampler, hand,
protocols, output format), and only the counts shrink: at most `OBJECTS` generated objects (enough for the five
cross-validation folds), `CANDIDATES` candidates per object and one rotation, a planner of `POPULATION` poses for
`STEPS` steps, one training epoch of batches of at most `BATCH`, the first value of each swept setting, one benchmark batch of 32, and grasp
batches of at most `GRASPS`. The command says so in one line on stderr. Results are not meant to be good, only to
come out of the same code path.
"""

import dataclasses
import os
import sys
from typing import Any

ENV = "FFCGS_SMOKE"
OBJECTS = 5
CANDIDATES = 4
POPULATION = 64
STEPS = 10
GRASPS = 64
TRIALS = 1  # physics: one nominal trial per grasp (the robust verdict's own tests run its trials)
BATCH = 8  # a smoke build's few grasps still make a batch


def active() -> bool:
    """Whether `FFCGS_SMOKE` is set to anything but "", "0", "off" or "false"."""
    return os.environ.get("FFCGS_SMOKE", "").strip().lower() not in ("", "0", "off", "false", "no")


def _cap(value: int, most: int) -> int:
    return min(value, most)


def _grasp(cfg):
    return dataclasses.replace(cfg, n=_cap(cfg.n, GRASPS))


def _physics(cfg):
    return dataclasses.replace(cfg, robust=dataclasses.replace(cfg.robust, trials=_cap(cfg.robust.trials, TRIALS)))


def _dataset(cfg):
    planner = dataclasses.replace(cfg.planner, population=_cap(cfg.planner.population, POPULATION),
                                  steps=_cap(cfg.planner.steps, STEPS), refine=_cap(cfg.planner.refine, POPULATION))
    generated = cfg.procedural + cfg.complex
    procedural = _cap(cfg.procedural, OBJECTS)
    return dataclasses.replace(cfg, per_object=_cap(cfg.per_object, CANDIDATES), rotations=1, planner=planner,
                               procedural=procedural,
                               complex=_cap(cfg.complex, max(0, OBJECTS - procedural)) if generated else 0,
                               grasp=_grasp(cfg.grasp), physics=_physics(cfg.physics))


def _bench(cmd):
    return dataclasses.replace(cmd, batches=(32,), repeats=min(cmd.repeats, 2), lp_solvers=cmd.lp_solvers[:1],
                               devices=cmd.devices[:1], cli_start=False)


def _train(cfg):
    return dataclasses.replace(cfg, optim=dataclasses.replace(cfg.optim, epochs=1, batch=_cap(cfg.optim.batch,
                                                                                          BATCH)))


def sweep(grid: list[tuple[str, list]]) -> list[tuple[str, list]]:
    """A sweep's grid cut to the first value of each key (one run) under `FFCGS_SMOKE`, else as given."""
    return [(k, v[:1]) for k, v in grid] if active() else grid


_SCALE = {
    "grasp": lambda c: dataclasses.replace(c, grasp=_grasp(c.grasp), physics=_physics(c.physics)),
    "eval": lambda c: dataclasses.replace(c, physics=_physics(c.physics)),
    "dataset build": _dataset,
    "bench": _bench,
    "train": _train,
}


def scaled(name: str, cmd: Any) -> Any:
    """`cmd` (the parsed options of `ffcgs NAME`) cut down under `FFCGS_SMOKE` (saying so on stderr), else as given."""
    if not active() or name not in _SCALE:
        return cmd
    small = _SCALE[name](cmd)
    if small != cmd:
        print(f"ffcgs: {ENV} is set: {name} runs a small slice of its work (counts capped; see cli/smoke.py)",
              file=sys.stderr)
    return small
