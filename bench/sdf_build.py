"""Host and device Gradient-SDF builders side by side, on the built-in objects and optionally YCB meshes.

    python bench/sdf_build.py [--res 32 64] [--repeats 3] [--ycb DIR [--ycb-names 025_mug 011_banana ...]]

One row per object and resolution: faces; the median of `--repeats` warm calls of each builder, timed as a user
waits for them (`sdf.build_sdf(mesh, cfg, builder=..., cache=False)`, the grid copied back to the host); the device
builder's first call (compiling, unless an earlier object of the same padded size and resolution compiled it); the
largest |d_device - d_host| in voxels and the voxels whose sign differs, away from the surface (|d| > 1e-6 m).
JAX runs on its default device in its default float32.
"""

import argparse
import platform
import statistics
import time
from pathlib import Path

import jax
import numpy as np
import trimesh

from ffcgs_jax.geometry import mesh_io, objects, sdf, sdf_device
from ffcgs_jax.geometry.config import SDFConfig

SURFACE = 1e-6  # m: sign differences closer to the surface than this are float rounding, not counted


def timed(fn, repeats):
    """(first-call seconds, median warm seconds, last result) of fn()."""
    t0 = time.perf_counter()
    out = fn()
    first = time.perf_counter() - t0
    runs = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        runs.append(time.perf_counter() - t0)
    return first, statistics.median(runs), out


def build(mesh, res, builder):
    return np.asarray(sdf.build_sdf(mesh, SDFConfig(res=res), builder=builder, cache=False).grid)


def bench(name, mesh, res, repeats):
    _, host_s, host = timed(lambda: build(mesh, res, "host"), repeats)
    first_s, dev_s, dev = timed(lambda: build(mesh, res, "device"), repeats)
    voxel = float(sdf.build_sdf(mesh, SDFConfig(res=res), builder="host").voxel_size)
    d_host, d_dev = host[..., 0], dev[..., 0]
    away = np.abs(d_host) > SURFACE
    return {
        "object": name, "faces": len(mesh.faces), "res": res, "host_ms": host_s * 1e3, "device_ms": dev_s * 1e3,
        "first_s": first_s, "max_dev_vox": float(np.abs(d_dev - d_host).max() / voxel),
        "sign": int((np.sign(d_dev) != np.sign(d_host))[away].sum()),
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--res", type=int, nargs="+", default=[32, 64])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--ycb", type=Path, help="folder of YCB .stl meshes (e.g. ../shared/objects/ycb)")
    ap.add_argument("--ycb-names", nargs="+", help="only these YCB meshes (file stems); default all")
    args = ap.parse_args()
    meshes = [(n, mesh_io.load_mesh(n)) for n in objects.names()]
    if args.ycb:
        files = sorted(args.ycb.glob("*.stl"))
        files = [f for f in files if not args.ycb_names or f.stem in args.ycb_names]
        meshes += [(f.stem, trimesh.load(f, force="mesh")) for f in files]
    dev = jax.devices()[0]
    print(f"device: {dev.platform} ({dev.device_kind}), jax {jax.__version__}, "
          f"{platform.processor() or platform.machine()}; float32; median of {args.repeats} warm calls")
    print()
    print("| object | faces | res | host ms | device ms (whole call) | device first call s | "
          "max abs(d_device - d_host) (voxels) | sign mismatches |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    rows = []
    for res in args.res:
        for name, mesh in meshes:
            r = bench(name, mesh, res, args.repeats)
            rows.append(r)
            print(f"| {r['object']} | {r['faces']} | {r['res']} | {r['host_ms']:.0f} | {r['device_ms']:.1f} | "
                  f"{r['first_s']:.2f} | {r['max_dev_vox']:.1e} | {r['sign']} |", flush=True)
    for res in args.res:
        sel = [r for r in rows if r["res"] == res]
        ratio = statistics.median(r["host_ms"] / r["device_ms"] for r in sel)
        print(f"\n{res}^3: median host / device {ratio:.1f}x over {len(sel)} objects; device whole call median "
              f"{statistics.median(r['device_ms'] for r in sel):.1f} ms, max {max(r['device_ms'] for r in sel):.1f} ms")
    print(f"capacity retries: {sdf_device.retries()}")


if __name__ == "__main__":
    main()
