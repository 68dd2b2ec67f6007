"""Issue 47, "Trust on the first run", through the CLI: a resumed `ffcgs grasp` of a folder keys its skips on
contents (the hand spec and the MJCF it names, the weights files, the mesh's geometry), not on paths; and the
inputs that were silently ignored or blamed on the wrong thing each get one line naming the real cause.

Nothing here compiles the synthesis: the resume tests fill the output folder as a finished run would and stub the
synthesis (`synthesis.many.synthesize`), so that only which objects are done again is measured.
"""

import contextlib
import hashlib
import io
import shutil
from pathlib import Path

import numpy as np
import pytest
import trimesh

from ffcgs_jax.core import files
from ffcgs_jax.cli import grasp_many
from ffcgs_jax.cli import main as cli_main
from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.geometry import mesh_io
from ffcgs_jax.hand.spec import load_spec
from ffcgs_jax.learning import weights as shipped
from ffcgs_jax.training.config import EvaluatorTrainConfig, TrainConfig, to_toml
from ffcgs_jax.synthesis import grasp_io, many

TOY_HAND = Path(__file__).parents[1] / "data" / "toy_hand"
SVH = load_spec("svh").name  # the shipped weights' files are named after the spec's name
BOXES = {"a_box": (0.05, 0.08, 0.14), "b_box": (0.06, 0.09, 0.10)}


def _main(*argv) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = cli_main.main([str(a) for a in argv])
    return code, out.getvalue(), err.getvalue()


def _one_line(code: int, err: str, pattern: str) -> None:
    assert code == 2 and err.startswith("ffcgs: error:") and err.count("\n") == 1, err
    assert pattern in err, err


def _cmd(*argv):
    _, _, cmd = cli_main.parse_command(["grasp", *map(str, argv)])
    return cmd


@pytest.fixture
def hand(tmp_path) -> Path:
    """The toy hand's spec and MJCF, copied where a test may edit them in place."""
    shutil.copytree(TOY_HAND, tmp_path / "hand")
    return tmp_path / "hand" / "toy.toml"


@pytest.fixture
def evaluator(tmp_path) -> Path:
    """A success-predictor weights file of the user's (the shipped one's bytes), to be overwritten in place."""
    path = tmp_path / "evaluator.npz"
    shutil.copyfile(shipped.shipped_evaluator(SVH), path)
    return path


# ----------------------------------------------------------------------------------------------------------------
# resume keys from contents: unit level
# ----------------------------------------------------------------------------------------------------------------

def test_settings_follow_the_hand_spec_content_not_its_path(hand, tmp_path):
    before = grasp_many.settings_text(_cmd("box", "--hand", hand))
    elsewhere = tmp_path / "moved"
    shutil.copytree(hand.parent, elsewhere)
    assert grasp_many.settings_text(_cmd("box", "--hand", elsewhere / "toy.toml")) == before  # same content
    hand.write_text(hand.read_text().replace("upper = [1.2, 1.0]", "upper = [1.1, 1.0]"))  # edited in place
    edited = grasp_many.settings_text(_cmd("box", "--hand", hand))
    assert edited != before
    mjcf = hand.parent / "toy.xml"  # the spec file unchanged; the MJCF it names edited in place
    mjcf.write_text(mjcf.read_text().replace('size="0.03 0.01 0.02"', 'size="0.03 0.01 0.025"'))
    assert grasp_many.settings_text(_cmd("box", "--hand", hand)) not in (before, edited)


def test_settings_follow_the_weights_content(evaluator, tmp_path, monkeypatch):
    before = grasp_many.settings_text(_cmd("box", "--evaluator", evaluator))
    evaluator.write_bytes(shipped.shipped_weights(SVH).read_bytes())  # another file copied over it
    assert grasp_many.settings_text(_cmd("box", "--evaluator", evaluator)) != before
    # the shipped defaults count by content too: a package whose shipped sampler changed does again
    cvae = tmp_path / "cvae_svh.npz"
    shutil.copyfile(shipped.shipped_weights(SVH), cvae)
    monkeypatch.setattr(shipped, "shipped_weights", lambda name: cvae)
    default = grasp_many.settings_text(_cmd("box"))
    assert grasp_many.weights_sha256(_cmd("box").grasp, SVH)["cvae"] == hashlib.sha256(cvae.read_bytes()).hexdigest()
    cvae.write_bytes(cvae.read_bytes() + b"\0")
    assert grasp_many.settings_text(_cmd("box")) != default
    # a geometric sampler reads no CVAE weights: they do not key its files
    geometric = grasp_many.settings_text(_cmd("box", "--sampler", "geometric"))
    cvae.write_bytes(cvae.read_bytes() + b"\0")
    assert grasp_many.settings_text(_cmd("box", "--sampler", "geometric")) == geometric


def test_the_mesh_counts_by_its_geometry_as_loaded(tmp_path):
    """A .gltf whose buffer file changes keeps its own bytes: the key still changes. The scale counts."""
    box = trimesh.creation.box((0.05, 0.06, 0.07))
    for name, data in trimesh.exchange.gltf.export_gltf(trimesh.Scene(box)).items():
        (tmp_path / name).write_bytes(data)
    gltf = tmp_path / "model.gltf"
    key = grasp_many.mesh_key(str(gltf), 1.0)
    assert key == mesh_io.mesh_sha256(mesh_io.load_mesh(gltf)) and len(key) == 64
    assert grasp_many.mesh_key(str(gltf), 0.5) != key
    gltf_bytes = gltf.read_bytes()
    bigger = trimesh.creation.box((0.05, 0.06, 0.09))
    for name, data in trimesh.exchange.gltf.export_gltf(trimesh.Scene(bigger)).items():
        if name.endswith(".bin"):
            (tmp_path / name).write_bytes(data)
    assert gltf.read_bytes() == gltf_bytes and grasp_many.mesh_key(str(gltf), 1.0) != key
    assert grasp_many.mesh_key(str(tmp_path / "missing.obj"), 1.0) == ""
    settings = grasp_many.settings_text(_cmd("box"))
    assert grasp_many.run_key(settings, key) != grasp_many.run_key(settings, "0" * 64)
    assert grasp_many.run_key(settings, "") == ""  # a mesh that does not load is never "done"


# ----------------------------------------------------------------------------------------------------------------
# resume keys from contents: `ffcgs grasp DIR --out O` after an edit in place
# ----------------------------------------------------------------------------------------------------------------

@pytest.fixture
def finished(tmp_path, monkeypatch, hand, evaluator):
    """A folder of two boxes and an --out folder holding what a finished run with these options wrote (as far as
    resuming reads it), and the synthesis stubbed: each object it is asked for is recorded and fails."""
    meshes = tmp_path / "meshes"
    meshes.mkdir()
    for name, extents in BOXES.items():
        trimesh.creation.box(extents=extents).apply_translation((0, 0, extents[2] / 2)).export(meshes / f"{name}.obj")
    out = tmp_path / "grasps"
    argv = ["grasp", meshes, "--out", out, "--hand", hand, "--evaluator", evaluator]
    cmd = _cmd(*argv[1:])
    settings = grasp_many.settings_text(cmd)
    out.mkdir()
    for name in BOXES:
        key = grasp_many.run_key(settings, grasp_many.mesh_key(str(meshes / f"{name}.obj"), 1.0))
        files.add_to_manifest(out, f"{name}.npz", grasp_many.WRITTEN_BY)
        grasp_io.save_arrays({"wrist_pose": np.eye(4)[None], "q": np.zeros((1, 2)), "valid": np.ones(1, bool),
                              "E": np.ones(1), "run_key": np.array(key)}, out / f"{name}.npz")
    calls = []

    def stub(hand, mesh, cfg, object_name):
        calls.append(object_name)
        raise FfcgsError("stubbed synthesis")

    monkeypatch.setattr(many, "synthesize", stub)
    monkeypatch.setattr(many, "build_sdf", lambda mesh, cfg: None)  # no SDF compile for the stub
    return argv, calls, meshes


def test_a_finished_run_is_skipped_whole(finished):
    argv, calls, _ = finished
    code, out, err = _main(*argv)
    assert code == 0, err
    assert calls == [] and "2 of 2 objects already written with these settings, skipped" in out


def test_a_hand_spec_edited_in_place_does_every_object_again(finished, hand):
    argv, calls, _ = finished
    hand.write_text(hand.read_text().replace("upper = [1.2, 1.0]", "upper = [1.1, 1.0]"))
    code, out, err = _main(*argv)
    assert calls == ["a_box", "b_box"], out
    assert "0 of 2 objects already written with these settings, skipped; 2 written with other settings" in out
    assert code == 1 and err.count("stubbed synthesis") == 2


def test_weights_copied_over_the_file_do_every_object_again(finished, evaluator):
    argv, calls, _ = finished
    evaluator.write_bytes(shipped.shipped_weights(SVH).read_bytes())
    _main(*argv)
    assert calls == ["a_box", "b_box"]


def test_a_mesh_rewritten_with_other_geometry_is_done_again_alone(finished):
    argv, calls, meshes = finished
    trimesh.creation.box(extents=(0.05, 0.08, 0.12)).export(meshes / "a_box.obj")
    code, out, _ = _main(*argv)
    assert calls == ["a_box"] and "1 of 2 objects already written with these settings, skipped" in out


# ----------------------------------------------------------------------------------------------------------------
# options that were ignored, and causes that were misnamed
# ----------------------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("given, said", [
    (["--need", "5", "--protocol", "lift-shake"], "--need and --protocol take effect only with --validate"),
    (["--need", "5"], "--need takes effect only with --validate"),
    (["--protocol", "six-dir"], "--protocol takes effect only with --validate"),
])
def test_physics_options_without_validate_are_refused(tmp_path, given, said):
    code, _, err = _main("grasp", "mug", *given, "--out", tmp_path / "g.npz")
    _one_line(code, err, said)
    assert not (tmp_path / "g.npz").exists()


def test_the_same_file_given_twice_is_named(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    trimesh.creation.box().export("a.stl")
    code, _, err = _main("grasp", "a.stl", "a.stl", "--out", "O")
    _one_line(code, err, "the same object 'a.stl' is given twice")
    assert "rename" not in err
    code, _, err = _main("grasp", "a.stl", "./a.stl", "--out", "O")
    _one_line(code, err, "the same object 'a.stl' (also as './a.stl') is given twice")
    assert not Path("O").exists()


@pytest.mark.parametrize("scale, size", [("1e300", "1.17e+299 m across"), ("1e-300", "1.17e-301 m across")])
def test_an_absurd_scale_is_named_not_the_mesh(tmp_path, scale, size):
    code, _, err = _main("sdf", "mug", "--scale", scale, "--out", tmp_path / "s.npz")
    _one_line(code, err, f"scale {float(scale):g} (--scale) makes mesh")
    assert size in err and "degenerate" not in err


def _grasp_file(path: Path, q_width: int, names: bool) -> Path:
    n, svh = 2, load_spec("svh").channel_names
    arrays = {"wrist_pose": np.tile(np.eye(4), (n, 1, 1)), "q": np.zeros((n, q_width)),
              "squeeze_dir": np.ones((n, len(svh))), "valid": np.ones(n, bool)}
    grasp_io.save_arrays(arrays | ({"channel_names": np.array(svh)} if names else {}), path)
    return path


def test_a_q_of_the_wrong_width_is_named_with_the_hands_width(tmp_path):
    code, _, err = _main("eval", _grasp_file(tmp_path / "g.npz", 8, names=True), "--object", "box")
    _one_line(code, err, "q has 8 columns, but the hand the grasps were made for has 9 channels")
    assert "q must have shape (B, 9)" in err and "squeeze_dir must" not in err
    # a file without channel_names: neither array is blamed alone
    code, _, err = _main("eval", _grasp_file(tmp_path / "h.npz", 8, names=False), "--object", "box")
    _one_line(code, err, "q has 8 columns and squeeze_dir 9")


def test_the_advice_to_resume_an_evaluator_run_works(tmp_path, monkeypatch):
    """The refusal of another config's run folder advises a command; following it must not lead to "unknown config
    key net" (the sampler's parser reading the predictor's config)."""
    monkeypatch.chdir(tmp_path)
    run = Path("run")
    run.mkdir()
    (run / "config.toml").write_text(to_toml(EvaluatorTrainConfig(out="run", seed=5)))
    (run / "checkpoint.npz").write_bytes(b"a run's checkpoint")
    code, _, err = _main("train", "--model", "evaluator", "--out", "run")
    _one_line(code, err, "resume it with `ffcgs train --model evaluator --config run/config.toml`")
    code, _, err = _main("train", "--model", "evaluator", "--config", "run/config.toml")
    assert "unknown config key" not in err  # the advice parses (what follows is the missing dataset)
    code, _, err = _main("train", "--config", "run/config.toml")  # --model left out: the hint says so
    _one_line(code, err, "[net] is the evaluator's section: add --model evaluator")
    sampler = Path("sampler")
    sampler.mkdir()
    (sampler / "config.toml").write_text(to_toml(TrainConfig(out="sampler", seed=5)))
    (sampler / "checkpoint.npz").write_bytes(b"a run's checkpoint")
    code, _, err = _main("train", "--out", "sampler")
    _one_line(code, err, "resume it with `ffcgs train --config sampler/config.toml`")

