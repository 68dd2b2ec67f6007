"""Outputs checked against inputs and each other before any work, written together or not at all, and folders
owned by the run that wrote them (`output_plan`, `files.outputs_together`, `files.write_folder`): the library
rules, random plans (hypothesis), and the cases a user met through the CLI."""

import errno
import hashlib
import json
import os
import re
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from paths import DATA

from ffcgs_jax.core import files
from ffcgs_jax.cli import main as cli_main
from ffcgs_jax.cli.commands import COMMANDS, PLANS
from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.cli.output_plan import FORMATS, Input, Output, Plan


def _tree(folder: Path) -> dict[str, str]:
    return {p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def _error(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    errors = [ln for ln in err if ln.startswith("ffcgs: error: ")]
    assert len(errors) == 1, err
    return errors[0]


# ------------------------------------------------------------------------------------------------------------------
# The plan's rules
# ------------------------------------------------------------------------------------------------------------------


def test_every_command_has_a_plan():
    assert set(PLANS) == set(COMMANDS)


@pytest.mark.parametrize("plan,message", [
    (Plan((Input("object", "a.stl"),), (Output("--out", "a.stl", "npz"),)), "is the input a.stl"),
    (Plan((Input("object", "sub/../a.stl"),), (Output("--out", "./a.stl", "npz"),)), "is the input"),
    (Plan((Input("object", "link.stl"),), (Output("--out", "a.stl", "npz"),)), "is the input"),  # link -> a.stl
    (Plan((), (Output("--out", "x.npz", "npz"), Output("--mcap", "x.npz", "mcap"))), "both name x.npz"),
    (Plan((), (Output("--out", "x.npz", "npz"), Output("--png", "x.jpg", "png"))), "must end in .png"),
    (Plan((), (Output("--out", "x.txt", "npz"),)), "must end in .npz"),
    (Plan((), (Output("--out", "dir", "folder"), Output("--png", "dir/p.png", "png"))), "inside the --out folder"),
    (Plan((Input("frames", "dir", folder=True),), (Output("--out", "dir/s.npz", "npz"),)), "inside the input folder"),
    (Plan((Input("object", "dir/m.stl"),), (Output("--out", "dir", "folder"),)), "holds the input"),
    (Plan((), (Output("--out", ".", "folder"),)), "current folder"),
    (Plan((), (Output("--out", "dir", "folder"),)), "did not write"),
])
def test_the_plan_refuses(tmp_path, monkeypatch, plan, message):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "a.stl").write_text("solid\n")
    (tmp_path / "sub").mkdir()
    (tmp_path / "link.stl").symlink_to(tmp_path / "a.stl")
    (tmp_path / "dir").mkdir()
    (tmp_path / "dir" / "m.stl").write_text("solid\n")
    before = _tree(tmp_path)
    with pytest.raises(FfcgsError, match=message):
        plan.check()
    assert _tree(tmp_path) == before


def test_the_plan_allows_an_update_in_place_and_built_in_names(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "g.npz").write_bytes(b"PK")
    Plan((Input("grasps", "g.npz", updated=True), Input("--object", "mug")),
         (Output("--out", "g.npz", "npz"), Output("--video", "g.gif", "video"))).check()
    Plan((Input("object", "mug"),), (Output("--out", "mug.npz", "npz"), Output("--png", "MUG.PNG", "png"))).check()


NAMES = st.sampled_from(["a.npz", "b.png", "a.png", "b.npz", "c.mcap", "d", "d/e.npz", "./a.npz", "d/../b.png"])


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(inputs=st.lists(NAMES, max_size=3), outputs=st.lists(st.tuples(NAMES, st.sampled_from(list(FORMATS))),
                                                            min_size=1, max_size=3))
def test_random_plans_pass_only_when_no_two_paths_meet(tmp_path_factory, inputs, outputs):
    """Whatever the names, a plan that passes has outputs that are pairwise apart, apart from every input (and
    not inside an input folder), and named with their format's extension; one that fails says so in one line."""
    root = tmp_path_factory.mktemp("plan")
    cwd = os.getcwd()
    os.chdir(root)
    try:
        for name in inputs:  # the inputs exist, as a user's files do
            p = root / name
            if p.suffix:
                p.parent.mkdir(parents=True, exist_ok=True)
                p.write_bytes(b"x")
            else:
                p.mkdir(parents=True, exist_ok=True)
        plan = Plan(tuple(Input(f"in{i}", n, folder=not Path(n).suffix) for i, n in enumerate(inputs)),
                    tuple(Output(f"--o{i}", n, f) for i, (n, f) in enumerate(outputs)))
        real = lambda n: Path(os.path.realpath(root / n))  # noqa: E731
        try:
            plan.check()
        except FfcgsError as e:
            assert "\n" not in str(e)
            return
        outs = [real(n) for n, _ in outputs]
        ins = [real(n) for n in inputs]
        assert len(set(outs)) == len(outs)
        for o, (name, fmt) in zip(outs, outputs):
            assert o not in ins and not any(i in o.parents for i in ins)
            suffixes = FORMATS[fmt][1]
            assert not suffixes or Path(name).suffix in suffixes
            if fmt == "folder":
                assert not any(o in x.parents for x in outs if x != o)
    finally:
        os.chdir(cwd)


# ------------------------------------------------------------------------------------------------------------------
# Outputs together, folders whole
# ------------------------------------------------------------------------------------------------------------------


def test_outputs_land_together_or_not_at_all(tmp_path):
    a, b, c = (tmp_path / n for n in ("a.npz", "b.png", "c.ply"))
    a.write_text("old a")
    with pytest.raises(FfcgsError, match="No space left"):
        with files.outputs_together([a, b, c]):
            files.write_text(a, "new a")
            files.write_text(b, "new b")
            assert a.read_text() == "old a" and not b.exists()  # written, not yet in place
            with files.atomic_path(c) as tmp:
                tmp.write_text("half")
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    assert a.read_text() == "old a" and not b.exists() and not c.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.npz"]  # no temporary left
    with files.outputs_together([a, b]):
        files.write_text(a, "new a")
        files.write_text(b, "new b")
        files.write_text(tmp_path / "side.txt", "not an output: in place at once")
        assert (tmp_path / "side.txt").exists() and a.read_text() == "old a"
    assert a.read_text() == "new a" and b.read_text() == "new b"


def test_an_output_written_twice_lands_once_with_the_last_content(tmp_path):
    a = tmp_path / "a.npz"
    with files.outputs_together([a]):
        files.write_text(a, "first")
        files.write_text(a, "second")
    assert a.read_text() == "second" and sorted(p.name for p in tmp_path.iterdir()) == ["a.npz"]


def test_an_interrupt_leaves_no_output_and_no_temporary(tmp_path):
    a = tmp_path / "a.npz"
    with pytest.raises(KeyboardInterrupt):
        with files.outputs_together([a]):
            files.write_text(a, "new")
            raise KeyboardInterrupt
    assert list(tmp_path.iterdir()) == []


def test_announcements_wait_for_the_outputs(tmp_path, capsys):
    a = tmp_path / "a.npz"
    with pytest.raises(RuntimeError):
        with files.outputs_together([a]):
            files.write_text(a, "x")
            files.announce("wrote a.npz")
            raise RuntimeError
    assert capsys.readouterr().out == "" and not a.exists()
    with files.outputs_together([a]):
        files.write_text(a, "x")
        files.announce("wrote a.npz")
        assert capsys.readouterr().out == ""
    assert capsys.readouterr().out == "wrote a.npz\n"


def test_a_folder_is_replaced_whole_and_an_interrupted_one_leaves_the_old(tmp_path):
    out = tmp_path / "frames"
    with files.write_folder(out, "test") as tmp:
        (tmp / "view_000.png").write_text("0")
        (tmp / "view_000_mask.png").write_text("m")
    assert files.manifest_files(out) == {"view_000.png", "view_000_mask.png"}
    before = _tree(out)
    with pytest.raises(KeyboardInterrupt):
        with files.write_folder(out, "test") as tmp:
            (tmp / "view_000.png").write_text("1")
            raise KeyboardInterrupt
    assert _tree(out) == before and sorted(p.name for p in tmp_path.iterdir()) == ["frames"]
    files.check_folder_output(out, "--out")  # ours, nothing added: may be replaced
    with files.write_folder(out, "test") as tmp:
        (tmp / "view_000.png").write_text("2")
    assert sorted(_tree(out)) == [files.MANIFEST, "view_000.png"]  # the old mask is gone with the old folder
    (out / "notes.txt").write_text("mine")
    with pytest.raises(FfcgsError, match=r"holds 1 file\(s\) that this command did not write \(e.g. notes.txt\)"):
        files.check_folder_output(out, "--out")
    files.check_folder_output(out, "--out", overwrite=True)


# ------------------------------------------------------------------------------------------------------------------
# The cases a user met (issue 36): exit 2 and nothing changed, or the right result
# ------------------------------------------------------------------------------------------------------------------


@pytest.fixture
def work(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "train.mcap").write_bytes((DATA / "dataset_v1.mcap").read_bytes())
    (tmp_path / "part.stl").write_bytes(b"solid part\nendsolid part\n")
    np.savez(tmp_path / "g.npz", wrist_pose=np.tile(np.eye(4), (2, 1, 1)), q=np.zeros((2, 9)))
    return tmp_path


@pytest.mark.parametrize("argv,message", [
    (["dataset", "info", "train.mcap", "--json", "train.mcap"], "--json train.mcap is the input train.mcap"),
    (["sdf", "part.stl", "--out", "part.stl"], "--out part.stl is the input part.stl"),
    (["grasp", "mug", "--out", "g2.npz", "--mcap", "g2.npz"], "--out and --mcap both name g2.npz"),
    (["sdf", "box", "--out", "x.png", "--png", "x.png"], "--out and --png both name x.png"),
    (["sdf", "box", "--png", "x.jpg"], "--png x.jpg: the command writes a PNG image there"),
    (["grasp", "mug", "--out", "x.txt"], "--out x.txt: the command writes a NumPy .npz archive"),
    (["eval", "g.npz", "--video", "v.gif", "--video-index", "99"], r"--video-index must be in \[0, 1\]"),
    (["eval", "g.npz", "--video-index", "0"], "--video-index chooses the grasp of --video"),
    (["fuse", "frames", "--out", "frames/view_000.png"], "inside the input folder frames"),
    (["render-depth", "box", "--out", "frames", "--png", "frames/f.png"], "inside the --out folder frames"),
    (["dataset", "export", "train.mcap", "--out", "train.mcap"], "is the input train.mcap"),
])
def test_a_command_never_writes_over_what_it_was_given(work, capsys, argv, message):
    (work / "frames").mkdir()
    (work / "frames" / "view_000.png").write_bytes(b"\x89PNG")
    before = _tree(work)
    assert cli_main.main(argv) == 2
    assert re.search(message, _error(capsys))
    assert _tree(work) == before


def test_a_failed_train_start_leaves_the_run_untouched(work, capsys):
    run = work / "RUN"
    run.mkdir()
    (run / "config.toml").write_text("# the earlier run's config\n")
    before = _tree(work)
    assert cli_main.main(["train", "--data.path", "missing.mcap", "--out", "RUN"]) == 2
    assert _tree(work) == before
    assert cli_main.main(["train", "--data.path", "missing.mcap", "--out", "NEW"]) == 2
    assert not (work / "NEW").exists()  # a new run that could not start leaves nothing behind
    capsys.readouterr()


def test_stale_frames_are_never_fused(work, capsys):
    """The user's sequence: masks of the mug, then frames of the box into the same folder; the box is fused from
    its own frames (no mug mask survives) and a file dropped there later is not read."""
    small = ["--width", "64", "--height", "48", "--no-noise"]
    assert cli_main.main(["render-depth", "mug", "--masks", "--views", "4", "--out", "fm", *small]) == 0
    assert cli_main.main(["render-depth", "box", "--views", "3", "--out", "fm", *small]) == 0
    names = sorted(p.name for p in (work / "fm").iterdir())
    assert names == [files.MANIFEST, "camera.json", "poses.json", "view_000.png", "view_001.png", "view_002.png"]
    (work / "fm" / "view_009_mask.png").write_bytes((work / "fm" / "view_000.png").read_bytes())
    from ffcgs_jax.geometry import depth_io

    frames = depth_io.load_frames(work / "fm")
    assert frames.mask is None and frames.names == ("view_000.png", "view_001.png", "view_002.png")
    assert cli_main.main(["render-depth", "box", "--views", "2", "--out", "fm", *small]) == 2  # a file not ours
    assert "view_009_mask.png" in _error(capsys)
    assert cli_main.main(["render-depth", "box", "--views", "2", "--out", "fm", "--overwrite", *small]) == 0
    assert json.loads((work / "fm" / files.MANIFEST).read_text())["files"] == \
        ["camera.json", "poses.json", "view_000.png", "view_001.png"]


def test_a_fuse_that_fails_writing_its_last_output_writes_none(work, capsys, monkeypatch):
    small = ["--width", "64", "--height", "48", "--no-noise", "--views", "3"]
    assert cli_main.main(["render-depth", "box", "--out", "fr", *small]) == 0
    capsys.readouterr()
    import trimesh

    def full_disk(self, *a, **k):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(trimesh.Trimesh, "export", full_disk)
    before = _tree(work)
    code = cli_main.main(["fuse", "fr", "--res", "16", "--out", "s.npz", "--png", "s.png", "--mesh", "s.ply"])
    out, err = capsys.readouterr()
    assert code == 2 and "No space left" in err and "wrote" not in out
    assert _tree(work) == before  # neither s.npz nor s.png, nor a temporary


@pytest.mark.parametrize("argv,module,message", [
    (["eval", "g.npz", "--video", "v.mp4"], "imageio_ffmpeg", "--video .mp4 needs imageio-ffmpeg"),
    (["grasp", "mug", "--show"], "viser", "--show needs viser"),
])
def test_a_missing_optional_module_is_named_before_the_work(work, capsys, monkeypatch, argv, module, message):
    import importlib.util

    find = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == module else find(name, *a))
    def no_work(*args, **kwargs):
        raise AssertionError("the work began (the hand loaded) before the missing module was named")

    # the first work of both commands: what a check that comes "before the work" must precede
    monkeypatch.setattr("ffcgs_jax.hand.kinematics.load_hand", no_work)
    monkeypatch.setattr("ffcgs_jax.synthesis.grasp_io.load_npz", no_work)
    before = _tree(work)
    assert cli_main.main(argv) == 2
    assert message in _error(capsys)
    assert _tree(work) == before
