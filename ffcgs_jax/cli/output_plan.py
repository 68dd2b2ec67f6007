"""A command's inputs and outputs, declared once and checked together before any work (nothing loaded or compiled
yet), so that no run ever writes over a file it was given, or one output over another.

Each `ffcgs` command builds a `Plan` from its options (`cli.commands.PLANS`); `Plan.check` refuses, with one line:
- an output that resolves (links and `..` resolved) to an input, unless the command updates that input by design
  (`ffcgs eval g.npz` adds its results to g.npz), or that lies inside an input folder, or whose folder holds an
  input;
- two outputs that resolve to one file, or an output inside a folder output (which is replaced whole);
- an extension that does not match what is written (`--png x.jpg`, `--out grasps.txt`);
- an output that cannot be written (`files.check_output`), and a folder output holding files that no run of this
  command wrote, or written by another command (its manifest says which), unless `--overwrite`
  (`files.check_folder_output`); a "files" output is such a folder that the command fills a file at a time,
  keeping what earlier runs wrote there.
`Plan.outputs_together()` then makes the command's outputs land together (`files.outputs_together`), holding the
lock of every input the command updates (`locks.locked`) from before it is read until the outputs are in place: two
`ffcgs eval g.npz` at once run one after the other, and the second adds its results to the first's.
"""

import contextlib
import dataclasses
import os
from pathlib import Path

from ffcgs_jax.core import files, locks
from ffcgs_jax.core.errors import FfcgsError

# format -> (what is written, the extensions its name may end in)
FORMATS: dict[str, tuple[str, tuple[str, ...]]] = {
    "npz": ("a NumPy .npz archive", (".npz",)),
    "png": ("a PNG image", (".png",)),
    "mcap": ("an MCAP file", (".mcap",)),
    "json": ("JSON", (".json",)),
    "markdown": ("Markdown", (".md",)),
    "video": ("a GIF or MP4 video", (".gif", ".mp4")),
    "mesh": ("a mesh", (".ply", ".obj", ".stl")),
    "folder": ("a folder", ()),
    "files": ("a folder filled one file at a time", ()),  # resumable: earlier runs' files stay (`ffcgs grasp` of many)
}


@dataclasses.dataclass(frozen=True)
class Input:
    """A file the command reads, or with `folder` a folder whose files it reads (depth frames, a mesh folder).
    `path` may also be a built-in name (`mug`), which is no file and is not compared. `updated`: the command writes
    its results back into it on purpose."""

    flag: str
    path: str | None
    updated: bool = False
    folder: bool = False


@dataclasses.dataclass(frozen=True)
class Output:
    """A file (or, with format "folder", a folder replaced whole) the command writes."""

    flag: str
    path: str | None
    format: str

    def __post_init__(self):
        if self.format not in FORMATS:
            raise ValueError(f"unknown output format {self.format!r}; formats: {', '.join(FORMATS)}")


@dataclasses.dataclass(frozen=True)
class Plan:
    inputs: tuple[Input, ...] = ()
    outputs: tuple[Output, ...] = ()
    overwrite: bool = False  # a folder output may replace a folder holding files of others

    @property
    def given(self) -> tuple[Output, ...]:
        """The outputs asked for (options left unset write nothing)."""
        return tuple(o for o in self.outputs if o.path is not None)

    def check(self, written_by: str | None = None) -> None:
        """FfcgsError with one line for the first problem (module docstring); the order puts the most telling
        message first: a collision with an input before an extension, an extension before permissions.
        `written_by` ("ffcgs render-depth"): the command, whose folder outputs may replace only folders it wrote."""
        outs = [(o, files.resolved(o.path)) for o in self.given]
        ins = [(i, files.resolved(i.path)) for i in self.inputs if i.path is not None and _exists(i.path)]
        for o, op in outs:
            for i, ip in ins:
                if op == ip and not i.updated:
                    raise FfcgsError(f"{o.flag} {o.path} is the input {_name(i)}: writing it would destroy it; "
                                     "give the output another name")
                if i.folder and op != ip and _inside(op, ip):  # (a file input given as a folder: its reader says)
                    raise FfcgsError(f"{o.flag} {o.path} lies inside the input folder {_name(i)}, which the "
                                     "command reads; write it elsewhere")
                if o.format == "folder" and _inside(ip, op):
                    raise FfcgsError(f"{o.flag} {o.path} holds the input {_name(i)}, and the folder is replaced "
                                     "whole; choose another folder")
        for n, (a, ap) in enumerate(outs):
            for b, bp in outs[n + 1:]:
                if ap == bp:
                    raise FfcgsError(f"{a.flag} and {b.flag} both name {a.path}: give each output its own name")
                for x, xp, y, yp in ((a, ap, b, bp), (b, bp, a, ap)):
                    if y.format == "folder" and _inside(xp, yp):
                        raise FfcgsError(f"{x.flag} {x.path} lies inside the {y.flag} folder {y.path}, which is "
                                         "replaced whole; write it elsewhere")
        updated = {ip for i, ip in ins if i.updated}
        for o, op in outs:
            what, suffixes = FORMATS[o.format]
            if op in updated:  # written back into the input it was read from: the reader judges the file
                continue
            if suffixes and Path(o.path).expanduser().is_dir():
                raise FfcgsError(f"{o.flag} {o.path} is a folder; give a file name")
            if suffixes and Path(o.path).suffix.lower() not in suffixes:
                raise FfcgsError(f"{o.flag} {o.path}: the command writes {what} there, so the name must end in "
                                 f"{' or '.join(suffixes)}")
        for o, op in outs:
            if op in updated:  # the reader of the input speaks first; the write is checked when it happens
                continue
            if o.format in ("folder", "files"):
                files.check_folder_output(o.path, o.flag, self.overwrite, whole=o.format == "folder",
                                          written_by=written_by)
            else:
                files.check_output(o.path, o.flag)

    @property
    def updated(self) -> list[Path]:
        """The outputs that are inputs updated in place (resolved, sorted): files read, then rewritten."""
        ins = {files.resolved(i.path) for i in self.inputs  # (a missing file: its reader says so, unlocked)
               if i.updated and i.path is not None and Path(i.path).expanduser().is_file()}
        return sorted({op for op in (files.resolved(o.path) for o in self.given) if op in ins})

    @contextlib.contextmanager
    def outputs_together(self):
        """The block in which the command writes: its outputs land together at the end, or none of them; the
        inputs it updates are locked throughout (sorted, so two commands never wait for each other)."""
        with contextlib.ExitStack() as stack:
            for path in self.updated:
                stack.enter_context(locks.locked(path))
            stack.enter_context(files.outputs_together([Path(o.path).expanduser() for o in self.given]))
            yield


def _name(i: Input) -> str:
    return f"{i.path} ({i.flag})"


def _exists(path: str) -> bool:
    return os.path.lexists(Path(path).expanduser())


def _inside(path: Path, folder: Path) -> bool:
    return path != folder and folder in path.parents
