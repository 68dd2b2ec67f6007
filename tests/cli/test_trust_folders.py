"""Issue 47, through the commands: no folder or file of the user's or of another command is replaced or deleted
(a folder of `ffcgs grasp` results given as `--out` elsewhere, files named like temporaries, a config.toml that is
no run's), two `ffcgs eval` of one file both keep their results, symlinks stay links, and a rendered folder's
manifest is named when it hides files that exist."""

import json
import os
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

from ffcgs_jax.core import files, locks
from ffcgs_jax.cli import main as cli_main
from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.geometry import depth_io, mesh_io
from ffcgs_jax.synthesis import grasp_io

from paths import DATA

SMALL = ["--width", "64", "--height", "48", "--no-noise", "--views", "3"]
PHYSICS_FAST = ["--close-time", "0.2", "--settle-time", "0.1", "--push-time", "0.2", "--trials", "1"]


def _tree(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in folder.rglob("*") if p.is_file()}


def _run(capsys, *argv) -> tuple[int, str, str]:
    code = cli_main.main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def _grasps(path: Path, n: int = 2) -> Path:
    """A grasp file as `ffcgs grasp` writes it (poses of the open hand above the ball)."""
    mesh = mesh_io.load_mesh("ball")
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, 3] = np.stack([np.zeros(n), np.linspace(0, 0.05, n), np.full(n, 0.3)], axis=1)
    grasp_io.save_arrays({"wrist_pose": T, "q": np.zeros((n, 9)), "valid": np.ones(n, bool),
                          "object_name": np.array("ball"), **mesh_io.identity("ball", 1.0, mesh)}, path)
    return path


@pytest.fixture
def work(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    g = tmp_path / "grasps"
    g.mkdir()
    _grasps(g / "mug.npz")
    (g / files.MANIFEST).write_text(json.dumps({"written_by": "ffcgs grasp", "run": {
        "id": "0123456789ab", "pid": 4242, "time": "2025-01-02T03:04:05+0000"}, "files": ["mug.npz"]}))
    return tmp_path


@pytest.mark.parametrize("argv", [
    ["render-depth", "box", "--out", "grasps", *SMALL],
    ["dataset", "export", str(DATA / "dataset_v1.mcap"), "--out", "grasps"],
    ["dataset", "info", str(DATA / "dataset_v1.mcap"), "--png", "grasps"],
], ids=["render-depth", "dataset-export", "dataset-info"])
def test_a_folder_of_grasp_results_is_not_replaced(work, capsys, argv):
    before = _tree(work / "grasps")
    code, _, err = _run(capsys, *argv)
    assert code == 2 and err.count("\n") == 1 and err.startswith("ffcgs: error: "), err
    assert "grasps was written by ffcgs grasp (run of time 2025-01-02T03:04:05+0000, pid 4242), not ffcgs " \
           f"{' '.join(argv[:2]) if argv[0] == 'dataset' else argv[0]}" in err, err
    assert "--overwrite" in err
    assert _tree(work / "grasps") == before


def test_overwrite_replaces_a_folder_of_another_command(work, capsys):
    code, _, err = _run(capsys, "render-depth", "box", "--out", "grasps", "--overwrite", *SMALL)
    assert code == 0, err
    m = files.read_manifest(work / "grasps")
    assert m["written_by"] == "ffcgs render-depth" and m["run"]["pid"] == os.getpid()
    assert "mug.npz" not in _tree(work / "grasps")
    code, _, err = _run(capsys, "render-depth", "box", "--out", "grasps", *SMALL)  # its own folder: replaced
    assert code == 0, err


def test_a_users_file_named_like_a_temporary_is_kept(work, capsys):
    frames = work / "frames"
    assert _run(capsys, "render-depth", "box", "--out", "frames", *SMALL)[0] == 0
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    for name in (f".notes.{dead.pid}.tmp.txt", f".draft.{dead.pid}.old"):
        (frames / name).write_text("the user's")
    code, _, err = _run(capsys, "render-depth", "box", "--out", "frames", *SMALL)
    assert code == 2 and "holds 2 file(s) that this command did not write" in err, err
    assert (frames / f".notes.{dead.pid}.tmp.txt").read_text() == "the user's"
    assert files.remove_left_behind(frames) == 0 and (frames / f".draft.{dead.pid}.old").exists()


def test_eval_waits_for_another_run_on_the_same_file_and_keeps_its_results(work):
    """The test holds the file's lock as a first `ffcgs eval` would, and adds "its" results while a second eval
    waits: the second reads the file only once the first is done, so the file ends with both runs' results."""
    g = work / "grasps" / "mug.npz"
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    with locks.locked(g):
        p = subprocess.Popen([sys.executable, "-m", "ffcgs_jax.cli", "eval", str(g), "--protocol", "six-dir",
                              *PHYSICS_FAST], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
        try:
            said = [p.stderr.readline() for _ in range(1)]
            while not said[-1].startswith("waiting for another ffcgs run that is updating") and said[-1]:
                said.append(p.stderr.readline())  # lines before it (a JAX notice) are not this test's
            assert said[-1].startswith("waiting for another ffcgs run"), said
            first = grasp_io.load_npz(g)
            first["first_run_result"] = np.arange(2)
            grasp_io.save_arrays(first, g)
        except BaseException:
            p.kill()
            raise
    out, err = p.communicate(timeout=300)
    assert p.returncode == 0, err
    assert f"wrote {g}" in out
    data = grasp_io.load_npz(g)
    assert "first_run_result" in data and "six_dir_success" in data, sorted(data)
    assert not locks.lock_file(g).exists()


def test_eval_through_a_link_updates_its_target(work, capsys):
    real = work / "grasps" / "mug.npz"
    link = work / "mug.npz"
    link.symlink_to(real)
    code, out, err = _run(capsys, "eval", "mug.npz", "--protocol", "six-dir", *PHYSICS_FAST)
    assert code == 0, err
    assert link.is_symlink() and "six_dir_success" in grasp_io.load_npz(real)


def test_a_linked_out_folder_gets_the_new_frames(work, capsys):
    store = work / "store"
    store.mkdir()
    assert _run(capsys, "render-depth", "box", "--out", "store/frames", "--views", "4", *SMALL[:-2])[0] == 0
    (work / "frames").symlink_to(store / "frames")
    code, _, err = _run(capsys, "render-depth", "box", "--out", "frames", *SMALL)
    assert code == 0, err
    assert (work / "frames").is_symlink()
    names = sorted(_tree(store / "frames"))
    assert names == [files.MANIFEST, "camera.json", "poses.json", "view_000.png", "view_001.png", "view_002.png"]
    assert sorted(p.name for p in store.iterdir()) == ["frames"]


def test_train_takes_only_a_runs_own_config(work, capsys):
    run = work / "RUN"
    run.mkdir()
    (run / "config.toml").write_text("# my own settings\n[optim]\nlr = 1e-3\n")
    before = _tree(run)
    code, _, err = _run(capsys, "train", "--data.path", "missing.mcap", "--out", "RUN")
    assert code == 2 and err.count("\n") == 1, err
    assert "--out RUN holds a config.toml that no ffcgs train run wrote (RUN/config.toml)" in err, err
    assert _tree(run) == before
    from ffcgs_jax.training.config import TrainConfig, to_toml
    from ffcgs_jax.training.run import RUN_CONFIG_MARK

    (run / "config.toml").write_text(f"{RUN_CONFIG_MARK} (an earlier run)\n{to_toml(TrainConfig(out='RUN'))}")
    code, _, err = _run(capsys, "train", "--data.path", "missing.mcap", "--out", "RUN")
    assert code == 2 and "config.toml" not in err and "missing.mcap" in err, err  # a run's own: on to the data


def test_files_the_manifest_hides_are_named(work, capsys):
    assert _run(capsys, "render-depth", "box", "--out", "fr", *SMALL)[0] == 0
    fr = work / "fr"
    for i in range(3):  # masks added by hand
        (fr / f"view_{i:03d}_mask.png").write_bytes((fr / f"view_{i:03d}.png").read_bytes())
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        frames = depth_io.load_frames(fr)
    assert frames.mask is None
    said = [str(w.message) for w in caught]
    assert len(said) == 1 and f"depth folder {fr} holds 3 file(s) that its manifest {fr / files.MANIFEST} does " \
                               "not name (e.g. view_000_mask.png); they are ignored" in said[0], said

    poses = json.loads((fr / "poses.json").read_text())
    poses["view_003.png"] = poses["view_000.png"]
    (fr / "poses.json").write_text(json.dumps(poses))
    (fr / "view_003.png").write_bytes((fr / "view_000.png").read_bytes())
    with pytest.raises(FfcgsError) as e, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        depth_io.load_frames(fr)
    assert "has a pose for view_003.png" in str(e.value)
    assert f"{fr / 'view_003.png'} exists, but the folder's manifest {fr / files.MANIFEST} does not name it" \
           in str(e.value)
