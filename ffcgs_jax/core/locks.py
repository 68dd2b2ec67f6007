"""Advisory locks that serialise the updates of one file across processes: `ffcgs eval g.npz` adding its results to
g.npz, `files.add_to_manifest` adding a name to a folder's manifest. A run holds the lock of the file (`locked`:
`fcntl.flock` on `.NAME.ffcgs.lock` beside it) from reading the file to replacing it, so a second run waits, then
reads what the first wrote and adds to it: both runs' results survive.

Why a lock rather than a check that the file did not change before the rename (mtime, size, hash): the check would
throw away the second run's work (minutes of simulation) where waiting keeps it, and it leaves a window between
the check and the rename unless it is itself done under a lock. The kernel releases a flock when its holder dies
(kill -9 included), so a crashed run never blocks the next one. The lock file is removed on release, while still
locked: a waiter that then holds a lock on the removed file sees that the name now leads elsewhere (or nowhere) and
locks again (`_acquire`), so two runs never both hold the lock of one file. A killed run's lock file is harmless
and `remove_if_free` cleans it. Lock files carry the package's mark (`MARK`), like its temporaries
(`files.temporary`), so no user's file is ever taken for one.
"""

import contextlib
import errno
import fcntl
import os
import re
import sys
import warnings
from collections.abc import Iterator
from pathlib import Path

from ffcgs_jax.core.errors import FfcgsError

MARK = "ffcgs"  # in the name of every temporary and lock file the package makes, and in no user's file
LOCK_NAME = re.compile(rf"\..+\.{MARK}\.lock")  # `lock_file`'s names
_HELD: set[Path] = set()  # lock files of the locks this process holds


def lock_file(path: str | Path) -> Path:
    """The lock file of `path`: `.NAME.ffcgs.lock` beside the file itself (links resolved: two names of one file
    share its lock)."""
    real = Path(os.path.realpath(Path(path).expanduser()))
    return real.with_name(f".{real.name}.{MARK}.lock")


@contextlib.contextmanager
def locked(path: str | Path) -> Iterator[None]:
    """Hold the advisory lock of file `path` (`lock_file(path)`) for the block: other processes of the package
    that update `path` wait until it ends (one line on stderr says so). Hold it from reading the file to replacing
    it. On a filesystem without locks the block runs unlocked, with a warning."""
    lock = lock_file(path)
    fd = _acquire(lock, path)
    if fd is not None:
        _HELD.add(lock)
    try:
        yield
    finally:
        if fd is not None:
            _HELD.discard(lock)
            with contextlib.suppress(OSError):  # removed while held (module docstring)
                lock.unlink()
            os.close(fd)


def _acquire(lock: Path, path: str | Path) -> int | None:
    """An open file descriptor of `lock` that holds its flock, once the lock is ours (None: the filesystem has no
    locks). Waiting is said once on stderr; an interrupt while waiting closes what was opened and leaves the lock
    file to its holder."""
    said = False
    while True:
        try:
            fd = os.open(lock, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        except OSError as e:
            raise FfcgsError(f"cannot update {path}: cannot create its lock file {lock}: {e.strerror or e}") from None
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                if not said:
                    print(f"waiting for another ffcgs run that is updating {path} (it holds {lock})",
                          file=sys.stderr, flush=True)
                    said = True
                fcntl.flock(fd, fcntl.LOCK_EX)
        except OSError as e:
            os.close(fd)
            if e.errno not in (errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS):
                raise FfcgsError(f"cannot lock {path} ({lock}): {e.strerror or e}") from None
            warnings.warn(f"{path} cannot be locked on its filesystem ({e.strerror}): a run that updates it at the "
                          "same time may overwrite this one's results", stacklevel=4)
            with contextlib.suppress(OSError):
                lock.unlink()
            return None
        except BaseException:
            os.close(fd)
            raise
        if _same_file(fd, lock):  # else the holder before us removed it on release: lock the new one
            return fd
        os.close(fd)


def _same_file(fd: int, path: Path) -> bool:
    try:
        a, b = os.fstat(fd), os.stat(path)
    except OSError:
        return False
    return (a.st_dev, a.st_ino) == (b.st_dev, b.st_ino)


def remove_if_free(lock: Path) -> bool:
    """Remove lock file `lock` if no run holds it (one that a killed run left); whether it was removed."""
    try:
        fd = os.open(lock, os.O_RDWR | os.O_CLOEXEC)
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)  # held by a live run: BlockingIOError, and it stays
        if _same_file(fd, lock):
            lock.unlink()
            return True
        return False
    except OSError:
        return False
    finally:
        os.close(fd)


def discard_held() -> None:
    """Remove the lock files of the locks this process holds: for a process about to exit at once (the CLI's
    SIGINT), which runs no `finally` blocks; the kernel releases the locks themselves."""
    for lock in list(_HELD):
        with contextlib.suppress(OSError):
            lock.unlink()
