"""traced_store: a trace kept on disk beside the compilation cache is lowered again without tracing, gives the same
results, and is keyed by what the trace depends on."""

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ffcgs_jax.runtime import traced_store


class Out(NamedTuple):
    total: jax.Array
    scaled: jax.Array


traced_store.register_outputs(Out)
TRACES = []


def _fn(params: dict, x, *, power: int):
    TRACES.append(power)  # runs only while tracing
    return Out(jnp.sum(params["w"] * x**power), x * params["b"])


@pytest.fixture
def cache(tmp_path, monkeypatch):
    # the store's folder, without turning JAX's own persistent cache on in this test process
    monkeypatch.setattr(traced_store, "folder", lambda: tmp_path / "ffcgs-traced")
    TRACES.clear()
    return tmp_path / "ffcgs-traced"


def _run(args, power=2, store=True):
    lowered, call = traced_store.lower("toy", lambda p, x: _fn(p, x, power=power), args, power, store)
    return call(lowered.compile(), *args)


ARGS = ({"w": jnp.arange(4.0), "b": jnp.float32(3.0)}, jnp.linspace(0.0, 1.0, 4))


def test_a_stored_trace_is_lowered_without_tracing_and_agrees(cache):
    want = jax.jit(lambda p, x: _fn(p, x, power=2))(*ARGS)
    first = _run(ARGS)
    assert len(list(cache.glob("toy-*.jaxexport"))) == 1 and len(TRACES) == 2  # the reference and the export
    second = _run(ARGS)
    assert len(TRACES) == 2  # read from the file: fn was not traced again
    for got in (first, second):
        assert isinstance(got, Out)
        np.testing.assert_array_equal(got.total, want.total)
        np.testing.assert_array_equal(got.scaled, want.scaled)


def test_the_key_follows_static_arguments_shapes_and_dtypes(cache):
    _run(ARGS)
    _run(ARGS, power=3)
    _run(({"w": jnp.arange(5.0), "b": jnp.float32(3.0)}, jnp.linspace(0.0, 1.0, 5)))
    _run((ARGS[0], ARGS[1].astype(jnp.int32)))
    assert len(list(cache.glob("toy-*.jaxexport"))) == 4 and len(TRACES) == 4
    np.testing.assert_allclose(_run(ARGS, power=3).total, np.sum(np.arange(4.0) * np.linspace(0, 1, 4) ** 3),
                               rtol=1e-6)


def test_a_damaged_file_is_traced_again_and_replaced(cache):
    _run(ARGS)
    (path,) = cache.glob("toy-*.jaxexport")
    path.write_bytes(b"not a trace")
    got = _run(ARGS)
    assert len(TRACES) == 2 and path.read_bytes() != b"not a trace"
    np.testing.assert_allclose(got.total, np.sum(np.arange(4.0) * np.linspace(0, 1, 4) ** 2), rtol=1e-6)


def test_nothing_is_stored_when_asked_not_to(cache):
    _run(ARGS, store=False)
    assert not cache.exists()


def test_the_folder_follows_the_compilation_cache(tmp_path):
    before = (jax.config.jax_compilation_cache_dir, jax.config.jax_enable_compilation_cache)
    try:
        jax.config.update("jax_compilation_cache_dir", str(tmp_path / "xla"))
        jax.config.update("jax_enable_compilation_cache", True)
        assert traced_store.folder() == tmp_path / "xla" / "ffcgs-traced"
        jax.config.update("jax_enable_compilation_cache", False)
        assert traced_store.folder() is None
    finally:
        jax.config.update("jax_compilation_cache_dir", before[0])
        jax.config.update("jax_enable_compilation_cache", before[1])


def _host(x):
    return jax.pure_callback(lambda v: np.asarray(v) * 2, jax.ShapeDtypeStruct(x.shape, x.dtype), x)


def test_a_program_that_cannot_be_stored_is_traced_said_once_and_marked(cache):
    x = (jnp.arange(3.0),)
    with pytest.warns(UserWarning, match="host: traced in every process"):
        lowered, call = traced_store.lower("host", _host, x, None)
    np.testing.assert_array_equal(call(lowered.compile(), *x), [0.0, 2.0, 4.0])
    assert [p.suffix for p in cache.iterdir()] == [".failed"]
    # the mark keeps a second lowering (a new process's) from trying again, and from saying so
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        lowered, call = traced_store.lower("host", _host, x, None)
    np.testing.assert_array_equal(call(lowered.compile(), *x), [0.0, 2.0, 4.0])
