"""`ffcgs dataset export`: a dataset file's records as numpy .npz files, for users who do not want MCAP.

Two layouts, chosen by the output path:

`--out FILE.npz`: one file, the records stacked (held in memory together; every record must share the SDF
resolution R and the channel count Q, else export to a folder). N = records, M = grasps of all records:
    per record:  record_id, object_name, mesh_sha256, split, category, info_json (N,) str; rotation_index (N,)
                 int64; rotation (N, 3, 3); grid (N, R, R, R, 4) float32; origin (N, 3); voxel_size, table_z (N,);
                 grasp_start (N + 1,) int64: record n's grasps are rows grasp_start[n]:grasp_start[n + 1] of the
                 per-grasp arrays.
    per grasp:   wrist_pose (M, 4, 4), q (M, Q), epsilon, E, E_g, E_c (M,), grasp_record (M,) int64 (its record's
                 row); and when any record has them, wrist_pose_noisy (M, 4, 4), lift_shake_success,
                 six_dir_success (M,) bool and a labelled build's labels (`schema.LABEL_ARRAYS`, (M, ...)), with
                 has_<name> (N,) bool marking the records that do (the others' rows are NaN / False / -1).
    whole file:  config_json () str (the /config message), format () str "ffcgs.dataset.npz.v1".

`--out DIR` (any path not ending in .npz): one DIR/<record_id>.npz per record, streamed (one record in memory at a
time; records may differ in R): the record's arrays as above without the record axis (grid (R, R, R, 4), wrist_pose
(G, 4, 4), ...; optional arrays only when the record has them), its metadata as 0-d arrays (record_id, ...,
info_json), config_json and format.

Strings are numpy unicode arrays, so `np.load(path)` reads every file without pickles. Field meanings and units:
`schema` module docstring.
"""

import json
from pathlib import Path

import numpy as np

from ffcgs_jax.core import files
from ffcgs_jax.dataset import mcap_io
from ffcgs_jax.dataset.schema import GRASP_ARRAYS, OPTIONAL_GRASP_ARRAYS, SDF_ARRAYS, Record, canonical_json
from ffcgs_jax.core.errors import FfcgsError

FORMAT = "ffcgs.dataset.npz.v1"

_TEXT = ("record_id", "object_name", "mesh_sha256", "split", "category")


def export(dataset: str | Path, out: str | Path) -> dict:
    """Write `dataset`'s records to `out` (module docstring); {"records", "grasps", "files"} (paths written)."""
    dataset, out = Path(dataset), Path(out).expanduser()
    config_json = _config_json(dataset)
    if out.suffix.lower() == ".npz":
        files.check_output(out, "--out")
        arrays = _stacked(dataset, mcap_io.iter_records(dataset))
        arrays.update(config_json=np.array(config_json), format=np.array(FORMAT))
        files.atomic_write(out, lambda f: np.savez_compressed(f, **arrays))
        return {"records": len(arrays["record_id"]), "grasps": len(arrays["grasp_record"]), "files": [out]}
    files.check_folder(out, "--out")
    written, grasps = [], 0
    for rec in mcap_io.iter_records(dataset):
        arrays = {**_record_arrays(rec), "config_json": np.array(config_json), "format": np.array(FORMAT)}
        path = out / f"{rec.record_id}.npz"
        written.append(files.atomic_write(path, lambda f, a=arrays: np.savez_compressed(f, **a)))
        grasps += rec.num_grasps
    if not written:
        raise FfcgsError(f"{dataset} holds no records; nothing to export")
    return {"records": len(written), "grasps": grasps, "files": written}


def _config_json(dataset: Path) -> str:
    """The /config message as JSON text, or one line saying why `dataset` is not a dataset file."""
    if dataset.is_dir():
        raise FfcgsError(f"dataset {dataset} is a folder; give the .mcap file `ffcgs dataset build` wrote")
    if not dataset.is_file():
        raise FfcgsError(f"dataset file not found: {dataset}")
    try:
        return json.dumps(mcap_io.read_config(dataset), sort_keys=True)
    except FfcgsError as e:
        reason = str(e)
        if reason.startswith(f"{dataset} "):  # "X is not an MCAP file (bad magic)", ...
            raise
        raise FfcgsError(f"{dataset} is not a dataset file (`ffcgs dataset build` writes them): "
                         f"{reason.removeprefix(f'{dataset}: ')}") from None


def _record_arrays(rec: Record) -> dict[str, np.ndarray]:
    out = {k: np.array(getattr(rec, k)) for k in _TEXT}
    out.update(rotation_index=np.int64(rec.rotation_index), rotation=rec.rotation,
               info_json=np.array(canonical_json(rec.info, "info")), **rec.sdf_arrays(), **rec.grasp_arrays())
    return out


def _stacked(dataset: Path, records) -> dict[str, np.ndarray]:
    recs = list(records)
    if not recs:
        raise FfcgsError(f"{dataset} holds no records; nothing to export")
    for what, shape in (("SDF grid", lambda r: r.grid.shape), ("channel count", lambda r: r.q.shape[1:])):
        seen = sorted({shape(r) for r in recs})
        if len(seen) > 1:
            raise FfcgsError(f"{dataset}: records differ in {what} ({seen[0]} and {seen[-1]}), so they do not stack "
                             f"into one .npz; export to a folder instead (--out DIR)")
    counts = np.array([r.num_grasps for r in recs], np.int64)
    out = {k: np.array([getattr(r, k) for r in recs]) for k in _TEXT}
    out.update(rotation_index=np.array([r.rotation_index for r in recs], np.int64),
               rotation=np.stack([r.rotation for r in recs]),
               info_json=np.array([canonical_json(r.info, "info") for r in recs]),
               **{k: np.stack([getattr(r, k) for r in recs]) for k in SDF_ARRAYS},
               grasp_start=np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
               grasp_record=np.repeat(np.arange(len(recs), dtype=np.int64), counts),
               **{k: np.concatenate([getattr(r, k) for r in recs]) for k in GRASP_ARRAYS})
    arrays = [r.grasp_arrays() for r in recs]
    for k, dtype in OPTIONAL_GRASP_ARRAYS.items():
        has = np.array([k in a for a in arrays])
        if has.any():
            # where a record lacks it: False, NaN, or -1 for the integer labels (reasons, counts)
            fill = {"b": False, "f": np.nan}.get(np.dtype(dtype).kind, -1)
            tail = next(a[k].shape[1:] for a in arrays if k in a)
            out[k] = np.concatenate([a[k] if k in a else np.full((r.num_grasps, *tail), fill, np.dtype(dtype))
                                     for r, a in zip(recs, arrays)])
            out[f"has_{k}"] = has
    return out
