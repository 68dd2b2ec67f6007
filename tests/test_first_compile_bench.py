"""bench/first_compile.py: its reading of JAX's compile log, and its refusal of a bad argument."""

import importlib.util
import logging
import subprocess
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "bench" / "first_compile.py"


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("first_compile", BENCH)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _record(msg: str) -> logging.LogRecord:
    return logging.LogRecord("jax._src.dispatch", logging.WARNING, __file__, 1, msg, None, None)


def test_the_three_stages_of_an_executable_are_read_apart(bench):
    log = bench.CompileStageLog()
    for msg in ("Finished tracing + transforming _device_part for pjit in 10.5 sec",
                "Finished tracing _device_part for jit in 10.25 sec",
                "Finished jaxpr to MLIR module conversion jit(_device_part) in 1.5 sec",
                "Finished XLA compilation of jit(_finish_mesh) in 6.125 sec",
                "Compiling _finish_mesh with global shapes and types"):
        log.emit(_record(msg))
    assert log.rows == [("trace", "_device_part", 10.25), ("lower", "_device_part", 1.5),
                        ("compile", "_finish_mesh", 6.125)]


def test_a_bad_repeat_count_is_one_line():
    r = subprocess.run([sys.executable, str(BENCH), "--repeats", "0"], capture_output=True, text=True)
    assert r.returncode == 2
    assert "--repeats must be >= 1, got 0" in r.stderr
    assert "Traceback" not in r.stderr
