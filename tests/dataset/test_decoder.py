"""The dataset's message encoding read without this package's reader: mcap's own reader with our decoder factory,
plain JSON + base64, and the JSON schemas describing whole messages; and files of the older "ffcgs.arrays.v1"
encoding, which stay readable (tests/data/dataset_v1.mcap was written by that version's writer)."""

import base64
import dataclasses
import hashlib
import json
import shutil

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer

from ffcgs_jax.dataset import mcap_io as dio
from ffcgs_jax.dataset import schema
from ffcgs_jax.dataset.decoder import DecoderFactory
from ffcgs_jax.core.errors import FfcgsError

from paths import DATA
from test_mcap_io import assert_records_equal, build, plan

V1_FILE = DATA / "dataset_v1.mcap"
V1_CONFIG, V1_EXTRA = {"format": "v1 fixture"}, {"hand": "svh"}


def old_records() -> list[schema.Record]:
    """The records of tests/data/dataset_v1.mcap, written by `DatasetWriter(path, V1_CONFIG, extra=V1_EXTRA)` with
    the "ffcgs.arrays.v1" encoder (commit 83f089a), in this order."""
    out = []
    specs = [("old_a", 0, 3, True), ("old b", 1, 0, False), ("old_c", 0, 2, False)]
    for i, (name, rot, g, physics) in enumerate(specs):
        rng = np.random.default_rng(100 + i)
        R = 4
        out.append(schema.Record.create(
            object_name=name, mesh_sha256=hashlib.sha256(name.encode()).hexdigest(), rotation_index=rot,
            rotation=np.eye(3), split="train" if i != 2 else "val",
            grid=rng.normal(size=(R, R, R, 4)).astype(np.float32), origin=rng.normal(size=3),
            voxel_size=np.float64(0.01), table_z=np.float64(-0.02),
            wrist_pose=np.tile(np.eye(4), (g, 1, 1)) + rng.normal(size=(g, 4, 4)),
            q=rng.normal(size=(g, 9)), epsilon=rng.uniform(size=g), E=rng.normal(size=g), E_g=rng.normal(size=g),
            E_c=rng.normal(size=g), lift_shake_success=rng.uniform(size=g) < 0.5 if physics else None,
            six_dir_success=rng.uniform(size=g) < 0.5 if physics else None,
            wrist_pose_noisy=np.tile(np.eye(4), (g, 1, 1)) if i == 2 else None,
            category="mug" if i == 0 else "", info={"note": "v1"} if i == 0 else None))
    return out


def _by_id(records):
    return sorted(records, key=lambda r: r.record_id)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("ds") / "data.mcap"
    recs = plan()
    build(out, recs)
    return out, _by_id(recs)


def decoded(path):
    with open(path, "rb") as f:
        return [(c.topic, s.name, c.message_encoding, d) for s, c, _, d in
                make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages(log_time_order=False)]


def check_decoded(path, records):
    """mcap's reader with our factory gives /config as a dict and each record's /sdf, /grasps as meta + numpy
    arrays equal to the records."""
    msgs = decoded(path)
    assert msgs[0][0] == "/config" and msgs[0][3] == dio.read_config(path)
    rest = msgs[1:]
    assert [t for t, *_ in rest] == ["/sdf", "/grasps"] * len(records)
    for rec, (sdf, grasps) in zip(records, zip(rest[::2], rest[1::2]), strict=True):
        for (_, name, _, d), want in ((sdf, rec.sdf_arrays()), (grasps, rec.grasp_arrays())):
            assert d["meta"] == rec.meta() and d["meta"]["record_id"] == rec.record_id, name
            assert d["arrays"].keys() == want.keys(), name
            for k, v in want.items():
                assert d["arrays"][k].dtype == v.dtype and np.array_equal(d["arrays"][k], v), (name, k)
    return msgs


def test_mcap_reader_decodes_with_our_factory(dataset):
    out, recs = dataset
    msgs = check_decoded(out, recs)
    assert {(name, enc) for _, name, enc, _ in msgs} == {("ffcgs.DatasetConfig", "json"), ("ffcgs.DatasetSdf", "json"),
                                                         ("ffcgs.DatasetGrasps", "json")}
    assert DecoderFactory().decoder_for("json", None) is None  # another channel: left to other factories


def test_plain_json_reader_and_whole_message_schemas(dataset):
    """No package code: json + base64 + numpy read a record, and the channel's JSON schema validates whole
    messages (and refuses a message without its arrays' data)."""
    jsonschema = pytest.importorskip("jsonschema")
    out, recs = dataset
    with open(out, "rb") as f:
        raw = [(c.topic, json.loads(s.data), json.loads(m.data)) for s, c, m in
               make_reader(f).iter_messages(log_time_order=False)]
    for topic, sch, msg in raw:
        jsonschema.Draft202012Validator.check_schema(sch)
        jsonschema.validate(msg, sch)
        assert sch == json.loads(json.dumps(schema.SCHEMAS[topic]))
    _, sch, grasps = raw[2]
    a = grasps["arrays"]["wrist_pose"]
    pose = np.frombuffer(base64.b64decode(a["data"]), a["dtype"]).reshape(a["shape"])
    assert grasps["meta"]["record_id"] == recs[0].record_id and np.array_equal(pose, recs[0].wrist_pose)
    broken = json.loads(json.dumps(grasps))
    del broken["arrays"]["q"]["data"]
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(broken, sch)
    with pytest.raises(jsonschema.ValidationError):  # an unknown array
        jsonschema.validate({**grasps, "arrays": {**grasps["arrays"], "extra": a}}, sch)


def test_old_format_file_stays_readable():
    recs = old_records()
    with open(V1_FILE, "rb") as f:
        encodings = {c.topic: c.message_encoding for _, c, _ in make_reader(f).iter_messages()}
    assert encodings == {"/config": "json", "/sdf": schema.LEGACY_ENCODING, "/grasps": schema.LEGACY_ENCODING}
    got = list(dio.iter_records(V1_FILE))
    assert [r.record_id for r in got] == [r.record_id for r in _by_id(recs)]
    for a, b in zip(got, _by_id(recs), strict=True):
        assert_records_equal(a, b)
        assert a.category == b.category and a.info == b.info
        assert (a.wrist_pose_noisy is None) == (b.wrist_pose_noisy is None)
    assert dio.read_config(V1_FILE)["config"] == V1_CONFIG
    s = dio.summary(V1_FILE)
    assert s["records"] == 3 and s["grasps"] == 5 and s["lift_shake_success_evaluated"] == 3
    assert sum(len(b["record"]) for b in dio.batches(V1_FILE, 2, seed=0)) == 5
    check_decoded(V1_FILE, _by_id(recs))  # the decoder factory reads the old encoding too


def _old_parts(parts_dir):
    """A parts folder as the old version left it: one part per record of dataset_v1.mcap, its payloads and
    schemas copied byte for byte."""
    dio.init_parts(parts_dir, V1_CONFIG, V1_EXTRA)
    with open(V1_FILE, "rb") as f:
        msgs = [(s, c, m) for s, c, m in make_reader(f).iter_messages(log_time_order=False) if c.topic != "/config"]
    for (s1, c1, m1), (s2, c2, m2) in zip(msgs[::2], msgs[1::2]):
        rid = json.loads(m1.data[12:12 + int.from_bytes(m1.data[8:12], "little")])["meta"]["record_id"]
        with open(parts_dir / f"{rid}.mcap", "wb") as f:
            w = Writer(f)
            w.start()
            for s, c, m in ((s1, c1, m1), (s2, c2, m2)):
                sid = w.register_schema(name=s.name, encoding=s.encoding, data=s.data)
                ch = w.register_channel(topic=c.topic, message_encoding=c.message_encoding, schema_id=sid)
                w.add_message(ch, log_time=0, publish_time=0, data=m.data)
            w.finish()


def test_build_resumed_over_old_parts_writes_the_new_encoding(tmp_path):
    """A build begun by the old version and finished by this one: the old parts count as done, writing the same
    record again is a no-op, and the merged file is in the new encoding, byte-identical to a build done now."""
    recs = old_records()
    out = tmp_path / "resumed.mcap"
    _old_parts(dio.parts_dir_for(out))
    w = dio.DatasetWriter(out, V1_CONFIG, extra=V1_EXTRA)
    assert w.done == {r.record_id for r in recs}
    assert dio.write_part(w.parts_dir, recs[0]).read_bytes()[:8] == b"\x89MCAP0\r\n"  # no-op, no error
    with pytest.raises(FfcgsError, match="different content"):
        dio.write_part(w.parts_dir, dataclasses.replace(recs[0], epsilon=np.zeros(3)))
    w.finish(expected=[r.record_id for r in recs])
    with open(out, "rb") as f:
        assert {c.message_encoding for _, c, _ in make_reader(f).iter_messages()} == {"json"}
    fresh = tmp_path / "fresh.mcap"
    dw = dio.DatasetWriter(fresh, V1_CONFIG, extra=V1_EXTRA)
    for r in recs:
        dw.add(r)
    dw.finish()
    assert out.read_bytes() == fresh.read_bytes()
    shutil.rmtree(dio.parts_dir_for(out))
