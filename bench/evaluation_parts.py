"""Where the device evaluation's time goes, part by part, on grasps the pipeline made, with alternatives side by side.

    python bench/evaluation_parts.py OBJECT.stl [--batches 32 65536] [--repeats 5]

For each batch B: the device part runs once (cvae sampler, defaults) and its grasps are evaluated on the mesh. Each
part is its own compiled function over the batch, timed as the median of `repeats` warm calls after one warm-up
(milliseconds; compile apart): the contacts by brute force (closest points, normals, winding-number signs), the
wrench sets, the Q-distance LP (E_g), the rank test, the epsilon search with every ray of a walk solved cold and with
the later rays warm-started (the default), and the whole `device_metrics.evaluate`. The rows of one batch sum to more than the whole: each part
re-reads its inputs and ends in a wait.
"""

import argparse
import functools
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np

from ffcgs_jax.evaluation import device_metrics as dm
from ffcgs_jax.evaluation import epsilon_search
from ffcgs_jax.kernels.directions import sphere_basis
from ffcgs_jax.geometry import mesh_io
from ffcgs_jax.geometry import sdf as S
from ffcgs_jax.hand import kinematics as K
from ffcgs_jax.synthesis import grasp
from ffcgs_jax.kernels import lp_jax
from ffcgs_jax.kernels import quality
from ffcgs_jax.synthesis.config import GraspConfig, OptimConfig
from ffcgs_jax.synthesis.energy import make_target


def timed(fn, repeats: int) -> tuple[float, float]:
    """(compile and first call, median warm call), milliseconds."""
    t0 = time.perf_counter()
    jax.block_until_ready(fn())
    first = time.perf_counter() - t0
    times = []
    for _ in range(repeats + 1):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return 1e3 * first, 1e3 * statistics.median(times[1:])


def parts(hand, mesh, target, out, cfg, repeats: int) -> dict[str, tuple[float, float]]:
    mcfg = grasp.metrics_config(cfg)
    contacts, q = out.opt.final.contacts, out.opt.q
    b, c = contacts.shape[:2]
    flat = contacts.reshape(-1, 3)
    table = dm.mesh_table(mesh)
    contacts_fn = jax.jit(dm.mesh_contacts)
    closest, normals, signed = contacts_fn(table, flat)
    closest, normals = closest.reshape(b, c, 3), normals.reshape(b, c, 3)
    U = quality.basis(mcfg.basis_size)
    starts = jnp.asarray(sphere_basis(epsilon_search.EPS_STARTS).T, contacts.dtype)
    wrench_fn = jax.jit(jax.vmap(lambda p, n: quality.primitive_wrenches(p, n, target.centre, target.radius, mcfg.lp_friction,
                                                                         mcfg.cone_edges)))
    W = wrench_fn(closest, normals)
    lp_fn = jax.jit(jax.vmap(lambda w: lp_jax.q_distance(w, U)[0]))
    rank_fn = jax.jit(jax.vmap(epsilon_search.full_rank))
    eps_fn = jax.jit(jax.vmap(epsilon_search.search_epsilon, (0, None)))
    cold_fn = jax.jit(jax.vmap(functools.partial(epsilon_search.search_epsilon, warm=False), (0, None)))
    rows = {
        "contacts (brute force)": timed(lambda: contacts_fn(table, flat), repeats),
        "wrench sets": timed(lambda: wrench_fn(closest, normals), repeats),
        "Q-distance LP (E_g)": timed(lambda: lp_fn(W), repeats),
        "rank test": timed(lambda: rank_fn(W), repeats),
        "epsilon search, cold rays": timed(lambda: cold_fn(W, starts), repeats),
        "epsilon search, warm rays": timed(lambda: eps_fn(W, starts), repeats),
    }
    e_cold, e_warm = np.asarray(cold_fn(W, starts)), np.asarray(eps_fn(W, starts))
    fc = e_cold > 0
    rel = np.abs(e_warm - e_cold)[fc] / e_cold[fc]
    print(f"  warm against cold rays, {fc.sum()} grasps with epsilon > 0: equal within 1e-5 relative "
          f"{np.mean(rel <= 1e-5):.2%}, largest difference {rel.max(initial=0):.2e}, warm lower on "
          f"{np.mean(e_warm[fc] < e_cold[fc] * (1 - 1e-5)):.2%}, sign agrees {np.mean((e_warm > 0) == (e_cold > 0)):.2%}")
    run, compile_s = dm.compile_evaluate(table, contacts, q, hand.lower, hand.upper, target.centre, target.radius,
                                         mcfg)
    first, warm = timed(run, repeats)
    rows["evaluate (whole)"] = (first + 1e3 * compile_s, warm)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("object")
    ap.add_argument("--batches", type=int, nargs="+", default=[32, 65536])
    ap.add_argument("--iters", type=int, default=50)
    ap.add_argument("--repeats", type=int, default=5)
    a = ap.parse_args()
    hand = K.load_hand("svh")
    mesh = mesh_io.load_mesh(a.object)
    target = make_target(S.build_sdf(mesh, GraspConfig().sdf))
    print(f"{jax.devices()[0].device_kind}, {a.object}: {len(mesh.faces)} faces; compile+first / median warm ms")
    for b in a.batches:
        cfg = GraspConfig(n=b, devices=1, optim=OptimConfig(iters=a.iters))
        run, _ = grasp.compile_device(hand, target, cfg)
        out = jax.block_until_ready(run(jax.random.PRNGKey(0)))
        print(f"B = {b}")
        for name, (first, warm) in parts(hand, mesh, target, out, cfg, a.repeats).items():
            print(f"  {name:<30} {first:>10.1f} {warm:>10.2f}")


if __name__ == "__main__":
    main()
