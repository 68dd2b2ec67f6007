"""The one writer every output goes through (`ffcgs_jax.core.files`): atomic replacement, outputs checked before the
work, input files recognised by their content."""

import os

import numpy as np
import pytest

from ffcgs_jax.core import files
from ffcgs_jax.core.errors import FfcgsError


def test_atomic_write_replaces_the_file(tmp_path):
    path = tmp_path / "a.bin"
    path.write_bytes(b"old")
    files.atomic_write(path, lambda f: f.write(b"new"))
    assert path.read_bytes() == b"new" and os.listdir(tmp_path) == ["a.bin"]


@pytest.mark.parametrize("error", [OSError(28, "No space left on device"), KeyboardInterrupt(), ValueError("bug")])
def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path, error):
    path = tmp_path / "grasps.npz"
    np.savez(path, q=np.arange(3))
    before = path.read_bytes()

    def half_then_fail(f):
        f.write(before[: len(before) // 2])
        raise error

    expected = FfcgsError if isinstance(error, OSError) else type(error)
    with pytest.raises(expected):
        files.atomic_write(path, half_then_fail)
    assert path.read_bytes() == before and os.listdir(tmp_path) == ["grasps.npz"]


def test_the_temporary_keeps_the_suffix_and_is_discarded_on_demand(tmp_path):
    """Writers that pick a format from the name (PIL, matplotlib, imageio) see the real suffix; the CLI's SIGINT
    handler removes what is being written."""
    with pytest.raises(RuntimeError):
        with files.atomic_path(tmp_path / "picture.png") as tmp:
            assert tmp.suffix == ".png" and tmp.parent == tmp_path
            tmp.write_bytes(b"half")
            files.discard_temporaries()
            assert not tmp.exists()
            raise RuntimeError("stop here")
    assert os.listdir(tmp_path) == []


def test_check_output_creates_the_folder_or_refuses(tmp_path):
    assert files.check_output(tmp_path / "a" / "b" / "out.npz") == tmp_path / "a" / "b" / "out.npz"
    assert (tmp_path / "a" / "b").is_dir()
    with pytest.raises(FfcgsError, match="is a folder"):
        files.check_output(tmp_path / "a", "--out")
    (tmp_path / "plain").write_text("x")
    with pytest.raises(FfcgsError, match="--png .*a file stands where its folder should be"):
        files.check_output(tmp_path / "plain" / "x.png", "--png")
    with pytest.raises(FfcgsError, match="is a file, not a folder"):
        files.check_folder(tmp_path / "plain", "--png")
    assert files.check_folder(tmp_path / "gallery").is_dir()


@pytest.mark.parametrize("content,kind", [(b"", "an empty file"), (b"hello\n", "a text file"),
                                          (b"\x89MCAP0\r\n", "an MCAP file"), (b"\x89PNG\r\n\x1a\n", "a PNG image"),
                                          (bytes(range(200, 256)), "a file of another format")])
def test_read_npz_names_what_the_file_is(tmp_path, content, kind):
    path = tmp_path / "x.npz"
    path.write_bytes(content)
    with pytest.raises(FfcgsError, match=f"x.npz is not a readable grasp .npz: it is {kind}$"):
        files.read_npz(path, "grasp file", "grasp .npz")


def test_read_npz_refuses_pickles_and_broken_zips_and_reads_npy(tmp_path):
    np.savez(tmp_path / "p.npz", a=np.array([{"x": 1}], dtype=object))
    with pytest.raises(FfcgsError, match="pickled Python objects"):
        files.read_npz(tmp_path / "p.npz")
    np.savez(tmp_path / "ok.npz", a=np.arange(1000))
    (tmp_path / "cut.npz").write_bytes((tmp_path / "ok.npz").read_bytes()[:300])
    with pytest.raises(FfcgsError, match="cut.npz is not a readable .npz"):
        files.read_npz(tmp_path / "cut.npz")
    np.save(tmp_path / "poses.npy", np.eye(4)[None])
    assert files.read_npz(tmp_path / "poses.npy", npy=True)[""].shape == (1, 4, 4)
    with pytest.raises(FfcgsError, match="is not a readable .npz: it is a NumPy .npy array"):
        files.read_npz(tmp_path / "poses.npy")
    with pytest.raises(FfcgsError, match="pose file not found"):
        files.read_npz(tmp_path / "none.npy", "pose file", npy=True)


def test_last_words_run_before_the_temporaries_go_and_only_while_their_block_runs(tmp_path):
    """A process that exits at once (the CLI's SIGINT, SIGTERM) still writes what its `last_words` record: a record
    that fails does not stop the others, nor the cleanup."""
    said = []

    def fails():
        raise OSError("the disk went away")

    with files.last_words(lambda: files.write_text(tmp_path / "said.txt", "stage: 12.5 s")), files.last_words(fails):
        with pytest.raises(RuntimeError), files.atomic_path(tmp_path / "half.npz") as tmp:
            tmp.write_bytes(b"half")
            files.discard_temporaries()
            raise RuntimeError("stop here")
    assert (tmp_path / "said.txt").read_text() == "stage: 12.5 s" and sorted(os.listdir(tmp_path)) == ["said.txt"]
    with files.last_words(lambda: said.append(1)):
        pass
    files.discard_temporaries()
    assert said == []  # the block ended: nothing left to say
