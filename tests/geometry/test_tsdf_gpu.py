"""TSDF fusion on a GPU against the same fusion on the CPU (skipped without a GPU; run on the device machine)."""

import jax
import numpy as np
import pytest
import trimesh

from ffcgs_jax.geometry import depth_io, depth_render, tsdf

GPUS = [d for d in jax.devices() if d.platform == "gpu"] if jax.default_backend() == "gpu" else []
pytestmark = pytest.mark.skipif(not GPUS, reason="no GPU: this compares the GPU's fusion with the CPU's")


@pytest.mark.parametrize("res", [32, 64])
def test_gpu_fusion_equals_cpu_fusion(res):
    mesh = trimesh.creation.box((0.06, 0.1, 0.04)).apply_translation((0.0, 0.0, 0.02))
    frames, table_z = depth_io.remove_table(depth_render.render_views(mesh, views=5, noise=True, seed=1))
    got = {}
    for device in (GPUS[0], jax.devices("cpu")[0]):
        with jax.default_device(device):
            got[device.platform] = tsdf.fuse(frames, res=res, table_z=table_z, on_device=True)
    gpu, cpu = (np.asarray(got[k].grid) for k in ("gpu", "cpu"))
    h = float(got["cpu"].voxel_size)
    d = np.abs(gpu[..., 0] - cpu[..., 0]) / h
    # float32 on both; a projected voxel centre that lands on a pixel border may round to the other pixel
    assert np.median(d) < 1e-5 and np.mean(d > 0.05) < 1e-3, (np.median(d), np.mean(d > 0.05))
    assert np.mean(np.sign(gpu[..., 0]) != np.sign(cpu[..., 0])) < 1e-3
