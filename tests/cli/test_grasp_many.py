"""`ffcgs grasp` of several objects or a folder: one file per object equal to a one-object run, a broken mesh that
costs only itself, resuming after an interruption with nothing partial left, and what is refused up front.

The objects are two boxes of 12 faces each (one SDF build, one descent and one evaluation executable for both) with
the settings of tests/cli/test_cli_grasp.py, so a session compiles once.
"""

import contextlib
import hashlib
import io
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

from ffcgs_jax.core import files
from ffcgs_jax.cli import main as cli_main
from ffcgs_jax.cli.commands import GraspCmd
from ffcgs_jax.geometry import mesh_io
from ffcgs_jax.geometry.config import SDFConfig
from ffcgs_jax.hand import kinematics as K
from ffcgs_jax.synthesis import many
from ffcgs_jax.synthesis.config import GraspConfig, OptimConfig
from ffcgs_jax.synthesis.grasp import synthesize

N, ITERS = 4, 5
SMALL = ["--n", str(N), "--iters", str(ITERS), "--res", "16"]
CFG = GraspConfig(n=N, sdf=SDFConfig(res=16), optim=OptimConfig(iters=ITERS))  # what SMALL sets
BOXES = {"a_box": (0.05, 0.08, 0.14), "b_flat": (0.06, 0.09, 0.10)}  # extents, metres


def _write_boxes(folder: Path) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for name, extents in BOXES.items():
        box = trimesh.creation.box(extents=extents)
        box.apply_translation((0, 0, extents[2] / 2))  # on the table
        box.export(folder / f"{name}.obj")
    return folder


def _main(*argv) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = cli_main.main(list(argv))
    return code, out.getvalue(), err.getvalue()


def _tree(folder: Path) -> dict[str, str]:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.iterdir())}


@pytest.fixture(scope="module")
def folder_run(tmp_path_factory):
    """A folder of two boxes and a text file named bad.obj, grasped in one call."""
    d = tmp_path_factory.mktemp("many")
    meshes = _write_boxes(d / "meshes")
    (meshes / "bad.obj").write_text("not a mesh at all\n")
    code, out, err = _main("grasp", str(meshes), "--out", str(d / "grasps"), *SMALL)
    return code, out, err, meshes, d / "grasps"


@pytest.mark.e2e  # the folder run of the module: 60 s on the 2-core CPU
def test_a_broken_mesh_is_one_line_and_the_others_are_done(folder_run):
    code, out, err, meshes, grasps = folder_run
    assert code == 1, err
    lines = [ln for ln in err.splitlines() if "bad.obj" in ln]
    assert len(lines) == 1 and lines[0].startswith("ffcgs: error: bad: ") and "holds no triangles" in lines[0], err
    assert re.search(r"^bad\s+-\s+-\s+-\s+\d+\.\d\d\s+failed$", out, re.M), out
    for name in BOXES:
        assert re.search(rf"^{name}\s+\d+ / {N}\s.*\sdone$", out, re.M), out
    assert re.search(r"^total\s+\d+ / 8\s.*2 done, 1 failed$", out, re.M), out
    assert sorted(p.name for p in grasps.iterdir()) == [files.MANIFEST, "a_box.npz", "b_flat.npz"]
    manifest = json.loads((grasps / files.MANIFEST).read_text())
    assert {k: manifest[k] for k in ("written_by", "files")} == {"written_by": "ffcgs grasp",
                                                                 "files": ["a_box.npz", "b_flat.npz"]}


@pytest.mark.e2e  # the folder run of the module: 60 s on the 2-core CPU
def test_each_file_equals_a_one_object_run(folder_run):
    from ffcgs_jax.synthesis import grasp_io

    _, _, _, meshes, grasps = folder_run
    hand = K.load_hand("svh")
    saved = {}
    for name in BOXES:
        gs = synthesize(hand, mesh_io.load_mesh(meshes / f"{name}.obj"), CFG, object_name=name)
        saved[name] = a = grasp_io.load_npz(grasps / f"{name}.npz")
        for k, v in gs.arrays.items():
            if not k.endswith("_s"):  # timings
                np.testing.assert_array_equal(a[k], v, err_msg=f"{name}: {k}")
        assert str(a["object_name"]) == name and str(a["object_source"]) == str((meshes / f"{name}.obj").resolve())
        assert len(str(a["run_key"])) == 64
    assert np.abs(saved["a_box"]["wrist_pose"] - saved["b_flat"]["wrist_pose"]).max() > 1e-3  # two objects' grasps


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


@pytest.mark.e2e  # 72 s on the 2-core CPU: two objects synthesised, one of them twice
@pytest.mark.parametrize("where", ["synthesis", "write"])
def test_an_interrupted_run_leaves_whole_files_and_resumes(tmp_path, monkeypatch, where):
    """Ctrl-C on the second object, in its synthesis or half-way through writing its file: the first object's file
    is whole and kept, nothing else is left; the same command again does only the second object."""
    meshes = _write_boxes(tmp_path / "meshes")
    out = tmp_path / "grasps"
    argv = ["grasp", str(meshes), "--out", str(out), *SMALL]
    calls = []
    real_synthesize, real_savez = many.synthesize, np.savez_compressed

    def synthesize_then_stop(hand, mesh, cfg, object_name):
        calls.append(object_name)
        if where == "synthesis" and len(calls) == 2:
            raise KeyboardInterrupt
        return real_synthesize(hand, mesh, cfg, object_name=object_name)

    def write_half_then_stop(f, **arrays):
        if len(calls) == 2:
            f.write(b"PK\x03\x04 half a zip")
            raise KeyboardInterrupt
        real_savez(f, **arrays)

    with monkeypatch.context() as m:
        m.setattr(many, "synthesize", synthesize_then_stop)
        m.setattr(np, "savez_compressed", write_half_then_stop if where == "write" else real_savez)
        code, _, err = _main(*argv)
    assert code == 130 and "interrupted" in err
    assert calls == ["a_box", "b_flat"]
    names = sorted(p.name for p in out.iterdir())
    assert names == [files.MANIFEST, "a_box.npz"], names  # no b_flat.npz, whole or partial; no temporary
    assert set(files.manifest_files(out)) >= {"a_box.npz"}  # the manifest names every file there
    first = _tree(out)["a_box.npz"]
    (out / f".b_flat.ffcgs.{_dead_pid()}.0123abcd.tmp.npz").write_bytes(b"left by a run that was killed")

    calls.clear()
    monkeypatch.setattr(many, "synthesize", lambda hand, mesh, cfg, object_name: calls.append(object_name) or
                        real_synthesize(hand, mesh, cfg, object_name=object_name))
    code, stdout, err = _main(*argv)
    assert code == 0, err
    assert calls == ["b_flat"]  # a_box was not done again
    assert "1 of 2 objects already written with these settings, skipped" in stdout
    assert re.search(r"^a_box\s+\d+ / 4\s.*\s-\s+skipped$", stdout, re.M), stdout
    assert sorted(_tree(out)) == [files.MANIFEST, "a_box.npz", "b_flat.npz"]  # the killed run's temporary is gone
    assert _tree(out)["a_box.npz"] == first

    calls.clear()
    code, stdout, _ = _main(*argv, "--seed", "1")  # other settings: both again
    assert code == 0 and calls == ["a_box", "b_flat"]
    assert "0 of 2 objects already written with these settings, skipped; 2 written with other settings" in stdout


@pytest.mark.e2e  # 69 s on the 2-core CPU: two objects synthesised and simulated
def test_validate_checks_each_object(tmp_path):
    meshes = tmp_path / "meshes"
    _write_boxes(meshes)
    (meshes / "b_flat.obj").unlink()
    code, out, err = _main("grasp", str(meshes), "--out", str(tmp_path / "g"), "--validate", "--protocol",
                           "lift-shake", *SMALL)
    assert code == 0, err
    from ffcgs_jax.synthesis import grasp_io

    a = grasp_io.load_npz(tmp_path / "g" / "a_box.npz")
    assert json.loads(str(a["physics_protocols"])) == ["lift-shake"] and "physics_passed" in a
    assert re.search(r"^object\s+valid / total\s+passed\s", out, re.M), out


@pytest.fixture
def work(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    for name in ("m", "m2"):
        (tmp_path / name).mkdir()
    trimesh.creation.box().export(tmp_path / "m" / "a.obj")
    trimesh.creation.box().export(tmp_path / "m2" / "a.stl")
    (tmp_path / "taken").mkdir()
    (tmp_path / "taken" / "notes.txt").write_text("mine")
    (tmp_path / "frames").mkdir()
    (tmp_path / "frames" / files.MANIFEST).write_text(json.dumps({"written_by": "ffcgs render-depth",
                                                                  "files": []}))
    return tmp_path


@pytest.mark.parametrize("argv, message", [
    (["m", "--png", "x.png"], "--png is about one object"),
    (["m", "box", "--show"], "--show is about one object"),
    (["m", "--depth", "frames"], "--depth is about one object"),
    (["m", "box", "--out", "g.npz"], "--out g.npz: with several objects or a folder, --out names a folder"),
    (["m", "m2"], r"two objects are named 'a' \(m/a.obj and m2/a.stl\)"),
    (["m", "--out", "taken"], r"--out taken holds 1 file\(s\) that this command did not write \(e.g. notes.txt\); "
                              "choose a new or empty folder, or one that earlier runs of this command filled"),
    (["m", "--out", "frames"], "frames was written by ffcgs render-depth, not ffcgs grasp"),
    (["m", "--out", "m/grasps"], "lies inside the input folder m"),
], ids=["png", "show", "depth", "out-npz", "same-name", "foreign-file", "another-command", "inside-input"])
def test_refused_with_one_line_before_any_work(work, argv, message):
    before = {p: p.stat().st_mtime_ns for p in work.rglob("*")}
    code, out, err = _main("grasp", *argv, *SMALL)
    assert code == 2 and err.startswith("ffcgs: error:") and err.count("\n") == 1, err
    assert re.search(message, err), err
    assert {p: p.stat().st_mtime_ns for p in work.rglob("*")} == before and not out


def test_the_default_out_is_a_file_for_one_object_and_a_folder_for_many(work):
    assert GraspCmd(object=("box",)).out_path == "grasps.npz"
    assert GraspCmd(object=("box", "mug")).out_path == GraspCmd(object=("m",)).out_path == "grasps/"
    assert GraspCmd(object=("m",), out="elsewhere").out_path == "elsewhere"
    assert not GraspCmd(object=("box",)).many and os.path.isdir("m")
