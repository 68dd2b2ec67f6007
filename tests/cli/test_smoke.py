"""FFCGS_SMOKE cuts the counts of long commands and nothing else, and says so; off, every command is as typed."""

import dataclasses

import pytest

from ffcgs_jax.physics.config import PhysicsConfig, RobustConfig
from ffcgs_jax.cli import smoke
from ffcgs_jax.cli.commands import BenchCmd, GraspCmd
from ffcgs_jax.dataset.config import DatasetConfig
from ffcgs_jax.training.config import EvaluatorTrainConfig, TrainConfig
from ffcgs_jax.synthesis.config import GraspConfig


@pytest.mark.parametrize("value, on", [("1", True), ("yes", True), ("", False), ("0", False), ("off", False)])
def test_the_variable_turns_it_on(monkeypatch, value, on):
    monkeypatch.setenv("FFCGS_SMOKE", value)
    assert smoke.active() is on


def test_off_every_command_is_as_typed(monkeypatch, capsys):
    monkeypatch.delenv("FFCGS_SMOKE", raising=False)
    cfg = DatasetConfig(procedural=2000, per_object=200)
    assert smoke.scaled("dataset build", cfg) is cfg
    assert smoke.sweep([("optim.lr", [1e-4, 3e-4])]) == [("optim.lr", [1e-4, 3e-4])]
    assert capsys.readouterr().err == ""


def test_a_labelled_build_keeps_its_options_and_cv_objects(monkeypatch, capsys):
    monkeypatch.setenv("FFCGS_SMOKE", "1")
    cfg = DatasetConfig(keep="all", sampler="cvae", procedural=150, complex=450, per_object=64, rotations=3,
                        protocols="lift-shake,six-dir", scale_min=0.8, scale_max=1.2, seed=5)
    small = smoke.scaled("dataset build", cfg)
    assert (small.procedural, small.complex, small.per_object, small.rotations) == (5, 0, 4, 1)
    assert small.planner.refine <= small.planner.population <= smoke.POPULATION
    same = ("keep", "sampler", "protocols", "scale_min", "scale_max", "seed", "out")
    assert all(getattr(small, f) == getattr(cfg, f) for f in same)
    # physics: one nominal trial per grasp, nothing else changed
    assert small.physics.robust.trials == smoke.TRIALS == 1 and cfg.physics.robust.trials == 8
    assert dataclasses.replace(small.physics, robust=cfg.physics.robust) == cfg.physics
    assert "FFCGS_SMOKE is set: dataset build" in capsys.readouterr().err
    mixed = smoke.scaled("dataset build", DatasetConfig(procedural=2, complex=10))
    assert (mixed.procedural, mixed.complex) == (2, 3)  # cross-validation's 5 folds still find 5 objects


def test_training_runs_one_epoch_and_a_sweep_its_first_point(monkeypatch):
    monkeypatch.setenv("FFCGS_SMOKE", "1")
    for cfg in (TrainConfig(), EvaluatorTrainConfig()):
        small = smoke.scaled("train", cfg)
        assert small.optim.epochs == 1 and small.optim.batch == smoke.BATCH
        assert dataclasses.replace(small, optim=cfg.optim) == cfg
    assert smoke.sweep([("optim.lr", [1e-4, 3e-4]), ("model.width", [8, 16])]) == [("optim.lr", [1e-4]),
                                                                                   ("model.width", [8])]


def test_grasp_and_bench_shrink_their_batches_only(monkeypatch):
    monkeypatch.setenv("FFCGS_SMOKE", "1")
    cmd = GraspCmd(object=("mug",), grasp=GraspConfig(n=4096, devices=2))
    small = smoke.scaled("grasp", cmd)
    assert small.grasp.n == smoke.GRASPS and small.grasp.devices == 2 and small.object == ("mug",)
    assert small.physics.robust.trials == 1  # --validate: one nominal trial per grasp
    one = GraspCmd(object=("mug",), physics=PhysicsConfig(robust=RobustConfig(trials=1)))
    assert smoke.scaled("grasp", one) == one  # 32 stays 32, one trial stays one
    bench = smoke.scaled("bench", BenchCmd())
    assert bench.batches == (32,) and bench.repeats <= 2 and not bench.cli_start and bench.object == "mug"
