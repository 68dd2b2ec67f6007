"""The cvae decoder's main convolution against a matmul of the same FLOPs, on this machine's default JAX device.

    python bench/conv_vs_matmul.py [--batch 64] [--repeats 7]
    XLA_FLAGS=--xla_cpu_use_onednn=true python bench/conv_vs_matmul.py   # the same with an XLA flag

The decoder's first convolution after its pooled first layer is 3x3x3, 32 -> 32 channels on an 8^3 volume per
candidate (`learning.cvae.fcn_head`, head = 32 at the shipped size). Rows: that convolution (and the 4^3 one after
it) as XLA runs it; the same FLOPs as one (B * 512, 864) @ (864, 32) matmul; and the convolution written as im2col (27
shifted copies concatenated) plus that matmul. Median of `repeats` warm calls, GFLOP/s counted as 2 multiply-adds.
"""

import argparse
import statistics
import time

import jax
import jax.numpy as jnp


def conv(x, w):
    return jax.lax.conv_general_dilated(x, w, (1, 1, 1), "SAME", dimension_numbers=("NDHWC", "DHWIO", "NDHWC"))


def im2col_conv(x, w):
    N, D, H, W, C = x.shape
    xp = jnp.pad(x, ((0, 0), (1, 1), (1, 1), (1, 1), (0, 0)))
    cols = jnp.concatenate([xp[:, i:i + D, j:j + H, k:k + W] for i in range(3) for j in range(3) for k in range(3)],
                           -1)
    return (cols.reshape(-1, 27 * C) @ w.reshape(27 * C, -1)).reshape(N, D, H, W, -1)


def timed(f, *args, repeats: int) -> float:
    f = jax.jit(f)
    jax.block_until_ready(f(*args))
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(f(*args))
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--batch", type=int, default=64, help="decoder candidates at once")
    ap.add_argument("--repeats", type=int, default=7)
    args = ap.parse_args()
    B, C = args.batch, 32
    k = jax.random.split(jax.random.PRNGKey(0), 4)
    w = jax.random.normal(k[0], (3, 3, 3, C, C))
    x8 = jax.random.normal(k[1], (B, 8, 8, 8, C))
    x4 = jax.random.normal(k[2], (B, 4, 4, 4, C))
    a = jax.random.normal(k[3], (B * 512, 27 * C))
    diff = float(jnp.abs(im2col_conv(x8, w) - conv(x8, w)).max())
    if diff > 1e-3 * float(jnp.abs(conv(x8, w)).max()):
        raise SystemExit(f"im2col and XLA's convolution disagree by {diff:.3g}")
    flops8, flops4 = 2 * B * 512 * 27 * C * C, 2 * B * 64 * 27 * C * C
    rows = [("convolution 8^3", timed(conv, x8, w, repeats=args.repeats), flops8),
            ("convolution 4^3", timed(conv, x4, w, repeats=args.repeats), flops4),
            ("matmul, same FLOPs as 8^3", timed(jnp.dot, a, w.reshape(-1, C), repeats=args.repeats), flops8),
            ("im2col + matmul 8^3", timed(im2col_conv, x8, w, repeats=args.repeats), flops8)]
    dev = jax.devices()[0]
    print(f"{dev.platform} ({dev.device_kind}), jax {jax.__version__}, batch {B}, median of {args.repeats}\n")
    print("| operation | median (ms) | GFLOP/s |\n|---|---|---|")
    for name, t, flops in rows:
        print(f"| {name} | {t * 1e3:.2f} | {flops / t / 1e9:.1f} |")


if __name__ == "__main__":
    main()
