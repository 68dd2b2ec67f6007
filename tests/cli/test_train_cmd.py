"""`ffcgs train`: the installed package's training command, and `python -m train.sampler`, its alias, run the same
code (`cli.train_command`) with the same flags; only the program name in messages differs."""

import subprocess
import sys

import pytest

from ffcgs_jax.cli import main as cli_main
from ffcgs_jax.cli import train_command

from paths import REPO


def test_ffcgs_train_help_lists_the_config_flags(tmp_path):
    r = subprocess.run([sys.executable, "-m", "ffcgs_jax.cli", "train", "--help"], capture_output=True, text=True,
                       cwd=tmp_path, timeout=300)  # not the checkout: the package alone
    assert r.returncode == 0, r.stderr[-2000:]
    assert "usage: ffcgs train" in r.stdout
    for flag in ("--out", "--data.path", "--optim.lr", "--model.res", "--cv.all"):
        assert flag in r.stdout, flag
    assert "--sweep" in r.stdout  # in the description: the one flag tyro does not parse


def test_ffcgs_help_names_train(capsys):
    with pytest.raises(SystemExit) as e:
        cli_main.main(["--help"])
    assert e.value.code == 0
    assert "\n  train " in capsys.readouterr().out


def _both(capsys, argv):
    """(exit status, stderr) of `ffcgs train ARGV` and of `python -m train.sampler ARGV`, in this process."""
    from train import sampler

    out = []
    for run in (lambda: cli_main.main(["train", *argv]), lambda: sampler.main(list(argv))):
        code = run()
        out.append((code, capsys.readouterr().err))
    return out


def test_same_error_line_on_a_missing_dataset(capsys, tmp_path):
    (c1, e1), (c2, e2) = _both(capsys, ["--data.path", str(tmp_path / "missing.mcap"), "--out", str(tmp_path / "o")])
    assert c1 == c2 == 2
    assert e1.startswith("ffcgs: error: ") and e2.startswith("train.sampler: error: ")
    assert e1.removeprefix("ffcgs: ") == e2.removeprefix("train.sampler: ")
    assert "dataset file not found" in e1 and e1.count("\n") == 1
    (c1, e1), (c2, e2) = _both(capsys, ["--sweep", "optim.nope=1,2"])
    assert c1 == c2 == 2 and e1.removeprefix("ffcgs: ") == e2.removeprefix("train.sampler: ")
    assert "unknown sweep key" in e1


def test_both_entries_run_the_same_training_code(capsys, monkeypatch, tmp_path):
    seen = []
    monkeypatch.setattr(train_command, "run_one", lambda cfg: seen.append(cfg) or {"val_rec": 0.0})
    argv = ["--config", str(REPO / "configs" / "sampler.toml"), "--optim.lr", "3e-4", "--out", str(tmp_path)]
    assert [code for code, _ in _both(capsys, argv)] == [0, 0]
    assert len(seen) == 2 and seen[0] == seen[1] and seen[0].optim.lr == 3e-4
