"""Training the CVAE (`training/train.py`, `training/data.py`, `python -m train.sampler`) on a toy dataset, and
the cvae sampler behind `synthesis.samplers.make_sampler` / `synthesize`."""

import dataclasses
import json
import subprocess
import sys

import jax
import numpy as np
import pytest

from ffcgs_jax.core.config import load
from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.hand import kinematics as K
from ffcgs_jax.learning import checkpoint
from ffcgs_jax.training import data as cvae_data
from ffcgs_jax.training import train as cvae_train
from ffcgs_jax.learning.config import ModelConfig
from ffcgs_jax.training.config import CVConfig, DataConfig, TrainConfig, TrainOptimConfig, to_toml
from ffcgs_jax.training.run import dataset_hand

from cvae_toy import make_toy_dataset
from paths import REPO

pytestmark = pytest.mark.e2e  # training runs end to end (compiles the CVAE's steps)

MODEL = ModelConfig(res=8, width=2, features=4, head=4, mlp=8, latent=2)
TINY = ["--model.res", "8", "--model.width", "2", "--model.features", "4", "--model.head", "4", "--model.mlp", "8"]


@pytest.fixture(scope="module")
def toy(tmp_path_factory):
    return make_toy_dataset(tmp_path_factory.mktemp("toy") / "toy.mcap", n_objects=5, grasps=8)


def config(toy, out, **kw) -> TrainConfig:
    base = TrainConfig(out=str(out), log_every=2, steps_per_call=3, model=MODEL,
                       optim=TrainOptimConfig(lr=3e-3, batch=8, epochs=2), data=DataConfig(path=str(toy)),
                       cv=CVConfig(fold=0))
    return dataclasses.replace(base, **kw)


def test_data_split_by_object_and_batches(toy):
    data = cvae_data.load(toy)
    assert data.grids.shape == (5, 8, 8, 8, 4) and len(data.pose) == 5 * 8 * 2 and data.noisy.sum() == 40
    seen = set()
    for fold in range(5):
        tr, va = cvae_data.split(data, 5, fold, seed=0)
        assert not set(data.objects[tr]) & set(data.objects[va])
        assert len(tr) + len(va) == 5
        seen |= set(data.objects[va])
    assert seen == set(data.objects)  # every object is validated exactly once over the folds
    tr, _ = cvae_data.split(data, 5, 0, seed=0)
    rng = np.random.default_rng(0)
    recs, grasps = cvae_data.epoch_batches(data, tr, 8, 1, rng)
    assert grasps.shape == (len(data.grasps_of(tr)) // 8, 8, 1)
    assert len(np.unique(grasps)) == grasps.size  # without replacement
    recs4, grasps4 = cvae_data.epoch_batches(data, tr, 8, 4, rng)
    assert grasps4.shape[1:] == (2, 4) and np.all(data.record[grasps4] == recs4[..., None])  # groups share an SDF
    assert len(recs4) == cvae_data.steps_per_epoch(data, tr, 8, 4)


def test_tiny_training_lowers_the_loss(toy, tmp_path):
    cfg = config(toy, tmp_path / "run", optim=TrainOptimConfig(lr=3e-3, batch=8, epochs=5), kl=dataclasses.replace(
        TrainConfig().kl, beta_max=0.0))
    summary = cvae_train.train(cfg, progress=False)
    steps, epochs = cvae_train.read_metrics(tmp_path / "run" / "metrics.jsonl")
    first, last = steps[0]["rec"], np.mean([r["rec"] for r in steps[-3:]])
    assert last < 0.8 * first, (first, last)
    assert len(epochs) == 5 and all("val_rec" in r for r in epochs)
    for name in ("config.toml", "metrics.png", "checkpoint.npz", "weights.npz", "summary.json"):
        assert (tmp_path / "run" / name).is_file(), name
    assert load(TrainConfig, tmp_path / "run" / "config.toml") == cfg  # the resolved config reloads to itself
    assert summary["val_objects"] and not set(summary["val_objects"]) & set(summary["train_objects"])


def test_resume_equals_uninterrupted(toy, tmp_path):
    one = cvae_train.train(config(toy, tmp_path / "a"), progress=False)
    assert cvae_train.train(config(toy, tmp_path / "b"), progress=False, until_epoch=1) is None  # "interrupted"
    assert not (tmp_path / "b" / "weights.npz").exists()
    two = cvae_train.train(config(toy, tmp_path / "b"), progress=False)
    pa, _ = checkpoint.load(tmp_path / "a" / "weights.npz")
    pb, _ = checkpoint.load(tmp_path / "b" / "weights.npz")
    jax.tree.map(np.testing.assert_array_equal, pa, pb)
    assert one["val_rec"] == two["val_rec"]
    la = (tmp_path / "a" / "metrics.jsonl").read_text().splitlines()
    lb = (tmp_path / "b" / "metrics.jsonl").read_text().splitlines()
    strip = lambda lines: [{k: v for k, v in json.loads(x).items() if k != "elapsed_s"} for x in lines]  # noqa: E731
    assert strip(la) == strip(lb)  # nothing lost, nothing duplicated


def test_a_sweep_over_the_step_size_and_epochs_compiles_once(toy, tmp_path):
    """lr is traced and the epochs never reach the step: a sweep's points share one executable, yet each trains
    with its own step size."""
    cvae_train.train(config(toy, tmp_path / "a"), progress=False)
    compiled = cvae_train.train_steps._cache_size()
    cvae_train.train(config(toy, tmp_path / "b", optim=TrainOptimConfig(lr=1e-4, batch=8, epochs=3)), progress=False)
    assert cvae_train.train_steps._cache_size() == compiled
    pa, _ = checkpoint.load(tmp_path / "a" / "weights.npz")
    pb, _ = checkpoint.load(tmp_path / "b" / "weights.npz")
    assert any(not np.array_equal(a, b) for a, b in zip(jax.tree.leaves(pa), jax.tree.leaves(pb)))


def test_run_folder_with_other_config_is_refused(toy, tmp_path):
    cvae_train.train(config(toy, tmp_path / "r", optim=TrainOptimConfig(lr=3e-3, batch=8, epochs=1)), progress=False)
    with pytest.raises(FfcgsError, match="different config"):
        cvae_train.train(config(toy, tmp_path / "r", seed=3), progress=False)


def test_config_toml_round_trip_and_bad_values(tmp_path):
    cfg = TrainConfig(out="x y/\"q\"", optim=TrainOptimConfig(lr=3e-4), cv=CVConfig(all=True))
    (tmp_path / "c.toml").write_text(to_toml(cfg))
    assert load(TrainConfig, tmp_path / "c.toml") == cfg
    for text, match in (("[optim]\nlr = -1.0\n", "optim.lr"), ("[model]\nres = 12\n", "multiple of 8"),
                        ("[cv]\nfold = 5\n", "cv.fold"), ("[optim]\nlearning_rate = 1.0\n", "unknown config key"),
                        ("[data]\ngrasps_per_sdf = 3\n", "multiple of data.grasps_per_sdf")):
        (tmp_path / "bad.toml").write_text(text)
        with pytest.raises(FfcgsError, match=match):
            load(TrainConfig, tmp_path / "bad.toml")


def test_bad_dataset(tmp_path):
    with pytest.raises(FfcgsError, match="dataset file not found"):
        cvae_data.load(tmp_path / "none.mcap")
    small = make_toy_dataset(tmp_path / "s.mcap", n_objects=2, grasps=2)
    with pytest.raises(FfcgsError, match="at least 5 objects"):
        cvae_data.split(cvae_data.load(small), 5, 0, 0)


def _script(args, cwd):
    return subprocess.run([sys.executable, "-m", "train.sampler", *args], cwd=cwd, capture_output=True, text=True,
                          env={"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin", "JAX_PLATFORMS": "cpu"},
                          timeout=600)


@pytest.mark.slow  # a training run in a fresh process compiles the step (~30 s on 2 cores); CI runs near its budget
def test_script_sweep(toy, tmp_path):
    r = _script(["--config", str(REPO / "configs" / "sampler.toml"), "--data.path", str(toy), "--out",
                 str(tmp_path / "sw"), "--optim.epochs", "1", "--optim.batch", "8", "--steps_per_call", "4", *TINY,
                 "--sweep", "optim.lr=1e-3,3e-3"], REPO)
    assert r.returncode == 0, r.stderr[-2000:]
    table = (tmp_path / "sw" / "sweep.md").read_text().splitlines()
    assert len(table) == 4 and "| 0.001 |" in table[2] and "| 0.003 |" in table[3]
    for lr in ("0.001", "0.003"):
        run = tmp_path / "sw" / "sweep" / f"optim.lr={lr}"
        assert load(TrainConfig, run / "config.toml").optim.lr == float(lr)
        assert (run / "weights.npz").is_file()


def test_script_errors(tmp_path):
    r = _script(["--optim.learning_rate", "1"], REPO)
    assert r.returncode != 0 and "learning_rate" in r.stderr and "Traceback" not in r.stderr
    r = _script(["--data.path", str(tmp_path / "missing.mcap"), "--out", str(tmp_path / "m")], REPO)
    assert r.returncode == 2 and "dataset file not found" in r.stderr and "Traceback" not in r.stderr
    r = _script(["--sweep", "optim.nope=1,2"], REPO)
    assert r.returncode == 2 and "unknown sweep key" in r.stderr


def test_cross_validation_runs_every_fold(toy, tmp_path):
    from train.sampler import run_cv

    cfg = config(toy, tmp_path / "cv", optim=TrainOptimConfig(lr=3e-3, batch=8, epochs=1), cv=CVConfig(all=True))
    out = run_cv(cfg)
    cv = (tmp_path / "cv" / "cv.md").read_text()
    assert sum(line[:3] in {f"| {k}" for k in range(5)} for line in cv.splitlines()) == 5  # one row per fold
    held = [json.loads((tmp_path / "cv" / f"fold{k}" / "summary.json").read_text())["val_objects"] for k in range(5)]
    assert sorted(sum(held, [])) == [f"toy{i}" for i in range(5)]  # each object validated once
    assert out["val_rec"] == pytest.approx(np.mean([json.loads((tmp_path / "cv" / f"fold{k}" / "summary.json")
                                                               .read_text())["val_rec"] for k in range(5)]))


# ---------------------------------------------------------------------------------------------------------------
# The cvae sampler in the pipeline
# ---------------------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def weights32(tmp_path_factory):
    """An untrained res-32 network in the weights format (the sampler's contract does not depend on training)."""
    from ffcgs_jax.learning import cvae

    cfg = TrainConfig(model=ModelConfig(width=2, features=4, head=4, mlp=8))
    params = jax.tree.map(lambda x: np.asarray(x, np.float32), cvae.init(jax.random.key(0), cfg.model))
    path = tmp_path_factory.mktemp("w") / "weights.npz"
    checkpoint.save(path, {"params": params}, cvae_train.weights_meta(cfg, K.load_hand("svh"), {}))
    return path


def test_cvae_sampler_contract(svh, weights32, tmp_path):
    from ffcgs_jax.geometry import mesh_io, sdf
    from ffcgs_jax.geometry.config import SDFConfig
    from ffcgs_jax.synthesis import samplers
    from ffcgs_jax.synthesis.config import SamplerConfig

    grid = sdf.build_sdf(mesh_io.load_mesh("box"), SDFConfig(res=32))
    sample = samplers.make_sampler("cvae", svh, SamplerConfig(weights=str(weights32)))
    a = np.asarray(sample(jax.random.key(0), grid, 6))
    assert a.shape == (6, 4, 4)
    np.testing.assert_allclose(a[:, :3, :3] @ np.swapaxes(a[:, :3, :3], 1, 2), np.broadcast_to(np.eye(3), (6, 3, 3)),
                               atol=1e-6)
    np.testing.assert_array_equal(a, np.asarray(sample(jax.random.key(0), grid, 6)))  # a key fixes the output
    assert not np.array_equal(a, np.asarray(sample(jax.random.key(1), grid, 6)))
    # another resolution is resampled to the network's 32^3 (the poses then match those of a 32^3 build closely)
    b16 = np.asarray(sample(jax.random.key(0), sdf.build_sdf(mesh_io.load_mesh("box"), SDFConfig(res=16)), 6))
    assert b16.shape == (6, 4, 4) and np.isfinite(b16).all()
    with pytest.raises(FfcgsError, match="weights file not found"):
        samplers.make_sampler("cvae", svh, SamplerConfig(weights=str(tmp_path / "none.npz")))
    np.savez(tmp_path / "other.npz", __meta__=np.frombuffer(b'{"format": "x"}', np.uint8))
    with pytest.raises(FfcgsError, match="not a CVAE weights file"):
        samplers.make_sampler("cvae", svh, SamplerConfig(weights=str(tmp_path / "other.npz")))


@pytest.mark.slow  # cvae inside synthesize runs in the default suite anyway (the default sampler: test_grasp,
# test_cli_grasp); this adds a non-default weights file, for another ~30 s compile
def test_cvae_sampler_in_synthesize(svh, weights32):
    from ffcgs_jax.geometry import mesh_io
    from ffcgs_jax.synthesis.config import GraspConfig, OptimConfig, SamplerConfig
    from ffcgs_jax.synthesis.grasp import synthesize

    cfg = GraspConfig(n=4, sampler="cvae", sampling=SamplerConfig(weights=str(weights32)),
                      optim=OptimConfig(iters=2))
    gs = synthesize(svh, mesh_io.load_mesh("box"), cfg, "box")
    assert gs["wrist_pose"].shape == (4, 4, 4) and np.isfinite(gs["E"]).all()


def test_resample_same_resolution_is_identity_and_coarse_is_close():
    from ffcgs_jax.geometry import mesh_io, sdf
    from ffcgs_jax.geometry.config import SDFConfig

    mesh = mesh_io.load_mesh("box")
    g32 = sdf.build_sdf(mesh, SDFConfig(res=32))
    same = sdf.resample(g32, 32)
    np.testing.assert_allclose(same.grid[..., 0], g32.grid[..., 0], atol=1e-9)
    np.testing.assert_allclose(same.origin, g32.origin, atol=1e-12)
    g16 = sdf.build_sdf(mesh, SDFConfig(res=16))
    up = sdf.resample(g16, 32)
    assert up.grid.shape == (32, 32, 32, 4)
    near = np.abs(np.asarray(g32.grid[..., 0])) < 0.02
    err = np.abs(np.asarray(up.grid[..., 0]) - np.asarray(g32.grid[..., 0]))[near]
    assert np.median(err) < 0.1 * float(g16.voxel_size), (np.median(err), float(g16.voxel_size))


def test_training_takes_the_datasets_hand(tmp_path):
    """The sampler is trained for the hand its dataset was built for; naming another hand is refused in one line;
    files from before the field are the SVH's."""
    allegro = make_toy_dataset(tmp_path / "a.mcap", n_objects=2, grasps=2, hand="allegro", channels=16)
    assert dataset_hand(str(allegro)) == "allegro"
    assert dataset_hand(str(allegro), "allegro") == "allegro"
    with pytest.raises(FfcgsError, match="built for hand 'allegro', not 'svh'"):
        dataset_hand(str(allegro), "svh")
    old = make_toy_dataset(tmp_path / "o.mcap", n_objects=2, grasps=2)
    assert dataset_hand(str(old)) == "svh"
