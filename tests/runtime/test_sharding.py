"""Splitting the pose batch over several devices (`GraspConfig.devices`): same grasps as on one device."""

import json
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.synthesis import grasp

# Two CPU "devices" need an XLA flag set before JAX starts, hence a fresh interpreter. The cheap configuration
# (no whole-hand penalty, the host LP, 3 steps) keeps its two compilations short; the sharding does not depend on
# what the energy computes.
SCRIPT = textwrap.dedent("""
    import json, os
    os.environ["XLA_FLAGS"] = "--xla_force_host_platform_device_count=2"
    import jax, numpy as np
    from ffcgs_jax.geometry import mesh_io
    from ffcgs_jax.hand import kinematics as K
    from ffcgs_jax.hand import sites
    from ffcgs_jax.synthesis.config import EnergyConfig, GraspConfig, OptimConfig
    from ffcgs_jax.synthesis.grasp import synthesize
    from ffcgs_jax.geometry.sdf import build_sdf
    from ffcgs_jax.geometry.config import SDFConfig
    import jax.numpy as jnp
    hand, mesh = K.load_hand("svh"), mesh_io.load_mesh("box")
    out = {"devices": len(jax.devices())}
    for d in (1, 2):
        cfg = GraspConfig(n=3, devices=d, sampler="random", optim=OptimConfig(iters=3),
                          energy=EnergyConfig(a_pen=0.0, lp_solver="proxsuite"))
        gs = synthesize(hand, mesh, cfg)
        out[d] = {k: np.asarray(gs[k], float).tolist() for k in ("q", "E", "wrist_pose", "valid", "penetration")}
        out[d]["trace"] = gs.trace["E"].tolist()
    # the cvae sampler splits its candidates (decoder and pose filters) over the devices
    from functools import partial
    from ffcgs_jax.synthesis import samplers
    from ffcgs_jax.synthesis.energy import make_target
    from ffcgs_jax.synthesis.grasp import device_mesh
    from ffcgs_jax.synthesis.samplers import SamplerConfig
    sdf = make_target(build_sdf(mesh, SDFConfig(res=32))).sdf
    palm = jnp.asarray(sites.palm_centre_root(hand))
    for name in ("cvae",):
        params, res = samplers.sampler_params(name, hand, SamplerConfig())
        for d in (1, 2):
            core = jax.jit(partial(samplers.CORES[name], cfg=SamplerConfig(), res=res, mesh=device_mesh(d)),
                           static_argnames="n")
            out[f"{name}{d}"] = np.asarray(core(hand, palm, jax.random.PRNGKey(3), sdf, n=5, params=params)).tolist()
    print(json.dumps(out))
""")


@pytest.mark.slow  # 74 s on two cores: a subprocess compiles the pipeline for two devices
def test_two_devices_give_the_one_device_grasps():
    """3 poses over 2 devices (one padded): every output, trace included, equals the single-device run."""
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    r = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, env=env, timeout=900)
    assert r.returncode == 0, r.stderr[-2000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert out["devices"] == 2

    for name in ("cvae",):  # 5 poses from 20 candidates, 10 decoded and filtered on each device
        np.testing.assert_allclose(out[f"{name}2"], out[f"{name}1"], atol=1e-5, err_msg=name)
        assert np.asarray(out[f"{name}1"]).shape == (5, 4, 4)
    one, two = out["1"], out["2"]
    for k in one:
        a, b = np.asarray(one[k]), np.asarray(two[k])
        assert a.shape == b.shape, k
        np.testing.assert_allclose(b, a, atol=1e-5, err_msg=k)  # float32 rounding of different batch shapes
    assert np.asarray(one["trace"]).shape == (4, 3)


def test_more_devices_than_the_machine_has_is_refused():
    with pytest.raises(FfcgsError, match=r"devices = 4096 asked for, but this machine has 1 cpu device"):
        grasp.device_mesh(4096)


def test_devices_must_be_a_non_negative_integer():
    from ffcgs_jax.synthesis.config import GraspConfig

    with pytest.raises(FfcgsError, match=r"devices must be an integer in \[0, 4096\], got -1"):
        GraspConfig(devices=-1).check()
