"""Pivots of warm-started against cold LP solves along random walks of the contacts (a stand-in for the descent).

    python bench/lp_warm_pivots.py [--step 0.002] [--batch 32] [--steps 50]

32 grasps of 5 contacts on a 5 cm sphere, half of them one-sided (E_g > 0), half spread (force closure, degenerate
vertices); each step moves every contact by `step` per coordinate and re-solves, warm from the last basis and cold.
Prints the mean pivots per LP and the mean over steps of the batch's worst LP (a batch pivots in lockstep), and
checks that both starts give the same values. float32, as the descent runs.
"""

import argparse

import jax
import jax.numpy as jnp
import numpy as np

from ffcgs_jax.kernels import lp_jax
from ffcgs_jax.kernels import quality


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--step", type=float, default=0.002)
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--steps", type=int, default=50)
    args = ap.parse_args()
    U = quality.basis(64)
    axes = lp_jax.axis_columns(U)
    rng = np.random.default_rng(0)
    B = args.batch
    c = rng.normal(size=(B, 5, 3))
    c[: B // 2] = np.abs(c[: B // 2]) + 0.3
    wrench = jax.jit(jax.vmap(lambda c: quality.primitive_wrenches(
        c, c / jnp.linalg.norm(c, axis=1, keepdims=True), jnp.zeros(3), 0.05, 0.2, 8)))
    solve = jax.jit(jax.vmap(lambda W, b: lp_jax.solve(W, jnp.asarray(U, W.dtype), axes, basis0=b)))
    none = jnp.full((B, 7), -1, jnp.int32)
    basis, warm, cold = none, [], []
    for t in range(args.steps):
        c = 0.05 * c / np.linalg.norm(c, axis=-1, keepdims=True)
        W = wrench(jnp.asarray(c, jnp.float32))
        sw, sc = solve(W, basis), solve(W, none)
        gap = float(np.abs(np.asarray(sw.value - sc.value)).max())
        if gap > 2e-5 or not bool(sw.ok.all()):
            raise SystemExit(f"step {t}: warm and cold starts disagree by {gap:.2e} (or a solve failed)")
        if t:  # step 0 has no warm start
            warm.append(np.asarray(sw.pivots))
            cold.append(np.asarray(sc.pivots))
        basis = sw.basis
        c = c + args.step * rng.normal(size=c.shape)
    warm, cold = np.array(warm), np.array(cold)
    print(f"step {args.step} m, batch {B}, {args.steps} steps, backend {jax.default_backend()}")
    print("| start | mean pivots per LP | batch's worst LP per step (mean) |")
    print("|---|---|---|")
    print(f"| cold | {cold.mean():.1f} | {cold.max(1).mean():.1f} |")
    print(f"| warm | {warm.mean():.1f} | {warm.max(1).mean():.1f} |")


if __name__ == "__main__":
    main()
