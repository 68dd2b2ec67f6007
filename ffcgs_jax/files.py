"""Every file the package writes goes through here: outputs checked before the work starts, then written
atomically, so a failed or interrupted write leaves the previous file exactly as it was.

`check_output` is the one rule for output paths: the folder is created if missing, and a path that cannot be
written (a folder, a read-only place, a name under a file) is refused with one line before anything is loaded or
compiled. `atomic_write` / `atomic_path` write a temporary file in the same folder, flush and fsync it, then
`os.replace` it over the target; on any failure, KeyboardInterrupt included, the temporary file is removed and the
target is untouched.
"""

import codecs
import contextlib
import os
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO

import numpy as np

from ffcgs_jax.errors import FfcgsError


def check_output(path: str | Path, what: str = "output") -> Path:
    """`path` as a Path once it is known to be writable: its folder exists (created if missing) and it is not a
    folder itself. FfcgsError naming `what` and the path otherwise."""
    path = Path(path).expanduser()
    if not path.name or path.is_dir():
        raise FfcgsError(f"{what} {path} is a folder; give a file name")
    parent = path.parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):
        raise FfcgsError(f"cannot write {what} {path}: a file stands where its folder should be") from None
    except OSError as e:
        raise FfcgsError(f"cannot create the folder of {what} {path}: {e.strerror or e}") from None
    if not os.access(parent, os.W_OK | os.X_OK) or (path.exists() and not os.access(path, os.W_OK)):
        raise FfcgsError(f"cannot write {what} {path}: permission denied")
    return path


def check_outputs(*named: tuple[str, str | None]) -> None:
    """`check_output` on every (flag, path) pair of a command whose path is given, before the command does any work."""
    for flag, path in named:
        if path is not None:
            check_output(path, flag)


def check_folder(path: str | Path, what: str = "output folder") -> Path:
    """`path` as a writable folder (created if missing), or FfcgsError naming `what` and the path."""
    path = Path(path).expanduser()
    if path.exists() and not path.is_dir():
        raise FfcgsError(f"{what} {path} is a file, not a folder")
    check_output(path / ".probe", what)  # same rule as for files: parents created, write permission
    return path


_ACTIVE: set[Path] = set()  # temporary files being written now, for `discard_temporaries`


def discard_temporaries() -> None:
    """Remove the temporary files of writes in progress: for a process about to exit at once (the CLI's SIGINT),
    which runs no `finally` blocks."""
    for tmp in list(_ACTIVE):
        with contextlib.suppress(OSError):
            tmp.unlink()


def _temporary(path: Path) -> Path:
    # same folder (os.replace is atomic only within a filesystem), hidden, the suffix kept last so writers that
    # pick a format from the extension (PIL, imageio) still see it
    return path.with_name(f".{path.stem}.{os.getpid()}.tmp{path.suffix}")


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """A temporary path to write in place of `path`; it replaces `path` when the block ends without an error."""
    path = Path(path)
    tmp = _temporary(path)
    _ACTIVE.add(tmp)
    try:
        yield tmp
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except OSError as e:
        raise FfcgsError(f"cannot write {path}: {e.strerror or e}") from None
    finally:
        _ACTIVE.discard(tmp)
        with contextlib.suppress(OSError):
            tmp.unlink()


def atomic_write(path: str | Path, write: Callable[[IO[bytes]], object]) -> Path:
    """Call `write(f)` on a binary file that replaces `path` once `write` returns."""
    path = Path(path)
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        write(f)
        f.flush()
    return path


def write_text(path: str | Path, text: str) -> Path:
    """`text` (UTF-8) to `path`, atomically."""
    return atomic_write(path, lambda f: f.write(text.encode()))


_ZIP, _NPY = b"PK\x03\x04", b"\x93NUMPY"


def duplicate_stems(paths) -> list[str]:
    """The file stems (names without suffix) that more than one of `paths` shares, sorted: files a folder's reader
    would name alike (a.png and a.npy, a.obj and a.stl)."""
    stems = [Path(p).stem for p in paths]
    return sorted({s for s in stems if stems.count(s) > 1})


def _kind(head: bytes) -> str:
    """What a file whose first bytes are `head` is, in words ("a PNG image"), for messages about a file of the
    wrong kind."""
    if not head:
        return "an empty file"
    for magic, kind in _MAGIC:
        if head.startswith(magic):
            return kind
    try:  # incremental: the head may end inside a multi-byte character
        codecs.getincrementaldecoder("utf-8")().decode(head, final=False)
        return "a text file" if b"\0" not in head else "a file of another format"
    except UnicodeDecodeError:
        return "a file of another format"


_MAGIC = ((b"\x89MCAP", "an MCAP file"), (b"\x89PNG", "a PNG image"), (_ZIP, "a zip archive (.npz)"),
          (_NPY, "a NumPy .npy array"), (b"ply", "a PLY mesh"), (b"glTF", "a binary glTF (.glb)"),
          (b"\xff\xd8\xff", "a JPEG image"), (b"%PDF", "a PDF document"))


def read_npz(path: str | Path, what: str = "file", label: str = ".npz", npy: bool = False) -> dict[str, np.ndarray]:
    """The arrays of an .npz file (or, with `npy`, of an .npy file as {"": array}), recognised by its content and
    read without pickles. FfcgsError with one line naming the file and what is wrong with it: `what` names a
    missing file ("grasp file not found: ..."), `label` the format ("... is not a readable grasp .npz: ...")."""
    path = Path(path)
    if path.is_dir():
        raise FfcgsError(f"{what} {path} is a folder, not a file")
    if not path.is_file():
        raise FfcgsError(f"{what} not found: {path}")
    with open(path, "rb") as f:
        head = f.read(8)
    if not (head.startswith(_ZIP) or (npy and head.startswith(_NPY))):
        raise FfcgsError(f"{path} is not a readable {label}: it is {_kind(head)}")
    try:
        if head.startswith(_NPY):
            return {"": np.load(path, allow_pickle=False)}
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except ValueError as e:
        if "allow_pickle" in str(e):
            raise FfcgsError(f"{path} is not a readable {label}: it holds pickled Python objects, which are not "
                             "loaded (unsafe)") from None
        raise FfcgsError(f"{path} is not a readable {label}: {e}") from None
    except Exception as e:  # noqa: BLE001 - a truncated zip, a bad member: any parse failure is the file's
        raise FfcgsError(f"{path} is not a readable {label}: {type(e).__name__}: {e}") from None
