"""Pytrees of arrays to and from `.npz` files, without pickle: nested dicts of arrays are flattened to
"a/b/c" keys, and a JSON metadata dict rides along as a uint8 array under "__meta__".

Loading uses `np.load(allow_pickle=False)`, so a checkpoint cannot run code; writes are atomic (temporary file,
then rename), so an interrupted save leaves the previous checkpoint intact.
"""

import json
from pathlib import Path

import numpy as np

from ffcgs_jax.core import files
from ffcgs_jax.core.errors import FfcgsError

_META = "__meta__"


def flatten(tree: dict, prefix: str = "") -> dict[str, np.ndarray]:
    """{"a": {"b": x}} -> {"a/b": x}; leaves become host numpy arrays. Keys must be strings without "/"."""
    out = {}
    for k, v in tree.items():
        if not isinstance(k, str) or "/" in k or not k:
            raise FfcgsError(f"checkpoint keys must be non-empty strings without '/', got {k!r}")
        if isinstance(v, dict):
            out.update(flatten(v, f"{prefix}{k}/"))
        else:
            out[prefix + k] = np.asarray(v)
    return out


def unflatten(flat: dict[str, np.ndarray]) -> dict:
    tree: dict = {}
    for key, v in flat.items():
        *path, leaf = key.split("/")
        node = tree
        for p in path:
            node = node.setdefault(p, {})
            if not isinstance(node, dict):
                raise FfcgsError(f"checkpoint entry {key!r} lies under the array {p!r}")
        if isinstance(node.get(leaf), dict):
            raise FfcgsError(f"checkpoint entry {key!r} is both an array and a group")
        node[leaf] = v
    return tree


def save(path: str | Path, tree: dict, meta: dict | None = None) -> Path:
    """Write `tree` (nested dicts of arrays) and `meta` (JSON-serialisable) to `path` atomically."""
    flat = flatten(tree)
    flat[_META] = np.frombuffer(json.dumps(meta or {}, sort_keys=True).encode(), np.uint8)
    return files.atomic_write(files.check_output(path, "checkpoint"), lambda f: np.savez(f, **flat))


def load(path: str | Path) -> tuple[dict, dict]:
    """(tree, meta) from a file written by `save`."""
    path = Path(path)
    flat = files.read_npz(path, "checkpoint file", ".npz checkpoint")
    if _META not in flat:
        raise FfcgsError(f"{path} is not an ffcgs checkpoint (no {_META} entry)")
    raw = flat.pop(_META)
    try:
        meta = json.loads(raw.tobytes().decode()) if raw.dtype == np.uint8 else None
    except ValueError:  # JSONDecodeError and UnicodeDecodeError included
        meta = None
    if meta is None:
        raise FfcgsError(f"{path} is not an ffcgs checkpoint: its {_META} entry is not JSON text (uint8)")
    if not isinstance(meta, dict):
        raise FfcgsError(f"{path} is not an ffcgs checkpoint: its {_META} entry is not a JSON object")
    try:
        return unflatten(flat), meta
    except FfcgsError as e:
        raise FfcgsError(f"{path} is not an ffcgs checkpoint: {e}") from None
