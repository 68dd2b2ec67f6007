"""`runtime.progress`: the compile ticker's line on a terminal and in a log, how it ends (compiled, loaded from the
cache, stopped by an error or Ctrl-C), silence outside the CLI, and the record of compile times behind the estimate."""

import io
import re
import threading
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax import monitoring

from ffcgs_jax.runtime import progress


class Terminal(io.StringIO):
    def isatty(self):
        return True


def _compile_something(k: float) -> None:
    """A real XLA compile in the block (a new constant: a new program each call)."""
    jax.jit(lambda x: jnp.sin(x) * k + k)(np.ones(3)).block_until_ready()


def _tickers_alive() -> int:
    return sum(t.name == "ffcgs-progress" and t.is_alive() for t in threading.enumerate())


@pytest.fixture
def record(tmp_path, monkeypatch):
    path = tmp_path / progress.RECORD_NAME
    monkeypatch.setattr(progress, "record_path", lambda: path)
    return path


def test_a_terminal_sees_one_line_redrawn_every_tick_then_how_it_ended(record, monkeypatch):
    monkeypatch.setenv("COLUMNS", "200")
    out = Terminal()
    with progress.compiling("the synthesis", show=True, stream=out, tick_s=0.02, quiet_s=0.0):
        _compile_something(1.5)
        time.sleep(0.5)  # 25 ticks: 5 leave room for a ticker thread starved on a loaded machine
    text = out.getvalue()
    frames = [f.removesuffix("\x1b[K") for f in text.rstrip("\n").split("\r") if f]
    assert text.endswith("\n") and text.count("\n") == 1, repr(text)  # one line on the screen
    assert len(frames) >= 5, frames  # redrawn in place, not a line per tick
    assert re.fullmatch(r"compiling the synthesis on .*, once per configuration: typically 30-90 s \.\.\. \d+ s",
                        frames[0]) or re.fullmatch(r"compiling the synthesis, once per .*", frames[0]), frames[0]
    assert re.fullmatch(r"compiled the synthesis in \d+ s", frames[-1]), frames[-1]
    assert _tickers_alive() == 0


def test_a_line_wider_than_the_terminal_is_shortened_so_that_it_can_be_redrawn(record, monkeypatch):
    monkeypatch.setenv("COLUMNS", "40")
    out = Terminal()
    with progress.compiling("the synthesis", show=True, stream=out, tick_s=0.02, quiet_s=0.0):
        time.sleep(0.1)
    frames = [f.removesuffix("\x1b[K") for f in out.getvalue().rstrip("\n").split("\r") if f]
    assert frames[0].endswith("...") and all(len(f) <= 39 for f in frames), frames


def test_a_log_gets_a_line_every_log_every_s_not_every_tick(record):
    out = io.StringIO()
    t0 = time.perf_counter()
    with progress.compiling("the evaluation", show=True, stream=out, tick_s=0.01, log_every_s=0.1, quiet_s=0.0):
        _compile_something(2.5)
        time.sleep(0.45)
    seconds = time.perf_counter() - t0  # the compile's share depends on the machine: the bound follows it
    lines = out.getvalue().splitlines()
    assert "\r" not in out.getvalue()
    ticks = [ln for ln in lines if ln.startswith("compiling the evaluation")]
    assert 2 <= len(ticks) <= seconds / 0.1 + 2, (seconds, lines)  # a line per 0.1 s, not one per 0.01 s tick
    assert re.fullmatch(r"compiled the evaluation in \d+ s", lines[-1]), lines


def test_a_block_that_ends_at_once_prints_nothing(record):
    """Already compiled in this process: no line for a few milliseconds of dispatch."""
    out = Terminal()
    with progress.compiling("the synthesis", show=True, stream=out, quiet_s=0.5):
        pass
    assert out.getvalue() == ""
    assert not record.exists()


@pytest.mark.parametrize("error", [ValueError("bad"), KeyboardInterrupt()])
def test_an_error_or_ctrl_c_ends_the_line_and_stops_the_ticker(record, error):
    out = io.StringIO()
    with pytest.raises(type(error)):
        with progress.compiling("the synthesis", show=True, stream=out, tick_s=0.01, quiet_s=0.0):
            time.sleep(0.05)
            raise error
    assert re.search(r"compiling the synthesis: stopped after \d+ s\n\Z", out.getvalue()), out.getvalue()
    assert _tickers_alive() == 0
    assert not record.exists()  # a stopped compile is no estimate


def test_a_library_call_prints_nothing(record, capsys):
    with progress.compiling("the synthesis", quiet_s=0.0):
        _compile_something(3.5)
        time.sleep(0.05)
    assert capsys.readouterr().err == ""
    assert not record.exists()


def test_inside_shown_the_headline_comes_once_before_the_first_line(record):
    out = io.StringIO()
    with progress.shown(stream=out, headline="ffcgs grasp: mug, hand svh, 32 grasps"):
        for k in (4.5, 5.5):
            with progress.compiling("the synthesis", quiet_s=0.0):
                _compile_something(k)
    lines = out.getvalue().splitlines()
    assert lines[0] == "ffcgs grasp: mug, hand svh, 32 grasps" and lines.count(lines[0]) == 1, lines
    assert sum(ln.startswith("compiled the synthesis") for ln in lines) == 2
    with progress.compiling("the synthesis", quiet_s=0.0):  # shown() ended: silent again
        _compile_something(6.5)
    assert out.getvalue().splitlines() == lines


def test_a_second_ticker_at_the_same_time_stays_silent(record):
    out = io.StringIO()
    with progress.compiling("the synthesis", show=True, stream=out, tick_s=0.01, quiet_s=0.0):
        with progress.compiling("the evaluation", show=True, stream=out, tick_s=0.01, quiet_s=0.0):
            time.sleep(0.05)
    assert "evaluation" not in out.getvalue() and "the synthesis" in out.getvalue()


def test_loaded_from_the_cache_is_said_and_not_recorded(record):
    out = io.StringIO()
    with progress.compiling("the synthesis", show=True, stream=out, quiet_s=0.0):
        # what JAX reports for an executable read from its persistent cache
        monitoring.record_event("/jax/compilation_cache/compile_requests_use_cache")
        monitoring.record_event("/jax/compilation_cache/cache_hits")
        monitoring.record_event_duration_secs("/jax/core/compile/backend_compile_duration", 0.01)
    assert re.search(r"loaded the synthesis from the compilation cache in \d+ s\n\Z", out.getvalue())
    assert not record.exists()


def test_a_full_compile_is_recorded_and_becomes_the_estimate(record):
    _, machine = progress.device()
    assert progress.estimate("the synthesis", machine) == "typically 30-90 s"  # no record: the default
    with progress.compiling("the synthesis", show=True, stream=io.StringIO(), quiet_s=0.0):
        _compile_something(7.5)
    (seconds,) = progress.recorded("the synthesis", machine)
    assert 0 <= seconds < 60
    for s in (41.2, 70.4):
        progress.remember("the synthesis", machine, s)
    assert progress.estimate("the synthesis", machine) == f"about {seconds:.0f}-70 s on this machine"
    for s in range(10):
        progress.remember("the synthesis", machine, 100.0 + s)
    assert progress.recorded("the synthesis", machine) == [105.0, 106.0, 107.0, 108.0, 109.0]  # the last KEEP
    assert progress.estimate("the synthesis", machine) == "about 105-109 s on this machine"
    progress.remember("the training step", machine, 400.0)
    assert progress.estimate("the training step", machine) == "about 7 min on this machine"
    assert progress.recorded("the evaluation", machine) == []  # per work


def test_no_record_while_the_cache_is_off_and_a_damaged_one_is_ignored(tmp_path, monkeypatch):
    monkeypatch.setattr(progress, "record_path", lambda: None)  # FFCGS_JAX_CACHE=off: no cache folder
    with progress.compiling("the synthesis", show=True, stream=io.StringIO(), quiet_s=0.0):
        _compile_something(8.5)
    assert list(tmp_path.iterdir()) == []
    damaged = tmp_path / progress.RECORD_NAME
    damaged.write_text("{not json")
    assert progress.recorded("the synthesis", "m", damaged) == []
    assert progress.estimate("the synthesis", "m", damaged) == "typically 30-90 s"
    progress.remember("the synthesis", "m", 12.0, damaged)  # replaced by a good record
    assert progress.recorded("the synthesis", "m", damaged) == [12.0]
