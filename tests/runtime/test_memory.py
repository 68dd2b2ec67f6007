"""Memory known before it is spent: a compiled batch that does not fit is refused before it runs, with the
largest batch that fits."""

import jax
import jax.numpy as jnp
import pytest

from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.geometry import mesh_io
from ffcgs_jax.hand import kinematics as K
from ffcgs_jax.runtime import memory
from ffcgs_jax.synthesis import grasp
from ffcgs_jax.synthesis.config import EnergyConfig, GraspConfig, OptimConfig

from paths import DATA


def _compiled(n: int):
    return jax.jit(lambda x: jnp.cumsum(x * x, axis=0)).lower(jnp.ones((n, 256))).compile()


def test_needed_bytes_grow_with_the_batch():
    small, large = memory.needed_bytes(_compiled(64)), memory.needed_bytes(_compiled(1024))
    assert small >= 64 * 256 * 4 and 12 * small <= large <= 20 * small


def test_check_fits_names_the_largest_batch_that_fits():
    c, n = _compiled(1024), 1024
    need = memory.needed_bytes(c)
    memory.check_fits(c, n, jax.devices()[0], free=2 * need)  # fits: no error
    free = need // 4
    with pytest.raises(FfcgsError, match=rf"a batch of 1024 poses needs .* which has .* free: the largest batch "
                                         rf"that fits is about {int(n * memory.HEADROOM * free / need)} "):
        memory.check_fits(c, n, jax.devices()[0], free=free)
    with pytest.raises(FfcgsError, match="not even one pose fits"):
        memory.check_fits(c, n, jax.devices()[0], free=1)


def test_the_host_reports_free_memory():
    free = memory.free_bytes(jax.devices("cpu")[0])
    assert free is None or free > 0


@pytest.mark.e2e  # a full synthesize compiled to be refused
def test_synthesize_refuses_before_running(monkeypatch):
    """The pipeline asks before it allocates: with (pretend) 1 kB free, one line and no run."""
    monkeypatch.setattr(memory, "free_bytes", lambda device: 1000)
    ran = []
    monkeypatch.setattr(grasp, "finish", lambda *a, **k: ran.append(1))
    hand, mesh = K.load_hand(DATA / "toy_hand" / "toy.toml"), mesh_io.load_mesh("box")
    cfg = GraspConfig(n=2, sampler="random", optim=OptimConfig(iters=1), energy=EnergyConfig(a_pen=0.0))
    with pytest.raises(FfcgsError, match="poses needs about .* GB on cpu"):
        grasp.synthesize(hand, mesh, cfg)
    assert ran == []
