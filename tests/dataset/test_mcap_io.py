"""Dataset MCAP files: parts -> merge -> stream round trip, resumability, batching, summary, bad input."""

import gc
import hashlib
import json
import weakref

import numpy as np
import pytest

from ffcgs_jax.dataset import mcap_io as dio
from ffcgs_jax.dataset import schema
from ffcgs_jax.core.errors import FfcgsError

R = 8
CONFIG = {"rotations": 2, "sdf": {"resolution": R}, "seed": 3}


def _rotation(rng):
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def make_record(obj: str, rot: int, g: int, seed: int, physics: bool = True) -> schema.Record:
    rng = np.random.default_rng(seed)
    return schema.Record.create(
        object_name=obj, mesh_sha256=hashlib.sha256(obj.encode()).hexdigest(), rotation_index=rot,
        rotation=_rotation(rng), split="val" if obj.endswith("c") else "train",
        grid=rng.normal(size=(R, R, R, 4)).astype(np.float32), origin=rng.normal(size=3),
        voxel_size=np.float64(0.004), table_z=np.float64(-0.05), wrist_pose=rng.normal(size=(g, 4, 4)),
        q=rng.normal(size=(g, 9)), epsilon=rng.uniform(size=g), E=rng.normal(size=g), E_g=rng.normal(size=g),
        E_c=rng.normal(size=g),
        lift_shake_success=rng.uniform(size=g) < 0.7 if physics else None,
        six_dir_success=rng.uniform(size=g) < 0.4 if physics else None)


def plan():
    """6 records, in build order (not id order), with varied grasp counts (one empty, one without physics)."""
    specs = [("obj_b", 0, 5), ("obj_a", 1, 3), ("obj_a", 0, 4), ("obj b.c", 0, 0), ("obj_b", 1, 7),
             ("obj_c", 0, 6)]
    return [make_record(o, r, g, seed=i, physics=(i != 5)) for i, (o, r, g) in enumerate(specs)]


def build(out, records):
    w = dio.DatasetWriter(out, CONFIG, extra={"note": "test"})
    for rec in records:
        w.add(rec)
    return w.finish(expected=[r.record_id for r in records])


def assert_records_equal(a: schema.Record, b: schema.Record):
    for f in ("object_name", "mesh_sha256", "rotation_index", "split"):
        assert getattr(a, f) == getattr(b, f)
    for f in (*schema.SDF_ARRAYS, *schema.GRASP_ARRAYS, *schema.PHYSICS_ARRAYS, "rotation"):
        x, y = getattr(a, f), getattr(b, f)
        if x is None or y is None:
            assert x is None and y is None, f
        else:
            assert x.dtype == y.dtype and x.shape == y.shape and np.array_equal(x, y), f


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("ds") / "data.mcap"
    recs = plan()
    build(out, recs)
    return out, recs


def test_record_ids_deterministic_unique_and_safe():
    assert schema.record_id("obj_a", 3) == "obj_a.r0003"
    weird = schema.record_id("obj b.c", 0)
    assert weird == schema.record_id("obj b.c", 0) and weird.startswith("obj_b_c-") and "/" not in weird
    assert schema.record_id("obj b/c", 0) != weird  # same sanitised name, different hash
    ids = [r.record_id for r in plan()]
    assert len(set(ids)) == len(ids)


def test_round_trip_exact(dataset):
    out, recs = dataset
    got = list(dio.iter_records(out))
    want = sorted(recs, key=lambda r: r.record_id)
    assert [r.record_id for r in got] == [r.record_id for r in want]
    assert [r.index for r in got] == list(range(len(want)))
    for a, b in zip(got, want):
        assert_records_equal(a, b)
    cfg = dio.read_config(out)
    assert cfg == {"version": dio.__version__, "config": CONFIG, "extra": {"note": "test"}}


def test_merged_file_layout(dataset):
    from mcap.reader import make_reader

    out, recs = dataset
    with open(out, "rb") as f:
        msgs = [(c.topic, c.message_encoding, s.encoding, m.log_time) for s, c, m in
                make_reader(f).iter_messages(log_time_order=False)]
    assert msgs[0] == ("/config", "json", "jsonschema", 0)
    rest = msgs[1:]
    assert [t for t, *_ in rest] == ["/sdf", "/grasps"] * len(recs)
    assert [lt for *_, lt in rest] == [i for i in range(len(recs)) for _ in range(2)]
    assert all(e == schema.ARRAYS_ENCODING == "json" for _, e, _, _ in rest)


def test_resume_after_crash_equals_one_go(tmp_path, dataset):
    one_go, recs = dataset
    out = tmp_path / "data.mcap"
    parts = dio.parts_dir_for(out)
    w = dio.DatasetWriter(out, CONFIG, extra={"note": "test"})
    for rec in recs[:3]:
        w.add(rec)
    # crash: a stray temporary file and a truncated part under its final name
    (parts / f".{recs[3].record_id}.mcap.999.tmp").write_bytes(b"\x89MCAP0\r\npartial")
    full = dio.part_bytes(recs[4])
    (parts / f"{recs[4].record_id}.mcap").write_bytes(full[: len(full) // 2])
    assert dio.done_records(parts) == sorted(r.record_id for r in recs[:3])
    with pytest.raises(FfcgsError, match="incomplete part"):
        dio.merge(parts, tmp_path / "early.mcap")
    with pytest.raises(FfcgsError, match="different config"):
        dio.DatasetWriter(out, {**CONFIG, "seed": 4}, extra={"note": "test"})

    w2 = dio.DatasetWriter(out, CONFIG, extra={"note": "test"})  # resume: re-runs the whole plan
    written = [w2.add(rec) for rec in recs]
    assert written == [False, False, False, True, True, True]
    assert dio.write_part(parts, recs[0]) == parts / f"{recs[0].record_id}.mcap"  # identical: no-op
    with pytest.raises(FfcgsError, match="different content"):
        dio.write_part(parts, make_record("obj_b", 0, 2, seed=99))
    w2.finish(expected=[r.record_id for r in recs])
    assert sorted(p.name for p in parts.glob("*.mcap")) == sorted(r.record_id + ".mcap" for r in recs)
    assert out.read_bytes() == one_go.read_bytes()
    ids = [r.record_id for r in dio.iter_records(out)]
    assert ids == sorted(r.record_id for r in recs)
    with pytest.raises(FfcgsError, match="missing record"):
        dio.merge(parts, tmp_path / "x.mcap", expected=[*ids, "obj_z.r0000"])


def test_batches_deterministic_and_exactly_once(dataset):
    out, recs = dataset
    total = sum(r.num_grasps for r in recs)
    by_id = {r.record_id: r for r in recs}
    order = [r.record_id for r in dio.iter_records(out)]

    def run(seed, buf):
        return list(dio.batches(out, batch_size=4, seed=seed, shuffle_buffer=buf, epochs=2))

    a, b, c = run(0, 5), run(0, 5), run(1, 5)
    for x, y in zip(a, b, strict=True):
        assert x.keys() == y.keys() and all(np.array_equal(x[k], y[k]) for k in x)
    pairs = lambda bs: [(int(r), int(g)) for bt in bs for r, g in zip(bt["record"], bt["grasp"])]
    assert pairs(a) != pairs(c)
    per_epoch = pairs(a)
    assert len(per_epoch) == 2 * total
    expected = sorted((i, g) for i, rid in enumerate(order) for g in range(by_id[rid].num_grasps))
    assert sorted(per_epoch[:total]) == expected and sorted(per_epoch[total:]) == expected
    assert per_epoch[:total] != per_epoch[total:]  # epochs reshuffle
    bt = a[0]
    assert bt["sdf"].shape == (4, R, R, R, 4) and bt["sdf"].dtype == np.float32
    assert bt["pose"].shape == (4, 4, 4) and bt["q"].shape == (4, 9) and bt["record"].dtype == np.int64
    for bt in a:  # each grasp is paired with its own record's SDF and arrays
        for k in range(len(bt["record"])):
            rec = by_id[order[bt["record"][k]]]
            g = bt["grasp"][k]
            assert np.array_equal(bt["sdf"][k], rec.grid) and np.array_equal(bt["pose"][k], rec.wrist_pose[g])
            assert np.array_equal(bt["q"][k], rec.q[g]) and np.array_equal(bt["origin"][k], rec.origin)
    sizes = [len(bt["record"]) for bt in run(0, 0)]
    assert sum(sizes) == 2 * total and max(sizes) == 4
    no_shuffle = pairs(run(0, 0))[:total]
    assert no_shuffle == expected
    dropped = list(dio.batches(out, 4, seed=0, shuffle_buffer=5, drop_remainder=True))
    assert all(len(bt["record"]) == 4 for bt in dropped) and len(dropped) == total // 4


def test_shuffle_stream_memory_bounded():
    pulled = [0]

    def source(n):
        for i in range(n):
            pulled[0] += 1
            yield i

    rng = np.random.default_rng(0)
    seen = []
    for x in dio.shuffle_stream(source(1000), 16, rng):
        seen.append(x)
        assert pulled[0] - len(seen) <= 16
    assert sorted(seen) == list(range(1000)) and seen != list(range(1000))


def test_batches_hold_bounded_records(dataset, monkeypatch):
    out, recs = dataset
    real = dio.iter_records
    refs, pulled = [], [0]

    def counting(path):
        for rec in real(path):
            pulled[0] += rec.num_grasps
            refs.append(weakref.ref(rec))
            yield rec

    monkeypatch.setattr(dio, "iter_records", counting)
    buf, emitted, g_max = 3, 0, max(r.num_grasps for r in recs)
    for bt in dio.batches(out, batch_size=2, seed=0, shuffle_buffer=buf):
        emitted += len(bt["record"])
        gc.collect()
        alive = sum(r() is not None for r in refs)
        assert alive <= buf + 2  # records referenced by buffered grasps + the one being read
        assert pulled[0] - emitted <= buf + g_max  # grasps read but not yet emitted
    assert emitted == sum(r.num_grasps for r in recs)


def test_summary(dataset):
    out, recs = dataset
    s = dio.summary(out)
    assert s["records"] == 6 and s["objects"] == 4 and s["grasps"] == sum(r.num_grasps for r in recs)
    assert s["grasps_per_object"] == {"obj b.c": 0, "obj_a": 7, "obj_b": 12, "obj_c": 6}
    assert s["splits"] == {"train": {"records": 4, "grasps": 19}, "val": {"records": 2, "grasps": 6}}
    eps = np.concatenate([r.epsilon for r in recs])
    assert s["epsilon"]["median"] == pytest.approx(np.median(eps)) and s["epsilon"]["max"] == eps.max()
    phys = [r for r in recs if r.lift_shake_success is not None]
    assert s["lift_shake_success_evaluated"] == sum(r.num_grasps for r in phys)
    assert s["lift_shake_success_rate"] == pytest.approx(
        np.concatenate([r.lift_shake_success for r in phys]).mean())
    assert s["version"] == dio.__version__
    json.dumps(s)  # plain types only


def test_bad_input(tmp_path, dataset):
    out, _ = dataset
    with pytest.raises(FfcgsError, match="not found"):
        list(dio.iter_records(tmp_path / "missing.mcap"))
    with pytest.raises(FfcgsError, match="not found"):
        next(dio.batches(tmp_path / "missing.mcap", 2, seed=0))
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"hello, not an mcap file")
    with pytest.raises(FfcgsError, match="not an MCAP"):
        dio.summary(junk)
    truncated = tmp_path / "trunc.mcap"
    truncated.write_bytes(out.read_bytes()[:3000])
    with pytest.raises(FfcgsError, match="not a readable MCAP"):
        list(dio.iter_records(truncated))

    from mcap.writer import Writer  # an MCAP of the wrong schema
    wrong = tmp_path / "wrong.mcap"
    with open(wrong, "wb") as f:
        w = Writer(f)
        w.start()
        sid = w.register_schema(name="other", encoding="jsonschema", data=b"{}")
        ch = w.register_channel(topic="/sdf", message_encoding="json", schema_id=sid)
        w.add_message(ch, log_time=0, publish_time=0, data=b"{}")
        w.finish()
    with pytest.raises(FfcgsError, match="expected 'json' or 'ffcgs.arrays.v1' and 'ffcgs.DatasetSdf'"):
        list(dio.iter_records(wrong))

    with pytest.raises(FfcgsError, match=r"q must have shape \(G, Q\) with G = 3"):
        schema.Record.create(**{**_fields(make_record("o", 0, 3, 0)), "q": np.zeros((2, 9))})
    with pytest.raises(FfcgsError, match="grid must have shape"):
        schema.Record.create(**{**_fields(make_record("o", 0, 3, 0)), "grid": np.zeros((4, 4, 5, 4))})
    with pytest.raises(FfcgsError, match="rotation"):
        schema.Record.create(**{**_fields(make_record("o", 0, 3, 0)), "rotation": 2 * np.eye(3)})
    with pytest.raises(FfcgsError, match="mesh_sha256"):
        schema.Record.create(**{**_fields(make_record("o", 0, 3, 0)), "mesh_sha256": "abc"})
    with pytest.raises(FfcgsError, match="bad magic"):
        schema.decode_legacy(b"x" * 20)
    with pytest.raises(FfcgsError, match="not a readable"):
        schema.decode_message(b'{"meta": {}}')
    good = json.loads(schema.encode_message({}, {"a": np.zeros(3)}))
    with pytest.raises(FfcgsError, match=r"bad array 'a'.*24 bytes for shape \(2,\)"):
        schema.decode_message(json.dumps({**good, "arrays": {"a": {**good["arrays"]["a"], "shape": [2]}}}).encode())
    with pytest.raises(FfcgsError, match="bad array 'a'"):
        schema.decode_message(json.dumps({**good, "arrays": {"a": {**good["arrays"]["a"], "data": "!!"}}}).encode())
    with pytest.raises(FfcgsError, match="not an initialised parts"):
        dio.write_part(tmp_path / "nowhere", make_record("o", 0, 3, 0))
    with pytest.raises(FfcgsError, match="batch_size"):
        next(dio.batches(out, 0, seed=0))

    # a record whose arrays disagree in shape inside a well-formed file
    rec = make_record("o", 0, 3, 0)
    bad = tmp_path / "badshape.mcap"
    with open(bad, "wb") as f:
        w, ch = dio.new_writer(f, ("/sdf", "/grasps"))
        w.add_message(ch["/sdf"], log_time=0, publish_time=0, data=schema.encode_message(rec.meta(), rec.sdf_arrays()))
        ga = {**rec.grasp_arrays(), "q": np.zeros((2, 9))}
        w.add_message(ch["/grasps"], log_time=0, publish_time=0, data=schema.encode_message(rec.meta(), ga))
        w.finish()
    with pytest.raises(FfcgsError, match=r"q must have shape"):
        list(dio.iter_records(bad))


def _fields(rec):
    d = {f: getattr(rec, f) for f in ("object_name", "mesh_sha256", "rotation_index", "rotation", "split",
                                      *schema.SDF_ARRAYS, *schema.GRASP_ARRAYS, *schema.PHYSICS_ARRAYS)}
    return d


def test_importable_without_jax():
    import subprocess
    import sys

    code = ("import sys; sys.modules['jax'] = None; import ffcgs_jax.dataset.mcap_io as d; "
            "assert 'jax' not in [m for m in sys.modules if sys.modules[m] is not None]")
    subprocess.run([sys.executable, "-c", code], check=True)
