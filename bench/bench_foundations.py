"""Benchmark the foundations: SVH FK + Jacobian (MJX), Gradient-SDF builds, SDF query throughput.

    python bench/bench_foundations.py [--mesh PATH] [--repeats 5] [--quick]

Prints a Markdown table: the median of `--repeats` warm runs, compile time (first call minus a warm call) apart.
JAX runs on its default device (GPU when a CUDA jaxlib is installed) in its default float32.
"""

import argparse
import platform
import statistics
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from scipy.spatial.transform import Rotation

from ffcgs_jax.geometry import mesh_io, sdf
from ffcgs_jax.geometry.config import SDFConfig
from ffcgs_jax.hand import kinematics as K

REPO = Path(__file__).resolve().parents[1]
DEFAULT_MESH = REPO.parent / "shared" / "objects" / "ycb" / "025_mug.stl"


def timed(fn, repeats):
    """(first-call seconds, median warm seconds) of fn(), blocking on its result."""
    t0 = time.perf_counter()
    jax.block_until_ready(fn())
    first = time.perf_counter() - t0
    runs = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        runs.append(time.perf_counter() - t0)
    return first, statistics.median(runs)


def bench_fk(rows, repeats, batches):
    hand = K.load_hand("svh")
    rng = np.random.default_rng(0)
    fk = jax.jit(lambda T, q: K.forward_kinematics_batch(hand, T, q).contacts)
    jac = jax.jit(lambda T, q: K.contact_jacobian_batch(hand, T, q))
    for b in batches:
        T = np.tile(np.eye(4), (b, 1, 1))
        T[:, :3, :3] = Rotation.random(b, random_state=rng).as_matrix()
        T = jnp.asarray(T, jnp.float32)
        q = jnp.asarray(rng.uniform(hand.lower, hand.upper, (b, 9)), jnp.float32)
        for name, f in (("FK contacts", fk), ("FK + Jacobian", jac)):
            first, warm = timed(lambda: f(T, q), repeats)
            rows.append((f"{name}, batch {b}", warm * 1e3, first - warm, b / warm))


def bench_sdf_build(rows, repeats, mesh_path, resolutions):
    mesh = mesh_io.load_mesh(mesh_path)
    for r in resolutions:
        cfg = SDFConfig(res=r)
        first, warm = timed(lambda: sdf.build_sdf(mesh, cfg), repeats)
        rows.append((f"SDF build {r}^3 ({len(mesh.faces)} faces)", warm * 1e3, first - warm, r**3 / warm))
    return mesh


def bench_query(rows, repeats, mesh, n_points):
    grid = sdf.build_sdf(mesh, SDFConfig(res=32))
    grid = jax.tree.map(lambda x: jnp.asarray(x, jnp.float32), grid)
    lo, hi = mesh.bounds
    pts = jnp.asarray(np.random.default_rng(1).uniform(lo - 0.02, hi + 0.02, (n_points, 3)), jnp.float32)
    q = jax.jit(sdf.query)
    first, warm = timed(lambda: q(grid, pts), repeats)
    rows.append((f"SDF query, {n_points} points", warm * 1e3, first - warm, n_points / warm))
    g = jax.jit(jax.grad(lambda p: sdf.distance(grid, p).sum()))
    first, warm = timed(lambda: g(pts), repeats)
    rows.append((f"SDF distance + grad, {n_points} points", warm * 1e3, first - warm, n_points / warm))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mesh", default=str(DEFAULT_MESH if DEFAULT_MESH.is_file() else "mug"))
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--quick", action="store_true", help="small sizes only (a smoke run)")
    args = ap.parse_args()
    rows: list[tuple] = []
    batches = (1, 32) if args.quick else (1, 32, 4096)
    res = (32,) if args.quick else (32, 64, 128)
    bench_fk(rows, args.repeats, batches)
    mesh = bench_sdf_build(rows, args.repeats, args.mesh, res)
    bench_query(rows, args.repeats, mesh, 10_000 if args.quick else 1_000_000)
    dev = jax.devices()[0]
    print(f"device: {dev.platform} ({dev.device_kind}), jax {jax.__version__}, {platform.processor() or platform.machine()}, "
          f"{len(jax.devices())} device(s); SDF builds run on the host CPU")
    print()
    print(f"| {'what':<42} | {'median (ms)':>12} | {'compile (s)':>11} | {'per second':>12} |")
    print(f"|{'-' * 44}|{'-' * 14}|{'-' * 13}|{'-' * 14}|")
    for name, ms, comp, rate in rows:
        print(f"| {name:<42} | {ms:>12.3f} | {comp:>11.2f} | {rate:>12.4g} |")


if __name__ == "__main__":
    main()
