"""Training-data files for the wrist-pose sampler: per object (and per random rotation of it) the Gradient-SDF grid
and the kept grasps, in one MCAP file, built resumably and read back as a stream. The format (records, topics,
schemas, the array encoding) is `schema`'s.

Resumable build (an MCAP cannot be appended to once finished):
    * `init_parts(parts_dir, config, extra)` creates `parts_dir` (by convention `OUT.parts/`, see `parts_dir_for`)
      and writes `config.json` there; on a resumed build it checks the config is the same (else FfcgsError).
    * `write_part(parts_dir, record)` writes the record as its own small MCAP `<record_id>.mcap` (topics /sdf and
      /grasps) to a temporary file (`files.temporary`: hidden, marked as ours), fsyncs it and renames it into place, so
      a crash leaves either a complete part or a stray temporary file, never a half part under the final name.
      Writing a record that already has a part is a no-op if the bytes are identical, an FfcgsError otherwise.
    * `done_records(parts_dir)` lists the ids of finished parts (temporary files, and files without the MCAP magic
      at both ends, are not finished); a build loop skips those and writes the rest.
    * `merge(parts_dir, out_path)` writes the single MCAP (/config, then every record in record-id order) via a
      temporary file + rename. Timestamps are fixed (log_time = record index), message payloads are copied from
      the parts (re-encoded when a part is in the older "ffcgs.arrays.v1" encoding), so the merged bytes depend only
      on the set of records and the config: a build interrupted and resumed gives the same file as one done in one
      go.
    `DatasetWriter` wraps these four calls.

Reading: `iter_records(path)` streams records (one record in memory at a time, reading the MCAP linearly);
`batches(path, batch_size, seed, shuffle_buffer, epochs)` yields numpy batches pairing each grasp with its record's
SDF through a bounded shuffle buffer; `summary(path)` counts. Files of either array encoding are read (`schema`).
Without this package: `decoder.DecoderFactory` with mcap's own reader, or any JSON reader. This module imports numpy
and mcap only (no JAX): call `jnp.asarray` on the batches yourself.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import NamedTuple

import numpy as np

from ffcgs_jax.core import files
from ffcgs_jax.core.version import __version__
from ffcgs_jax.dataset.schema import (
    MESSAGE_ENCODINGS,
    PHYSICS_ARRAYS,
    READ_ENCODINGS,
    SCHEMAS,
    Record,
    canonical_json,
    decode_message,
    encode_message,
    record_from,
)
from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.core.files import check_file

_MCAP_MAGIC = b"\x89MCAP0\r\n"

PART_SUFFIX = ".mcap"

CONFIG_NAME = "config.json"


class Payload(NamedTuple):
    """One message's bytes and its channel's message encoding."""

    encoding: str
    data: bytes


def new_writer(f, topics):
    """An MCAP writer started on the open binary file f, and its channel id per topic in `topics`."""
    from mcap.writer import Writer

    w = Writer(f)
    w.start(profile="", library=f"ffcgs-jax {__version__}")
    ch = {}
    for topic in topics:
        schema = SCHEMAS[topic]
        sid = w.register_schema(name=schema["title"], encoding="jsonschema",
                                data=json.dumps(schema, sort_keys=True).encode())
        ch[topic] = w.register_channel(topic=topic, message_encoding=MESSAGE_ENCODINGS[topic], schema_id=sid)
    return w, ch


def _iter_messages(path: Path) -> Iterator[tuple[str, Payload]]:
    """(topic, payload) in file order, streaming; checks the file, schemas and encodings."""
    from mcap.reader import NonSeekingReader

    check_file(path, "dataset file")
    with open(path, "rb") as f:
        head = f.read(8)
        if head != _MCAP_MAGIC:
            raise FfcgsError(f"{path} is not an MCAP file (bad magic): it is {files.kind_of(head)}")
        f.seek(0)
        it = NonSeekingReader(f).iter_messages(log_time_order=False)
        while True:
            try:
                item = next(it)
            except StopIteration:
                return
            except Exception:  # noqa: BLE001 - any parse failure means a broken or truncated file
                raise FfcgsError(f"{path} is not a readable MCAP file: it is truncated or corrupt (a record before "
                                 f"byte {f.tell()} cannot be read)") from None
            schema, channel, message = item
            topic = channel.topic
            if topic not in SCHEMAS:
                raise FfcgsError(f"{path}: unexpected topic {topic!r} (a dataset has {', '.join(SCHEMAS)})")
            if (channel.message_encoding not in READ_ENCODINGS[topic] or schema is None
                    or schema.name != SCHEMAS[topic]["title"] or schema.encoding != "jsonschema"):
                raise FfcgsError(f"{path}: topic {topic} has message encoding {channel.message_encoding!r} and "
                                 f"schema {getattr(schema, 'name', None)!r}, expected "
                                 f"{' or '.join(map(repr, READ_ENCODINGS[topic]))} and {SCHEMAS[topic]['title']!r}")
            yield topic, Payload(channel.message_encoding, bytes(message.data))


def _pairs(path: Path) -> Iterator[tuple[str, Payload, Payload | None]]:
    """Yield ('config', payload, None) and ('record', sdf_payload, grasps_payload) in file order."""
    pending = None
    for topic, data in _iter_messages(path):
        if topic == "/config":
            if pending is not None:
                raise FfcgsError(f"{path}: /config message inside a record")
            yield "config", data, None
        elif topic == "/sdf":
            if pending is not None:
                raise FfcgsError(f"{path}: /sdf message without its /grasps message")
            pending = data
        else:
            if pending is None:
                raise FfcgsError(f"{path}: /grasps message without a preceding /sdf message")
            yield "record", pending, data
            pending = None
    if pending is not None:
        raise FfcgsError(f"{path}: last /sdf message has no /grasps message")


def _decode_record(path: Path, sdf: Payload, grasps: Payload, index: int) -> Record:
    what = f"{path} record {index}"
    sm, sa = decode_message(sdf.data, sdf.encoding, what + " /sdf")
    gm, ga = decode_message(grasps.data, grasps.encoding, what + " /grasps")
    return record_from(sm, sa, gm, ga, index, what)


def _messages(record: Record) -> tuple[bytes, bytes]:
    """The record's /sdf and /grasps message bytes in the current encoding."""
    meta = record.meta()
    return encode_message(meta, record.sdf_arrays()), encode_message(meta, record.grasp_arrays())


def parts_dir_for(out_path: str | Path) -> Path:
    """The conventional parts directory of an output file: `OUT.parts/` beside it."""
    out_path = Path(out_path)
    return out_path.with_name(out_path.name + ".parts")


def init_parts(parts_dir: str | Path, config: dict, extra: dict | None = None) -> Path:
    """Create (or reopen, checking the config is unchanged) a parts directory; returns it."""
    parts_dir = Path(parts_dir)
    if not isinstance(config, dict) or not (extra is None or isinstance(extra, dict)):
        raise FfcgsError("config and extra must be dicts")
    text = canonical_json({"version": __version__, "config": config, "extra": extra or {}}, "config")
    cfg = parts_dir / CONFIG_NAME
    if cfg.is_file():
        try:
            old = json.loads(cfg.read_text())
        except ValueError as e:
            raise FfcgsError(f"{cfg} is not JSON: {e}") from None
        new = json.loads(text)
        # a build started before a setting's rename resumes: its stored config read under the current names
        from ffcgs_jax.core.config import upgrade_keys
        from ffcgs_jax.dataset.config import DatasetConfig

        if (upgrade_keys(DatasetConfig, old.get("config")), old.get("extra")) != (new["config"], new["extra"]):
            raise FfcgsError(f"{parts_dir} was started with a different config; finish it with the same config "
                             f"or use a new output path")
        return parts_dir
    try:
        parts_dir.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise FfcgsError(f"cannot create {parts_dir}: {e}") from None
    files.atomic_write(cfg, lambda f: f.write(text.encode()))
    return parts_dir


def part_bytes(record: Record) -> bytes:
    """`record` as the bytes of one part file (`write_part`): an MCAP file of its /sdf and /grasps messages."""
    import io

    buf = io.BytesIO()
    w, ch = new_writer(buf, ("/sdf", "/grasps"))
    sdf, grasps = _messages(record)
    w.add_message(ch["/sdf"], log_time=0, publish_time=0, sequence=0, data=sdf)
    w.add_message(ch["/grasps"], log_time=0, publish_time=0, sequence=0, data=grasps)
    w.finish()
    return buf.getvalue()


def _is_complete(path: Path) -> bool:
    try:
        size = path.stat().st_size
        if size < 2 * len(_MCAP_MAGIC):
            return False
        with open(path, "rb") as f:
            head = f.read(len(_MCAP_MAGIC))
            f.seek(size - len(_MCAP_MAGIC))
            return head == _MCAP_MAGIC and f.read() == _MCAP_MAGIC
    except OSError:
        return False


def write_part(parts_dir: str | Path, record: Record) -> Path:
    """Write one record as `<parts_dir>/<record_id>.mcap`, atomically (temporary file, fsync, rename).

    A finished part with identical bytes (or the same record in the older encoding) makes this a no-op; one with
    different content is an FfcgsError (the same (object, rotation) written twice with different data)."""
    parts_dir = Path(parts_dir)
    if not (parts_dir / CONFIG_NAME).is_file():
        raise FfcgsError(f"{parts_dir} is not an initialised parts directory (call init_parts first)")
    if not isinstance(record, Record):
        raise FfcgsError(f"write_part takes a Record, got {type(record).__name__}")
    data = part_bytes(record)
    path = parts_dir / (record.record_id + PART_SUFFIX)
    if _is_complete(path):
        if path.read_bytes() == data or _reencoded(path) == data:
            return path
        raise FfcgsError(f"record {record.record_id} already has a part {path} with different content")
    files.atomic_write(path, lambda f: f.write(data))
    return path


def _reencoded(part: Path) -> bytes | None:
    """A finished part's bytes as this version writes them (None if it does not hold exactly one good record)."""
    try:
        records = list(iter_records(part))
    except FfcgsError:
        return None
    return part_bytes(records[0]) if len(records) == 1 else None


def part_done(parts_dir: str | Path, rid: str) -> bool:
    """Whether record `rid` has a finished part in `parts_dir` (one file looked at, not the whole folder)."""
    return _is_complete(Path(parts_dir) / (rid + PART_SUFFIX))


def done_records(parts_dir: str | Path) -> list[str]:
    """Ids of the finished parts in `parts_dir`, sorted (temporary and truncated files are not finished)."""
    parts_dir = Path(parts_dir)
    if not parts_dir.is_dir():
        return []
    return sorted(p.name[:-len(PART_SUFFIX)] for p in parts_dir.iterdir()
                  if p.name.endswith(PART_SUFFIX) and not p.name.startswith(".") and _is_complete(p))


def merge(parts_dir: str | Path, out_path: str | Path, expected: Iterable[str] | None = None) -> Path:
    """Write the single dataset MCAP from the finished parts, in record-id order (atomic; deterministic bytes).

    `expected` (record ids), if given, must equal the finished set: a missing or unexpected record is an error.
    Every part is decoded and checked before its payloads are copied; where the config's extra lists the build's
    objects with their `mesh_sha256` (`dataset build` does), a part of another object or geometry (from another
    build: a foreign part copied in) is refused, naming the part and the object."""
    parts_dir, out_path = Path(parts_dir), Path(out_path)
    cfg = parts_dir / CONFIG_NAME
    if not cfg.is_file():
        raise FfcgsError(f"{parts_dir} is not a parts directory (no {CONFIG_NAME})")
    config_text = cfg.read_text()
    hashes = build_objects(config_text, cfg)
    bad = [p.name for p in parts_dir.iterdir()
           if p.name.endswith(PART_SUFFIX) and not p.name.startswith(".") and not _is_complete(p)]
    if bad:
        raise FfcgsError(f"{parts_dir} has incomplete part(s) {', '.join(sorted(bad))}: delete them and resume "
                         f"the build")
    ids = done_records(parts_dir)
    if expected is not None:
        want = set(expected)
        missing, unexpected = sorted(want - set(ids)), sorted(set(ids) - want)
        if missing or unexpected:
            raise FfcgsError(f"{parts_dir}: missing record(s) {missing[:10]}, unexpected record(s) "
                             f"{unexpected[:10]}")

    def write(f):
        w, ch = new_writer(f, ("/config", "/sdf", "/grasps"))
        w.add_message(ch["/config"], log_time=0, publish_time=0, sequence=0, data=config_text.encode())
        for i, rid in enumerate(ids):
            part = parts_dir / (rid + PART_SUFFIX)
            pairs = [p for p in _pairs(part) if p[0] == "record"]
            if len(pairs) != 1:
                raise FfcgsError(f"part {part} holds {len(pairs)} records, expected 1")
            _, sdf, grasps = pairs[0]
            rec = _decode_record(part, sdf, grasps, i)
            if rec.record_id != rid:
                raise FfcgsError(f"part {part} holds record {rec.record_id!r}, not {rid!r}")
            if hashes is not None and hashes.get(rec.object_name) != rec.mesh_sha256:
                raise FfcgsError(foreign_part(part, rec, hashes))
            current = sdf.encoding == MESSAGE_ENCODINGS["/sdf"] and grasps.encoding == MESSAGE_ENCODINGS["/grasps"]
            sdf_data, grasp_data = (sdf.data, grasps.data) if current else _messages(rec)
            w.add_message(ch["/sdf"], log_time=i, publish_time=i, sequence=i, data=sdf_data)
            w.add_message(ch["/grasps"], log_time=i, publish_time=i, sequence=i, data=grasp_data)
        w.finish()

    files.atomic_write(out_path, write)
    return out_path


def build_objects(config_text: str, where: Path) -> dict[str, str] | None:
    """{object name: mesh_sha256} of the objects a parts directory's config lists (`extra.objects`), or None for
    a config without such a list (a writer used without `dataset build`, or a build older than the hashes)."""
    try:
        objects = json.loads(config_text).get("extra", {}).get("objects")
    except (ValueError, AttributeError) as e:
        raise FfcgsError(f"{where} does not describe a build ({type(e).__name__}: {e})") from None
    if not isinstance(objects, list) or not all(isinstance(o, dict) and isinstance(o.get("name"), str) and
                                                isinstance(o.get("mesh_sha256"), str) for o in objects):
        return None
    return {o["name"]: o["mesh_sha256"] for o in objects}


def foreign_part(part: Path, rec: Record, hashes: dict[str, str]) -> str:
    """The line that refuses a part of another build."""
    if rec.object_name not in hashes:
        return (f"part {part} holds object {rec.object_name!r}, which this build does not have: it comes from "
                f"another build; remove it and merge again")
    return (f"part {part} holds object {rec.object_name!r} with mesh_sha256 {rec.mesh_sha256[:12]}..., but this "
            f"build's {rec.object_name!r} has {hashes[rec.object_name][:12]}...: it comes from another build (another "
            f"mesh); remove it and rerun the build, which makes it again")


class DatasetWriter:
    """A resumable build of `out_path`: parts in `OUT.parts/`, then `finish()` merges.

        w = DatasetWriter("data.mcap", config)
        for rec in plan:                       # skip cheaply by id before computing: rid in w.done
            w.add(rec)
        w.finish()
    """

    def __init__(self, out_path: str | Path, config: dict, extra: dict | None = None):
        self.out_path = Path(out_path)
        self.parts_dir = init_parts(parts_dir_for(self.out_path), config, extra)
        self.done = set(done_records(self.parts_dir))

    def add(self, record: Record) -> bool:
        """Write the record's part; False (nothing written) if it was already finished."""
        if record.record_id in self.done:
            return False
        write_part(self.parts_dir, record)
        self.done.add(record.record_id)
        return True

    def finish(self, expected: Iterable[str] | None = None) -> Path:
        return merge(self.parts_dir, self.out_path, expected)


def read_config(path: str | Path) -> dict:
    """The /config message of a dataset file: {"version", "config", "extra"}."""
    path = Path(path)
    for kind, payload, _ in _pairs(path):
        if kind == "config":
            try:
                return json.loads(payload.data)
            except ValueError as e:
                raise FfcgsError(f"{path}: /config is not JSON: {e}") from None
        break
    raise FfcgsError(f"{path}: no /config message at the start of the file")


def iter_records(path: str | Path) -> Iterator[Record]:
    """Stream the records of a merged dataset file (or a part), in file order, `index` = position."""
    path = Path(path)
    i = 0
    for kind, sdf, grasps in _pairs(path):
        if kind == "record":
            yield _decode_record(path, sdf, grasps, i)
            i += 1


def shuffle_stream(items: Iterable, buffer_size: int, rng: np.random.Generator) -> Iterator:
    """Bounded-buffer shuffle: holds at most `buffer_size` items; a permutation of the input."""
    buf: list = []
    for item in items:
        if len(buf) < buffer_size:
            buf.append(item)
            continue
        j = int(rng.integers(buffer_size))
        out, buf[j] = buf[j], item
        yield out
    for j in rng.permutation(len(buf)):
        yield buf[j]


def _grasp_items(path: Path, rng: np.random.Generator | None, held_only: bool
                 ) -> Iterator[tuple[Record, int]]:
    """(record, grasp index) for every grasp (that holds, `Record.holds`, if `held_only`), records in file order,
    grasps permuted by `rng` unless None."""
    for rec in iter_records(path):
        idx = np.flatnonzero(rec.holds()) if held_only else np.arange(rec.num_grasps)
        for g in idx if rng is None else rng.permutation(idx):
            yield rec, int(g)


def batches(path: str | Path, batch_size: int, seed: int, shuffle_buffer: int = 4096, epochs: int = 1,
            drop_remainder: bool = False, held_only: bool = False) -> Iterator[dict[str, np.ndarray]]:
    """Batches of grasps (with `held_only`, only those that passed every protocol their record was labelled with,
    `Record.holds`: a labelled build's successes, what the learned sampler trains on), each paired with its
    record's SDF, as stacked numpy arrays:

        {"sdf": (B, R, R, R, 4) float32, "origin": (B, 3), "voxel_size": (B,), "table_z": (B,),
         "pose": (B, 4, 4), "q": (B, Q), "epsilon": (B,), "record": (B,) int64, "grasp": (B,) int64}

    Shuffling: per epoch e, a generator seeded with (seed, e) permutes each record's grasps and feeds them through
    a shuffle buffer of `shuffle_buffer` grasps (records stream in file order). Memory: at most `shuffle_buffer`
    grasps are held, plus the records they belong to (so at most shuffle_buffer + 1 records' SDFs), plus one batch;
    never the whole file. `shuffle_buffer=0` keeps file order. Each grasp appears exactly once per epoch; the last
    batch of an epoch is smaller unless `drop_remainder`. All SDFs must share one resolution R.
    """
    path = Path(path)
    for name, v, lo in (("batch_size", batch_size, 1), ("shuffle_buffer", shuffle_buffer, 0), ("epochs", epochs, 0)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
            raise FfcgsError(f"{name} must be an integer >= {lo}, got {v!r}")
    check_file(path, "dataset file")
    for epoch in range(epochs):
        rng = np.random.default_rng([int(seed), epoch])

        items = _grasp_items(path, rng if shuffle_buffer > 0 else None, held_only)
        stream = shuffle_stream(items, shuffle_buffer, rng) if shuffle_buffer > 1 else items
        batch: list = []
        shape = None
        for rec, g in stream:
            if shape is None:
                shape = rec.grid.shape
            elif rec.grid.shape != shape:
                raise FfcgsError(f"{path}: record {rec.record_id} has SDF grid {rec.grid.shape}, others {shape}; "
                                 f"batches need one resolution")
            batch.append((rec, g))
            if len(batch) == batch_size:
                yield _stack(batch)
                batch = []
        if batch and not drop_remainder:
            yield _stack(batch)


def _stack(batch: list) -> dict[str, np.ndarray]:
    return {"sdf": np.stack([r.grid for r, _ in batch]),
            "origin": np.stack([r.origin for r, _ in batch]),
            "voxel_size": np.array([r.voxel_size for r, _ in batch]),
            "table_z": np.array([r.table_z for r, _ in batch]),
            "pose": np.stack([r.wrist_pose[g] for r, g in batch]),
            "q": np.stack([r.q[g] for r, g in batch]),
            "epsilon": np.array([r.epsilon[g] for r, g in batch]),
            "record": np.array([r.index for r, _ in batch], dtype=np.int64),
            "grasp": np.array([g for _, g in batch], dtype=np.int64)}


_QUANTILES = {"min": 0.0, "q05": 0.05, "q25": 0.25, "median": 0.5, "q75": 0.75, "q95": 0.95, "max": 1.0}


def quantiles(x) -> dict | None:
    """{min, q05, q25, median, q75, q95, max, mean} of a 1-D array, or None when it is empty."""
    x = np.asarray(x, np.float64)
    return ({k: float(np.quantile(x, v)) for k, v in _QUANTILES.items()} | {"mean": float(x.mean())}) if x.size else None


def summary(path: str | Path) -> dict:
    """Counts and quality statistics of a dataset file (streams; keeps one float per grasp)."""
    path = Path(path)
    n_records, per_object, splits = 0, {}, {}
    eps, physics = [], {k: [0, 0] for k in PHYSICS_ARRAYS}  # [passed, evaluated]
    config = None
    for kind, first, grasps in _pairs(path):
        if kind == "config":
            config = json.loads(first.data)
            continue
        meta, ga = decode_message(grasps.data, grasps.encoding, f"{path} record {n_records} /grasps")
        if "object_name" not in meta or "split" not in meta or "epsilon" not in ga or ga["epsilon"].ndim != 1:
            raise FfcgsError(f"{path} record {n_records}: /grasps message lacks object_name, split or epsilon (G,)")
        g = int(ga["epsilon"].shape[0])
        n_records += 1
        per_object[meta["object_name"]] = per_object.get(meta["object_name"], 0) + g
        s = splits.setdefault(meta["split"], {"records": 0, "grasps": 0})
        s["records"] += 1
        s["grasps"] += g
        eps.append(ga["epsilon"])
        for k in PHYSICS_ARRAYS:
            if k in ga:
                physics[k][0] += int(ga[k].sum())
                physics[k][1] += int(ga[k].size)
    e = np.concatenate(eps) if eps else np.zeros(0)
    return {"version": None if config is None else config.get("version"),
            "records": n_records, "objects": len(per_object), "grasps": int(e.size),
            "grasps_per_object": dict(sorted(per_object.items())), "splits": dict(sorted(splits.items())),
            "epsilon": quantiles(e),
            **{f"{k}_rate": (p / n if n else None) for k, (p, n) in physics.items()},
            **{f"{k}_evaluated": n for k, (p, n) in physics.items()}}
