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
PHYSICS_FAST = ["--close-time", "0.2", "--settle-time", "0.1", "--push-time", "0.2", "--protocol", "six-dir",
                "--trials", "1"]


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
    (tmp_path / "meshes" / "box.ply").write_bytes(objects.path("box").read_bytes())
    tiny = mesh_io.load_mesh("ball")
    tiny.apply_scale(0.001)
    tiny.export(tmp_path / "tiny.stl")
    _more_inputs(tmp_path)
    return tmp_path


def _more_inputs(tmp_path: Path) -> None:
    """Issue 36's careless inputs: folders for files, files of another kind, wrong types and shapes in files."""
    for name in ("dir.obj", "dir.npz", "dir.toml", "dir.npy", "emptyframes"):
        (tmp_path / name).mkdir()
    np.save(tmp_path / "p_empty.npy", np.zeros((0, 4, 4)))
    np.save(tmp_path / "p_str.npy", np.array(["a", "b"]))
    np.save(tmp_path / "p_complex.npy", np.tile(np.eye(4), (2, 1, 1)).astype(complex))
    good = dict(np.load(tmp_path / "good.npz"))
    for name, change in [("g_rows", {"q": np.zeros((3, 9))}), ("g_33", {"wrist_pose": np.tile(np.eye(3), (2, 1, 1))}),
                         ("g_nan", {"wrist_pose": np.full((2, 4, 4), np.nan)}), ("g_q16", {"q": np.zeros((2, 16))}),
                         ("g_q0d", {"q": np.array(1.0)}), ("g_scale", {"object_scale": np.array("abc")}),
                         ("g_strq", {"q": np.full((2, 9), "a")}), ("g_sha", {"object_sha256": np.array(["a", "b"])}),
                         ("g_channels", {"channel_names": np.array(1.0)}),
                         ("g_scaled", {"wrist_pose": np.tile(np.diag([2.0, 2, 2, 1]), (2, 1, 1))}),
                         ("g_none", {"wrist_pose": np.zeros((0, 4, 4)), "q": np.zeros((0, 9)), "valid": np.zeros(0, bool)})]:
        np.savez(tmp_path / f"{name}.npz", **{**good, **change})
    (tmp_path / "random.toml").write_bytes(bytes(range(128, 256)) * 2)
    (tmp_path / "png.toml").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(64))
    (tmp_path / "latin1.toml").write_bytes("# caf\xe9\n[grasp]\nn = 3\n".encode("latin-1"))
    (tmp_path / "bool_iters.toml").write_text("[grasp.optim]\niters = true\n")
    (tmp_path / "bounds.toml").write_text("bounds = 'x'\n")
    (tmp_path / "hand_mjcf.toml").write_text("name = 'x'\nmjcf = 3\nroot_body = 'a'\ncontact_sites = []\n"
                                              "palm_site = 'a'\npalm_normal = [0, 0, 1]\ntetrahedron_sites = []\n"
                                              "[channels]\nnames = []\nlower = []\nupper = []\n"
                                              "[coupling]\njoints = []\nmatrix = []\n")
    (tmp_path / "random_hand.toml").write_bytes(bytes(range(128, 256)))
    box = tmp_path / "box.stl"
    mesh_io.load_mesh("box").export(box)
    (tmp_path / "stl.obj").write_bytes(box.read_bytes())
    (tmp_path / "obj.stl").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    (tmp_path / "random.ply").write_bytes(bytes(range(256)))
    _grasps_on_file(tmp_path, box)
    (tmp_path / "fr_json").mkdir()
    (tmp_path / "fr_json" / "camera.json").write_bytes(b"\x89PNG\r\n\x1a\n")
    (tmp_path / "magic.mcap").write_bytes(b"\x89MCAP0\r\n" + bytes(range(256)))
    meta = lambda m: np.frombuffer(m, np.uint8)  # noqa: E731
    np.savez(tmp_path / "w_meta.npz", __meta__=meta(b"\xff\xfe{"))
    np.savez(tmp_path / "w_list.npz", __meta__=meta(b"[1, 2]"))
    np.savez(tmp_path / "w_shapes.npz", __meta__=meta(b'{"format": "ffcgs.cvae.v1", "hand": "schunk_svh_right", '
                                                      b'"model": {}}'), **{"params/a": np.zeros(3)})


def _grasps_on_file(tmp_path: Path, mesh_file: Path) -> None:
    """box_grasps.npz: grasps made on `mesh_file`, which is then changed (a tiny move of one vertex)."""
    mesh = mesh_io.load_mesh(mesh_file)
    arrays = dict(np.load(tmp_path / "good.npz"))
    grasp_io.save_arrays({**arrays, **mesh_io.identity(mesh_file, 1.0, mesh)}, tmp_path / "box_grasps.npz")
    mesh.vertices[0] += 1e-4
    mesh.export(mesh_file)


def snapshot(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): (hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else "dir")
            for p in sorted(folder.rglob("*"))}


# (arguments, what the error line must say); FILE/ stands for a path under the working folder
CASES = [
    (["frobnicate"], "unknown command 'frobnicate'"),
    (["dataset"], "needs a subcommand"),
    (["dataset", "mrege"], "needs a subcommand"),
    (["dataset", "merge", "d.mcap"], "is not a build's parts folder"),
    (["dataset", "merge", "d.txt"], "must be an .mcap file"),
    # grasp
    (["grasp"], "needs an object .* or --depth FRAMES"),
    (["grasp", "nosuchobject"], "mesh file not found: nosuchobject"),
    (["grasp", "mug", "--n", "0"], r"n must be an integer in \[1, 1000000\]"),
    (["grasp", "mug", "--n", "abc"], "Error parsing --n"),
    (["grasp", "mug", "--bogus", "1"], "bogus"),
    (["grasp", "mug", "--sampler", "magic"], "invalid choice 'magic' for argument '--sampler'"),
    (["grasp", "mug", "--iters", "0"], r"optim.iters must be an integer in \[1, 100000\]"),
    (["grasp", "mug", "--res", "8"], r"sdf.res must be an integer in \[16, 128\]"),
    (["grasp", "mug", "--lp-solver", "cplex"], "invalid choice 'cplex' for argument '--lp-solver'"),
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
    (["eval", "good.npz", "--backend", "tpu"], "invalid choice 'tpu' for argument '--backend'"),
    (["eval", "good.npz", "--video", "trial.avi"], "--video trial.avi: .* must end in .gif or .mp4"),
    (["eval", "good.npz", "--sim-friction", "-1"], r"physics.sim_friction must be in \[0.0, 10.0\]"),
    (["eval", "good.npz", "--out", "a_file/out.npz"], "a file stands where its folder should be"),
    (["eval", "good.npz", "--video", "a_file/v.gif"], "--video a_file/v.gif"),
    # sdf, hand, objects
    (["sdf", "mug", "--res", "500"], r"sdf.res must be an integer in \[16, 128\]"),
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
    # issue 36: tracebacks before
    (["grasp", "mug", "--poses", "p_empty.npy"], r"wrist poses in p_empty.npy holds no poses \(shape \(0, 4, 4\)\)"),
    (["grasp", "mug", "--poses", "p_str.npy"], "wrist poses in p_str.npy must hold real numbers, got dtype <U1"),
    (["grasp", "mug", "--poses", "p_complex.npy"], "p_complex.npy must hold real numbers, got dtype complex128"),
    (["grasp", "mug", "--poses", "g_rows.npz"], "g_rows.npz: its arrays must have one row per grasp, got 2 in "
                                                 "wrist_pose, 3 in q"),
    (["eval", "g_rows.npz"], "grasp file g_rows.npz: its arrays must have one row per grasp"),
    (["show", "g_rows.npz"], "grasp file g_rows.npz: its arrays must have one row per grasp"),
    (["eval", "g_q0d.npz"], r"g_q0d.npz: q must have shape \(B, Q\), got \(\)"),
    (["eval", "g_strq.npz"], "g_strq.npz: q must hold real numbers"),
    (["eval", "g_scale.npz"], "g_scale.npz: object_scale must be one number > 0, got 'abc'"),
    (["show", "g_scale.npz"], "g_scale.npz: object_scale must be one number > 0, got 'abc'"),
    (["show", "g_channels.npz"], "g_channels.npz: channel_names must be a list of strings"),
    (["grasp", "mug", "--config", "random.toml"], "config file random.toml is not UTF-8 text: it is a file of another"),
    (["grasp", "mug", "--config", "png.toml"], "config file png.toml is not UTF-8 text: it is a PNG image"),
    (["grasp", "mug", "--config", "bool_iters.toml"], "config key grasp.optim.iters must be int, got True"),
    (["grasp", "--depth", "emptyframes", "--config", "bounds.toml"], "config key bounds must be a list, got 'x'"),
    (["grasp", "mug", "--hand", "random_hand.toml"], "hand spec random_hand.toml is not UTF-8 text"),
    (["grasp", "mug", "--hand", "hand_mjcf.toml"], "hand spec hand_mjcf.toml mjcf must be a string, got 3"),
    (["train", "--out", "a_file"], "--out a_file is a file, not a folder"),
    (["grasp", "mug", "--seed", str(2**63)], r"seed must be an integer in \[0, 9223372036854775807\]"),
    (["render-depth", "mug", "--seed", str(2**63)], r"--seed must be an integer in \[0, 9223372036854775807\]"),
    (["render-depth", "mug", "--seed", "-1"], r"--seed must be an integer in \[0, 9223372036854775807\]"),
    (["dataset", "build", "--objects", "meshes", "--out", "d.mcap", "--seed", str(2**63)], "seed must be an integer"),
    (["train", "--seed", str(2**63)], "seed must be an integer in"),
    (["grasp", "mug", "--weights", "w_meta.npz"], "w_meta.npz is not an ffcgs checkpoint: its __meta__ entry is not "
                                                  "JSON text"),
    (["grasp", "mug", "--weights", "w_list.npz"], "w_list.npz is not an ffcgs checkpoint: its __meta__ entry is not a "
                                                  "JSON object"),
    # issue 36: unclear messages before
    (["grasp", "dir.obj"], r"folder dir.obj holds no mesh files \(obj, stl"),  # a folder is a list of objects
    (["eval", "dir.npz"], "grasp file dir.npz is a folder, not a file"),
    (["grasp", "mug", "--poses", "dir.npy"], "pose file dir.npy is a folder, not a file"),
    (["grasp", "mug", "--config", "dir.toml"], "config file dir.toml is a folder, not a file"),
    (["grasp", "mug", "--hand", "dir.toml"], "hand spec dir.toml is a folder, not a file"),
    (["grasp", "mug", "--weights", "dir.npz"], "cvae weights file dir.npz is a folder, not a file"),
    (["dataset", "info", "dir.npz"], "dataset file dir.npz is a folder, not a file"),
    (["train", "--data.path", "dir.npz"], "dataset file dir.npz is a folder, not a file"),
    (["dataset", "build", "--objects", "a_file", "--out", "d.mcap"], "objects directory a_file is a file, not a folder"),
    (["grasp", "--depth", "fr_json"], "fr_json/camera.json is not UTF-8 text: it is a PNG image"),
    (["grasp", "--depth", "emptyframes"], "depth folder emptyframes is empty: it holds no depth frames"),
    (["grasp", "stl.obj"], "stl.obj is not a Wavefront OBJ: it looks like a binary STL"),
    (["grasp", "obj.stl"], "obj.stl is not an STL: it looks like a Wavefront OBJ"),
    (["grasp", "random.ply"], "random.ply is not a PLY mesh: it is a file of another format"),
    (["eval", "box_grasps.npz"], r"box.stl \(scale 1\) is not the object these grasps were made for \(.*box.stl, "
                                 r"scale 1\): its content changed since \(content hash"),
    (["eval", "g_none.npz", "--all"], "g_none.npz has no grasps$"),
    (["eval", "g_33.npz"], r"grasp file g_33.npz: wrist_pose must have shape \(B, 4, 4\), got \(2, 3, 3\)"),
    (["eval", "g_nan.npz"], r"grasp file g_nan.npz: wrist_pose contains NaN or inf \(grasp 0\)"),
    (["eval", "g_scaled.npz"], "grasp file g_scaled.npz: wrist_pose must be rigid transforms"),
    (["eval", "g_q16.npz"], "grasp file g_q16.npz: q has 16 channels, hand schunk_svh_right has 9: pass --hand"),
    (["eval", "g_sha.npz"], "grasp file g_sha.npz: object_sha256 must be one string"),
    (["grasp", "mug", "--config", "latin1.toml"], "latin1.toml is not UTF-8 text: byte 5 is not UTF-8"),
    (["grasp", "mug", "--weights", "w_shapes.npz"], "w_shapes.npz: its parameters do not fit its model config"),
    (["dataset", "info", "notes.txt"], "notes.txt is not an MCAP file .bad magic.: it is a text file"),
    (["dataset", "info", "magic.mcap"], r"magic.mcap is not a readable MCAP file: it is truncated or corrupt \(a record"),
]


@pytest.mark.parametrize("argv,message", CASES, ids=[" ".join(a) for a, _ in CASES])
def test_bad_input_gives_one_line_and_touches_nothing(inputs, capsys, argv, message):
    before = snapshot(inputs)
    code = cli_main.main(argv)
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    errors = [ln for ln in lines if ln.startswith("ffcgs: error: ")]
    assert code == 2, err
    # warnings may precede the error, and so may what the command said while it ran before it found the problem
    # (its first line and its compiles, `runtime.progress`): nothing else, and exactly one error
    talk = [ln for ln in lines if not ln.startswith("ffcgs: ")]
    assert len(errors) == 1 and all(PROGRESS.match(ln) for ln in talk), err
    assert "Traceback" not in err
    assert re.search(message, errors[0]), errors[0]
    assert snapshot(inputs) == before


PROGRESS = re.compile(r"ffcgs [a-z -]+: |compiling .*|compiled .* in \d+ s|loaded .* from the compilation cache in "
                      r"\d+ s|.* ready in \d+ s")


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


# The command under test, with one line on stderr once its work has begun (at the command's start, or at its first
# large compile): the signal lands mid-run on a fast machine and a slow one alike, with no sleep to guess.
READY = "ffcgs-test: ready"
_READY_WRAPPER = f"""
import contextlib, sys
from ffcgs_jax.cli import commands, main
from ffcgs_jax.runtime import progress

def ready():
    print({READY!r}, file=sys.stderr, flush=True)

def at_start(fn):
    def run(cmd):
        ready()
        return fn(cmd)
    return run

at, argv = sys.argv[1], sys.argv[2:]
if at == "command":
    commands.COMMANDS.update({{k: (cls, at_start(fn)) for k, (cls, fn) in commands.COMMANDS.items()}})
else:
    compiling = progress.compiling

    @contextlib.contextmanager
    def compiling_ready(*args, **kwargs):
        with compiling(*args, **kwargs):
            ready()
            yield

    progress.compiling = compiling_ready
raise SystemExit(main.main(argv))
"""


def _interrupted(argv: list[str], cwd: Path, at: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "FFCGS_JAX_CACHE": "off"}
    proc = subprocess.Popen([sys.executable, "-c", _READY_WRAPPER, at, *argv], cwd=cwd, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    before = []
    for line in proc.stderr:
        if line.strip() == READY:
            break
        before.append(line)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=300)
    return subprocess.CompletedProcess(argv, proc.returncode, out, "".join(before) + err)


@pytest.mark.parametrize("argv,at", [
    (["grasp", "mug", "--out", "new/grasps.npz", "--mcap", "new/run.mcap"], "compile"),
    (["eval", "many.npz", "--all", "--protocol", "both"], "command"),
    (["dataset", "build", "--objects", "meshes", "--out", "new/d.mcap", "--per-object", "2", "--rotations", "1",
      "--planner.population", "64", "--planner.refine", "8"], "command"),
], ids=["grasp", "eval", "dataset-build"])
def test_sigint_ends_with_one_line_and_no_partial_output(inputs, argv, at):
    before = {p: (inputs / p).read_bytes() for p in ("good.npz", "many.npz")}
    r = _interrupted(argv, inputs, at)
    assert r.returncode == 130, (r.returncode, r.stderr[-2000:])
    assert r.stderr.strip().splitlines()[-1] == "ffcgs: interrupted" and "Traceback" not in r.stderr, r.stderr
    assert {p: (inputs / p).read_bytes() for p in before} == before
    written = [p for p in (inputs / "new").rglob("*") if p.is_file()] if (inputs / "new").exists() else []
    # the dataset build keeps its finished parts and config (that is how it resumes); nothing else may appear
    assert all(".tmp" not in p.name for p in written) and not list(inputs.glob(".*tmp*")), written
    if argv[0] != "dataset":
        assert written == [], written


def test_an_interrupt_before_the_package_loads_is_one_line_too(tmp_path):
    """Ctrl-C in the first moments of `ffcgs` (the handler is set before numpy, JAX or the commands load)."""
    code = ("import os, signal, sys\n"
            "from ffcgs_jax.cli import main\n"
            "signal.signal = (lambda set_: lambda s, h: (set_(s, h), os.kill(os.getpid(), s))[0])(signal.signal)\n"
            "raise SystemExit(main.main(['grasp', 'mug']))\n")
    r = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=120,
                       env={**os.environ, "JAX_PLATFORMS": "cpu"})
    assert r.returncode == 130 and r.stderr.strip().splitlines() == ["ffcgs: interrupted"], r.stderr


def test_help_into_a_closed_pipe_ends_quietly(tmp_path):
    r = subprocess.run(f"'{FFCGS}' grasp --help | head -1", shell=True, capture_output=True, text=True,
                       cwd=tmp_path)
    assert r.stdout.startswith("usage: ffcgs grasp") and "Traceback" not in r.stderr, r.stderr
