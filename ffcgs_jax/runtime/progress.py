"""Compiles that say so while they run: a ticker line on stderr with what compiles, on which device, the seconds
so far and an estimate, then how it ended ("compiled the synthesis in 71 s", "loaded the synthesis from the
compilation cache in 3 s").

A cold `ffcgs grasp` compiles for a minute or more on a 2-core CPU; without this it printed nothing until the
summary. `compiling(what)` wraps the large compiles where they happen (`synthesis.grasp`'s SDF build, device part
and evaluation, `synthesis.prediction`, the training steps of `learning`). It shows only inside `shown()` (the CLI's
commands run in it) or where the caller asks (`show=True`): a library call prints nothing. On a terminal the line
is redrawn every second; into a file or a pipe one line comes every `log_every_s` (15 s) so that logs do not flood.
A block that ends within `quiet_s` (0.5 s: already compiled in this process) prints nothing.

The estimate: the last compile times of the same work on this machine (backend, device kind, usable cores),
recorded in `ffcgs-compile-times.json` in the compilation-cache folder (`runtime.jax_cache`; nothing is recorded
while the cache is off, `FFCGS_JAX_CACHE=off`). Without a record, `DEFAULT_SECONDS`: the cold ranges measured on
the 2-core CPU and one H100 (bench/RESULTS.md, "First grasp: where a cold process's compile goes": device part
trace, lower and XLA 47-62 s, evaluation 11-20 s; the SDF build's kernels about 2 s), widened for a loaded host;
the CVAE's training step: 23 s on one H100 (bench/RESULTS.md, the sampler's training) and over 5 minutes on the
2-core CPU (issue 47). Only full compiles are recorded; loads from the cache are not an estimate of a compile.
(`ffcgs train` runs without the compilation cache, so its estimate is always the default.)
"""

import contextlib
import os
import shutil
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from ffcgs_jax.core import files

DEFAULT_SECONDS = {"the SDF build": (1, 10), "the synthesis": (30, 90), "the evaluation": (10, 30),
                   "the success predictor": (2, 15), "the CVAE's training step": (20, 600),
                   "the predictor's training step": (5, 60)}
RECORD_NAME = "ffcgs-compile-times.json"
KEEP = 5  # compile times kept per (work, machine): the estimate is their range

_shown = False  # inside `shown()`: tickers show by default; outside (library use) only with show=True
_stream: Any = None  # `shown()`'s stream; None: sys.stderr as it is when a ticker starts
_headline: str | None = None  # `shown()`'s line to print before the first ticker's first output, once
_lock = threading.Lock()  # one ticker line at a time
_active = 0  # tickers running: a second one at the same time (another thread) stays silent
_described: set[str] = set()  # devices named once already: later tickers leave the device out
_local = threading.local()
_registered = False


@contextlib.contextmanager
def shown(stream: Any = None, headline: str | None = None) -> Iterator[None]:
    """Show every `compiling` block inside on `stream` (default stderr: stdout stays the command's output).
    `headline` is printed before the first ticker's first line, if one shows (the CLI's first line where it was
    not printed at once: into a log, bad input stays one line)."""
    global _shown, _stream, _headline
    before = _shown, _stream, _headline
    _shown, _stream, _headline = True, stream, headline
    try:
        yield
    finally:
        _shown, _stream, _headline = before


_COUNTED = {"/jax/compilation_cache/compile_requests_use_cache": "asked", "/jax/compilation_cache/cache_hits": "hits",
            "/jax/core/compile/backend_compile_duration": "compiles"}  # the last: compiled or loaded, either way


def _listener(event: str, *_, **__) -> None:
    if event in _COUNTED:
        for counts in getattr(_local, "open", ()):
            counts[_COUNTED[event]] += 1


def _watch() -> dict:
    """Counters of this thread's compiles and of the compilation cache's requests and hits in a block (JAX
    compiles on the calling thread)."""
    global _registered
    from jax import monitoring

    with _lock:
        if not _registered:  # once per process: jax.monitoring has no public way to remove a listener
            monitoring.register_event_listener(_listener)
            monitoring.register_event_duration_secs_listener(_listener)
            _registered = True
    return dict.fromkeys(_COUNTED.values(), 0)


def device() -> tuple[str, str]:
    """(words for the device JAX computes on, e.g. "cpu (2 cores)", the record's key for this machine)."""
    import jax

    d = jax.devices()
    try:
        cores = len(os.sched_getaffinity(0))  # what this process may use (taskset, containers), not the host's
    except AttributeError:
        cores = os.cpu_count() or 1
    if d[0].platform == "cpu":
        words = f"cpu ({cores} cores)"
    else:
        words = f"{d[0].device_kind}" + (f" x {len(d)}" if len(d) > 1 else "")
    return words, f"{d[0].platform} | {d[0].device_kind} | {len(d)} devices | {cores} cores"


def record_path() -> Path | None:
    """The record of compile times, in JAX's compilation-cache folder; None while that cache is off."""
    import jax

    where = jax.config.jax_compilation_cache_dir
    if not where or not jax.config.jax_enable_compilation_cache:
        return None
    return Path(where) / RECORD_NAME


def _times(data: dict, what: str, machine: str) -> list[float]:
    return [float(s) for s in data.get(f"{what} | {machine}", []) if isinstance(s, (int, float))][-KEEP:]


def recorded(what: str, machine: str, path: Path | None = None) -> list[float]:
    """The last compile times of `what` on `machine` (`device()`'s key), oldest first."""
    return _times(files.read_record(record_path() if path is None else path), what, machine)


def remember(what: str, machine: str, seconds: float, path: Path | None = None) -> None:
    """Add a full compile's seconds to the record (the last `KEEP` kept); nothing while the cache is off."""

    def add(data: dict) -> None:
        data[f"{what} | {machine}"] = (_times(data, what, machine) + [round(float(seconds), 1)])[-KEEP:]

    files.update_record(record_path() if path is None else path, add)


def estimate(what: str, machine: str, path: Path | None = None) -> str:
    """Words for how long compiling `what` takes: from the record when there is one, else `DEFAULT_SECONDS`."""
    seen = recorded(what, machine, path)
    lo, hi = (min(seen), max(seen)) if seen else DEFAULT_SECONDS.get(what, (10, 120))
    (a, unit_a), (b, unit_b) = _duration(float(lo)), _duration(float(hi))
    span = f"{a} {unit_a}" if (a, unit_a) == (b, unit_b) else \
        f"{a}-{b} {unit_b}" if unit_a == unit_b else f"{a} {unit_a}-{b} {unit_b}"
    return f"about {span} on this machine" if seen else f"typically {span}"


def _duration(seconds: float) -> tuple[str, str]:
    return (f"{seconds:.0f}", "s") if seconds < 120 else (f"{seconds / 60:.0f}", "min")


class _Ticker:
    def __init__(self, stream: Any, text: str, tick_s: float, log_every_s: float, quiet_s: float):
        self.stream, self.text = stream, text
        self.tty = bool(getattr(stream, "isatty", lambda: False)())
        self.tick_s, self.log_every_s, self.quiet_s = tick_s, log_every_s, quiet_s
        self.start = time.monotonic()
        self.shown = False
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, name="ffcgs-progress", daemon=True)

    def _write(self, line: str, end: str = "") -> None:
        global _headline
        with _lock:
            headline, _headline = _headline, None
        if self.tty:  # redraw in place; a line wider than the terminal would wrap and never be overwritten
            width = shutil.get_terminal_size((120, 24)).columns - 1
            line = "\r" + (line if len(line) <= width else line[:width - 3] + "...") + "\x1b[K"
        try:
            self.stream.write((f"{headline}\n" if headline else "") + line + end)
            self.stream.flush()
        except (OSError, ValueError):  # a closed or broken stream must not end the compile it reports
            pass

    def _run(self) -> None:
        if self.stop.wait(self.quiet_s):
            return
        last = None
        while True:
            s = time.monotonic() - self.start
            if self.tty:
                self._write(f"{self.text} ... {s:.0f} s")
            elif last is None or s - last >= self.log_every_s:
                self._write(f"{self.text} ... {s:.0f} s", "\n")
                last = s
            self.shown = True
            if self.stop.wait(self.tick_s):
                return

    def end(self, line: str) -> None:
        self.stop.set()
        self.thread.join(timeout=2)
        if self.shown or time.monotonic() - self.start >= self.quiet_s:
            self._write(line, "\n")


@contextlib.contextmanager
def compiling(what: str, show: bool | None = None, stream: Any = None, tick_s: float = 1.0,
              log_every_s: float = 15.0, quiet_s: float = 0.5) -> Iterator[None]:
    """Report the compile of `what` ("the synthesis") that happens in the block; see the module docstring.

    `show`: None shows inside `shown()`, True always (on `stream`, any text stream; default stderr), False
    never. The line ends on an error and on Ctrl-C too ("stopped after ..."), and the ticker thread stops with the
    block."""
    global _active
    if show or (show is None and _shown):
        out = stream or (_stream if show is None else None) or sys.stderr
    else:
        out = None
    with _lock:
        _active += 1
        first = _active == 1
    if out is None or not first:
        try:
            yield
        finally:
            with _lock:
                _active -= 1
        return
    counts = _watch()
    try:
        words, machine = device()
        on = "" if words in _described else f" on {words}"
        _described.add(words)
        ticker = _Ticker(out, f"compiling {what}{on}, once per configuration: {estimate(what, machine)}", tick_s,
                         log_every_s, quiet_s)
        blocks = _local.__dict__.setdefault("open", [])
        blocks.append(counts)
        ticker.thread.start()
        ok = False
        try:
            yield
            ok = True
        finally:
            del blocks[next(i for i, b in enumerate(blocks) if b is counts)]
            seconds = time.monotonic() - ticker.start
            if not ok:
                ticker.end(f"compiling {what}: stopped after {seconds:.0f} s")
            elif not counts["compiles"]:  # compiled earlier in this process after all
                ticker.end(f"{what} ready in {seconds:.0f} s")
            elif counts["hits"] and counts["hits"] == counts["asked"]:
                ticker.end(f"loaded {what} from the compilation cache in {seconds:.0f} s")
            else:  # hits here may be a program compiled twice in the block: "compiled" all the same
                ticker.end(f"compiled {what} in {seconds:.0f} s")
                if not counts["hits"]:  # a compile with nothing from the cache: the next estimate on this machine
                    remember(what, machine, seconds)
    finally:
        with _lock:
            _active -= 1
