"""The CLI's persistent compilation cache: on by default, in FFCGS_JAX_CACHE, off with FFCGS_JAX_CACHE=off."""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ffcgs_jax.runtime import jax_cache


def test_cache_dir_from_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("FFCGS_JAX_CACHE", str(tmp_path / "c"))
    assert jax_cache.cache_dir() == tmp_path / "c"
    for off in ("off", "0", "FALSE", "no"):
        monkeypatch.setenv("FFCGS_JAX_CACHE", off)
        assert jax_cache.cache_dir() is None and jax_cache.enable() is None
    monkeypatch.delenv("FFCGS_JAX_CACHE")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert jax_cache.cache_dir() == tmp_path / "xdg" / "ffcgs-jax" / "xla"


def _grasp(tmp_path, cache: str):
    exe = Path(sys.executable).parent / "ffcgs"
    env = dict(os.environ, FFCGS_JAX_CACHE=cache, JAX_PLATFORMS="cpu")
    return subprocess.run([str(exe), "grasp", "box", "--n", "2", "--iters", "1", "--res", "16", "--sampler", "geometric",
                           "--out", str(tmp_path / "g.npz")], capture_output=True, text=True, timeout=600, env=env)


@pytest.mark.slow  # a full CLI compile (~45 s on 2 cores); the default suite keeps the environment logic above
def test_cli_fills_the_cache(tmp_path):
    cache = tmp_path / "xla"
    r = _grasp(tmp_path, str(cache))
    assert r.returncode == 0, r.stderr[-2000:]
    assert cache.is_dir() and any(cache.iterdir())  # the synthesis executable was written
    traces = sorted(p.name for p in (cache / "ffcgs-traced").iterdir())
    assert [t.split("-")[0] for t in traces] == ["device_part", "evaluate_mesh"], traces
    first = dict(np.load(tmp_path / "g.npz"))
    r = _grasp(tmp_path, str(cache))  # a second process: both traces read back, nothing traced or stored anew
    assert r.returncode == 0 and "warning" not in r.stderr, r.stderr[-2000:]
    assert sorted(p.name for p in (cache / "ffcgs-traced").iterdir()) == traces
    second = dict(np.load(tmp_path / "g.npz"))
    for k in ("q", "wrist_pose", "E", "epsilon", "valid"):
        np.testing.assert_array_equal(second[k], first[k], err_msg=k)
