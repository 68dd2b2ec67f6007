"""Collision geometry for the physics test, candidates side by side: time, size, fidelity and physics outcomes.

    python bench/collision_geometry.py --objects builtin "complex 7" [ycb-test ycb-train ycb] [--methods ...]
        [--agree builtin] [--n 16] [--budget 20] [--json out.json]

Per method and object set: wall time of the decomposition (median, worst; each method on one core, CoACD and V-HACD
in a worker process killed at `--budget` s, "today" at `--today-budget`), parts and vertices, surface error in mm
(both ways between 10k points on the mesh and 10k on the boundary of the union of parts, nearest neighbours:
p50/p95/max), volume error (|union xor mesh| / mesh volume, 8k Monte-Carlo points: trimesh's ray test, slow
without embree), and "open": the share of probe points at least 4 mm outside the mesh but inside its hull (handle openings, cup mouths, the gap of a C) that no
part covers. `--agree`: grasps synthesised on those objects (`synthesize`, `--n` each, the valid ones) run through
`physics.runner.evaluate` (lift-shake and six-dir, friction 0.6) with each method's parts; the share of outcomes
identical to today's CoACD geometry ("today": threshold 0.05, 32 hulls, 64 vertices, CoACD's default search).
"""

import argparse
import json
import os
import statistics
import time
import warnings
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from ffcgs_jax.geometry import mesh_io, objects, procedural
from ffcgs_jax.physics import collision, voxel_parts
from ffcgs_jax.physics.config import PROTOCOLS, PhysicsConfig

YCB = Path(os.environ.get("FFCGS_YCB", Path(__file__).resolve().parents[2] / "shared" / "objects" / "ycb"))
METHODS = ("today", "voxel-hulls", "coacd", "vhacd", "voxel-boxes", "patch-hulls")
TODAY = dict(threshold=0.05, max_convex_hull=32, max_ch_vertex=64, decimate=True, seed=0)
PROBE_GAP = 0.004  # m outside the mesh for a probe point to count as an opening


def object_set(spec: str) -> list[tuple[str, trimesh.Trimesh]]:
    """`builtin`, `complex N`, `ycb`, `ycb-train`, `ycb-test` (sorted index % 5 == 4)."""
    if spec == "builtin":
        return [(n, mesh_io.load_mesh(n)) for n in objects.names()]
    if spec.startswith("complex"):
        n = int(spec.split()[1])
        return [procedural.complex_shape(0, i) for i in range(n)]
    files = sorted(YCB.glob("*.stl"))
    keep = {"ycb": lambda i: True, "ycb-test": lambda i: i % 5 == 4, "ycb-train": lambda i: i % 5 != 4}[spec]
    return [(f.stem, mesh_io.load_mesh(str(f))) for i, f in enumerate(files) if keep(i)]


def method_config(method: str, budget: float) -> PhysicsConfig:
    """The PhysicsConfig of a method name, "NAME" or "NAME:field=value,..." (a variant: `voxel-hulls:voxel_cells=96,
    max_hulls=64`; fields of PhysicsConfig)."""
    name, _, rest = method.partition(":")
    pairs = (kv.split("=") for kv in rest.split(",") if kv)
    fields = {k: float(v) if "." in v or "e" in v else int(v) for k, v in pairs}
    return PhysicsConfig(collision=name, collision_budget=budget, **fields)


def decompose(method: str, mesh: trimesh.Trimesh, budget: float, today_budget: float):
    """(parts, seconds, fell_back)."""
    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        if method == "today":
            parts = collision.in_worker("coacd", mesh, TODAY, today_budget)
            fell = parts is None
            parts = parts if parts is not None else []
        else:
            parts = collision.parts(mesh, method_config(method, budget))
            fell = any(issubclass(w.category, collision.BudgetWarning) for w in caught)
    return parts, time.perf_counter() - t0, fell


class Reference:
    """What every method is measured against, computed once per mesh."""

    def __init__(self, mesh: trimesh.Trimesh, rng: np.random.Generator):
        self.mesh = mesh
        self.surface = trimesh.sample.sample_surface(mesh, 10_000, seed=1)[0]
        self.tree = cKDTree(self.surface)
        lo, hi = mesh.bounds
        self.box = np.prod(hi - lo)
        self.points = rng.uniform(lo, hi, (8_000, 3))
        self.inside = mesh.contains(self.points)
        hull = mesh.convex_hull
        outside = ~self.inside & hull.contains(self.points)
        far = self.tree.query(self.points[outside])[0] > PROBE_GAP
        self.probes = self.points[outside][far]


def covered(parts, points: np.ndarray, margin: float = 0.0, planes=None) -> np.ndarray:
    planes = [voxel_parts.planes(p) for p in parts] if planes is None else planes
    hit = np.zeros(len(points), bool)
    for p, pl in zip(parts, planes):
        lo, hi = p[0].min(0) - margin, p[0].max(0) + margin
        near = np.flatnonzero(((points >= lo) & (points <= hi)).all(1) & ~hit)
        hit[near] = (points[near] @ pl[:, :3].T + pl[:, 3] <= margin).all(axis=1)
    return hit


def fidelity(parts, ref: Reference) -> dict:
    """Surface error (mm) and volume error of the union of parts against the mesh."""
    samples = []
    planes = [voxel_parts.planes(p) for p in parts]
    total = sum_area(parts)
    for i, p in enumerate(parts):  # points on a part that no other part covers (within 0.1 mm): the union's boundary
        m = trimesh.Trimesh(*p, process=False)
        pts = trimesh.sample.sample_surface(m, max(50, int(10_000 * m.area / total)), seed=2)[0]
        rest = [j for j in range(len(parts)) if j != i]
        samples.append(pts[~covered([parts[j] for j in rest], pts, 1e-4, [planes[j] for j in rest])])
    union = np.concatenate(samples)
    d = np.concatenate([ref.tree.query(union)[0], cKDTree(union).query(ref.surface)[0]]) * 1e3
    vol = covered(parts, ref.points)
    return dict(p50_mm=float(np.percentile(d, 50)), p95_mm=float(np.percentile(d, 95)), max_mm=float(d.max()),
                volume_err=float((vol != ref.inside).mean() * ref.box / ref.mesh.volume),
                open=float((~covered(parts, ref.probes)).mean()) if len(ref.probes) else None,
                probes=int(len(ref.probes)))


def sum_area(parts) -> float:
    return sum(trimesh.Trimesh(*p, process=False).area for p in parts)


def geometry_rows(sets, methods, budget, today_budget) -> list[dict]:
    rows = []
    rng = np.random.default_rng(0)
    for spec in sets:
        for name, mesh in object_set(spec):
            ref = Reference(mesh, rng)
            for method in methods:
                parts, seconds, fell = decompose(method, mesh, budget, today_budget)
                row = dict(set=spec, object=name, method=method, seconds=seconds, fell_back=fell,
                           parts=len(parts), vertices=int(sum(len(v) for v, _ in parts)))
                if parts:
                    row.update(fidelity(parts, ref))
                rows.append(row)
                print(json.dumps(row), flush=True)
    return rows


def summary(rows: list[dict]) -> list[dict]:
    out = []
    for spec in dict.fromkeys(r["set"] for r in rows):
        for method in dict.fromkeys(r["method"] for r in rows):
            rs = [r for r in rows if r["set"] == spec and r["method"] == method]
            done = [r for r in rs if "p50_mm" in r]
            opens = [r["open"] for r in done if r["open"] is not None]
            t = [r["seconds"] for r in rs]
            out.append(dict(
                set=spec, method=method, objects=len(rs), median_s=statistics.median(t), worst_s=max(t),
                fell_back=sum(r["fell_back"] for r in rs),
                parts=statistics.median([r["parts"] for r in done]) if done else None,
                vertices=statistics.median([r["vertices"] for r in done]) if done else None,
                p50_mm=statistics.median([r["p50_mm"] for r in done]) if done else None,
                p95_mm=statistics.median([r["p95_mm"] for r in done]) if done else None,
                max_mm=max([r["max_mm"] for r in done]) if done else None,
                volume_err=statistics.median([r["volume_err"] for r in done]) if done else None,
                open=statistics.median(opens) if opens else None))
    return out


def pick(objs: list, part: str | None) -> list:
    """`part` "K/N": the objects at index K, K + N, ... (parallel runs split a set; `--merge` joins them)."""
    if not part:
        return objs
    k, n = (int(x) for x in part.split("/"))
    return objs[k::n]


def agreement(sets, methods, n: int, budget: float, today_budget: float, part: str | None = None,
              log: list | None = None) -> list[dict]:
    """Share of identical physics outcomes per protocol against today's CoACD geometry, grasp by grasp; `log`
    collects each object's per-grasp outcomes (what `--merge` pools)."""
    import ffcgs_jax as fj
    from ffcgs_jax.hand import spec as hand_spec
    from ffcgs_jax.physics import runner

    hand, spec = fj.load_hand("svh"), hand_spec.load_spec("svh")
    cfg = PhysicsConfig(sim_friction=0.6, backend="cpu")
    same = {m: {p: [] for p in PROTOCOLS} for m in methods if m != "today"}
    for s in sets:
        for name, mesh in pick(object_set(s), part):
            gs = fj.synthesize(hand, mesh, fj.GraspConfig(n=n))
            ok = np.asarray(gs.arrays["valid"], bool)
            if not ok.any():
                continue
            T, q = gs.arrays["wrist_pose"][ok], gs.arrays["q"][ok]
            ref_parts, _, fell = decompose("today", mesh, budget, today_budget)
            if fell:
                print(f"{name}: today's CoACD did not finish in {today_budget} s; skipped", flush=True)
                continue
            ref = runner.evaluate(spec, mesh, T, q, cfg, parts=ref_parts)
            for m in same:
                res = runner.evaluate(spec, mesh, T, q, cfg, parts=decompose(m, mesh, budget, today_budget)[0])
                for p in PROTOCOLS:
                    key = f"{p.replace('-', '_')}_success"
                    same[m][p].extend((res[key] == ref[key]).tolist())
                    if log is not None:
                        log.append(dict(set=s, object=name, method=m, protocol=p, ref=ref[key].tolist(),
                                        got=res[key].tolist()))
            print(f"{name}: {int(ok.sum())} valid grasps", flush=True)
    return pooled(same)


def pooled(same: dict) -> list[dict]:
    rows = []
    for m, by in same.items():
        both = np.logical_and(*[np.asarray(by[p], bool) for p in PROTOCOLS])
        rows.append(dict(method=m, grasps=len(both), **{p: float(np.mean(by[p])) for p in PROTOCOLS},
                         both=float(both.mean()) if len(both) else None))
    return rows


def fmt(v, spec=".2f") -> str:
    return "-" if v is None else format(v, spec)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--objects", nargs="*", default=["builtin", "complex 7"])
    ap.add_argument("--methods", nargs="+", default=list(METHODS),
                    help=f"{', '.join(METHODS)}, or a variant NAME:field=value,... of PhysicsConfig's fields")
    ap.add_argument("--part", help="K/N: only every N-th object from the K-th, for parallel runs")
    ap.add_argument("--merge", nargs="+", type=Path, help="no run: pool the agreement of these --json files")
    ap.add_argument("--agree", nargs="*", default=[], help="object sets for the physics agreement")
    ap.add_argument("--n", type=int, default=16)
    ap.add_argument("--budget", type=float, default=20.0)
    ap.add_argument("--today-budget", type=float, default=60.0)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    if args.merge:
        logs = [r for f in args.merge for r in json.loads(f.read_text()).get("log", [])]
        same = {}
        for r in logs:
            same.setdefault(r["method"], {p: [] for p in PROTOCOLS})[r["protocol"]].extend(
                np.equal(r["got"], r["ref"]).tolist())
        print_agreement(pooled(same), len({(r["set"], r["object"]) for r in logs}))
        return
    for m in args.methods:
        if m.partition(":")[0] not in METHODS:
            ap.error(f"unknown method {m!r}; methods: {', '.join(METHODS)}")
    rows = geometry_rows(args.objects, args.methods, args.budget, args.today_budget)
    table = summary(rows)
    print("| set | method | objects | median s | worst s | fell back | parts | vertices | p50 mm | p95 mm | max mm "
          "| volume err | open |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in table:
        print(f"| {r['set']} | {r['method']} | {r['objects']} | {r['median_s']:.2f} | {r['worst_s']:.2f} | "
              f"{r['fell_back']} | {fmt(r['parts'], '.0f')} | {fmt(r['vertices'], '.0f')} | {fmt(r['p50_mm'])} | "
              f"{fmt(r['p95_mm'])} | {fmt(r['max_mm'], '.1f')} | {fmt(r['volume_err'], '.3f')} | "
              f"{fmt(r['open'], '.2f')} |")
    log = []
    agree = agreement(args.agree, args.methods, args.n, args.budget, args.today_budget, args.part, log) \
        if args.agree else []
    if agree:
        print_agreement(agree, len({(r["set"], r["object"]) for r in log}))
    if args.json:
        args.json.write_text(json.dumps(dict(rows=rows, summary=table, agreement=agree, log=log), indent=1))


def print_agreement(rows: list[dict], objects: int) -> None:
    from ffcgs_jax.physics.protocols import wilson

    print(f"\n{objects} objects\n\n| method | grasps | lift-shake same | six-dir same | both same (95 % CI) |\n"
          "|---|---|---|---|---|")
    for r in rows:
        k = round(r["both"] * r["grasps"]) if r["both"] is not None else 0
        lo, hi = wilson(k, r["grasps"])
        print(f"| {r['method']} | {r['grasps']} | {r['lift-shake']:.3f} | {r['six-dir']:.3f} | "
              f"{fmt(r['both'], '.3f')} ({100 * lo:.0f}-{100 * hi:.0f} %) |")


if __name__ == "__main__":
    main()
