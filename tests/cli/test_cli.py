"""The `ffcgs` command as a user runs it: outputs written, bad input refused with one line and exit status 2."""

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from ffcgs_jax.cli import commands as cli
from ffcgs_jax.cli import main as cli_main
from ffcgs_jax.core.config import from_dict
from ffcgs_jax.geometry import objects
from ffcgs_jax.geometry import sdf as sdf_mod

from paths import REPO


def run(capsys, *argv):
    code = cli_main.main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def test_objects_lists_every_builtin(capsys):
    code, out, _ = run(capsys, "objects")
    assert code == 0
    for name in objects.names():
        assert f"\n{name} " in "\n" + out
    assert {"mug", "bottle", "box", "ball", "can", "banana"} <= set(objects.names())


def test_sdf_writes_a_loadable_grid_and_picture(capsys, tmp_path):
    out_npz, png = tmp_path / "s.npz", tmp_path / "s.png"
    code, out, err = run(capsys, "sdf", "ball", "--res", "16", "--out", str(out_npz), "--png", str(png))
    assert code == 0, err
    g = sdf_mod.load(out_npz)
    assert g.grid.shape == (16, 16, 16, 4)
    d = np.asarray(g.grid[..., 0])
    assert d.min() < 0 < d.max()  # the ball's inside and outside are both in the grid
    assert Image.open(png).size == (3 * 256 + 4, 256)


def test_config_file_then_command_line_override(capsys, tmp_path):
    cfg = tmp_path / "c.toml"
    cfg.write_text('out = "%s"\n[sdf]\nres = 20\nmargin = 0.3\n' % (tmp_path / "a.npz"))
    code, _, err = run(capsys, "sdf", "box", "--config", str(cfg), "--res", "18")
    assert code == 0, err
    g = sdf_mod.load(tmp_path / "a.npz")
    assert g.grid.shape[0] == 18  # the command line wins over the file


@pytest.mark.parametrize("argv, message", [
    (["sdf", "nonexistent_thing"], "nonexistent_thing"),
    (["sdf", "mug", "--res", "8"], r"sdf.res must be an integer in \[16, 128\]"),
    (["hand", "--q", "1", "2"], r"--q must have shape \(9,\)"),
    (["hand", "--q", "0", "0", "0", "0", "0", "0", "0", "0", "3"], "outside the joint limits"),
    (["hand", "--close", "2"], r"--close must be in \[0, 1\]"),
    (["hand", "--views", "back"], "unknown view"),
    (["hand", "--hand", "shadow"], "built-in hands: svh, allegro"),
    (["frobnicate"], "unknown command 'frobnicate'"),
    (["sdf", "mug", "--config", "/no/such.toml"], "config file not found"),
])
def test_bad_input_is_one_line_exit_2(capsys, argv, message):
    code, _, err = run(capsys, *argv)
    assert code == 2
    assert err.startswith("ffcgs: error:") and err.count("\n") == 1
    assert re.search(message, err), err


def test_unknown_config_key_lists_valid_keys(capsys, tmp_path):
    cfg = tmp_path / "c.toml"
    cfg.write_text("[sdf]\nresolution = 64\n")
    code, _, err = run(capsys, "sdf", "mug", "--config", str(cfg))
    assert code == 2
    assert "unknown config key(s) sdf.resolution" in err and "res" in err


@pytest.mark.parametrize("path", sorted((REPO / "configs").glob("*.toml")), ids=lambda p: p.name)
def test_shipped_configs_load(path):
    import tomllib

    data = tomllib.loads(path.read_text())
    from ffcgs_jax.training.config import TrainConfig

    cls = {"sdf": cli.SdfCmd, "hand": cli.HandCmd, "grasp": cli.GraspCmd, "paper": cli.GraspCmd,
           "sampler": TrainConfig}[path.stem.split("_")[0]]
    assert from_dict(cls, data) is not None


def test_hand_png_via_console_script(tmp_path):
    """The quick-start command, as a subprocess through the installed entry point."""
    png = tmp_path / "hand.png"
    exe = Path(sys.executable).parent / "ffcgs"
    r = subprocess.run([str(exe), "hand", "--object", "mug", "--close", "0.3", "--png", str(png),
                        "--width", "96", "--height", "96"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "thumb_tip" in r.stdout and "Failed to import" not in r.stdout
    img = np.asarray(Image.open(png))
    assert img.shape == (96, 3 * 96, 3)
    assert img.std() > 10  # a picture, not a blank canvas


def test_hand_with_wrist_pose_moves_the_contacts(capsys, tmp_path):
    common = ["--png", str(tmp_path / "h.png"), "--backend", "software", "--width", "64", "--height", "64",
              "--views", "top"]
    _, out0, _ = run(capsys, "hand", *common)
    _, out1, _ = run(capsys, "hand", "--wrist", "0.1", "0", "0", "0", "0", "0", *common)
    row0 = next(l.split() for l in out0.splitlines() if l.startswith("thumb_tip"))
    row1 = next(l.split() for l in out1.splitlines() if l.startswith("thumb_tip"))
    assert float(row1[1]) == pytest.approx(float(row0[1]) + 0.1, abs=1e-4)
    assert row1[2:] == row0[2:]
