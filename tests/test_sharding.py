"""Splitting the pose batch over several devices (`GraspConfig.devices`): same grasps as on one device."""

import json
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from ffcgs_jax import grasp
from ffcgs_jax.errors import FfcgsError

# Two CPU "devices" need an XLA flag set before JAX starts, hence a fresh interpreter. The cheap configuration
# (no whole-hand penalty, the host LP, 3 steps) keeps its two compilations short; the sharding does not depend on
# what the energy computes.
SCRIPT = textwrap.dedent("""
    import json, os
    os.environ["XLA_FLAGS"] = "--xla_force_host_platform_device_count=2"
    import jax, numpy as np
    from ffcgs_jax import kinematics as K, mesh_io
    from ffcgs_jax.config import EnergyConfig, GraspConfig, OptimConfig
    from ffcgs_jax.grasp import synthesize
    hand, mesh = K.load_hand("svh"), mesh_io.load_mesh("box")
    out = {"devices": len(jax.devices())}
    for d in (1, 2):
        cfg = GraspConfig(n=3, devices=d, sampler="random", optim=OptimConfig(iters=3),
                          energy=EnergyConfig(a_pen=0.0, lp_solver="proxsuite"))
        gs = synthesize(hand, mesh, cfg)
        out[d] = {k: np.asarray(gs[k], float).tolist() for k in ("q", "E", "wrist_pose", "valid", "penetration")}
        out[d]["trace"] = gs.trace["E"].tolist()
    print(json.dumps(out))
""")


def test_two_devices_give_the_one_device_grasps():
    """3 poses over 2 devices (one padded): every output, trace included, equals the single-device run."""
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    r = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, env=env, timeout=900)
    assert r.returncode == 0, r.stderr[-2000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert out["devices"] == 2

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
    from ffcgs_jax.config import GraspConfig

    with pytest.raises(FfcgsError, match=r"devices must be an integer in \[0, 4096\], got -1"):
        GraspConfig(devices=-1).check()
