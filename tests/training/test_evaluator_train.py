"""Training the success predictor (`training/evaluator_train.py`, `training/evaluator_data.py`): a known rule
learnt on held-out objects, folds by object, resumption, the labelled-file path through `ffcgs train --model
evaluator` (its features are the inference path's), sweeps and cross-validation, and the files it refuses."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ffcgs_jax.cli import train_command
from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.dataset import mcap_io as dio
from ffcgs_jax.dataset import schema
from ffcgs_jax.geometry import mesh_io
from ffcgs_jax.geometry import sdf as sdf_mod
from ffcgs_jax.geometry.config import SDFConfig
from ffcgs_jax.learning import checkpoint, evaluator
from ffcgs_jax.learning.config import EvaluatorNetConfig
from ffcgs_jax.learning.weights import load_evaluator
from ffcgs_jax.physics.protocols import wilson
from ffcgs_jax.synthesis import prediction
from ffcgs_jax.training import evaluator_data, evaluator_train
from ffcgs_jax.training.config import CVConfig, EvaluatorDataConfig, EvaluatorOptimConfig, EvaluatorTrainConfig

from evaluator_toy import grasps, write_labelled


@pytest.fixture(scope="module")
def box_sdf():
    return sdf_mod.build_sdf(mesh_io.load_mesh("box"), SDFConfig(res=16))


def synthetic(n_obj=12, per=40, width=6, seed=0) -> evaluator_data.LabelData:
    """A known rule: passing = x0 + 0.5 x1 > 0 (head 0), x2 > 0 (head 1), both (head "all")."""
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n_obj * per, width)).astype(np.float32)
    y0, y1 = x[:, 0] + 0.5 * x[:, 1] > 0, x[:, 2] > 0
    y = np.stack([y0, y1, y0 & y1], 1).astype(np.float32)
    objs = np.repeat([f"o{i:02d}" for i in range(n_obj)], per)
    return evaluator_data.LabelData(x, y, objs, np.ones(len(x), bool), rng.normal(size=len(x)),
                                    ("lift_shake", "six_dir", "all"), np.full(len(x), "train"))


def cfg_for(tmp_path, name, **kw) -> EvaluatorTrainConfig:
    return EvaluatorTrainConfig(out=str(tmp_path / name), hand="svh", data=EvaluatorDataConfig("unused.mcap"),
                                net=EvaluatorNetConfig(hidden=32, depth=2),
                                optim=EvaluatorOptimConfig(lr=3e-3, epochs=kw.pop("epochs", 25), batch=32,
                                                           weight_decay=0.0),
                                cv=CVConfig(folds=3, fold=kw.pop("fold", 0)), **kw)


def test_training_recovers_a_known_rule_on_held_out_objects(tmp_path):
    data = synthetic()
    s = evaluator_train.train(cfg_for(tmp_path, "rule"), progress=False, data=data)
    assert s["val_auc_lift_shake"] > 0.97 and s["val_auc_six_dir"] > 0.97 and s["val_auc_all"] > 0.97
    assert s["val_within_auc_valid"] > 0.95
    # the folds hold whole objects: no object is on both sides
    assert s["val_objects"] and not set(s["val_objects"]) & set(data.objects[~np.isin(data.objects,
                                                                                       s["val_objects"])])
    assert s["train_objects"] + len(s["val_objects"]) == 12
    assert (tmp_path / "rule" / "metrics.png").is_file() and (tmp_path / "rule" / "weights.npz").is_file()


def test_every_object_is_held_out_exactly_once_across_folds(tmp_path):
    data = synthetic(n_obj=7, per=20)
    held = []
    for k in range(3):
        s = evaluator_train.train(cfg_for(tmp_path, f"f{k}", fold=k, epochs=1), progress=False, data=data)
        held += s["val_objects"]
    assert sorted(held) == sorted(set(data.objects.tolist()))


def test_a_resumed_run_equals_an_uninterrupted_one(tmp_path):
    data = synthetic(n_obj=6, per=30)
    whole = evaluator_train.train(cfg_for(tmp_path, "a", epochs=4), progress=False, data=data)
    assert evaluator_train.train(cfg_for(tmp_path, "b", epochs=4), progress=False, data=data, until_epoch=2) is None
    resumed = evaluator_train.train(cfg_for(tmp_path, "b", epochs=4), progress=False, data=data)
    wa, _ = checkpoint.load(tmp_path / "a" / "weights.npz")
    wb, _ = checkpoint.load(tmp_path / "b" / "weights.npz")
    for x, y in zip(jax.tree.leaves(wa), jax.tree.leaves(wb)):
        np.testing.assert_array_equal(x, y)
    assert whole["train_auc_all"] == resumed["train_auc_all"]


@pytest.mark.e2e  # over 20 s on the 2-core CPU: kept out of plain `pytest` (README)
def test_ffcgs_train_model_evaluator_on_a_labelled_file(tmp_path, svh, box_sdf, capsys):
    f = write_labelled(tmp_path / "labels.mcap", svh, box_sdf)
    data = evaluator_data.load(f, svh, progress=False)
    assert data.heads == ("lift_shake", "six_dir", "all") and data.x.shape == (96, evaluator.feature_width(svh))
    # the training path's features are the inference path's: the same numbers give the same predictions
    out = tmp_path / "run"
    rc = train_command.main(["--model", "evaluator", "--data.path", str(f), "--cv.fold", "-1", "--optim.epochs",
                             "2", "--optim.batch", "16", "--net.hidden", "16", "--out", str(out)])
    assert rc == 0, capsys.readouterr().err
    weights, meta = load_evaluator(out / "weights.npz", svh)
    assert meta["heads"] == ["lift_shake", "six_dir", "all"]
    rec = next(iter(dio.iter_records(f)))
    arrays = rec.grasp_arrays()
    sdf = sdf_mod.GradientSDF(*(jnp.asarray(getattr(rec, k), jnp.float32)
                                for k in ("grid", "origin", "voxel_size", "table_z")))
    pred = prediction.predictions(weights, meta, svh, sdf, arrays)
    rows = evaluator_train.predict_rows(weights, data.x[:24])
    np.testing.assert_allclose(pred["pred_success"], rows[:, -1], atol=1e-5)
    np.testing.assert_allclose(pred["pred_six_dir"], rows[:, 1], atol=1e-5)


@pytest.mark.e2e  # 25-38 s on the 2-core CPU: kept out of plain `pytest` (README)
def test_a_sweep_from_the_command_line_writes_its_table(tmp_path, svh, box_sdf, capsys):
    f = write_labelled(tmp_path / "labels.mcap", svh, box_sdf, n_obj=3, per=16)
    out = tmp_path / "sweep"
    rc = train_command.main(["--model=evaluator", "--data.path", str(f), "--cv.folds", "3", "--optim.epochs", "1",
                             "--optim.batch", "8", "--net.hidden", "8", "--out", str(out),
                             "--sweep", "optim.weight_decay=0,2"])
    assert rc == 0, capsys.readouterr().err
    table = (out / "sweep.md").read_text().splitlines()
    assert table[0].startswith("| optim.weight_decay | val within-object AUC") and len(table) == 4
    assert (out / "sweep" / "optim.weight_decay=2.0" / "weights.npz").is_file()
    rc = train_command.main(["--model", "evaluator", "--data.path", str(f), "--cv.folds", "3", "--cv.all",
                             "--optim.epochs", "1", "--optim.batch", "8", "--net.hidden", "8", "--out", str(tmp_path / "cv")])
    assert rc == 0, capsys.readouterr().err
    cv = (tmp_path / "cv" / "cv.md").read_text()
    assert cv.count("\n| ") == 3 and "over 3 folds: within-object AUC" in cv  # a row per fold
    assert train_command.main(["--model", "critic", "--data.path", str(f)]) == 2
    assert "unknown --model 'critic'" in capsys.readouterr().err


def test_test_split_records_are_refused(tmp_path, svh, box_sdf):
    f = write_labelled(tmp_path / "t.mcap", svh, box_sdf, split="test", n_obj=2, per=4)
    with pytest.raises(FfcgsError, match="test-split"):
        evaluator_data.load(f, svh, progress=False)


def test_unlabelled_files_are_refused(tmp_path, svh, box_sdf):
    w = dio.DatasetWriter(tmp_path / "u.mcap", {"hand": "svh"}, extra={})
    a = grasps(svh, 3, seed=0)
    rec = schema.Record.create(object_name="u", mesh_sha256="0" * 64, rotation_index=0, rotation=np.eye(3),
                               split="train", sdf=box_sdf, wrist_pose=a["wrist_pose"], q=a["q"], epsilon=a["epsilon"],
                               E=a["E"], E_g=a["E_g"], E_c=a["E_c"])
    w.add(rec)
    f = w.finish(expected=[rec.record_id])
    with pytest.raises(FfcgsError, match="keep all"):
        evaluator_data.load(f, svh, progress=False)


def test_robust_records_give_rates_as_targets_and_holds_as_positives():
    rng = np.random.default_rng(3)
    trials = {p: rng.random((20, 8)) < q for p, q in (("lift_shake", 0.9), ("six_dir", 0.6), ("dexgraspbench", 0.8))}
    arrays = {}
    for p, t in trials.items():
        passed = t.sum(1)
        lo, _ = wilson(passed, 8, 0.9)
        arrays.update({f"{p}_trials": t, f"{p}_rate": passed / 8, f"{p}_success": lo >= 0.5})
    keys = [f"{p}_success" for p in trials]
    y, hit = evaluator_data.targets(arrays, keys)
    np.testing.assert_allclose(y[:, :3], np.stack([trials[p].mean(1) for p in trials], 1), atol=1e-7)
    # "all" is lift-shake and six-dir passed in the same trial; DexGraspBench is its own head, not part of it
    joint = (trials["lift_shake"] & trials["six_dir"]).sum(1)
    np.testing.assert_allclose(y[:, 3], joint / 8, atol=1e-7)
    assert hit[:, 3].tolist() == (joint >= 7).tolist()  # the 7-of-8 rule at the default confidence
    assert hit[:, :3].tolist() == np.stack([arrays[k] for k in keys], 1).tolist()
    # a single-trial record: its outcomes, 0/1, as before (and "all" over lift-shake and six-dir only)
    single = {k: arrays[k] for k in keys}
    y1, hit1 = evaluator_data.targets(single, keys)
    assert set(np.unique(y1)) <= {0.0, 1.0} and (y1 > 0.5).tolist() == hit1.tolist()
    assert hit1[:, 3].tolist() == (single["lift_shake_success"] & single["six_dir_success"]).tolist()
