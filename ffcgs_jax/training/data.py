"""Training data for the CVAE: a dataset file read once into compact arrays (one SDF per record, not per grasp),
split by object into cross-validation folds, and cut into fixed-shape batches of indices per epoch.

The SDFs of a full dataset fit in memory many times over (a 32^3 record is 0.5 MB; the YCB training set has a few
hundred records), so training keeps them on the device and gathers batches inside the compiled step; the file is
still read as a stream (`dataset.mcap_io.iter_records`), never whole.
"""

from pathlib import Path
from typing import NamedTuple

import numpy as np

from ffcgs_jax.dataset import mcap_io as dataset_io
from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.core.files import check_file


class TrainData(NamedTuple):
    """Host arrays. S records, N grasps.

    Attributes:
        grids: (S, R, R, R, 4) float32 Gradient-SDFs; origin (S, 3); voxel_size (S,).
        objects: (S,) object name of each record (folds split by it).
        pose: (N, 4, 4) wrist poses in their record's frame; record: (N,) int32 record of each grasp.
        noisy: (N,) bool, True for the stored noisy copies.
    """

    grids: np.ndarray
    origin: np.ndarray
    voxel_size: np.ndarray
    objects: np.ndarray
    pose: np.ndarray
    record: np.ndarray
    noisy: np.ndarray

    @property
    def res(self) -> int:
        return int(self.grids.shape[1])

    def grasps_of(self, records: np.ndarray) -> np.ndarray:
        """Indices of the grasps that belong to `records`."""
        return np.flatnonzero(np.isin(self.record, records))


def load(path: str | Path, noisy: bool = True) -> TrainData:
    """Read a dataset file's successful grasps (`Record.holds`: all of a "keep passing" build, those that passed
    every protocol of a labelled one); records without any are dropped. `noisy` adds each grasp's noisy copy."""
    path = Path(path)
    if not path.exists():
        raise FfcgsError(f"dataset file not found: {path} (build one with `ffcgs dataset build`)")
    check_file(path, "dataset file")
    grids, origins, voxels, names, poses, recs, flags = [], [], [], [], [], [], []
    for rec in dataset_io.iter_records(path):
        held = rec.holds()  # a labelled build holds its failures too: the sampler learns the successes
        if not held.any():
            continue
        s = len(grids)
        if grids and rec.grid.shape != grids[0].shape:
            raise FfcgsError(f"{path}: record {rec.record_id} has SDF grid {rec.grid.shape}, others "
                             f"{grids[0].shape}; training needs one resolution")
        grids.append(rec.grid.astype(np.float32))
        origins.append(rec.origin)
        voxels.append(float(rec.voxel_size))
        names.append(rec.object_name)
        copies = [(rec.wrist_pose[held], False)]
        if noisy:
            if rec.wrist_pose_noisy is None:
                raise FfcgsError(f"{path}: record {rec.record_id} has no noisy poses; set data.noisy = false")
            copies.append((rec.wrist_pose_noisy[held], True))
        for p, flag in copies:
            poses.append(p)
            recs.append(np.full(len(p), s, np.int32))
            flags.append(np.full(len(p), flag))
    if not grids:
        raise FfcgsError(f"{path}: no record has grasps; nothing to train on")
    return TrainData(np.stack(grids), np.asarray(origins, np.float32), np.asarray(voxels, np.float32),
                     np.asarray(names), np.concatenate(poses).astype(np.float32), np.concatenate(recs),
                     np.concatenate(flags))


def fold_of(objects: np.ndarray, folds: int, seed: int) -> dict[str, int]:
    """Object name -> fold: the sorted distinct names, shuffled with `seed`, dealt round-robin (sizes differ by <= 1)."""
    names = sorted(set(objects.tolist()))
    if len(names) < folds:
        raise FfcgsError(f"cross-validation needs at least {folds} objects (cv.folds), the dataset has {len(names)}")
    order = np.random.default_rng([seed, 7]).permutation(len(names))
    return {names[j]: i % folds for i, j in enumerate(order)}


def split(data: TrainData, folds: int, fold: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(train, validation) record indices for held-out `fold`; fold -1 trains on everything (validation empty).

    Indices refer to the whole `data`, so every fold trains on the same device arrays (and compiles once)."""
    everything = np.arange(len(data.objects))
    if fold < 0:
        return everything, everything[:0]
    f = fold_of(data.objects, folds, seed)
    held = np.array([f[o] == fold for o in data.objects.tolist()])
    return everything[~held], everything[held]


def steps_per_epoch(data: TrainData, records: np.ndarray, batch: int, per_sdf: int) -> int:
    """How many batches `epoch_batches` yields (the same every epoch); refuses a set smaller than one batch."""
    counts = np.bincount(data.record, minlength=len(data.objects))[records]
    steps = int(np.sum(-(-counts // per_sdf)) // (batch // per_sdf))
    if steps == 0:
        raise FfcgsError(f"the training set has {int(counts.sum())} grasps, fewer than one batch ({batch})")
    return steps


def epoch_batches(data: TrainData, records: np.ndarray, batch: int, per_sdf: int,
                  rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """One epoch's batches over the grasps of `records`, as indices into `data`: records (steps, batch / per_sdf)
    and grasps (steps, batch / per_sdf, per_sdf).

    Each record's grasps are permuted and cut into groups of `per_sdf` (a short last group is filled with other
    grasps of the same record), the groups are permuted, and consecutive groups form a batch. The epoch has
    floor(groups / (batch / per_sdf)) steps: a partial last batch is dropped so every step has one shape.
    """
    groups = []
    for r in records:
        idx = np.flatnonzero(data.record == r)
        idx = idx[rng.permutation(len(idx))]
        n_groups = -(-len(idx) // per_sdf)
        fill = (-len(idx)) % per_sdf
        if fill:
            idx = np.concatenate([idx, rng.choice(idx, fill, replace=len(idx) < fill)])
        groups.append(idx.reshape(n_groups, per_sdf))
    steps = steps_per_epoch(data, records, batch, per_sdf)
    g = np.concatenate(groups)
    g = g[rng.permutation(len(g))]
    per_batch = batch // per_sdf
    g = g[: steps * per_batch].reshape(steps, per_batch, per_sdf)
    return data.record[g[:, :, 0]], g
