"""The short text tables the commands print, for Python callers (`fj.summary`): of a grasp set, as `ffcgs grasp`,
or of physics results, as `ffcgs eval`."""

import numpy as np

from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.physics import protocols as physics_protocols
from ffcgs_jax.physics.config import ALL_PROTOCOLS
from ffcgs_jax.physics.results import PhysicsResult
from ffcgs_jax.synthesis.grasp import GraspSet, summary_rows


def summary(results, protocols=None) -> str:
    """A grasp set's table (counts and medians over the valid grasps), or for `fj.evaluate_physics`'s result (or
    its flat arrays, `as_arrays()`, as a file holds them) the success rates with 95 % intervals and failure reasons
    of `protocols` (default: every protocol the results hold). One row a line, names aligned."""
    if isinstance(results, PhysicsResult):
        results = results.as_arrays()
    if isinstance(results, GraspSet):
        rows = summary_rows(results)
    elif isinstance(results, dict):
        if protocols is None:
            protocols = [p for p in ALL_PROTOCOLS if physics_protocols.result_key(p, "success") in results]
        protocols = (protocols,) if isinstance(protocols, str) else tuple(protocols)
        absent = [p for p in protocols if physics_protocols.result_key(p, "reason") not in results]
        if absent or not protocols:
            raise FfcgsError(f"the results hold no {absent[0]} outcome" if absent else
                             "the results hold no physics outcome (fj.evaluate_physics's arrays)")
        rows = physics_protocols.summary_rows({k: np.asarray(v) for k, v in results.items()}, protocols)
    else:
        raise FfcgsError(f"summary takes a GraspSet or fj.evaluate_physics's results, got {type(results).__name__}")
    width = max(len(name) for name, _ in rows)
    return "\n".join(f"{name:<{width}}  {value}" for name, value in rows)
