"""The success predictor in the synthesis call: which weights a config asks for, and the per-grasp predictions
`finish` adds to a GraspSet (`pred_success` and one `pred_<protocol>` per head), on the device that holds the SDF.

`GraspConfig.rank` decides the order (`evaluation.ranking`): "auto" ranks by `pred_success` where a predictor
exists for the hand (shipped, or `GraspConfig.evaluator`), else by E; "predicted" requires one; "energy" ranks by
E (the predictions are still computed and stored when a predictor exists). The choice rides in the arrays as
`rank_by`, so a grasp file is ranked later as it was when written.
"""

import contextlib
from pathlib import Path

import cachetools
import jax.numpy as jnp
import numpy as np

from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.learning import evaluator
from ffcgs_jax.learning.weights import cached, default_weights, load_evaluator
from ffcgs_jax.runtime import COMPILED_MAX, compiled, progress
from ffcgs_jax.runtime.fixed_shapes import pad_rows
from ffcgs_jax.synthesis.config import RANKS


BUCKET = 32
# call signatures compiled in this process, so that only a new one gets the compile's ticker; as many as the
# executables kept, and emptied with them (a cleared signature only shows the ticker again)
_SIGNATURES = cachetools.LRUCache(COMPILED_MAX)
compiled.register("synthesis.prediction signatures", _SIGNATURES)


def _load(path: str, hand) -> tuple[dict, dict]:
    """Loaded once per file version and hand (`weights.cached`): a synthesis call must not re-read weights."""
    return cached(path, ("evaluator", hand.spec), lambda: load_evaluator(path, hand))


def weights_for(hand, path: str = "") -> tuple[dict, dict] | None:
    """(weights, metadata) of the predictor `path` names, or the one installed or shipped for `hand` when `path`
    is ""; None when there is none for the hand. A file that is named but missing or wrong is one line (FfcgsError)."""
    if path:
        if not Path(path).expanduser().is_file():
            raise FfcgsError(f"evaluator weights not found: {path}")
        return _load(str(Path(path).expanduser()), hand)
    found = default_weights("evaluator", hand.spec.name)
    return _load(str(found), hand) if found.is_file() else None


def resolve(rank: str, hand, path: str = "") -> tuple[str, tuple[dict, dict] | None]:
    """(the order used, "predicted" or "energy"; the predictor or None)."""
    if rank not in RANKS:
        raise FfcgsError(f"rank must be one of {', '.join(RANKS)}, got {rank!r}")
    found = weights_for(hand, path)
    if rank == "predicted" and found is None:
        raise FfcgsError(f"rank 'predicted' needs a success predictor, and none is installed or ships for hand "
                         f"{hand.spec.name}; "
                         "train one (`ffcgs train --model evaluator`) and pass it with --evaluator, or rank by "
                         "energy")
    return ("energy" if rank == "energy" or found is None else "predicted"), found


def predictions(weights: dict, meta: dict, hand, sdf, arrays: dict) -> dict[str, np.ndarray]:
    """{"pred_success": (G,), "pred_<head>": (G,) per protocol head} of a grasp set's host arrays on `sdf`."""
    n = len(arrays["q"])
    heads = list(meta["heads"])
    if n == 0:
        return {"pred_success": np.zeros(0)} | {f"pred_{h}": np.zeros(0) for h in heads[:-1]}
    dt = sdf.grid.dtype
    inputs = evaluator.grasp_inputs(arrays, len(hand.spec.contact_sites))
    # padded to a multiple of BUCKET rows: every call of up to 32 grasps (and so on) shares one executable
    m = -(-n // BUCKET) * BUCKET
    rows = [pad_rows(np.asarray(arrays[k]), m) for k in ("wrist_pose", "q", "contacts")] + [pad_rows(inputs, m)]
    signature = (m, str(dt), hand.spec, sdf.grid.shape, len(heads))
    with progress.compiling("the success predictor") if signature not in _SIGNATURES else contextlib.nullcontext():
        p = evaluator.predict(weights, hand, sdf, *(jnp.asarray(r, dt) for r in rows))
    _SIGNATURES[signature] = True
    p = np.asarray(p, np.float64)[:n]
    return {"pred_success": p[:, -1]} | {f"pred_{h}": p[:, i] for i, h in enumerate(heads[:-1])}
