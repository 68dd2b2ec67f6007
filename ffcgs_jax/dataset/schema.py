"""The training-data format: what one record holds, the MCAP topics and schemas, and the array encoding.

The files themselves (writing parts, merging, reading back) are `mcap_io`'s; this module only defines and
(de)serialises a record.

Records
    A build is a sequence of *object records* (`Record`): one object mesh under one rotation. Each carries the
    metadata object name, SHA-256 of the source mesh, rotation index, the 3x3 rotation matrix applied to the mesh,
    split name ("train", "val", ...); the SDF (grid (R, R, R, 4) float32, origin (3,), voxel_size, table_z, in the
    rotated object's frame, see `geometry.sdf.GradientSDF`); and the kept grasps: wrist_pose (G, 4, 4) in the
    object frame, q (G, Q) channels of the hand (9 on the SVH, 16 on the Allegro), per-grasp epsilon, E, E_g, E_c (G,) and optionally the physics results
    lift_shake_success, six_dir_success (G,) bool. G = 0 is allowed.

    Record id: `record_id(object_name, rotation_index)` = "<name>.r<rotation_index:04d>", where <name> is the object
    name if it only uses [A-Za-z0-9_-], else the name with other characters replaced by "_" plus "-" and the first 8
    hex digits of the name's SHA-256 (so distinct names never collide). Ids are deterministic, unique per
    (object, rotation), usable as file names, and their string order is the record order of the merged file.

MCAP topics (every message JSON: message encoding "json", schema encoding "jsonschema"; the schemas are `SCHEMAS`
below and describe the whole message):
    /config   one message: {"version": package version, "config": the build config dict, "extra": anything else
              passed to `mcap_io.init_parts`}. log_time 0.
    /sdf      one message per record (schema "ffcgs.DatasetSdf"): meta + arrays grid <f4 (R,R,R,4), origin <f8 (3,),
              voxel_size <f8 (), table_z <f8 ().
    /grasps   one message per record (schema "ffcgs.DatasetGrasps"): meta + arrays wrist_pose <f8 (G,4,4),
              q <f8 (G,Q), epsilon, E, E_g, E_c <f8 (G,), and if present wrist_pose_noisy <f8 (G,4,4),
              lift_shake_success, six_dir_success |b1 (G,).
    Record i (0-based, in record-id order) has its /sdf then its /grasps message, both with log_time = publish_time =
    sequence = i. The "meta" of both messages is {"record_id", "object_name", "mesh_sha256", "rotation_index",
    "rotation" (3x3 nested list), "split"} and, when set, "category" and "info".

Array messages (/sdf, /grasps), a JSON object:
    {"meta": {...},
     "arrays": {name: {"dtype": numpy dtype string ("<f4", "<f8", "|b1"),
                       "shape": [d0, d1, ...],
                       "data": base64 (RFC 4648, standard alphabet, padded) of the array's raw bytes, C order,
                               little-endian: prod(shape) * itemsize bytes}}}
    Any JSON reader reads it (`mcap cat --json`, Foxglove's raw message view); an array is then, in numpy,
    `np.frombuffer(base64.b64decode(a["data"]), a["dtype"]).reshape(a["shape"])`, which `decoder.DecoderFactory`
    does for mcap's reader: `mcap.reader.make_reader(f, decoder_factories=[DecoderFactory()])
    .iter_decoded_messages()` yields each message with its arrays as numpy arrays. Base64 is how Foxglove's own JSON
    schemas carry bytes (`contentEncoding: base64`). The JSON is compact with sorted keys, so the same record gives
    the same bytes. No compression inside the message; the MCAP chunks are zstd-compressed.

Older files (read, never written): /sdf and /grasps in message encoding "ffcgs.arrays.v1", whose channel schema
described only the header:
    bytes [0, 8)      magic b"FFCGSAR1"
    bytes [8, 12)     n = header length, uint32 little-endian
    bytes [12, 12+n)  header, UTF-8 JSON: {"meta": {...}, "arrays": {name: {"dtype", "shape", "offset": byte offset
                      into the data section}}}
    zero padding to the next multiple of 8, then the data section: each array's raw C-order little-endian bytes at
    its offset (offsets are multiples of 8).
The readers (`mcap_io`, `decoder.DecoderFactory`) take either encoding, per channel.
"""

from __future__ import annotations

import base64
import binascii
import dataclasses
import hashlib
import json
import re
import struct

import numpy as np

from ffcgs_jax.core.errors import FfcgsError

ARRAYS_ENCODING = "json"
"""Message encoding of the /sdf and /grasps messages written now (module docstring)."""

LEGACY_ENCODING = "ffcgs.arrays.v1"
"""Message encoding of /sdf and /grasps in older files: read, never written."""

MAGIC = b"FFCGSAR1"

_META_SCHEMA = {
    "type": "object",
    "description": "The record's metadata; the same in its /sdf and /grasps messages",
    "properties": {"record_id": {"type": "string"}, "object_name": {"type": "string"},
                   "mesh_sha256": {"type": "string", "pattern": "^[0-9a-f]{64}$"},
                   "rotation_index": {"type": "integer", "minimum": 0},
                   "rotation": {"type": "array", "items": {"type": "array", "items": {"type": "number"}}},
                   "split": {"type": "string"}, "category": {"type": "string"}, "info": {"type": "object"}},
    "required": ["record_id", "object_name", "mesh_sha256", "rotation_index", "rotation", "split"],
}

SDF_ARRAYS = {"grid": "<f4", "origin": "<f8", "voxel_size": "<f8", "table_z": "<f8"}

GRASP_ARRAYS = {"wrist_pose": "<f8", "q": "<f8", "epsilon": "<f8", "E": "<f8", "E_g": "<f8", "E_c": "<f8"}

PHYSICS_ARRAYS = {"lift_shake_success": "|b1", "six_dir_success": "|b1"}


def _label_arrays() -> dict[str, str]:
    """The labels a labelled build (`DatasetConfig.keep` "all") stores beside every candidate, failures included:
    per protocol p (its name with '-' written '_') what `physics.runner.evaluate` returns, and the synthesis's
    analytic metrics and features. Floats beside the grasp itself are float32 (NaN where a protocol did not get
    that far, e.g. a push after a penetration failure). With robust trials (the default since issue 45) `_success`
    is the robust verdict and `_trials` (G, K), `_rate`, `_rate_low`, `_rate_high` come with it; files without
    them are single-trial labels."""
    from ffcgs_jax.physics.config import ALL_PROTOCOLS

    out = {"initial_penetration": "<f4", "palm_contact": "|b1", "physics_rerun_cpu": "|b1"}
    for p in ALL_PROTOCOLS:
        k = p.replace("-", "_")
        out |= {f"{k}_success": "|b1", f"{k}_reason": "|i1", f"{k}_move": "<f4", f"{k}_rot": "<f4",
                f"{k}_move_dir": "<f4", f"{k}_rot_dir": "<f4",
                # robust trials (`physics.robust`): (G, K) outcomes, the pass rate and its Wilson interval
                f"{k}_trials": "|b1", f"{k}_rate": "<f4", f"{k}_rate_low": "<f4", f"{k}_rate_high": "<f4"}
        if p.startswith("dexgraspbench"):
            out[f"{k}_pregrasp_penetration"] = "<f4"
    for k in PHYSICS_ARRAYS:
        out.pop(k)  # the two fields every record format had
    out |= {k: "|b1" for k in ("valid", "force_closure", "pose_collides", "palm_up", "tips_below_table", "lp_ok")}
    out |= {k: "<f4" for k in ("E_q", "E_m", "support_min", "E_g_mesh", "E_c_mesh", "penetration",
                               "table_penetration", "score", "contact_dist", "contacts")}
    out["squeeze_dir"] = "<f8"  # the physics test's own input: a re-run must see the same numbers
    out |= {"n_contacts": "|i1", "iters": "<i4"}
    return out


LABEL_ARRAYS = _label_arrays()
"""Per-grasp labels and features of a labelled build; every one optional, the first dimension G."""

OPTIONAL_GRASP_ARRAYS = {"wrist_pose_noisy": "<f8", **PHYSICS_ARRAYS, **LABEL_ARRAYS}

_NDIM = {"grid": 4, "origin": 1, "voxel_size": 0, "table_z": 0, "wrist_pose": 3, "wrist_pose_noisy": 3, "q": 2,
         "contact_dist": 2, "contacts": 3, "squeeze_dir": 2,
         **{k: 2 for k in LABEL_ARRAYS if k.endswith(("_move_dir", "_rot_dir", "_trials"))}}
"""Array ranks (1 where not listed: per-grasp values)."""

SUCCESS_KEYS = tuple(k for k in OPTIONAL_GRASP_ARRAYS if k.endswith("_success"))
"""Every per-protocol outcome a record can carry."""


def _array_schema(name: str, dtype: str) -> dict:
    n = _NDIM.get(name, 1)
    return {"type": "object", "additionalProperties": False, "required": ["dtype", "shape", "data"],
            "description": f"{name}: {n}-D array of numpy dtype {dtype}",
            "properties": {"dtype": {"const": dtype, "description": "numpy dtype string"},
                           "shape": {"type": "array", "items": {"type": "integer", "minimum": 0},
                                     "minItems": n, "maxItems": n},
                           "data": {"type": "string", "contentEncoding": "base64",
                                    "description": "base64 of the raw little-endian C-order bytes"}}}


def _arrays_schema(title: str, required: dict[str, str], optional: dict[str, str]) -> dict:
    return {"title": title, "type": "object",
            "description": "One record's arrays with its metadata (ffcgs_jax/dataset/schema.py): each array as "
                           "dtype, shape and base64 data; decode with ffcgs_jax.dataset.decoder.DecoderFactory or "
                           "np.frombuffer(base64.b64decode(data), dtype).reshape(shape)",
            "properties": {"meta": _META_SCHEMA,
                           "arrays": {"type": "object",
                                      "properties": {k: _array_schema(k, d) for k, d in {**required,
                                                                                        **optional}.items()},
                                      "required": list(required), "additionalProperties": False}},
            "required": ["meta", "arrays"], "additionalProperties": False}


SCHEMAS = {
    "/config": {"title": "ffcgs.DatasetConfig", "type": "object",
                "properties": {"version": {"type": "string"}, "config": {"type": "object"},
                               "extra": {"type": "object"}},
                "required": ["version", "config", "extra"]},
    "/sdf": _arrays_schema("ffcgs.DatasetSdf", SDF_ARRAYS, {}),
    "/grasps": _arrays_schema("ffcgs.DatasetGrasps", GRASP_ARRAYS, OPTIONAL_GRASP_ARRAYS),
}

MESSAGE_ENCODINGS = {"/config": "json", "/sdf": ARRAYS_ENCODING, "/grasps": ARRAYS_ENCODING}
"""What the writer uses; the readers also take LEGACY_ENCODING on /sdf and /grasps."""

READ_ENCODINGS = {"/config": ("json",), "/sdf": (ARRAYS_ENCODING, LEGACY_ENCODING),
                  "/grasps": (ARRAYS_ENCODING, LEGACY_ENCODING)}


def canonical_json(obj, what: str) -> str:
    try:
        return json.dumps(obj, sort_keys=True, separators=(",", ":"), allow_nan=False)
    except (TypeError, ValueError) as e:
        raise FfcgsError(f"{what} must be JSON-serialisable (finite numbers, str keys): {e}") from None


def record_id(object_name: str, rotation_index: int) -> str:
    """The deterministic, file-name-safe id of (object, rotation); see the module docstring."""
    if not isinstance(object_name, str) or not object_name:
        raise FfcgsError(f"object name must be a non-empty string, got {object_name!r}")
    if isinstance(rotation_index, bool) or not isinstance(rotation_index, (int, np.integer)) or rotation_index < 0:
        raise FfcgsError(f"rotation index must be an integer >= 0, got {rotation_index!r}")
    safe = re.sub(r"[^A-Za-z0-9_-]", "_", object_name)
    if safe != object_name:
        safe += "-" + hashlib.sha256(object_name.encode()).hexdigest()[:8]
    return f"{safe}.r{int(rotation_index):04d}"


@dataclasses.dataclass(eq=False)
class Record:
    """One object under one rotation: metadata, SDF and kept grasps (numpy arrays; see the module docstring).

    `index` is the record's position in a merged file (set by `mcap_io.iter_records`; -1 for a record not read from
    one). `Record.create` checks and converts everything; the reader builds records through it too.
    """

    object_name: str
    mesh_sha256: str
    rotation_index: int
    rotation: np.ndarray
    split: str
    grid: np.ndarray
    origin: np.ndarray
    voxel_size: np.ndarray
    table_z: np.ndarray
    wrist_pose: np.ndarray
    q: np.ndarray
    epsilon: np.ndarray
    E: np.ndarray
    E_g: np.ndarray
    E_c: np.ndarray
    lift_shake_success: np.ndarray | None = None
    six_dir_success: np.ndarray | None = None
    wrist_pose_noisy: np.ndarray | None = None
    category: str = ""
    info: dict = dataclasses.field(default_factory=dict)
    index: int = -1
    labels: dict = dataclasses.field(default_factory=dict)

    @property
    def record_id(self) -> str:
        return record_id(self.object_name, self.rotation_index)

    @property
    def num_grasps(self) -> int:
        return int(self.wrist_pose.shape[0])

    @classmethod
    def create(cls, *, object_name: str, mesh_sha256: str, rotation_index: int, rotation, split: str, sdf=None,
               grid=None, origin=None, voxel_size=None, table_z=None, wrist_pose, q, epsilon, E, E_g, E_c,
               lift_shake_success=None, six_dir_success=None, wrist_pose_noisy=None, category: str = "",
               info: dict | None = None, index: int = -1, **labels) -> Record:
        """Check and convert. The SDF is either `sdf` (a `GradientSDF` or anything with .grid, .origin,
        .voxel_size, .table_z) or the four arrays; float arrays become float32 (grid) / float64 (the rest).
        `labels`: any of `LABEL_ARRAYS`, each with G rows (floats may be NaN: not simulated that far)."""
        if sdf is not None:
            grid, origin, voxel_size, table_z = (np.asarray(getattr(sdf, k))
                                                 for k in ("grid", "origin", "voxel_size", "table_z"))
        rid = record_id(object_name, rotation_index)  # checks name and index
        where = f"record {rid}"
        if not isinstance(mesh_sha256, str) or not re.fullmatch(r"[0-9a-f]{64}", mesh_sha256):
            raise FfcgsError(f"{where}: mesh_sha256 must be 64 lowercase hex digits, got {mesh_sha256!r}")
        if not isinstance(split, str) or not split:
            raise FfcgsError(f"{where}: split must be a non-empty string, got {split!r}")

        def arr(name, value, dtype, shape_ok, shape_text, nan_ok=False):
            if value is None:
                raise FfcgsError(f"{where}: {name} is missing")
            a = np.asarray(value)
            if dtype == "|b1":
                if a.dtype.kind not in "biu" or (a.dtype.kind != "b" and not np.isin(a, (0, 1)).all()):
                    raise FfcgsError(f"{where}: {name} must be booleans, got dtype {a.dtype}")
            elif a.dtype.kind not in "fiu" or not (np.isfinite(a) | (nan_ok and np.isnan(a))).all():
                raise FfcgsError(f"{where}: {name} must be finite numbers{' or NaN' if nan_ok else ''} "
                                 f"(dtype {a.dtype})")
            if not shape_ok(a.shape):
                raise FfcgsError(f"{where}: {name} must have shape {shape_text}, got {a.shape}")
            return np.array(a, dtype=np.dtype(dtype), order="C")  # copy; keeps 0-d shapes

        grid = arr("grid", grid, "<f4", lambda s: len(s) == 4 and s[3] == 4 and s[0] == s[1] == s[2] >= 2,
                   "(R, R, R, 4) with R >= 2")
        origin = arr("origin", origin, "<f8", lambda s: s == (3,), "(3,)")
        voxel_size = arr("voxel_size", voxel_size, "<f8", lambda s: s == (), "()")
        if not voxel_size > 0:
            raise FfcgsError(f"{where}: voxel_size must be > 0, got {voxel_size}")
        table_z = arr("table_z", table_z, "<f8", lambda s: s == (), "()")
        rotation = arr("rotation", rotation, "<f8", lambda s: s == (3, 3), "(3, 3)")
        if not np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-5) or np.linalg.det(rotation) <= 0:
            raise FfcgsError(f"{where}: rotation must be a proper rotation matrix (orthonormal, det +1)")
        wrist_pose = arr("wrist_pose", wrist_pose, "<f8", lambda s: len(s) == 3 and s[1:] == (4, 4), "(G, 4, 4)")
        g = wrist_pose.shape[0]
        q = arr("q", q, "<f8", lambda s: len(s) == 2 and s[0] == g and s[1] >= 1, f"(G, Q) with G = {g}")
        scalars = {k: arr(k, v, "<f8", lambda s: s == (g,), f"(G,) = ({g},)")
                   for k, v in (("epsilon", epsilon), ("E", E), ("E_g", E_g), ("E_c", E_c))}
        physics = {k: None if v is None else arr(k, v, "|b1", lambda s: s == (g,), f"(G,) = ({g},)")
                   for k, v in (("lift_shake_success", lift_shake_success), ("six_dir_success", six_dir_success))}
        if wrist_pose_noisy is not None:
            wrist_pose_noisy = arr("wrist_pose_noisy", wrist_pose_noisy, "<f8", lambda s: s == (g, 4, 4),
                                   f"(G, 4, 4) = ({g}, 4, 4)")
        unknown = sorted(set(labels) - set(LABEL_ARRAYS))
        if unknown:
            raise FfcgsError(f"{where}: unknown label(s) {unknown}; labels: schema.LABEL_ARRAYS")
        labels = {k: arr(k, v, LABEL_ARRAYS[k], lambda s: len(s) == _NDIM.get(k, 1) and s[0] == g,
                         f"{_NDIM.get(k, 1)}-D with G = {g} rows", nan_ok=LABEL_ARRAYS[k][1] == "f")
                  for k, v in sorted(labels.items()) if v is not None}
        if not isinstance(category, str):
            raise FfcgsError(f"{where}: category must be a string, got {category!r}")
        info = {} if info is None else info
        if not isinstance(info, dict):
            raise FfcgsError(f"{where}: info must be a dict, got {type(info).__name__}")
        canonical_json(info, f"{where}: info")  # JSON-serialisable, or a clear error now rather than at write time
        return cls(object_name=object_name, mesh_sha256=mesh_sha256, rotation_index=int(rotation_index),
                   rotation=rotation, split=split, grid=grid, origin=origin, voxel_size=voxel_size, table_z=table_z,
                   wrist_pose=wrist_pose, q=q, **scalars, **physics, wrist_pose_noisy=wrist_pose_noisy,
                   category=category, info=info, index=int(index), labels=labels)

    def meta(self) -> dict:
        meta = {"record_id": self.record_id, "object_name": self.object_name, "mesh_sha256": self.mesh_sha256,
                "rotation_index": self.rotation_index, "rotation": self.rotation.tolist(), "split": self.split}
        if self.category:
            meta["category"] = self.category
        if self.info:
            meta["info"] = self.info
        return meta

    def sdf_arrays(self) -> dict[str, np.ndarray]:
        return {k: getattr(self, k) for k in SDF_ARRAYS}

    def grasp_arrays(self) -> dict[str, np.ndarray]:
        out = {k: getattr(self, k) for k in GRASP_ARRAYS}
        out.update({k: getattr(self, k) for k in ("wrist_pose_noisy", *PHYSICS_ARRAYS) if getattr(self, k) is not None})
        return out | self.labels

    def holds(self) -> np.ndarray:
        """(G,) bool: the grasps that passed every protocol this record was labelled with (all, when none): the
        training set of the learned sampler is this filter over the records, successes only."""
        return holds(self.grasp_arrays(), self.num_grasps)


def holds(arrays: dict[str, np.ndarray], n: int) -> np.ndarray:
    """(n,) bool: the grasps of `arrays` (a record's grasp arrays) that passed every protocol they carry an outcome
    of (`SUCCESS_KEYS`); all of them when they carry none."""
    out = np.ones(n, bool)
    for k in SUCCESS_KEYS:
        if k in arrays:
            out &= np.asarray(arrays[k], bool)
    return out


def encode_message(meta: dict, arrays: dict[str, np.ndarray]) -> bytes:
    """An /sdf or /grasps message (module docstring): compact JSON, sorted keys; arrays must be little-endian."""
    descr = {}
    for name, a in arrays.items():
        a = np.asarray(a, order="C")
        if a.dtype.byteorder == ">":
            raise FfcgsError(f"array {name} is big-endian; convert to little-endian first")
        descr[name] = {"dtype": a.dtype.str, "shape": list(a.shape),
                       "data": base64.b64encode(a.tobytes()).decode("ascii")}
    return canonical_json({"meta": meta, "arrays": descr}, "record metadata").encode()


def _array(name: str, d: dict, buffer: bytes | None, start: int, what: str, encoding: str) -> np.ndarray:
    """One array of a message: from its base64 "data" (JSON) or at its "offset" in `buffer` (legacy)."""
    try:
        dtype = np.dtype(d["dtype"])
        shape = tuple(int(s) for s in d["shape"])
        if dtype.kind not in "biuf" or dtype.byteorder == ">" or any(s < 0 for s in shape):
            raise ValueError(f"dtype {dtype} / shape {shape} not allowed")
        count = int(np.prod(shape, dtype=np.int64))
        if buffer is None:
            raw = base64.b64decode(d["data"], validate=True)
            if len(raw) != count * dtype.itemsize:
                raise ValueError(f"{len(raw)} bytes for shape {shape} of {dtype}")
            return np.frombuffer(raw, dtype=dtype, count=count).reshape(shape).copy()
        lo = start + int(d["offset"])
        if lo < start or lo + count * dtype.itemsize > len(buffer):
            raise ValueError("extent out of range")
        return np.frombuffer(buffer, dtype=dtype, count=count, offset=lo).reshape(shape).copy()
    except (KeyError, TypeError, ValueError, binascii.Error) as e:
        raise FfcgsError(f"{what}: bad array {name!r} in {encoding} payload: {e}") from None


def decode_message(data: bytes, encoding: str = ARRAYS_ENCODING, what: str = "message"
                   ) -> tuple[dict, dict[str, np.ndarray]]:
    """(meta, {name: array}) of an /sdf or /grasps message in either encoding, arrays copied out of `data`."""
    if encoding == LEGACY_ENCODING:
        return decode_legacy(data, what)
    if encoding != ARRAYS_ENCODING:
        raise FfcgsError(f"{what}: unknown message encoding {encoding!r} (expected {ARRAYS_ENCODING!r} or "
                         f"{LEGACY_ENCODING!r})")
    try:
        msg = json.loads(bytes(data))
        meta, descr = msg["meta"], msg["arrays"]
        if not isinstance(meta, dict) or not isinstance(descr, dict):
            raise TypeError("meta and arrays must be objects")
    except (UnicodeDecodeError, ValueError, KeyError, TypeError) as e:
        raise FfcgsError(f"{what}: not a readable {SCHEMAS['/sdf']['title']} / {SCHEMAS['/grasps']['title']} "
                         f"JSON message: {type(e).__name__}: {e}") from None
    return meta, {name: _array(name, d, None, 0, what, encoding) for name, d in descr.items()}


def decode_legacy(data: bytes, what: str = "message") -> tuple[dict, dict[str, np.ndarray]]:
    """Decode "ffcgs.arrays.v1" (older files; module docstring): (meta, {name: array}) copied out of `data`."""
    if len(data) < 12 or data[:8] != MAGIC:
        raise FfcgsError(f"{what}: not an {LEGACY_ENCODING} payload (bad magic)")
    (n,) = struct.unpack("<I", data[8:12])
    try:
        header = json.loads(data[12:12 + n].decode())
        meta, descr = header["meta"], header["arrays"]
    except (UnicodeDecodeError, ValueError, KeyError, TypeError) as e:
        raise FfcgsError(f"{what}: unreadable {LEGACY_ENCODING} header: {type(e).__name__}: {e}") from None
    start = 12 + n + (-(12 + n) % 8)
    return meta, {name: _array(name, d, data, start, what, LEGACY_ENCODING) for name, d in descr.items()}


def record_from(sdf_meta: dict, sdf_arrays: dict, grasp_meta: dict, grasp_arrays: dict, index: int,
                 what: str) -> Record:
    if sdf_meta != grasp_meta:
        raise FfcgsError(f"{what}: /sdf and /grasps messages disagree on the record metadata "
                         f"({sdf_meta.get('record_id')!r} vs {grasp_meta.get('record_id')!r})")
    missing = [k for k in _META_SCHEMA["required"] if k not in sdf_meta]
    missing += [k for k in (*SDF_ARRAYS,) if k not in sdf_arrays]
    missing += [k for k in (*GRASP_ARRAYS,) if k not in grasp_arrays]
    if missing:
        raise FfcgsError(f"{what}: record lacks field(s) {', '.join(missing)}")
    extra = set(grasp_arrays) - set(GRASP_ARRAYS) - set(OPTIONAL_GRASP_ARRAYS)
    if extra or set(sdf_arrays) - set(SDF_ARRAYS):
        raise FfcgsError(f"{what}: unknown array(s) {sorted(extra | (set(sdf_arrays) - set(SDF_ARRAYS)))}")
    try:
        rec = Record.create(**{k: sdf_meta[k] for k in _META_SCHEMA["required"] if k != "record_id"},
                            category=sdf_meta.get("category", ""), info=sdf_meta.get("info"),
                            **sdf_arrays, **grasp_arrays, index=index)
    except FfcgsError as e:
        raise FfcgsError(f"{what}: {e}") from None
    if rec.record_id != sdf_meta["record_id"]:
        raise FfcgsError(f"{what}: record id {sdf_meta['record_id']!r} does not match its object name and "
                         f"rotation index (expected {rec.record_id!r})")
    return rec
