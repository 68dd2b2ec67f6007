"""Every file the package writes goes through here: outputs checked before the work starts, then written
atomically, so a failed or interrupted write leaves the previous file exactly as it was.

Several outputs of one command land together: inside `outputs_together(paths)`, a write to one of `paths` stays a
temporary file until the block ends without an error, and then every one of them is renamed into place; on an
error or an interrupt none is (`output_plan` declares a command's outputs and checks them before any work). A
folder output (`write_folder`) is written as a hidden sibling folder and swapped in whole, with a manifest
(`MANIFEST`) naming the files the run wrote: readers of such folders (`manifest_files`) trust it over whatever
else lies there, and `check_folder_output` refuses to replace a folder holding files that no run of ours wrote.

`check_output` is the one rule for output paths: the folder is created if missing, and a path that cannot be
written (a folder, a read-only place, a name under a file) is refused with one line before anything is loaded or
compiled. `atomic_write` / `atomic_path` write a temporary file in the same folder, flush and fsync it, then
`os.replace` it over the target; on any failure, KeyboardInterrupt included, the temporary file is removed and the
target is untouched.

A folder's manifest also names the command and the run that wrote it (`written_by`; `run`: an id, the process id
and the time; manifests of older versions have no `run` and are read as they are): a folder that another command
wrote is refused without `--overwrite` (`check_folder_output`), so `render-depth --out` given a folder of
`ffcgs grasp` results never replaces it. Temporaries are named `.STEM.ffcgs.PID.RANDOM.tmp.SUFFIX` (`temporary`):
only names with that mark are the package's, so only those are ever cleaned (`remove_left_behind`) or passed over
as not the user's; a user's `.notes.4242.tmp.txt` is a file like any other.

Updates of one file that read it first (`ffcgs eval g.npz` adding its results to g.npz, `add_to_manifest`) are
serialised by an advisory lock held from the read to the rename (`locks.locked`; its docstring says why a lock):
a second run waits, then reads what the first wrote and adds to it, so both runs' results survive.

Symlinks are followed to their target: writing through a link `g.npz -> runs/g.npz` replaces runs/g.npz
atomically and the link stays a link; a folder output that is a link is swapped in beside the link's target, which
gets the new files (no stale frame stays in the target), and the link keeps pointing at it.
"""

import codecs
import contextlib
import json
import os
import re
import secrets
import shutil
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO

import numpy as np

from ffcgs_jax.core import locks
from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.core.locks import MARK, locked


def check_output(path: str | Path, what: str = "output") -> Path:
    """`path` as a Path once it is known to be writable: its folder exists (created if missing) and it is not a
    folder itself. FfcgsError naming `what` and the path otherwise."""
    path = Path(path).expanduser()
    if not path.name or path.is_dir():
        raise FfcgsError(f"{what} {path} is a folder; give a file name")
    parent = target(path).parent  # a link is written through: its target's folder is the one written
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):
        raise FfcgsError(f"cannot write {what} {path}: a file stands where its folder should be") from None
    except OSError as e:
        raise FfcgsError(f"cannot create the folder of {what} {path}: {e.strerror or e}") from None
    if not os.access(parent, os.W_OK | os.X_OK) or (path.exists() and not os.access(path, os.W_OK)):
        raise FfcgsError(f"cannot write {what} {path}: permission denied")
    return path


def target(path: str | Path) -> Path:
    """Where a write to `path` lands: the target of a symlink (resolved), `path` itself otherwise. Writes follow
    links so that the link stays a link and the file or folder it points to is the one updated."""
    path = Path(path).expanduser()
    return resolved(path) if path.is_symlink() else path


def check_folder(path: str | Path, what: str = "output folder") -> Path:
    """`path` as a writable folder (created if missing), or FfcgsError naming `what` and the path."""
    path = Path(path).expanduser()
    if path.exists() and not path.is_dir():
        raise FfcgsError(f"{what} {path} is a file, not a folder")
    check_output(path / ".probe", what)  # same rule as for files: parents created, write permission
    return path


_ACTIVE: set[Path] = set()  # temporary files and folders being written now, for `discard_temporaries`


_LAST_WORDS: list = []  # callables for `discard_temporaries` to run first (`last_words`)


@contextlib.contextmanager
def last_words(record):
    """While the block runs, a process that exits at once (`discard_temporaries`) calls `record()` first: what a
    `finally` would have written, such as the seconds a stage ran (`learn.pipeline`)."""
    _LAST_WORDS.append(record)
    try:
        yield
    finally:
        _LAST_WORDS.remove(record)


def discard_temporaries() -> None:
    """Run the `last_words`, then remove the temporary files of writes in progress and the lock files of locks held:
    for a process about to exit at once (the CLI's SIGINT and SIGTERM), which runs no `finally` blocks (the kernel
    releases the locks themselves)."""
    for record in reversed(_LAST_WORDS):
        with contextlib.suppress(Exception):  # the exit goes on whatever a record meets
            record()
    for tmp in list(_ACTIVE):
        _remove(tmp)
    locks.discard_held()


def _remove(tmp: Path) -> None:
    with contextlib.suppress(OSError):
        shutil.rmtree(tmp) if tmp.is_dir() else tmp.unlink()


_MARKED = re.compile(rf"\..+\.{MARK}\.(\d+)\.[0-9a-f]{{8}}\.(tmp|old)(\.[^.]*)?")  # `temporary`'s names


def temporary(path: str | Path, kind: str = "tmp") -> Path:
    """A fresh name beside `path` for a temporary of this process: `.STEM.ffcgs.PID.RANDOM.tmp.SUFFIX` (`kind`
    "tmp": a file or folder being written; "old": a folder being swapped out). Same folder (os.replace is atomic
    only within a filesystem), hidden, marked as the package's (`is_ours`) and the suffix kept last so writers that
    pick a format from the extension (PIL, imageio) still see it. Every temporary name of the package comes from
    here."""
    path = Path(path)
    if kind not in ("tmp", "old"):
        raise ValueError(f"temporary kind must be tmp or old, got {kind!r}")
    return path.with_name(f".{path.stem}.{MARK}.{os.getpid()}.{secrets.token_hex(4)}.{kind}{path.suffix}")


def is_ours(name: str) -> bool:
    """Whether a file name is one of the package's temporaries or lock files (`temporary`, `locks.lock_file`)."""
    return bool(_MARKED.fullmatch(name) or locks.LOCK_NAME.fullmatch(name))


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """A temporary path to write in place of `path`; it replaces `path` when the block ends without an error (or,
    for an output of an `outputs_together` block, when that block ends). A link `path` stays a link: its target
    is replaced."""
    path = target(path)
    with _staged(temporary(path), path, _fsync, os.replace) as tmp:
        yield tmp


def _fsync(tmp: Path) -> None:
    with open(tmp, "rb+") as f:
        os.fsync(f.fileno())


@contextlib.contextmanager
def _staged(tmp: Path, target: Path, finish: Callable[[Path], object], put: Callable[[Path, Path], object]
            ) -> Iterator[Path]:
    """The one way a file or folder lands: written at `tmp`, then `finish(tmp)`, then put in place over `target`
    by `put(tmp, target)` now, or at the end of the `outputs_together` block that declares `target`. On any failure,
    KeyboardInterrupt included, `tmp` is removed and `target` is untouched."""
    _ACTIVE.add(tmp)
    deferred = False
    try:
        yield tmp
        finish(tmp)
        deferred = _defer(tmp, target)
        if not deferred:
            put(tmp, target)
    except OSError as e:
        raise FfcgsError(f"cannot write {target}: {e.strerror or e}") from None
    finally:
        if not deferred:
            _ACTIVE.discard(tmp)
            _remove(tmp)


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


def read_record(path: Path | None) -> dict:
    """The JSON object a machine-local record (`update_record`) holds at `path`; {} when there is none, it is
    damaged or not an object (a record only steers estimates: a lost one starts again)."""
    try:
        data = json.loads(path.read_text()) if path is not None and path.is_file() else {}
        return data if isinstance(data, dict) else {}
    except (OSError, ValueError):
        return {}


def blended(old, new: float, keep: float) -> float:
    """A record's figure after a new measurement: `new` where there was none (or a damaged entry), else the
    exponential average that weighs `new` by `keep` (machines drift, runs vary)."""
    return float(new) if not isinstance(old, (int, float)) else (1 - keep) * float(old) + keep * float(new)


_record_lock = threading.Lock()


def update_record(path: Path | None, change: Callable[[dict], object]) -> None:
    """Apply `change` to the record at `path` (`read_record`) and write it back atomically, so another process
    reading it meanwhile sees all of it or the old one. Nothing when `path` is None or cannot be written (a
    read-only cache folder costs only the estimates the record steers)."""
    if path is None:
        return
    with _record_lock:
        data = read_record(path)
        change(data)
        with contextlib.suppress(OSError):
            path.parent.mkdir(parents=True, exist_ok=True)
            write_text(path, json.dumps(data, indent=1))


def resolved(path: str | Path) -> Path:
    """The absolute path with links and `..` resolved as far as it exists: two names of one file compare equal."""
    return Path(os.path.realpath(Path(path).expanduser()))


class _Together:
    def __init__(self, paths):
        self.paths = {resolved(p) for p in paths}
        self.pending: list[tuple[Path, Path]] = []  # (temporary, target), in the order written
        self.said: list[str] = []  # `announce`d lines, said once their outputs are in place


_TOGETHER: _Together | None = None


def _defer(tmp: Path, target: Path) -> bool:
    """Queue `tmp` to replace `target` at the end of the current `outputs_together` block when `target` is one of
    its outputs (True), else False: the caller puts it in place now."""
    if _TOGETHER is None or resolved(target) not in _TOGETHER.paths:
        return False
    if (tmp, target) not in _TOGETHER.pending:  # written again in the block: the last content lands
        _TOGETHER.pending.append((tmp, target))
    return True


@contextlib.contextmanager
def outputs_together(paths) -> Iterator[None]:
    """Writes to any of `paths` inside the block land together when it ends without an error; on an error (or
    KeyboardInterrupt) every temporary is removed and no target changes. Blocks do not nest."""
    global _TOGETHER
    if _TOGETHER is not None:
        raise RuntimeError("outputs_together blocks do not nest")
    _TOGETHER = together = _Together(paths)
    try:
        yield
        commit_outputs()
    finally:
        _TOGETHER = None
        for tmp, _ in together.pending:
            _ACTIVE.discard(tmp)
            _remove(tmp)


def commit_outputs() -> None:
    """Put every output written so far in the current `outputs_together` block into place now (before a command
    hands over to something that may end the process, such as a viewer served until Ctrl-C); later writes of the
    block land at its end. Nothing to do outside such a block."""
    if _TOGETHER is None:
        return
    pending = _TOGETHER.pending
    while pending:  # what is left after a failed rename stays pending, and the block's end removes it
        tmp, target = pending[0]
        try:
            _swap_folder(tmp, target) if tmp.is_dir() else os.replace(tmp, target)
        except OSError as e:
            raise FfcgsError(f"cannot write {target}: {e.strerror or e}") from None
        pending.pop(0)
        _ACTIVE.discard(tmp)
    for line in _TOGETHER.said:
        print(line)
    _TOGETHER.said.clear()


def announce(line: str) -> None:
    """Print `line` ("wrote grasps.npz") now, or inside an `outputs_together` block once its outputs are in place:
    a run that fails after writing one of several outputs must not have said it wrote it."""
    if _TOGETHER is None:
        print(line)
    else:
        _TOGETHER.said.append(line)


MANIFEST = ".ffcgs-manifest.json"  # in a folder a command wrote: the files of that run (`write_folder`)


def manifest_files(folder: str | Path) -> set[str] | None:
    """The files (paths relative to `folder`, '/'-separated) that the run which wrote `folder` names in its
    manifest, or None for a folder without one (written by hand or by another program). Readers of a folder
    take only these files when there is a manifest."""
    m = read_manifest(folder)
    return None if m is None else set(m["files"])


def read_manifest(folder: str | Path) -> dict | None:
    """The manifest of `folder` ({"written_by": command, "run": `this_run()` of the run that wrote it last, or None
    in a manifest of an older version, "files": names}), or None for a folder without one; FfcgsError for one that
    cannot be read."""
    path = Path(folder) / MANIFEST
    if not path.is_file():
        return None
    try:
        m = json.loads(path.read_text())
        names, by, run = m["files"], m.get("written_by", ""), m.get("run")
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        raise FfcgsError(f"{path} is not a readable manifest (delete it to read the folder as it is)") from None
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise FfcgsError(f"{path} is not a readable manifest: 'files' must be a list of names")
    return {"written_by": str(by), "run": run if isinstance(run, dict) else None, "files": names}


_RUN: dict = {}


def this_run() -> dict:
    """This process's run as a manifest names it: {"id": random hex, "pid": process id, "time": when it began
    writing, ISO 8601}; one per process (a fork gets its own)."""
    if _RUN.get("pid") != os.getpid():
        _RUN.clear()
        _RUN.update(id=secrets.token_hex(6), pid=os.getpid(), time=time.strftime("%Y-%m-%dT%H:%M:%S%z"))
    return dict(_RUN)


def _manifest_text(written_by: str, names) -> str:
    return json.dumps({"written_by": written_by, "run": this_run(), "files": sorted(names)}, indent=1) + "\n"


def add_to_manifest(folder: str | Path, name: str, written_by: str) -> None:
    """Name file `name` in the manifest of `folder`, a folder that a command fills one file at a time over one run
    or several (`ffcgs grasp` of many objects), before the file is written: a crash between the two leaves a name
    without a file, which a rerun writes, never a file that the manifest does not name (which
    `check_folder_output` would refuse as someone else's). The read and the write hold the manifest's lock
    (`locked`), so runs that fill one folder at once lose no name. FfcgsError when another command wrote the
    folder."""
    folder = Path(folder)
    with locked(folder / MANIFEST):
        m = manifest_by(folder, written_by) or {"files": []}
        if name not in m["files"]:
            write_text(folder / MANIFEST, _manifest_text(written_by, {*m["files"], name}))


def writer(m: dict) -> str:
    """Who wrote a folder, from its manifest (`read_manifest`), for messages: "ffcgs grasp (a run of TIME, pid
    N)", or without the run for manifests of older versions."""
    run = m.get("run") or {}
    when = ", ".join(f"{k} {run[k]}" for k in ("time", "pid") if k in run)
    return (m.get("written_by") or "another command") + (f" (run of {when})" if when else "")


def manifest_by(folder: str | Path, written_by: str) -> dict | None:
    """The manifest of `folder` (`read_manifest`), or None for a folder without one; FfcgsError when a command other
    than `written_by` wrote it (a folder of depth frames is no place for grasp files)."""
    m = read_manifest(folder)
    if m is not None and m["written_by"] != written_by:
        raise FfcgsError(f"{folder} was written by {writer(m)}, not {written_by}; choose another folder")
    return m


def unlisted(folder: str | Path) -> list[str] | None:
    """The files in `folder` (paths relative to it, sorted) that its manifest does not name, leaving out the
    manifest and the package's own temporaries and locks (`is_ours`); None for a folder without a manifest.
    Readers ignore these files, and say so."""
    folder = Path(folder)
    named = manifest_files(folder)
    if named is None:
        return None
    return [n for n in _listing(folder) if n != MANIFEST and n not in named and not is_ours(Path(n).name)]


def _left_behind(path: Path) -> bool:
    """Whether `path` is a temporary of ours that a process killed without a chance to clean up (SIGKILL, power
    loss) left: marked as ours (`temporary`'s names; a user's `.notes.4242.tmp.txt` never is), by a process that
    no longer runs."""
    m = _MARKED.fullmatch(path.name)
    if m is None or int(m[1]) == os.getpid():
        return False
    try:
        os.kill(int(m[1]), 0)
    except ProcessLookupError:
        return True
    except OSError:  # alive, another user's
        return False
    return False


def remove_left_behind(folder: str | Path) -> int:
    """Remove the temporaries that killed runs left in `folder` (`_left_behind`), and lock files that no run holds
    (a run killed while it held one); how many."""
    folder = Path(folder)
    here = list(folder.iterdir()) if folder.is_dir() else []
    stale = [p for p in here if _left_behind(p)]
    for p in stale:
        _remove(p)
    return len(stale) + sum(locks.remove_if_free(p) for p in here if locks.LOCK_NAME.fullmatch(p.name))


def _listing(folder: Path) -> list[str]:
    return sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*") if not p.is_dir())


def check_folder_output(path: str | Path, what: str = "output folder", overwrite: bool = False,
                        whole: bool = True, written_by: str | None = None) -> Path:
    """`path` as a folder a command may write whole, checked before the work: not a file, its parent writable, and
    either missing, empty, or written by an earlier run of ours with nothing added since (its manifest names every
    file in it; the package's temporaries and locks do not count, `is_ours`) and, given `written_by`, by that
    command (a folder of `ffcgs grasp` results is no `render-depth --out`). `overwrite` allows replacing any
    folder whole. `whole` False: a folder the command fills one file at a time rather than replaces
    (`add_to_manifest`), which earlier runs may have begun. A link is checked as its target, which is what is
    written (`target`). FfcgsError naming `what` otherwise."""
    path = Path(path).expanduser()
    if path.exists() and not path.is_dir():
        raise FfcgsError(f"{what} {path} is a file, not a folder")
    here = Path.cwd().resolve()
    if resolved(path) == here or resolved(path) in here.parents:
        raise FfcgsError(f"{what} {path} is the current folder or holds it"
                         f"{', and the folder is replaced whole' if whole else ''}; name a subfolder")
    real = target(path)
    check_output(real.parent / f".{real.name or 'folder'}.probe", what)  # parents created, write permission
    if path.is_dir() and not overwrite:
        fix = "pass --overwrite to replace it whole" if whole else "one that earlier runs of this command filled"
        m = read_manifest(path)
        if m is not None and written_by is not None and m["written_by"] != written_by:
            raise FfcgsError(f"{what} {path} was written by {writer(m)}, not {written_by}; choose another folder"
                             f"{', or pass --overwrite to replace it whole' if whole else ''}")
        ours = None if m is None else set(m["files"])
        foreign = [n for n in _listing(path) if n != MANIFEST and (ours is None or n not in ours)
                   and not is_ours(Path(n).name)]
        if foreign:
            raise FfcgsError(f"{what} {path} holds {len(foreign)} file(s) that this command did not write (e.g. "
                             f"{foreign[0]}); choose a new or empty folder, or {fix}")
    return path


def _swap_folder(tmp: Path, target: Path) -> None:
    old = None
    if target.exists():
        old = temporary(target, "old")
        os.rename(target, old)
    os.rename(tmp, target)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


@contextlib.contextmanager
def write_folder(path: str | Path, written_by: str) -> Iterator[Path]:
    """A fresh hidden folder beside `path` to write the folder's files into; when the block ends without an error
    it gets a manifest (`MANIFEST`: `written_by` and its files) and replaces `path` whole (at the end of the
    `outputs_together` block, for a declared output). On an error or an interrupt it is removed and `path` is left
    as it was. A link `path` stays a link: the folder it points to is the one replaced. Check the folder first with
    `check_folder_output`."""
    path = target(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temporary(path)
    tmp.mkdir()

    def manifest(folder: Path) -> None:
        write_text(folder / MANIFEST, _manifest_text(written_by, _listing(folder)))

    with _staged(tmp, path, manifest, _swap_folder) as staged:
        yield staged


_ZIP, _NPY = b"PK\x03\x04", b"\x93NUMPY"


def duplicate_stems(paths) -> list[str]:
    """The file stems (names without suffix) that more than one of `paths` shares, sorted: files a folder's reader
    would name alike (a.png and a.npy, a.obj and a.stl)."""
    stems = [Path(p).stem for p in paths]
    return sorted({s for s in stems if stems.count(s) > 1})


def kind_of(head: bytes) -> str:
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


def check_file(path: str | Path, what: str) -> Path:
    """`path` as a Path once it is known to be a file: FfcgsError "{what} not found: PATH" or "{what} PATH is a
    folder, not a file" otherwise."""
    path = Path(path)
    if path.is_dir():
        raise FfcgsError(f"{what} {path} is a folder, not a file")
    if not path.is_file():
        raise FfcgsError(f"{what} not found: {path}")
    return path


def read_text(path: str | Path, what: str) -> str:
    """The UTF-8 text of file `path` (`check_file` first); FfcgsError naming the file and what it is when it is not
    UTF-8 text (a PNG image, random bytes, Latin-1 text)."""
    path = check_file(path, what)
    try:
        data = path.read_bytes()
    except OSError as e:
        raise FfcgsError(f"cannot read {what} {path}: {e.strerror or e}") from None
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as e:
        kind = kind_of(data[:8])
        legacy = e.start > 0 and kind in ("a text file", "a file of another format") and all(  # Latin-1 text
            b >= 0x20 or b in b"\t\n\r" for b in data[:512])
        why = f"byte {e.start} is not UTF-8 (save the file as UTF-8)" if legacy else f"it is {kind}"
        raise FfcgsError(f"{what} {path} is not UTF-8 text: {why}") from None
    if "\0" in text:
        raise FfcgsError(f"{what} {path} is not text: it holds NUL bytes (a binary file)")
    return text


def read_npz(path: str | Path, what: str = "file", label: str = ".npz", npy: bool = False) -> dict[str, np.ndarray]:
    """The arrays of an .npz file (or, with `npy`, of an .npy file as {"": array}), recognised by its content and
    read without pickles. FfcgsError with one line naming the file and what is wrong with it: `what` names a
    missing file ("grasp file not found: ..."), `label` the format ("... is not a readable grasp .npz: ...")."""
    path = check_file(path, what)
    with open(path, "rb") as f:
        head = f.read(8)
    if not (head.startswith(_ZIP) or (npy and head.startswith(_NPY))):
        raise FfcgsError(f"{path} is not a readable {label}: it is {kind_of(head)}")
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
