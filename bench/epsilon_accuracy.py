"""The device evaluation against the float64 host reference on synthesised grasps, side by side.

    python bench/epsilon_accuracy.py [--objects mug,box,...] [--ycb DIR] [--n 32] [--json out.json]

For each object: `synthesize` (cvae sampler, the defaults), then the returned contacts and channels are scored twice:
by `evaluation.device_metrics.evaluate` (what `synthesize` uses, here in float64 on this machine's default device)
and by `evaluation.metrics.evaluate` (trimesh closest points, Qhull epsilon, HiGHS E_g, the reference). Printed per
object and pooled: agreement of force closure and of the touching count, the largest contact-distance difference,
and for grasps in force closure under both the searched epsilon against Qhull's (share within 1e-9 relative,
median and largest relative excess; the search never goes below Qhull's by construction, so a negative excess
would be a bug), and the time of each path.
"""

import argparse
import json
import time
from pathlib import Path

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

from ffcgs_jax.evaluation import device_metrics, metrics  # noqa: E402
from ffcgs_jax.geometry import mesh_io, sdf  # noqa: E402
from ffcgs_jax.hand import kinematics as K  # noqa: E402
from ffcgs_jax.synthesis.config import GraspConfig  # noqa: E402
from ffcgs_jax.synthesis.energy import make_target  # noqa: E402
from ffcgs_jax.synthesis.grasp import metrics_config, synthesize  # noqa: E402


def compare(hand, name, mesh, n):
    cfg = GraspConfig(n=n)
    gs = synthesize(hand, mesh, cfg, name)
    target = make_target(sdf.build_sdf(mesh, cfg.sdf))  # the grid synthesize planned on (from the cache)
    mcfg = metrics_config(cfg)
    args = (gs["contacts"], gs["q"], np.asarray(hand.lower), np.asarray(hand.upper))
    centre, radius = np.asarray(target.centre), float(target.radius)
    t0 = time.perf_counter()
    dev = jax.device_get(device_metrics.evaluate(device_metrics.mesh_table(mesh), *map(jax.numpy.asarray, args[:2]),
                                                 *args[2:], centre, radius, mcfg))
    dev_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    ref = metrics.evaluate(mesh, *args, mcfg, centre=centre, radius=radius)
    ref_s = time.perf_counter() - t0
    both = dev["force_closure"] & ref["force_closure"]
    rel = (dev["epsilon"][both] - ref["epsilon"][both]) / ref["epsilon"][both]
    return {"object": name, "grasps": len(gs["q"]),
            "fc_agree": int((dev["force_closure"] == ref["force_closure"]).sum()),
            "touch_agree": int((dev["n_contacts"] == ref["n_contacts"]).sum()),
            "max_dist_diff_m": float(np.abs(dev["contact_dist"] - ref["contact_dist"]).max()),
            "fc_both": int(both.sum()), "rel_excess": rel.tolist(), "device_s": dev_s, "host_s": ref_s}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--objects", default="mug,box,banana,bottle,can,ball")
    ap.add_argument("--ycb", type=Path, help="also every YCB test-split mesh (sorted index % 5 == 4) of this folder")
    ap.add_argument("--n", type=int, default=32)
    ap.add_argument("--json")
    a = ap.parse_args()
    hand = K.load_hand("svh")
    meshes = [(o, mesh_io.load_mesh(o)) for o in a.objects.split(",") if o]
    if a.ycb:
        files = sorted(a.ycb.glob("*.stl"))
        meshes += [(f.stem, mesh_io.load_mesh(str(f))) for i, f in enumerate(files) if i % 5 == 4]
    rows = [compare(hand, name, mesh, a.n) for name, mesh in meshes]
    print(f"device: {jax.default_backend()}, float64; n {a.n} per object, cvae sampler, defaults\n")
    print("| object | grasps | force closure agrees | touching count agrees | max contact distance diff (m) | "
          "FC both | epsilon exact (1e-9) | median / max excess | device s | host s |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        e = np.asarray(r["rel_excess"])
        ex = f"{np.mean(e <= 1e-9):.0%}" if len(e) else "-"
        mm = f"{np.median(e):.1e} / {e.max():.1e}" if len(e) else "-"
        print(f"| {r['object']} | {r['grasps']} | {r['fc_agree']} | {r['touch_agree']} | {r['max_dist_diff_m']:.1e} | "
              f"{r['fc_both']} | {ex} | {mm} | {r['device_s']:.3f} | {r['host_s']:.3f} |")
    e = np.concatenate([np.asarray(r["rel_excess"]) for r in rows])
    g = sum(r["grasps"] for r in rows)
    print(f"\npooled: force closure agrees on {sum(r['fc_agree'] for r in rows)}/{g} grasps, touching count on "
          f"{sum(r['touch_agree'] for r in rows)}/{g}; epsilon of {len(e)} grasps in force closure: exact (within "
          f"1e-9 relative) {np.mean(e <= 1e-9):.1%}, within 1 % {np.mean(e <= 0.01):.1%}, median excess "
          f"{np.median(e):.1e}, largest {e.max():.1e}, smallest {e.min():.1e}")
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
