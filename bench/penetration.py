"""How deep the returned grasps' hands sink into the object, for candidate fixes side by side in one run (issue 45,
item 4, "Contacts that do not sink in").

    python bench/penetration.py                       # built-ins + 6 complex shapes of seed 7000, every candidate
    python bench/penetration.py --complex 40 --builtin 0 --candidates default,project5

The figure: per returned (valid) grasp, the deepest overlap of the hand's collision spheres with the object,
max_s max(0, r_s - d(c_s)): the grasp set's own `penetration` (d from the SDF the synthesis planned on), and the
same with d the signed distance to the mesh itself (`evaluation.device_metrics.mesh_contacts`), which says whether
the SDF's error explains the overlap. Medians and 90th percentiles pool the returned grasps of every object. Valid
yield: returned grasps per object. Time: the warm call's wall time (the first call of each candidate, which
compiles, is run once before on the first object and not counted).

Candidates (each a GraspConfig; "pen_tol0" patches `filters.CONTACT_TOL`, the penalty's free overlap, for the bench
only, and clears the compiled programs before and after so no other candidate reuses them):
- default: GraspConfig() as shipped.
- a_pen1e5: the whole-hand penalty 10x stronger (energy.a_pen 1e5).
- pen_tol0: the penalty from zero overlap instead of 2 mm.
- project5 / project5_allow05: the final projection (`synthesis.project`, optim.project_steps 5; allow 0 / 0.5 mm).
- sdf64: a finer SDF (sdf.res 64, voxels half as large).
"""

import argparse
import contextlib
import dataclasses
import sys
import time

import numpy as np

CANDIDATES = ("default", "a_pen1e5", "pen_tol0", "project5", "project5_allow05", "sdf64")
COMPLEX_SEED = 7000  # never used for training or for the other benches' held-out families (2000)


def candidate(name: str):
    """(GraspConfig, context manager to run it under) of a candidate name."""
    from ffcgs_jax.synthesis import filters
    from ffcgs_jax.synthesis.config import EnergyConfig, GraspConfig, OptimConfig
    from ffcgs_jax.geometry.config import SDFConfig

    base = GraspConfig()
    if name == "default":
        return base, contextlib.nullcontext()
    if name == "a_pen1e5":
        return dataclasses.replace(base, energy=dataclasses.replace(EnergyConfig(), a_pen=1e5)), contextlib.nullcontext()
    if name == "pen_tol0":
        @contextlib.contextmanager
        def patched():
            import ffcgs_jax as fj

            old = filters.CONTACT_TOL
            fj.clear_compiled()
            filters.CONTACT_TOL = 0.0
            try:
                yield
            finally:
                filters.CONTACT_TOL = old
                fj.clear_compiled()
        # a distinct config (same meaning) so the grasp set says which row it is; the patch is what differs
        return dataclasses.replace(base, seed=base.seed), patched()
    if name.startswith("project"):
        allow = 0.0005 if name.endswith("allow05") else 0.0
        steps = int(name[len("project"):].split("_")[0])
        return dataclasses.replace(base, optim=dataclasses.replace(OptimConfig(), project_steps=steps,
                                                                   project_allow=allow)), contextlib.nullcontext()
    if name == "sdf64":
        return dataclasses.replace(base, sdf=dataclasses.replace(SDFConfig(), res=64)), contextlib.nullcontext()
    raise SystemExit(f"penetration.py: unknown candidate {name!r} (known: {', '.join(CANDIDATES)})")


def objects(n_builtin: int, n_complex: int) -> list:
    from ffcgs_jax.geometry import mesh_io, objects as builtin, procedural

    out = [(name, mesh_io.load_mesh(name)) for name in builtin.names()[:n_builtin]]
    return out + [procedural.complex_shape(COMPLEX_SEED, i) for i in range(n_complex)]


def mesh_penetration(hand, mesh, gs) -> np.ndarray:
    """Per valid grasp, the collision spheres' deepest overlap with the mesh itself (not the SDF)."""
    import jax
    import jax.numpy as jnp

    from ffcgs_jax.evaluation import device_metrics
    from ffcgs_jax.hand import kinematics as K

    v = np.asarray(gs["valid"], bool)
    if not v.any():
        return np.zeros(0)
    # every grasp, the valid ones picked after: one shape per batch size, so the search's kernels are reused
    H = jnp.asarray(gs["wrist_pose"], jnp.float32)
    q = jnp.asarray(gs["q"], jnp.float32)
    c, r = jax.vmap(lambda h, x: K.collision_spheres(hand, h, x))(H, q)
    _, _, d = device_metrics.mesh_contacts(device_metrics.mesh_table(mesh), c.reshape(-1, 3))
    return np.maximum(np.asarray(r) - np.asarray(d).reshape(r.shape), 0).max(axis=1)[v]


def run(args) -> list[dict]:
    import ffcgs_jax as fj

    hand = fj.load_hand("svh")
    objs = objects(args.builtin, args.complex)
    rows = []
    for name in args.candidates:
        cfg, ctx = candidate(name)
        with ctx:
            t0 = time.perf_counter()
            fj.synthesize(hand, objs[0][1], cfg, objs[0][0])  # compiles; not counted
            first = time.perf_counter() - t0
            pen, pen_mesh, valid, E, wall = [], [], [], [], []
            for obj, mesh in objs:
                t0 = time.perf_counter()
                gs = fj.synthesize(hand, mesh, cfg, obj)
                wall.append(time.perf_counter() - t0)
                v = np.asarray(gs["valid"], bool)
                valid.append(int(v.sum()))
                pen.append(np.asarray(gs["penetration"])[v])
                E.append(np.asarray(gs["E"])[v])
                pen_mesh.append(mesh_penetration(hand, mesh, gs) if args.mesh else np.zeros(0))
        cat = lambda xs: np.concatenate(xs) if xs else np.zeros(0)  # noqa: E731
        p, pm = cat(pen) * 1000, cat(pen_mesh) * 1000
        q = lambda x, k: float(np.quantile(x, k)) if len(x) else float("nan")  # noqa: E731
        rows.append({"candidate": name, "med": q(p, 0.5), "p90": q(p, 0.9), "med_mesh": q(pm, 0.5),
                     "p90_mesh": q(pm, 0.9), "valid": float(np.mean(valid)), "valid_n": sum(valid),
                     "n": len(objs) * cfg.n, "E": q(cat(E), 0.5), "wall": float(np.median(wall)), "first": first,
                     "per_object": valid})
        print(f"{name}: done ({first:.0f} s first call)", file=sys.stderr, flush=True)
    return rows


def table(rows: list[dict]) -> str:
    lines = ["| candidate | median pen (mm) | p90 (mm) | median / p90 vs mesh (mm) | valid per object | median E "
             "| warm call (s) |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['candidate']} | {r['med']:.2f} | {r['p90']:.2f} | {r['med_mesh']:.2f} / "
                     f"{r['p90_mesh']:.2f} | {r['valid']:.1f} ({r['valid_n']}/{r['n']}) | {r['E']:.4f} "
                     f"| {r['wall']:.2f} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--builtin", type=int, default=6, help="built-in objects (the first N of 6)")
    p.add_argument("--complex", type=int, default=6, help=f"complex shapes of seed {COMPLEX_SEED}")
    p.add_argument("--candidates", default=",".join(CANDIDATES), help="comma-separated, of: " + ", ".join(CANDIDATES))
    p.add_argument("--no-mesh", dest="mesh", action="store_false", help="skip the penetration measured on the mesh")
    args = p.parse_args(argv)
    args.candidates = [c for c in args.candidates.split(",") if c]
    for c in args.candidates:
        candidate(c)  # an unknown name is refused before anything compiles
    if args.builtin + args.complex == 0:
        raise SystemExit("penetration.py: no objects (--builtin 0 --complex 0)")
    rows = run(args)
    print(table(rows))
    for r in rows:
        print(f"{r['candidate']}: valid per object {r['per_object']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
