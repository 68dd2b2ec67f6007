"""The user's input files: the checks every loader makes before it parses one, so a folder, a missing file or a
file of another kind is named as such in one line (`FfcgsError`)."""

from pathlib import Path

from ffcgs_jax import files
from ffcgs_jax.errors import FfcgsError


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
        kind = files.kind_of(data[:8])
        legacy = e.start > 0 and kind in ("a text file", "a file of another format") and all(  # Latin-1 text
            b >= 0x20 or b in b"\t\n\r" for b in data[:512])
        why = f"byte {e.start} is not UTF-8 (save the file as UTF-8)" if legacy else f"it is {kind}"
        raise FfcgsError(f"{what} {path} is not UTF-8 text: {why}") from None
    if "\0" in text:
        raise FfcgsError(f"{what} {path} is not text: it holds NUL bytes (a binary file)")
    return text
