"""`ffcgs dataset export`: a dataset file to one stacked .npz or a folder of per-record .npz files, read back
without pickles and equal to the records; bad input refused with one line."""

import json
import re

import numpy as np
import pytest
from mcap.writer import Writer

from ffcgs_jax.core import files
from ffcgs_jax.cli import main as cli_main
from ffcgs_jax.dataset import export
from ffcgs_jax.dataset import mcap_io as dio
from ffcgs_jax.dataset import schema

from paths import DATA
from test_mcap_io import build, make_record, plan

V1_FILE = DATA / "dataset_v1.mcap"


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("ds") / "data.mcap"
    recs = plan()
    build(out, recs)
    return out, sorted(recs, key=lambda r: r.record_id)


def run(capsys, *argv):
    code = cli_main.main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def test_export_one_stacked_npz(dataset, tmp_path, capsys):
    path, recs = dataset
    out = tmp_path / "data.npz"
    code, stdout, err = run(capsys, "dataset", "export", str(path), "--out", str(out))
    assert code == 0, err
    assert stdout.strip() == f"wrote {out}: {len(recs)} records, {sum(r.num_grasps for r in recs)} grasps"
    with np.load(out) as z:  # allow_pickle=False: no object arrays anywhere
        a = {k: z[k] for k in z.files}
    assert str(a["format"]) == export.FORMAT and json.loads(str(a["config_json"])) == dio.read_config(path)
    assert list(a["record_id"]) == [r.record_id for r in recs]
    start = a["grasp_start"]
    assert start[0] == 0 and start[-1] == len(a["q"]) == len(a["grasp_record"])
    for n, rec in enumerate(recs):
        rows = slice(start[n], start[n + 1])
        assert (a["grasp_record"][rows] == n).all() and a["object_name"][n] == rec.object_name
        assert a["rotation_index"][n] == rec.rotation_index and np.array_equal(a["rotation"][n], rec.rotation)
        assert json.loads(a["info_json"][n]) == rec.info and a["split"][n] == rec.split
        for k in schema.SDF_ARRAYS:
            assert a[k].dtype == getattr(rec, k).dtype and np.array_equal(a[k][n], getattr(rec, k)), k
        for k in schema.GRASP_ARRAYS:
            assert a[k].dtype == getattr(rec, k).dtype and np.array_equal(a[k][rows], getattr(rec, k)), k
        for k in schema.PHYSICS_ARRAYS:  # one record of plan() has no physics results
            has = getattr(rec, k) is not None
            assert a[f"has_{k}"][n] == has and a[k].dtype == bool
            assert np.array_equal(a[k][rows], getattr(rec, k) if has else np.zeros(rec.num_grasps, bool)), k
    assert "wrist_pose_noisy" not in a  # no record has it


def test_export_folder_per_record_and_old_files(tmp_path, capsys):
    """A folder gets one npz per record (optional arrays only where present); an old-encoding file exports too."""
    from test_decoder import old_records

    recs = sorted(old_records(), key=lambda r: r.record_id)
    out = tmp_path / "records"
    code, stdout, err = run(capsys, "dataset", "export", str(V1_FILE), "--out", str(out))
    assert code == 0, err
    assert stdout.strip() == f"wrote 3 files to {out}: 3 records, 5 grasps"
    assert sorted(p.name for p in out.iterdir()) == [files.MANIFEST] + [f"{r.record_id}.npz" for r in recs]
    for rec in recs:
        with np.load(out / f"{rec.record_id}.npz") as z:
            a = {k: z[k] for k in z.files}
        assert str(a["record_id"]) == rec.record_id and str(a["category"]) == rec.category
        assert json.loads(str(a["info_json"])) == rec.info and str(a["format"]) == export.FORMAT
        for k, v in {**rec.sdf_arrays(), **rec.grasp_arrays()}.items():
            assert a[k].dtype == v.dtype and np.array_equal(a[k], v), k
        assert ("lift_shake_success" in a) == (rec.lift_shake_success is not None)
        assert ("wrist_pose_noisy" in a) == (rec.wrist_pose_noisy is not None)
    stacked = tmp_path / "v1.npz"
    export.export(V1_FILE, stacked)
    with np.load(stacked) as z:  # a record with wrist_pose_noisy: its rows, NaN for the others
        assert list(z["has_wrist_pose_noisy"]) == [r.wrist_pose_noisy is not None for r in recs]
        assert np.isnan(z["wrist_pose_noisy"][: z["grasp_start"][2]]).all()


def test_export_refuses_with_one_line(dataset, tmp_path, capsys):
    path, _ = dataset
    junk = tmp_path / "junk.mcap"
    junk.write_text("not an mcap file")
    log = tmp_path / "run.mcap"  # an MCAP, but not a dataset: the start of an `ffcgs grasp --mcap` log
    with open(log, "wb") as f:
        w = Writer(f)
        w.start()
        sid = w.register_schema(name="ffcgs.Config", encoding="jsonschema", data=b"{}")
        w.add_message(w.register_channel(topic="/config", message_encoding="json", schema_id=sid), log_time=0,
                      publish_time=0, data=b"{}")
        w.finish()
    mixed = tmp_path / "mixed.mcap"  # two SDF resolutions do not stack
    w = dio.DatasetWriter(mixed, {"mixed": True})
    w.add(make_record("a", 0, 2, seed=0))
    small = make_record("b", 0, 2, seed=1)
    w.add(schema.Record.create(**{**{k: getattr(small, k) for k in (
        "object_name", "mesh_sha256", "rotation_index", "rotation", "split", "origin", "voxel_size", "table_z",
        "wrist_pose", "q", "epsilon", "E", "E_g", "E_c")}, "grid": np.zeros((4, 4, 4, 4), np.float32)}))
    w.finish()
    (tmp_path / "plain").write_text("a file")
    for argv, message in [
        ([str(tmp_path / "missing.mcap"), "--out", "x.npz"], "dataset file not found: .*missing.mcap"),
        ([str(junk), "--out", str(tmp_path / "x.npz")], "junk.mcap is not an MCAP file"),
        ([str(log), "--out", str(tmp_path / "x.npz")], "run.mcap is not a dataset file .*ffcgs.Config"),
        ([str(tmp_path), "--out", str(tmp_path / "x.npz")], "is a folder"),
        ([str(mixed), "--out", str(tmp_path / "x.npz")], r"differ in SDF grid .*--out DIR"),
        ([str(path), "--out", str(tmp_path / "plain")], "plain is a file, not a folder"),
        ([str(path)], "--out"),
    ]:
        code, out, err = run(capsys, "dataset", "export", *argv)
        assert code == 2 and err.startswith("ffcgs: error:") and err.count("\n") == 1, (argv, err)
        assert re.search(message, err), (message, err)
    assert not (tmp_path / "x.npz").exists()
    code, _, err = run(capsys, "dataset", "export", str(mixed), "--out", str(tmp_path / "mixed"))
    assert code == 0 and len(list((tmp_path / "mixed").glob("*.npz"))) == 2  # a folder takes any resolution
