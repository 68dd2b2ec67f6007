"""The public grasp file and preset round trips: `fj.save_grasps` / `fj.load_grasps` give a GraspSet back, and
`fj.load_config` reads a preset as the CLI does."""

import dataclasses
import json

import numpy as np
import pytest

import ffcgs_jax as fj
from ffcgs_jax.cli.commands import GraspCmd
from ffcgs_jax.core.config import load

from paths import REPO


def _grasps(n=5, cfg=fj.GraspConfig()):
    rng = np.random.default_rng(0)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, 3] = rng.normal(size=(n, 3))
    arrays = {"wrist_pose": poses, "q": rng.uniform(size=(n, 9)), "E": rng.uniform(size=n),
              "valid": rng.uniform(size=n) > 0.3, "squeeze_dir": rng.normal(size=(n, 9)),
              "channel_names": np.array([f"c{i}" for i in range(9)])}
    return fj.GraspSet(arrays, {}, cfg, "thing")


def test_a_grasp_set_comes_back_as_it_was_saved(tmp_path):
    cfg = dataclasses.replace(fj.GraspConfig(), n=5, seed=7,
                              optim=dataclasses.replace(fj.OptimConfig(), iters=12))
    gs = _grasps(cfg=cfg)
    fj.save_grasps(gs, tmp_path / "g.npz")
    back = fj.load_grasps(tmp_path / "g.npz")
    assert isinstance(back, fj.GraspSet) and back.object_name == "thing" and back.config == cfg
    assert set(back.arrays) == set(gs.arrays)
    for k, v in gs.arrays.items():
        np.testing.assert_array_equal(back[k], v, err_msg=k)
    np.testing.assert_array_equal(back.order(), gs.order())


def test_a_config_from_another_version_keeps_the_defaults_with_a_warning(tmp_path):
    gs = _grasps()
    fj.save_grasps(gs, tmp_path / "g.npz")
    data = dict(np.load(tmp_path / "g.npz"))
    data["config_json"] = np.array(json.dumps({"no_such_key": 1}))
    np.savez(tmp_path / "old.npz", **data)
    with pytest.warns(UserWarning, match="no_such_key"):
        back = fj.load_grasps(tmp_path / "old.npz")
    assert back.config == fj.GraspConfig()


def test_a_broken_file_is_one_line(tmp_path):
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    with pytest.raises(fj.FfcgsError, match="bad.npz"):
        fj.load_grasps(tmp_path / "bad.npz")


@pytest.mark.parametrize("preset", ["paper.toml", "grasp.toml"])
def test_a_preset_loads_as_the_cli_loads_it(preset):
    path = REPO / "configs" / preset
    assert fj.load_config(path) == load(GraspCmd, path).grasp
    if preset == "paper.toml":  # Algorithm 1 as published: plain descent, 50 steps
        assert fj.load_config(path).optim.iters == 50 and fj.load_config(path).optim.method == "gd"


def test_a_file_of_another_command_or_unknown_keys_is_refused(tmp_path):
    with pytest.raises(fj.FfcgsError, match="no \\[grasp\\] table"):
        fj.load_config(REPO / "configs" / "sdf.toml")
    (tmp_path / "x.toml").write_text("[grasp.optim]\nitres = 3\n")
    with pytest.raises(fj.FfcgsError, match="unknown config key"):
        fj.load_config(tmp_path / "x.toml")
