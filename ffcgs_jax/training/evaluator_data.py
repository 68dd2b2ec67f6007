"""Training data for the success predictor: a labelled dataset file (`ffcgs dataset build --keep all`) read once
into one feature row per grasp, its labels per head, and the object it belongs to (folds split by object).

Every candidate counts, failures included: the predictor must see what fails. The heads are the file's protocols,
then "all": passing lift-shake and six-dir (what `validate` checks by default; every protocol of the file when it
has neither). A robust build (`<protocol>_trials`, `physics.robust`) gives soft targets, each head's pass rate over
the trials ("all": both in the same trial), and the positives the figures count are the grasps that hold (the
Wilson rule). A single-trial build gives 0/1 targets, its outcomes, as before. The features are computed here once
(`evaluator.features`, on the JAX device, one compiled call per record size), so epochs only gather rows.
"""

from pathlib import Path
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from ffcgs_jax.dataset import mcap_io as dataset_io
from ffcgs_jax.dataset.schema import SUCCESS_KEYS
from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.core.files import check_file
from ffcgs_jax.geometry.sdf import GradientSDF
from ffcgs_jax.learning import evaluator
from ffcgs_jax.physics import robust
from ffcgs_jax.physics.config import PROTOCOLS, RobustConfig
from ffcgs_jax.runtime.fixed_shapes import pad_rows

PAD = 64  # records are padded to a multiple of this many grasps: one compilation for a whole build


class LabelData(NamedTuple):
    """Host arrays, N grasps: x (N, F) float32 features; y (N, H) float32 labels, heads as `heads`; objects (N,)
    object name; valid (N,) the synthesis's validity; E (N,) its energy (the analytic order, for comparison);
    hit (N, H) bool the positives of each head (a robust build: the grasps that hold; None: y > 0.5)."""

    x: np.ndarray
    y: np.ndarray
    objects: np.ndarray
    valid: np.ndarray
    E: np.ndarray
    heads: tuple[str, ...]
    splits: np.ndarray
    hit: np.ndarray | None = None


def positives(data: LabelData) -> np.ndarray:
    """(N, H) bool: the grasps each head's figures count as passing."""
    return data.y > 0.5 if data.hit is None else data.hit


def targets(arrays: dict, keys: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """(G, H) float32 training targets and (G, H) bool positives of one record's grasps (module docstring)."""
    protocols = [k.removesuffix("_success") for k in keys]
    joint = [p for p in protocols if p in {q.replace("-", "_") for q in PROTOCOLS}] or protocols
    hit = np.stack([np.asarray(arrays[k], bool) for k in keys], 1)
    if all(f"{p}_trials" in arrays for p in protocols):
        both = robust.joint(arrays, joint, RobustConfig())
        y = np.stack([np.asarray(arrays[f"{p}_rate"], np.float64) for p in protocols] + [both["physics_rate"]], 1)
        return y.astype(np.float32), np.concatenate([hit, both["physics_holds"][:, None]], 1)
    hit = np.concatenate([hit, hit[:, [protocols.index(p) for p in joint]].all(1, keepdims=True)], 1)
    return hit.astype(np.float32), hit


def heads_of(protocol_keys: list[str]) -> tuple[str, ...]:
    """Head names from a record's `<protocol>_success` keys: the protocols, then "all"."""
    return (*[k.removesuffix("_success") for k in protocol_keys], "all")


def record_features(hand, rec_arrays: dict, grid, origin, voxel_size, table_z) -> np.ndarray:
    """(G, F) float32 features of one record's grasps (its SDF and grasp arrays)."""
    n = len(rec_arrays["q"])
    c = len(hand.spec.contact_sites)
    inputs = evaluator.grasp_inputs(rec_arrays, c)
    m = -(-n // PAD) * PAD
    pad = lambda a: pad_rows(np.asarray(a), m)  # noqa: E731
    sdf = GradientSDF(jnp.asarray(grid, jnp.float32), jnp.asarray(origin, jnp.float32),
                      jnp.asarray(voxel_size, jnp.float32), jnp.asarray(table_z, jnp.float32))
    dt = np.float32
    x = evaluator.batch_features_jit(hand, sdf, jnp.asarray(pad(rec_arrays["wrist_pose"]), dt),
                                     jnp.asarray(pad(rec_arrays["q"]), dt),
                                     jnp.asarray(pad(np.asarray(rec_arrays["contacts"], dt)), dt),
                                     jnp.asarray(pad(inputs), dt))
    return np.asarray(x)[:n]


def load(path: str | Path, hand, progress: bool = True, held_out: bool = False) -> LabelData:
    """Read a labelled dataset file (every record must carry the same protocols' outcomes). Test-split records are
    refused unless `held_out` (a file read to measure a predictor, never to train one)."""
    path = Path(path)
    if not path.exists():
        raise FfcgsError(f"dataset file not found: {path} (build one with `ffcgs dataset build --keep all`)")
    check_file(path, "dataset file")
    xs, ys, hits, objs, valid, E, splits = [], [], [], [], [], [], []
    keys = None
    for rec in tqdm(dataset_io.iter_records(path), desc="features", unit="record", disable=not progress):
        if not rec.num_grasps:
            continue
        arrays = rec.grasp_arrays()
        have = [k for k in SUCCESS_KEYS if k in arrays]
        robust_ = [f"{k.removesuffix('_success')}_trials" in arrays for k in have]
        if "contacts" not in arrays or not have:
            raise FfcgsError(f"{path}: record {rec.record_id} has no physics labels for every candidate; the "
                             "success predictor trains on a labelled build (`ffcgs dataset build --keep all`)")
        if keys is None:
            keys, trials = have, robust_
        elif have != keys or robust_ != trials:
            raise FfcgsError(f"{path}: record {rec.record_id} carries the outcomes {have} (robust {robust_}), earlier "
                             f"records {keys} (robust {trials}); train on one labelled build")
        if arrays["q"].shape[1] != hand.lower.shape[0]:
            raise FfcgsError(f"{path}: its grasps have {arrays['q'].shape[1]} channels, hand {hand.spec.name} has "
                             f"{hand.lower.shape[0]}")
        xs.append(record_features(hand, arrays, rec.grid, rec.origin, rec.voxel_size, rec.table_z))
        y, hit = targets(arrays, keys)
        ys.append(y)
        hits.append(hit)
        objs += [rec.object_name] * rec.num_grasps
        splits += [rec.split] * rec.num_grasps
        valid.append(np.asarray(arrays["valid"], bool))
        E.append(np.asarray(arrays["E"], np.float64))
    if not xs:
        raise FfcgsError(f"{path}: no record has grasps; nothing to train on")
    if "test" in splits and not held_out:
        raise FfcgsError(f"{path} holds test-split objects; the predictor never trains on them (build with "
                         "--split train)")
    return LabelData(np.concatenate(xs), np.concatenate(ys), np.asarray(objs), np.concatenate(valid),
                     np.concatenate(E), heads_of(keys), np.asarray(splits), np.concatenate(hits))
