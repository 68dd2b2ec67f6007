"""One CPU-backend physics call, timed: the 2-core CPU path side by side across two checkouts (issue 43).

    python bench/cpu_physics_ab.py --grasps /tmp/g16.npz      # prints the call's seconds
    farm-bench -n 5 --vs "sh -c 'PYTHONPATH=OLD python bench/cpu_physics_ab.py --grasps G'" -- \\
        sh -c 'PYTHONPATH=. python bench/cpu_physics_ab.py --grasps G'

The grasps: 4 candidates of `fj.synthesize` (seed 0) on complex shape 0 of seed 900, tiled to 16, written to
`--grasps` on the first run (the synthesis compiles then) and read afterwards, so both checkouts time the same call:
`runner.evaluate(..., backend="cpu")`, lift-shake and six-dir, the collision parts built before the clock starts.
"""

import argparse
import time
from pathlib import Path

import numpy as np

from ffcgs_jax.geometry import procedural
from ffcgs_jax.hand import spec as hand_spec
from ffcgs_jax.physics import convex, runner
from ffcgs_jax.physics.config import PhysicsConfig


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--grasps", type=Path, required=True)
    args = ap.parse_args()
    _, mesh = procedural.complex_shape(900, 0)
    if not args.grasps.is_file():
        import ffcgs_jax as fj

        gs = fj.synthesize(fj.load_hand("svh"), mesh, fj.GraspConfig(n=4, seed=0))
        np.savez(args.grasps, **{k: np.asarray(gs[k]) for k in ("wrist_pose", "q", "squeeze_dir")})
    g = np.load(args.grasps)
    T, q, sq = (np.concatenate([g[k]] * 4) for k in ("wrist_pose", "q", "squeeze_dir"))
    cfg = PhysicsConfig(backend="cpu")
    parts = convex.decompose(mesh, cfg)
    t = time.perf_counter()
    runner.evaluate(hand_spec.load_spec("svh"), mesh, T, q, cfg, ("lift-shake", "six-dir"), backend="cpu",
                    squeeze_dir=sq, parts=parts)
    print(f"{time.perf_counter() - t:.2f}")


if __name__ == "__main__":
    main()
