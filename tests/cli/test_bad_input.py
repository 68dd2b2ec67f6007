"""Bad input, command by command: one clear error line, exit status 2, no traceback, and nothing a user passed in
(or anything else in the working folder) created or changed. Also: a write that fails half-way through `ffcgs eval`
leaves the user's grasp file as it was, SIGINT during the long commands ends with one line and leaves no partial
output, and a closed pipe ends `--help` quietly."""

import hashlib
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from ffcgs_jax.cli import main as cli_main
from ffcgs_jax.geometry import mesh_io, objects
from ffcgs_jax.synthesis import grasp_io

FFCGS = Path(sys.executable).parent / "ffcgs"
PHYSICS_FAST = ["--close-time", "0.2", "--settle-time", "0.1", "--push-time", "0.2", "--protocol", "six-dir"]


def _grasps(path: Path, obj: str = "ball", n: int = 2) -> Path:
    """A grasp file as `ffcgs grasp` writes it (poses of the open hand, 30 cm above the object)."""
    mesh = mesh_io.load_mesh(obj)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, 3] = np.stack([np.zeros(n), np.linspace(0, 0.05, n), np.full(n, 0.3)], axis=1)
    grasp_io.save_arrays({"wrist_pose": T, "q": np.zeros((n, 9)), "valid": np.ones(n, bool),
                          "object_name": np.array(obj), **mesh_io.identity(obj, 1.0, mesh)}, path)
    return path


@pytest.fixture
def inputs(tmp_path, monkeypatch):
    """The working folder with one file of each kind of bad input (and a good grasp file)."""
    monkeypatch.chdir(tmp_path)
    return make_inputs(tmp_path)


def make_inputs(tmp_path: Path) -> Path:
    """Write one file of each kind of bad input (and good grasp files) into `tmp_path`."""
    (tmp_path / "notes.txt").write_text("just some text\n")
    (tmp_path / "empty.npz").write_bytes(b"")
    np.savez(tmp_path / "pickled.npz", wrist_pose=np.array([{"a": 1}], dtype=object))
    np.savez(tmp_path / "nokeys.npz", a=np.zeros(3))
    good = _grasps(tmp_path / "good.npz").read_bytes()
    _grasps(tmp_path / "many.npz", n=512)  # enough closing work that an interrupt lands mid-run
    (tmp_path / "truncated.npz").write_bytes(good[: len(good) // 2])
    (tmp_path / "corrupt_weights.npz").write_bytes(b"PK\x03\x04" + os.urandom(200))
    (tmp_path / "bad.toml").write_text("n = = 3\n")
    (tmp_path / "unknown.toml").write_text("[grasp.sdf]\nresolution = 3\n")
    (tmp_path / "flat.obj").write_text("v 0 0 0\nv 0.1 0 0\nv 0 0.1 0\nv 0.1 0.1 0\nf 1 2 3\nf 2 4 3\n")
    (tmp_path / "nan.obj").write_text("v 0 0 0\nv nan 0 0\nv 0 0.1 0\nv 0 0 0.1\nf 1 2 3\nf 1 3 4\nf 1 4 2\nf 2 4 3\n")
    (tmp_path / "empty.stl").write_bytes(b"")
    (tmp_path / "hand.toml").write_text("name = 'x'\n")
    (tmp_path / "a_file").write_text("I am a file, not a folder\n")
    (tmp_path / "meshes").mkdir()
    (tmp_path / "meshes" / "box.ply").write_bytes((objects._folder() / "box.ply").read_bytes())
    tiny = mesh_io.load_mesh("ball")
    tiny.apply_scale(0.001)
    tiny.export(tmp_path / "tiny.stl")
    return tmp_path


def snapshot(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): (hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else "dir")
            for p in sorted(folder.rglob("*"))}


# (arguments, what the error line must say); FILE/ stands for a path under the working folder
CASES = [
    (["frobnicate"], "unknown command 'frobnicate'"),
    (["dataset"], "needs a subcommand"),
    (["dataset", "merge"], "needs a subcommand"),
    # grasp
    (["grasp"], "needs an object .* or --depth FRAMES"),
    (["grasp", "nosuchobject"], "mesh file not found: nosuchobject"),
    (["grasp", "mug", "--n", "0"], "n must be >= 1"),
    (["grasp", "mug", "--n", "abc"], "Error parsing --n"),
    (["grasp", "mug", "--bogus", "1"], "bogus"),
    (["grasp", "mug", "--sampler", "magic"], "unknown sampler 'magic'"),
    (["grasp", "mug", "--iters", "0"], r"optim.iters must be in \[1, 100000\]"),
    (["grasp", "mug", "--res", "8"], r"sdf.res must be in \[16, 128\]"),
    (["grasp", "mug", "--lp-solver", "cplex"], "unknown energy.lp_solver 'cplex'"),
    (["grasp", "mug", "--protocol", "jump"], "unknown protocol 'jump'"),
    (["grasp", "mug", "--config", "missing.toml"], "config file not found: missing.toml"),
    (["grasp", "mug", "--config", "bad.toml"], "bad.toml is not valid TOML"),
    (["grasp", "mug", "--config", "unknown.toml"], r"unknown config key\(s\) grasp.sdf.resolution"),
    (["grasp", "mug", "--poses", "missing.npy"], "pose file not found: missing.npy"),
    (["grasp", "mug", "--poses", "notes.txt"], "notes.txt is not a readable .npy/.npz pose file: it is a text file"),
    (["grasp", "mug", "--poses", "pickled.npz"], "pickled Python objects"),
    (["grasp", "mug", "--poses", "nokeys.npz"], "has no 'wrist_pose' array"),
    (["grasp", "mug", "--out", "a_file/grasps.npz"], "a file stands where its folder should be"),
    (["grasp", "mug", "--out", "."], "is a folder"),
    (["grasp", "mug", "--mcap", "a_file/run.mcap"], "--mcap a_file/run.mcap"),
    (["grasp", "mug", "--png", "a_file/g.png"], "--png a_file/g.png"),
    (["grasp", "flat.obj"], "is flat"),
    (["grasp", "nan.obj"], "NaN or inf"),
    (["grasp", "empty.stl"], "empty.stl"),
    (["grasp", "notes.txt"], "notes.txt"),
    (["grasp", "mug", "--hand", "missing.toml"], "missing.toml"),
    (["grasp", "mug", "--hand", "hand.toml"], "hand.toml"),
    (["grasp", "mug", "--weights", "corrupt_weights.npz"], "corrupt_weights.npz is not a readable .npz checkpoint"),
    (["grasp", "mug", "--devices", "64"], "devices = 64 asked for"),
    # eval
    (["eval"], "required options"),
    (["eval", "missing.npz"], "grasp file not found: missing.npz"),
    (["eval", "notes.txt"], "notes.txt is not a readable grasp .npz: it is a text file"),
    (["eval", "empty.npz"], "empty.npz is not a readable grasp .npz: it is an empty file"),
    (["eval", "truncated.npz"], "truncated.npz is not a readable grasp .npz"),
    (["eval", "pickled.npz"], "pickled Python objects"),
    (["eval", "nokeys.npz"], "has no wrist_pose or q array"),
    (["eval", "good.npz", "--object", "mug"], "mug .scale 1. is not the object these grasps were made for .ball"),
    (["eval", "good.npz", "--scale", "0.5"], "is not the object these grasps were made for"),
    (["eval", "good.npz", "--scale", "-1"], "--scale must be a finite number > 0"),
    (["eval", "good.npz", "--protocol", "jump"], "unknown protocol 'jump'"),
    (["eval", "good.npz", "--backend", "tpu"], "unknown physics backend 'tpu'"),
    (["eval", "good.npz", "--video", "trial.avi"], "--video trial.avi: .* must end in .gif or .mp4"),
    (["eval", "good.npz", "--friction", "-1"], r"physics.friction must be in \[0.0, 10.0\]"),
    (["eval", "good.npz", "--out", "a_file/out.npz"], "a file stands where its folder should be"),
    (["eval", "good.npz", "--video", "a_file/v.gif"], "--video a_file/v.gif"),
    # sdf, hand, objects
    (["sdf", "mug", "--res", "500"], r"sdf.res must be in \[16, 128\]"),
    (["sdf", "mug", "--scale", "0"], "sdf.scale must be > 0"),
    (["grasp", "tiny.stl"], "smaller than a voxel because of a wrong --scale"),
    (["sdf", "mug", "--out", "a_file/sdf.npz"], "a file stands where its folder should be"),
    (["hand", "--q", "1", "2"], r"--q must have shape \(9,\)"),
    (["hand", "--close", "2"], r"--close must be in \[0, 1\]"),
    (["hand", "--views", "sideways"], "unknown view"),
    (["hand", "--wrist", "1", "2"], "Error parsing --wrist"),
    (["hand", "--wrist", "1", "2", "3", "4", "5", "nan"], "--wrist needs 6 finite numbers"),
    (["hand", "--png", "a_file/hand.png"], "--png a_file/hand.png"),
    # dataset, bench
    (["dataset", "build", "--objects", "meshes", "--out", "train.txt"], "--out must name an .mcap file"),
    (["dataset", "build", "--objects", "meshes", "--shard", "3/2"], "--shard must be K/N"),
    (["dataset", "build", "--objects", "nowhere", "--out", "d.mcap"], "nowhere"),
    (["dataset", "build", "--objects", "meshes", "--out", "d.mcap", "--no-annotate"], "would be empty"),
    (["dataset", "build", "--objects", "meshes", "--out", "a_file/d.mcap"], "a file stands where its folder"),
    (["dataset", "info", "missing.mcap"], "missing.mcap"),
    (["dataset", "info", "notes.txt"], "notes.txt"),
    (["dataset", "info", "notes.txt", "--png", "a_file"], "--png a_file is a file, not a folder"),
    (["bench", "--batches", "0"], r"--batches must be integers in \[1, 1000000\]"),
]


@pytest.mark.parametrize("argv,message", CASES, ids=[" ".join(a) for a, _ in CASES])
def test_bad_input_gives_one_line_and_touches_nothing(inputs, capsys, argv, message):
    before = snapshot(inputs)
    code = cli_main.main(argv)
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    errors = [ln for ln in lines if ln.startswith("ffcgs: error: ")]
    assert code == 2, err
    assert len(errors) == 1 and all(ln.startswith("ffcgs: ") for ln in lines), err  # warnings may precede it
    assert "Traceback" not in err
    assert re.search(message, errors[0]), errors[0]
    assert snapshot(inputs) == before


def test_the_suite_covers_every_command():
    commands = {a[0] if a[0] != "dataset" or len(a) < 2 else f"dataset {a[1]}" for a, _ in CASES}
    assert {"grasp", "eval", "sdf", "hand", "dataset build", "dataset info", "bench"} <= commands
    assert len(CASES) >= 40


def test_a_failed_write_leaves_the_grasp_file_as_it_was(inputs, capsys, monkeypatch):
    """`ffcgs eval` writes its results back into the grasp file: a disk that fills up half-way must not cost the
    user that file."""
    path = inputs / "good.npz"
    before = path.read_bytes()
    real = np.savez_compressed

    def half_then_full(f, **arrays):
        real(f, **arrays)
        f.truncate(f.tell() // 2)
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(grasp_io.np, "savez_compressed", half_then_full)
    code = cli_main.main(["eval", str(path), "--all", *PHYSICS_FAST])
    err = capsys.readouterr().err
    assert code == 2 and "No space left on device" in err and "Traceback" not in err, err
    assert path.read_bytes() == before
    assert grasp_io.load_npz(path)["wrist_pose"].shape == (2, 4, 4)
    assert sorted(p.name for p in inputs.iterdir() if ".tmp" in p.name) == []


def test_eval_simulates_the_recorded_object_and_says_what_it_simulated(inputs, capsys):
    """Without --object, the grasp file's own object (source and scale); with --other-object, the other one,
    recorded in the output."""
    grasps = inputs / "good.npz"
    assert cli_main.main(["eval", str(grasps), "--all", "--out", "same.npz", *PHYSICS_FAST]) == 0
    same = grasp_io.load_npz(inputs / "same.npz")
    assert str(same["physics_object_sha256"]) == str(same["object_sha256"])
    assert str(same["physics_object_source"]) == "ball"
    code = cli_main.main(["eval", str(grasps), "--all", "--object", "box", "--other-object", "--out", "other.npz",
                          *PHYSICS_FAST])
    assert code == 0, capsys.readouterr().err
    other = grasp_io.load_npz(inputs / "other.npz")
    assert str(other["physics_object_source"]) == "box" and str(other["object_source"]) == "ball"
    assert str(other["physics_object_sha256"]) == mesh_io.mesh_sha256(mesh_io.load_mesh("box"))


def _interrupted(argv: list[str], cwd: Path, after: float) -> subprocess.CompletedProcess:
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "FFCGS_JAX_CACHE": "off"}
    proc = subprocess.Popen([str(FFCGS), *argv], cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    time.sleep(after)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=300)
    return subprocess.CompletedProcess(argv, proc.returncode, out, err)


@pytest.mark.parametrize("argv,after", [
    (["grasp", "mug", "--out", "new/grasps.npz", "--mcap", "new/run.mcap"], 6.0),
    # protocol v1's long phases: the default protocol may finish these grasps before the signal arrives
    (["eval", "many.npz", "--all", "--protocol", "both", "--timestep", "0.002", "--shake-cycles", "6",
      "--push-time", "2"], 5.0),
    # no `ffcgs sdf` case: the device build of even a 128^3 grid ends within about 3 s, before a signal can be
    # timed to land in it; the handler is main's, the same for every command
    (["dataset", "build", "--objects", "meshes", "--out", "new/d.mcap", "--per-object", "2", "--rotations", "1",
      "--planner.population", "64", "--planner.refine", "8"], 8.0),
], ids=["grasp", "eval", "dataset-build"])
def test_sigint_ends_with_one_line_and_no_partial_output(inputs, argv, after):
    before = {p: (inputs / p).read_bytes() for p in ("good.npz", "many.npz")}
    r = _interrupted(argv, inputs, after)
    assert r.returncode == 130, (r.returncode, r.stderr[-2000:])
    assert r.stderr.strip().splitlines()[-1] == "ffcgs: interrupted" and "Traceback" not in r.stderr, r.stderr
    assert {p: (inputs / p).read_bytes() for p in before} == before
    written = [p for p in (inputs / "new").rglob("*") if p.is_file()] if (inputs / "new").exists() else []
    # the dataset build keeps its finished parts and config (that is how it resumes); nothing else may appear
    assert all(".tmp" not in p.name for p in written) and not list(inputs.glob(".*tmp*")), written
    if argv[0] != "dataset":
        assert written == [], written


def test_help_into_a_closed_pipe_ends_quietly(tmp_path):
    r = subprocess.run(f"'{FFCGS}' grasp --help | head -1", shell=True, capture_output=True, text=True,
                       cwd=tmp_path)
    assert r.stdout.startswith("usage: ffcgs grasp") and "Traceback" not in r.stderr, r.stderr
