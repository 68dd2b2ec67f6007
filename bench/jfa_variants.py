"""Jump flooding in the fused-SDF conversion: the offsets as a scan or unrolled, compile and warm time, this machine.

    python bench/jfa_variants.py [--res 64] [--repeats 20]
"""

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

from ffcgs_jax.geometry import depth_io, depth_render, mesh_io, tsdf


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--res", type=int, default=64)
    ap.add_argument("--repeats", type=int, default=20)
    args = ap.parse_args()
    frames, tz = depth_io.remove_table(depth_render.render_views(mesh_io.load_mesh("mug"), 5, noise=True))
    grid = tsdf.fuse(frames, args.res, table_z=tz)
    seeds, _ = tsdf.flood_seeds(jnp.asarray(grid.grid[..., 0]))
    print(f"{jax.devices()[0].device_kind}, res {args.res}")
    print("| offsets | compile s | median ms |\n|---|---|---|")
    for unroll in (False, True):
        fn = jax.jit(tsdf.jump_flood, static_argnums=1)
        t0 = time.perf_counter()
        compiled = fn.lower(seeds, unroll).compile()
        c = time.perf_counter() - t0
        ts = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            jax.block_until_ready(compiled(seeds))
            ts.append(time.perf_counter() - t0)
        print(f"| {'unrolled' if unroll else 'scan'} | {c:.2f} | {1000 * np.median(ts):.2f} |")


if __name__ == "__main__":
    main()
