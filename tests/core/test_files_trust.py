"""Folders and files that belong to their run (`ffcgs_jax.core.files`, issue 47): a manifest names the command and the
run that wrote it and a folder of another command is refused; only temporaries marked as the package's are cleaned;
updates of one file or manifest are serialised by a lock; writes follow symlinks."""

import json
import os
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import pytest

from ffcgs_jax.core import files, locks
from ffcgs_jax.cli import output_plan
from ffcgs_jax.core.errors import FfcgsError

PACKAGE = Path(files.__file__).parent.parent


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def _tree(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in folder.rglob("*") if p.is_file()}


def _grasp_folder(path: Path, run: bool = True) -> Path:
    """A folder of `ffcgs grasp` results: grasp files and the manifest that run wrote (an older version's, without
    the run, when `run` is False)."""
    path.mkdir()
    (path / "mug.npz").write_bytes(b"PK\x03\x04 the user's grasps")
    m = {"written_by": "ffcgs grasp", "files": ["mug.npz"]}
    if run:
        m["run"] = {"id": "0123456789ab", "pid": 4242, "time": "2025-01-02T03:04:05+0000"}
    (path / files.MANIFEST).write_text(json.dumps(m))
    return path


def test_a_manifest_names_the_command_and_the_run(tmp_path):
    with files.write_folder(tmp_path / "frames", "ffcgs render-depth") as tmp:
        (tmp / "view_000.png").write_bytes(b"0")
    m = files.read_manifest(tmp_path / "frames")
    assert m["written_by"] == "ffcgs render-depth" and m["files"] == ["view_000.png"]
    assert m["run"]["pid"] == os.getpid() and len(m["run"]["id"]) == 12 and m["run"]["time"][:2] == "20"
    (tmp_path / "grasps").mkdir()
    files.add_to_manifest(tmp_path / "grasps", "a.npz", "ffcgs grasp")
    assert files.read_manifest(tmp_path / "grasps")["run"] == files.this_run()


def test_an_old_manifest_without_a_run_is_read(tmp_path):
    old = _grasp_folder(tmp_path / "g", run=False)
    m = files.read_manifest(old)
    assert m == {"written_by": "ffcgs grasp", "run": None, "files": ["mug.npz"]}
    assert files.check_folder_output(old, "--out", whole=False, written_by="ffcgs grasp") == old
    files.add_to_manifest(old, "box.npz", "ffcgs grasp")
    assert files.manifest_files(old) == {"mug.npz", "box.npz"}


@pytest.mark.parametrize("run", [True, False], ids=["with-run", "old-manifest"])
def test_a_folder_another_command_wrote_is_refused_without_overwrite(tmp_path, run):
    g = _grasp_folder(tmp_path / "g", run)
    before = _tree(g)
    with pytest.raises(FfcgsError) as e:
        files.check_folder_output(g, "--out", written_by="ffcgs render-depth")
    msg = str(e.value)
    assert "\n" not in msg and f"--out {g} was written by ffcgs grasp" in msg and "not ffcgs render-depth" in msg
    assert ("(run of time 2025-01-02T03:04:05+0000, pid 4242)" in msg) == run
    assert "pass --overwrite to replace it whole" in msg
    with pytest.raises(FfcgsError, match="choose another folder$"):  # filled a file at a time: no --overwrite
        files.check_folder_output(g, "--out", whole=False, written_by="ffcgs render-depth")
    assert files.check_folder_output(g, "--out", overwrite=True, written_by="ffcgs render-depth") == g
    assert _tree(g) == before
    (g / files.MANIFEST).write_text(json.dumps({"files": ["mug.npz"]}))  # no written_by: not this command's
    with pytest.raises(FfcgsError, match="was written by another command, not ffcgs grasp"):
        files.check_folder_output(g, "--out", whole=False, written_by="ffcgs grasp")


def test_temporary_names_are_marked_fresh_and_keep_the_suffix(tmp_path):
    a, b = files.temporary(tmp_path / "picture.png"), files.temporary(tmp_path / "picture.png")
    assert a != b and a.parent == tmp_path and a.suffix == ".png" and a.name.startswith(".picture.ffcgs.")
    assert files.is_ours(a.name) and files.is_ours(files.temporary(tmp_path / "frames", "old").name)
    assert files.is_ours(locks.lock_file(tmp_path / "g.npz").name)
    for name in (".notes.4242.tmp.txt", ".draft.31337.old", ".picture.4242.tmp.png", "notes.ffcgs.txt"):
        assert not files.is_ours(name), name


def test_only_marked_temporaries_of_dead_runs_are_removed(tmp_path):
    dead = _dead_pid()
    users = [f".notes.{dead}.tmp.txt", f".draft.{dead}.old", f".b_flat.{dead}.tmp.npz"]
    for name in users:
        (tmp_path / name).write_text("the user's")
    left = tmp_path / f".b_flat.ffcgs.{dead}.0123abcd.tmp.npz"  # what a run killed with SIGKILL left
    left.write_bytes(b"half")
    (tmp_path / f".frames.ffcgs.{dead}.0123abcd.old").mkdir()
    mine = files.temporary(tmp_path / "c.npz")  # this process's: being written
    mine.write_bytes(b"in progress")
    assert files.remove_left_behind(tmp_path) == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([*users, mine.name])
    # and a folder holding such a file of the user's is not replaced as if it held nothing of the user's
    (tmp_path / files.MANIFEST).write_text(json.dumps({"written_by": "ffcgs grasp", "files": []}))
    with pytest.raises(FfcgsError, match=r"holds 3 file\(s\) that this command did not write"):
        files.check_folder_output(tmp_path, "--out", written_by="ffcgs grasp")


def test_no_module_names_temporaries_of_its_own():
    """Every temporary name comes from `files.temporary`: a name made elsewhere from the process id would be one
    that the cleaning cannot tell from a user's."""
    makers = [str(p.relative_to(PACKAGE)) for p in PACKAGE.rglob("*.py")
              if p.name != "files.py" and "getpid(" in p.read_text()]
    assert makers == []


def test_a_lock_serialises_updates_and_leaves_no_lock_file(tmp_path, capsys):
    path = tmp_path / "g.npz"
    path.write_bytes(b"0")
    held, order = threading.Event(), []

    def first():
        with locks.locked(path):
            held.set()
            time.sleep(2.0)  # long enough that the second surely asks while it is held, even on a loaded machine
            order.append("first done")

    t = threading.Thread(target=first)
    t.start()
    held.wait(5)
    assert locks.lock_file(path).exists()
    with locks.locked(path):  # another open file description: waits as another process would
        order.append("second")
    t.join()
    assert order == ["first done", "second"]
    assert "waiting for another ffcgs run that is updating" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["g.npz"]


def test_a_lock_of_a_killed_run_is_free_and_cleaned(tmp_path):
    path = tmp_path / "g.npz"
    code = f"from ffcgs_jax.core import locks\nwith locks.locked({str(path)!r}):\n    print('held', flush=True)\n" \
           "    import time; time.sleep(60)\n"
    p = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        assert p.stdout.readline().strip() == "held"
        assert files.remove_left_behind(tmp_path) == 0  # held by a live run: kept
        p.kill()
        p.wait()
    finally:
        p.kill()
    assert locks.lock_file(path).exists()  # SIGKILL ran no cleanup, but the kernel released the lock
    done = threading.Event()

    def lock_and_release():
        with locks.locked(path):
            done.set()

    t = threading.Thread(target=lock_and_release, daemon=True)
    t.start()
    assert done.wait(5), "the lock of a killed run was not released"
    t.join(5)
    assert not locks.lock_file(path).exists()  # released: removed
    locks.lock_file(path).write_bytes(b"")  # as a killed run leaves it
    assert files.remove_left_behind(tmp_path) == 1 and not locks.lock_file(path).exists()


def test_concurrent_manifest_updates_lose_no_name(tmp_path):
    """Four processes fill one folder at once, as four `ffcgs grasp` runs would: the manifest names every file."""
    code = textwrap.dedent("""
        import sys
        from ffcgs_jax.core import files
        for i in range(15):
            files.add_to_manifest(sys.argv[1], f"{sys.argv[2]}_{i}.npz", "ffcgs grasp")
    """)
    procs = [subprocess.Popen([sys.executable, "-c", code, str(tmp_path), f"p{k}"]) for k in range(4)]
    assert [p.wait(60) for p in procs] == [0] * 4
    assert files.manifest_files(tmp_path) == {f"p{k}_{i}.npz" for k in range(4) for i in range(15)}
    assert sorted(p.name for p in tmp_path.iterdir()) == [files.MANIFEST]  # no lock file or temporary left


def test_a_plan_locks_the_input_it_updates(tmp_path):
    g = tmp_path / "g.npz"
    g.write_bytes(b"0")
    plan = output_plan.Plan((output_plan.Input("grasps", str(g), updated=True),),
                            (output_plan.Output("--out", str(g), "npz"),))
    other = output_plan.Plan((output_plan.Input("grasps", str(g), updated=True),),
                             (output_plan.Output("--out", str(tmp_path / "h.npz"), "npz"),))
    assert plan.updated == [files.resolved(g)] and other.updated == []
    with plan.outputs_together():
        assert locks.lock_file(g).exists()  # held from before the command reads g until its outputs land
        files.write_text(g, "1")
        assert g.read_text() == "0"
    assert g.read_text() == "1" and not locks.lock_file(g).exists()


def test_writes_follow_symlinks(tmp_path):
    (tmp_path / "runs").mkdir()
    real = tmp_path / "runs" / "g.npz"
    real.write_bytes(b"old")
    link = tmp_path / "g.npz"
    link.symlink_to(real)
    files.atomic_write(files.check_output(link), lambda f: f.write(b"new"))
    assert link.is_symlink() and real.read_bytes() == b"new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["g.npz", "runs"] and os.listdir(real.parent) == ["g.npz"]

    target = tmp_path / "store" / "frames"
    with files.write_folder(target, "ffcgs render-depth") as tmp:
        (tmp / "view_000.png").write_bytes(b"stale")
        (tmp / "view_001.png").write_bytes(b"stale")
    out = tmp_path / "frames"
    out.symlink_to(target)
    files.check_folder_output(out, "--out", written_by="ffcgs render-depth")
    with files.write_folder(out, "ffcgs render-depth") as tmp:
        (tmp / "view_000.png").write_bytes(b"new")
    assert out.is_symlink() and files.resolved(out) == files.resolved(target)
    assert _tree(target) == {files.MANIFEST: (target / files.MANIFEST).read_bytes(), "view_000.png": b"new"}
    assert sorted(p.name for p in (tmp_path / "store").iterdir()) == ["frames"]  # no swapped-out folder left
