"""Where the small-batch latency goes: the synthesis call with parts of the descent step replaced by stand-ins.

    python bench/latency_parts.py [--n 32] [--iters 50] [--repeats 15] [--variants full,no-lp,no-mjx]

Variants (everything else is the real `ffcgs bench` device part: cvae sampler, descent, filters):
    full     as shipped
    no-lp    E_g by a cheap stand-in (no wrench matrix, no LP, no LP gradient): the floor of everything else
    no-mjx   MJX's forward kinematics by a cheap q-dependent shift of the q = 0 frames: the cost of MJX and its
             reverse pass is the difference to `full`

The grasps of the stand-in variants mean nothing; only their time does. For each variant the table gives the compile
time, the median and minimum of `repeats` warm calls, and the number of device kernels in one descent step (the
instructions of the descent loop's body in the optimised HLO that launch work: fusions, custom calls, copies).
"""

import argparse
import re

import jax
import jax.numpy as jnp

from ffcgs_jax.cli.benchmark import time_synthesis
from ffcgs_jax.geometry import mesh_io
from ffcgs_jax.geometry import sdf as S
from ffcgs_jax.geometry.config import SDFConfig
from ffcgs_jax.hand import kinematics as K
from ffcgs_jax.synthesis import grasp
from ffcgs_jax.kernels import quality
from ffcgs_jax.runtime import compiled
from ffcgs_jax.synthesis.config import GraspConfig, OptimConfig
from ffcgs_jax.synthesis.energy import make_target

VARIANTS = ("full", "no-lp", "no-mjx")
_NOT_KERNELS = {"parameter", "get-tuple-element", "tuple", "bitcast", "constant"}


def step_kernels(hlo: str, iters: int) -> int:
    """Kernels in the body of the while loop that runs `iters` times with the most instructions (the descent)."""
    bodies = {}
    name = None
    for line in hlo.splitlines():
        m = re.match(r"^(?:ENTRY )?%(\S+) .*\{$", line)
        if m:
            name, bodies[m.group(1)] = m.group(1), []
        elif name and line.startswith("  "):
            bodies[name].append(line)
    loops = re.findall(r"while\(.*body=%([\w.\-]+).*\"known_trip_count\":\{\"n\":\"(\d+)\"", hlo)
    counts = []
    for body, trips in loops:
        if int(trips) == iters and body in bodies:
            ops = [re.match(r"\s*(?:ROOT )?%\S+ = .*? ([\w\-]+)\(", x) for x in bodies[body]]
            counts.append(sum(1 for m in ops if m and m.group(1) not in _NOT_KERNELS))
    return max(counts) if counts else -1


def patch(variant: str, hand) -> None:
    if variant == "no-lp":
        quality.q_distance_warm = lambda c, n, *a, **k: (1e-3 * jnp.sum(c**2), jnp.array(True),
                                                          jnp.zeros(7, jnp.int32))
    elif variant == "no-mjx":
        d0 = jax.jit(K.mjx_kinematics)(hand, jnp.zeros_like(hand.lower))

        def shifted(hand, q):
            s = 0.01 * jnp.sum(jnp.sin(q))
            return d0.replace(xpos=d0.xpos + s, site_xpos=d0.site_xpos + s, xmat=d0.xmat * (1 + 0.1 * s))

        K.mjx_kinematics = shifted


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=32)
    ap.add_argument("--iters", type=int, default=50)
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--variants", default="full,no-lp,no-mjx")
    args = ap.parse_args()
    unknown = [v for v in args.variants.split(",") if v not in VARIANTS]
    if unknown:
        ap.error(f"unknown variant(s) {', '.join(unknown)}; known: {', '.join(VARIANTS)}")
    jax.config.update("jax_enable_compilation_cache", False)
    hand = K.load_hand("svh")
    target = make_target(S.build_sdf(mesh_io.load_mesh("mug"), SDFConfig(res=32)))
    print(f"{jax.devices()[0].device_kind}, jax {jax.__version__}; mug, 32^3, cvae sampler, n = {args.n}, "
          f"{args.iters} steps, median of {args.repeats} warm calls\n")
    print("| variant | compile (s) | median (ms) | min (ms) | kernels per step |\n|---|---|---|---|---|")
    real_lp, real_fk = quality.q_distance_warm, K.mjx_kinematics
    for variant in args.variants.split(","):
        quality.q_distance_warm, K.mjx_kinematics = real_lp, real_fk
        patch(variant, hand)
        compiled.clear_compiled()  # JAX's caches too: traced jaxprs do not see the patched module functions
        row = time_synthesis(hand, target, GraspConfig(n=args.n, devices=1, optim=OptimConfig(iters=args.iters)),
                             args.repeats)
        kernels = step_kernels(grasp.compiled_executables()[0].as_text(), args.iters)
        print(f"| {variant} | {row.compile_s:.1f} | {row.median_s * 1e3:.2f} | {row.min_s * 1e3:.2f} | {kernels} |",
              flush=True)

if __name__ == "__main__":
    main()
