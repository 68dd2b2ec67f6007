"""Objects seen only through depth frames: the fused surface against the mesh, and physics success of grasps planned
on the fused SDF against grasps planned on the mesh's own SDF; `--speed`: the time of each fusion step.

    python bench/depth.py                                    # ycb-test + builtin, 1/3/5 views, noise off and on
    python bench/depth.py --objects builtin --views 1,5 --noise on --width 160 --height 120 --n 4 --physics off
    python bench/depth.py --objects builtin --views 5 --noise on --scene plane,table,clutter   # the object's scene
    python bench/depth.py --json d.json --results bench/RESULTS.md
    python bench/depth.py --speed [--object mug --repeats 20]   # 5 noisy views of 640 x 480 into 64^3, step by step
    python bench/depth.py --report d.json [--results bench/RESULTS.md]   # the tables again, from a JSON

Accuracy (the default). Per object (`--objects`, groups as bench/quality.py) and `--views` count, depth frames of
`--width` x `--height` are rendered (`depth_render.render_views`: table plane at the mesh's lowest z, the renderer's
object masks), used clean and with RealSense-like noise (sigma = 0.0015 z^2, 2 % dropout, seed `--seed`) as
`--noise` asks, and fused by `depth_object.from_depth` at `--res` (table height by RANSAC, as for a real camera;
  no object masks unless `--masks`, so the object is isolated from its scene by `depth_isolate`). `--scene`: what
  stands around the object (`depth_scene`): `plane` (the infinite table plane alone), `table` (a 1 m x 1 m table
  3 cm thick, its edges, sides and the floor 75 cm below in view), `clutter` (that table, a second object 18 cm
  beside the first and a wall 60 cm behind); each scene is a row of its own.
- surface: `--points` points sampled on the true mesh (seed `--seed`); their unsigned distance to the fused zero
  level is |fused SDF| there (`sdf.distance`, the planner's own interpolation). Per object the median and p95 in
  voxels of the fused grid (and mm); a row shows the median over objects of each, and the worst object's p95.
- grasps: `synthesize` with `--sampler` (package defaults otherwise) on the fused grid, its filters (every tip
  within contact_tol of the surface, force closure) reading the fused SDF's zero level (`metrics.sdf_contacts`), as
  `ffcgs grasp --depth` and a robot without the mesh do (the object frame is the cameras' world, the mesh's own frame); `--filter-mesh true`
  gives them the true mesh instead (few grasps pass: the fingertips rest on the fused surface, 1-4 mm from the
  true one, and contact_tol is 2 mm). The `mesh` row plans on the mesh's own SDF. Physics as
  bench/quality.py (`runner.evaluate`, PhysicsConfig(sim_friction=0.6), lift-shake and six-dir, the grasps' squeeze
  directions) on the TRUE mesh, every returned (valid) grasp best first (`--max-grasps-per-object`).
  Shares pooled over grasps with 95 % Wilson intervals; "vs mesh": the both-protocol share minus the mesh row's, in
  percentage points (target: 5 noisy views within 5 pp); top-1: the object's best returned grasp passes both (no
  valid grasp or a failed fusion fails).

Speed (`--speed`): `--object`, 5 noisy views, fused into 64^3; median and min of `--repeats` warm calls, the first
(compiling) call apart: host->device transfer of the frames, `tsdf.integrate`, the conversion (`tsdf.resolve` +
`tsdf.to_gradient_sdf`), `tsdf.fuse` whole (frames in host memory, table already removed), `from_depth` whole
(table fit and surface-nets mesh included), and Open3D's VoxelBlockGrid on the same object readings when
`import open3d` works (a benchmark-only comparison, never a dependency). Surface figures as above, of the SDF where
there is one, and of the extracted mesh (distance to its triangles) for both fusions.
"""

import argparse
import contextlib
import dataclasses
import functools
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

import quality as Q  # the sibling scoreboard: object groups, machine, rates, physics pass of a record
from ffcgs_jax.core import files
from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.physics.config import BACKENDS, PROTOCOLS, PhysicsConfig
from ffcgs_jax.synthesis.config import SAMPLERS, GraspConfig

PROG = "depth.py"
SCENE_NAMES = ("table", "clutter")  # depth_scene.SCENES (not imported here: --help stays fast)
SPEED_RES, SPEED_VIEWS, TRUNC_VOXELS = 64, 5, 4.0


class Parser(Q.Parser):
    def error(self, message):
        sys.stderr.write(f"{PROG}: error: {message} (see {PROG} --help)\n")
        sys.exit(2)


def parser() -> Parser:
    ap = Parser(prog=PROG, description=__doc__.splitlines()[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--objects", default="ycb-test,builtin", help=f"comma list of {', '.join(Q.GROUPS)}")
    ap.add_argument("--ycb", default=str(Q.REPO.parent / "shared" / "objects" / "ycb"), help="folder of YCB *.stl")
    ap.add_argument("--only", metavar="NAMES", help="comma list: keep only these objects of the groups")
    ap.add_argument("--every-file", action="store_true", help="--ycb holds only the test split: take every file")
    ap.add_argument("--procedural", type=Q.int_at_least(0), default=8, help="procedural shapes (seed 1000)")
    ap.add_argument("--views", default="1,3,5", help="comma list of camera counts")
    ap.add_argument("--noise", default="off,on", help="comma list of off, on")
    ap.add_argument("--scene", default="plane", help="comma list of plane, " + ", ".join(SCENE_NAMES))
    ap.add_argument("--width", type=Q.int_at_least(16), default=640)
    ap.add_argument("--height", type=Q.int_at_least(16), default=480)
    ap.add_argument("--res", type=Q.int_at_least(16), default=32, help="voxels per axis of the fused grid")
    ap.add_argument("--points", type=Q.int_at_least(10), default=5000, help="mesh surface points for the distances")
    ap.add_argument("--sampler", default="cvae", choices=SAMPLERS)
    ap.add_argument("--hand", default="svh")
    ap.add_argument("--n", type=Q.int_at_least(1), default=32, help="wrist poses sampled per object")
    ap.add_argument("--seed", type=Q.int_at_least(0), default=0)
    ap.add_argument("--filter-mesh", default="fused", choices=("true", "fused"),
                    help="mesh that synthesize's contact and force-closure filters read for fused-planned grasps: "
                         "the fused SDF's zero level (default: as `ffcgs grasp --depth` and a robot without the "
                         "mesh) or the true mesh")
    ap.add_argument("--masks", action="store_true",
                    help="give fusion the renderer's object masks (default: none, as `ffcgs render-depth` writes and "
                         "a bare depth camera gives: the table fit separates the object)")
    ap.add_argument("--no-mesh-row", dest="mesh_row", action="store_false",
                    help="skip the mesh-planned row (when another run has it)")
    ap.add_argument("--physics", default="on", choices=("on", "off"), help="off: surface figures only")
    ap.add_argument("--friction", type=Q.positive_float, default=0.6)
    ap.add_argument("--backend", default="auto", choices=BACKENDS, help="physics backend")
    ap.add_argument("--max-grasps-per-object", type=Q.int_at_least(0), default=0, metavar="K",
                    help="physics-test at most the K best returned grasps per object (0: all)")
    ap.add_argument("--speed", action="store_true", help="time the fusion steps instead (see above)")
    ap.add_argument("--object", default="mug", help="--speed: built-in name or mesh file")
    ap.add_argument("--repeats", type=Q.int_at_least(1), default=20, help="--speed: warm calls per step")
    ap.add_argument("--json", metavar="PATH", help="write the config and every raw figure here (after every job)")
    ap.add_argument("--results", metavar="PATH", help="replace or append this script's block of a Markdown file")
    ap.add_argument("--report", metavar="JSON", help="no run: print (and --results) the tables of a --json")
    ap.add_argument("--no-jax-cache", action="store_true", help="compile instead of loading from JAX's disk cache")
    return ap


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = parser()
    args = ap.parse_args(argv)
    for flag, out in (("--json", args.json), ("--results", args.results)):
        if out and not Path(out).resolve().parent.is_dir():  # found out now, not after an hour of synthesis
            ap.error(f"{flag}: no such folder: {Path(out).parent}")
    if args.report:
        if not Path(args.report).is_file():
            ap.error(f"--report: no such file: {args.report}")
        return args
    if args.speed:
        from ffcgs_jax.geometry import objects

        if args.object not in objects.names() and not Path(args.object).is_file():
            ap.error(f"--object: neither a built-in ({', '.join(objects.names())}) nor a file: {args.object}")
        return args
    groups = Q.split_list(args.objects)
    bad = [g for g in groups if g not in Q.GROUPS]
    if bad or not groups:
        ap.error(f"--objects: unknown group(s) {', '.join(bad) or '(none given)'}; groups: {', '.join(Q.GROUPS)}")
    args.groups = list(dict.fromkeys(groups))
    if {"ycb-test", "ycb-train"} & set(groups) and not Path(args.ycb).is_dir():
        ap.error(f"--ycb: no such folder: {args.ycb}")
    views = Q.split_list(args.views)
    if not views or not all(v.isdigit() and int(v) >= 1 for v in views):
        ap.error(f"--views: expected a comma list of integers >= 1, got {args.views!r}")
    args.view_list = sorted({int(v) for v in views})
    noise = Q.split_list(args.noise)
    if not noise or not set(noise) <= {"off", "on"}:
        ap.error(f"--noise: expected a comma list of off, on, got {args.noise!r}")
    args.noise_list = [x for x in (False, True) if ("on" if x else "off") in noise]
    scenes = Q.split_list(args.scene)
    if not scenes or not set(scenes) <= {"plane", *SCENE_NAMES}:
        ap.error(f"--scene: expected a comma list of plane, {', '.join(SCENE_NAMES)}, got {args.scene!r}")
    args.scene_list = list(dict.fromkeys(scenes))
    if args.res > 128:
        ap.error(f"argument --res: must be <= 128, got {args.res}")
    try:
        PhysicsConfig(sim_friction=args.friction, backend=args.backend).check()
    except FfcgsError as e:
        ap.error(str(e))
    return args


# ----------------------------------------------------------------------------------------------------- measuring


def sdf_distance(grid, points: np.ndarray) -> np.ndarray:
    """|SDF| of `grid` at `points`: the distance to its zero level as the planner interpolates it."""
    import jax.numpy as jnp

    return np.abs(np.asarray(_distance()(grid, jnp.asarray(points, grid.grid.dtype))))


@functools.cache
def _distance():
    import jax

    from ffcgs_jax.geometry import sdf

    return jax.jit(sdf.distance)  # one compile per grid shape, not one trace per object


def surface_error(d: np.ndarray, h: float) -> dict:
    """Median and p95 of distances `d` (m) in voxels of size `h` and in mm."""
    med, p95 = float(np.median(d)), float(np.quantile(d, 0.95))
    return {"median_vox": med / h, "p95_vox": p95 / h, "median_mm": 1000 * med, "p95_mm": 1000 * p95,
            "voxel_mm": 1000 * h}


def grid_error(grid, points: np.ndarray) -> dict:
    return surface_error(sdf_distance(grid, points), float(grid.voxel_size))


def mesh_error(mesh, points: np.ndarray, h: float) -> dict:
    return surface_error(mesh.nearest.on_surface(points)[1], h)


def grasp_job(hand, mesh, name: str, cfg: GraspConfig, args, grid=None, filter_mesh=None) -> dict:
    """bench/quality.py's `run_job` with a grid to plan on (None: the mesh's own SDF) and the mesh synthesize's
    filters read (None: `mesh`), keeping what the tables use; physics always on `mesh`."""
    from ffcgs_jax.physics import runner
    from ffcgs_jax.synthesis.grasp import synthesize

    t0 = time.perf_counter()
    gs = synthesize(hand, mesh if filter_mesh is None else filter_mesh, cfg, name, grid=grid)
    wall = time.perf_counter() - t0
    valid = np.asarray(gs["valid"], bool)
    returned = np.asarray(gs.order())[:int(valid.sum())]  # order() puts the valid ones first
    cap = args.max_grasps_per_object
    tested = (returned[:cap] if cap else returned) if args.physics == "on" else returned[:0]
    physics, physics_s = {}, 0.0
    if len(tested):
        t1 = time.perf_counter()
        res = runner.evaluate(hand.spec, mesh, gs["wrist_pose"][tested], gs["q"][tested],
                              PhysicsConfig(sim_friction=args.friction, backend=args.backend), PROTOCOLS,
                              squeeze_dir=gs["squeeze_dir"][tested])
        physics_s = time.perf_counter() - t1
        physics = {k: np.asarray(v).tolist() for k, v in res.items() if k.endswith("_success")}
    a = gs.arrays  # why grasps planned on a fused surface fail the filters: tips off the (true) surface
    rejected = {"not all tips touching": int((a["n_contacts"] != a["contacts"].shape[1]).sum()),
                "no force closure": int((~np.asarray(a["force_closure"], bool)).sum()),
                "median |tip distance| mm": 1000 * float(np.median(np.abs(a["contact_dist"])))}
    return {"n": int(len(valid)), "valid": int(valid.sum()), "tested": tested.tolist(), "physics": physics,
            "filters": rejected, "wall_s": wall, "compile_s": float(a["compile_s"]), "physics_s": physics_s}


def conditions(args) -> list[tuple[str, int | None, bool, str]]:
    return [("mesh", None, False, "plane")] * args.mesh_row + [
        (f"{v} view{'s' * (v > 1)}, {'noisy' if z else 'clean'}" + (f", {sc}" if sc != "plane" else ""), v, z, sc)
        for sc in args.scene_list for v in args.view_list for z in args.noise_list]


def run(args) -> dict:
    import trimesh

    from ffcgs_jax.geometry import depth_object, depth_render, depth_scene, mesh_io
    from ffcgs_jax.hand import kinematics as K
    from ffcgs_jax.physics import runner

    if not args.no_jax_cache:
        from ffcgs_jax.runtime import jax_cache

        jax_cache.enable()
    only = set(Q.split_list(args.only or ""))
    objs = [(g, name, src if not isinstance(src, str) else mesh_io.load_mesh(src))
            for g, name, src in Q.object_sources(args) if not only or name in only]  # every mesh before compiling
    if not objs:
        raise FfcgsError(f"no objects in groups {', '.join(args.groups)}" + (f" named {args.only}" if only else ""))
    hand = K.load_hand(args.hand)
    cfg = dataclasses.replace(GraspConfig(), n=args.n, sampler=args.sampler, seed=args.seed)
    per_call = min(args.n, args.max_grasps_per_object or args.n)
    conf = {"mode": "accuracy", "command": command_line(), "machine": Q.machine(), "groups": args.groups,
            "group_counts": {g: sum(o[0] == g for o in objs) for g in args.groups}, "views": args.view_list,
            "noise": args.noise_list, "width": args.width, "height": args.height, "res": args.res,
            "points": args.points, "sampler": args.sampler, "n": args.n, "seed": args.seed, "hand": args.hand,
            "physics": args.physics, "friction": args.friction, "protocols": list(PROTOCOLS),
            "physics_backend": runner.resolve_backend(args.backend, per_call)[0],
            "max_grasps_per_object": args.max_grasps_per_object, "filter_mesh": args.filter_mesh,
            "masks": args.masks, "scenes": args.scene_list,
            "grasp_config": dataclasses.asdict(cfg)}
    records = []
    jobs = [(o, c) for o in objs for c in conditions(args)]
    frames = {}
    bar = tqdm(jobs, desc="depth", unit="job", file=sys.stderr)
    for (group, name, mesh), (label, views, noisy, scene) in bar:
        bar.set_postfix_str(f"{name} / {label}")
        rec = {"object": name, "group": group, "condition": label, "views": views, "noise": noisy, "scene": scene,
               "error": None, "surface": None, "fuse_s": None, "table_err_mm": None, "isolated": None}
        try:
            if views is None:
                rec.update(grasp_job(hand, mesh, name, cfg, args))
            else:
                if (name, views, scene) not in frames:  # one render per view count: clean and noisy see the same
                    frames = {(name, views, scene): depth_render.render_views(mesh, views, args.width, args.height)
                              if scene == "plane" else
                              depth_scene.render_scene(mesh, scene, views, args.width, args.height)}
                f = frames[name, views, scene] if args.masks else frames[name, views, scene]._replace(mask=None)
                if noisy:
                    depth = depth_render.add_noise(f.depth, np.random.default_rng(args.seed))
                    f = f._replace(depth=depth.astype(np.float32))
                fused = depth_object.from_depth(f, res=args.res)
                rec["isolated"] = None if fused.isolation is None else fused.isolation.summary()
                points = trimesh.sample.sample_surface(mesh, args.points, seed=args.seed)[0]
                rec.update(surface=grid_error(fused.grid, points), fuse_s=fused.fuse_s,
                           table_err_mm=1000 * (fused.table_z - float(mesh.bounds[0, 2])))
                rec.update(grasp_job(hand, mesh, name, cfg, args, grid=fused.grid,
                                     filter_mesh=fused.grid if args.filter_mesh == "fused" else None))
        except FfcgsError as e:  # a failed fusion is a result (its object fails top-1), not the end of the run
            rec["error"] = str(e)
        records.append(rec)
        if args.json:
            files.write_text(args.json, json.dumps({"config": conf, "records": records}))
    return {"config": conf, "records": records}


def _ready(fused):
    import jax

    jax.block_until_ready(fused.grid.grid)
    return fused


def _timed(fn, repeats: int) -> tuple[object, dict]:
    t0 = time.perf_counter()
    out = fn()
    first = time.perf_counter() - t0
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return out, {"first_ms": 1000 * first, "median_ms": 1000 * float(np.median(ts)), "min_ms": 1000 * min(ts)}


def open3d_rows(frames, h: float, points: np.ndarray, repeats: int) -> list[dict]:
    """Open3D's VoxelBlockGrid (its ScalableTSDFVolume gave empty meshes in 0.20.0 here) on the object readings of
    the same frames (the table's zeroed: it has no masks), our voxel and truncation, on CUDA when it has it."""
    try:
        import open3d as o3d
        import open3d.core as o3c
    except ImportError:
        return [{"step": "open3d VoxelBlockGrid", "note": "open3d not installed"}]
    import trimesh

    from ffcgs_jax.geometry import depth_io

    dev = o3c.Device("CUDA:0" if o3c.cuda.is_available() else "CPU:0")
    obj = depth_io.apply_mask(frames)
    K = o3c.Tensor(obj.K, o3c.float64)
    extr = [o3c.Tensor(np.linalg.inv(p), o3c.float64) for p in obj.poses]
    max_d = float(obj.depth.max()) + 1.0

    def fuse():
        vbg = o3d.t.geometry.VoxelBlockGrid(("tsdf", "weight"), (o3c.float32, o3c.float32), ((1), (1)), h, 8, 50000,
                                            dev)
        for d, e in zip(obj.depth, extr):
            img = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(d))).to(dev)
            blocks = vbg.compute_unique_block_coordinates(img, K, e, 1.0, max_d, TRUNC_VOXELS)
            vbg.integrate(blocks, img, K, e, 1.0, max_d, TRUNC_VOXELS)
        o3c.cuda.synchronize()
        return vbg

    vbg, t_fuse = _timed(fuse, repeats)
    # weight 1: a voxel seen by one frame counts, as in ours (Open3D's default 3 drops most of a 5-view object)
    m, t_mesh = _timed(lambda: vbg.extract_triangle_mesh(weight_threshold=1.0).to_legacy(), repeats)
    tm = trimesh.Trimesh(np.asarray(m.vertices), np.asarray(m.triangles), process=False)
    return [{"step": f"open3d {o3d.__version__} VoxelBlockGrid integrate ({dev}, incl. transfer)", **t_fuse},
            {"step": "open3d extract_triangle_mesh", **t_mesh,
             "surface_mesh": mesh_error(tm, points, h) if len(tm.faces) else None}]


def speed(args) -> dict:
    import jax
    import trimesh

    from ffcgs_jax.geometry import depth_io, depth_object, depth_render, mesh_io, tsdf

    if not args.no_jax_cache:
        from ffcgs_jax.runtime import jax_cache

        jax_cache.enable()
    mesh = mesh_io.load_mesh(args.object)
    frames = depth_render.render_views(mesh, SPEED_VIEWS, args.width, args.height, noise=True, seed=args.seed)
    clean, table_z = depth_io.remove_table(frames)  # before every timing but from_depth's, which fits its own
    points = trimesh.sample.sample_surface(mesh, args.points, seed=args.seed)[0]
    R, reps = SPEED_RES, args.repeats
    fused = {where: _timed(lambda where=where: jax.block_until_ready(
        tsdf.fuse(clean, R, TRUNC_VOXELS, table_z=table_z, on_device=where == "device")), reps)
        for where in ("device", "host")}
    grid = fused["device"][0]
    origin, h = np.asarray(grid.origin, np.float64), float(grid.voxel_size)  # fuse's own grid frame
    trunc = TRUNC_VOXELS * h
    fdt = jax.numpy.result_type(float)
    host = (clean.depth.astype(fdt), depth_io.object_mask(clean), clean.K.astype(fdt), clean.poses.astype(fdt))
    dev, t_put = _timed(lambda: jax.block_until_ready(jax.device_put(host)), reps)
    vol, t_int = _timed(lambda: jax.block_until_ready(
        tsdf.integrate(dev[0], dev[2], dev[3], origin, h, R, trunc, mask=dev[1])), reps)
    conv = lambda: jax.block_until_ready(  # noqa: E731
        tsdf.to_gradient_sdf(tsdf.resolve(vol, trunc, origin, h, table_z), origin, h, table_z))
    g2, t_conv = _timed(conv, reps)
    fo, t_fd = _timed(lambda: _ready(depth_object.from_depth(frames, res=R)), reps)
    rows = [{"step": f"host->device transfer ({SPEED_VIEWS} depth frames + masks)", **t_put},
            {"step": "tsdf.integrate", **t_int},
            {"step": "tsdf.resolve + tsdf.to_gradient_sdf", **t_conv, "surface": grid_error(g2, points)},
            *({"step": f"tsdf.fuse, conversion {label} (frames in host memory, table removed)", **fused[where][1],
               "surface": grid_error(fused[where][0], points)}
              for where, label in (("device", "compiled with the fusion (jump flooding)"),
                                   ("host", "on the host (KD-tree)"))),
            {"step": "depth_object.from_depth (checks, table fit on a sample, fuse)", **t_fd,
             "surface": grid_error(fo.grid, points), "surface_mesh": mesh_error(fo.mesh, points, h)}]
    ref = getattr(tsdf, "to_gradient_sdf_reference", None)
    if ref is not None:  # the host (KD-tree) conversion, where the module still has it
        values = tsdf.resolve(vol, trunc, origin, h, table_z)
        g3, t_ref = _timed(lambda: jax.block_until_ready(ref(values, origin, h, table_z)), reps)
        rows.insert(3, {"step": "tsdf.to_gradient_sdf_reference (host KD-tree)", **t_ref,
                        "surface": grid_error(g3, points)})
    rows += open3d_rows(clean, h, points, reps)
    conf = {"mode": "speed", "command": command_line(), "machine": Q.machine(), "object": args.object,
            "width": args.width, "height": args.height, "views": SPEED_VIEWS, "res": R, "noise": True,
            "repeats": reps, "points": args.points, "voxel_mm": 1000 * h}
    return {"config": conf, "records": rows}


def command_line() -> str:
    return Q.command_line().replace("bench/quality.py", "bench/depth.py", 1)


# ---------------------------------------------------------------------------------------------------- reporting


def summarise(report: dict) -> list[dict]:
    """One dict per condition, in the order run, of pooled counts, surface medians and times."""
    protocols = report["config"]["protocols"]
    med = lambda x: float(np.median(x)) if len(x) else math.nan  # noqa: E731
    out = []
    for label in dict.fromkeys(r["condition"] for r in report["records"]):
        recs = [r for r in report["records"] if r["condition"] == label]
        ok = [r for r in recs if not r["error"]]
        both = [Q.passed_every_protocol(r, protocols) for r in ok]
        tested = sum(len(r["tested"]) for r in ok)
        surf = [r["surface"] for r in ok if r["surface"]]
        out.append({
            "condition": label, "objects": len(recs), "failed": len(recs) - len(ok),
            "surface": {k: med([s[k] for s in surf]) for k in surf[0]} if surf else None,
            "worst_p95_vox": max(s["p95_vox"] for s in surf) if surf else math.nan,
            "valid": (sum(r["valid"] for r in ok), sum(r["n"] for r in ok)),
            "success": {p: (sum(int(np.sum(r["physics"].get(f"{p.replace('-', '_')}_success", [])))
                                for r in ok), tested) for p in protocols},
            "both": (int(sum(b.sum() for b in both)), tested), "tested": tested,
            "top1": (sum(bool(len(b) and b[0]) for b in both), len(recs))
            if report["config"]["physics"] == "on" else None,
            "fuse_s": med([r["fuse_s"] for r in ok if r["fuse_s"] is not None]),
            "wall_s": med([r["wall_s"] for r in ok]), "physics_s": med([r["physics_s"] for r in ok if r["tested"]]),
        })
    return out


def _pp(s: dict, base: dict | None) -> str:
    if base is None or not s["tested"] or not base["tested"] or s is base:
        return "-"
    return f"{100 * (s['both'][0] / s['tested'] - base['both'][0] / base['tested']):+.1f} pp"


def header_line(conf: dict) -> str:
    m = conf["machine"]
    where = f"{m['device']} x{m['device_count']} ({m['backend']}), {m['cpus']} CPUs · {m['date']}"
    if conf["mode"] == "speed":
        return (f"depth speed · {where} · {conf['object']}, {conf['views']} noisy views of {conf['width']} x "
                f"{conf['height']} into {conf['res']}^3 (voxel {conf['voxel_mm']:.2f} mm) · median of "
                f"{conf['repeats']} warm calls, first call apart · `{conf['command']}`")
    objs = ", ".join(f"{g} {c}" for g, c in conf["group_counts"].items())
    cap = conf["max_grasps_per_object"]
    phys = (f"physics {conf['physics_backend']} on the true mesh, friction {conf['friction']} "
            f"({', '.join(conf['protocols'])}; {f'at most {cap} returned grasp(s)' if cap else 'every returned grasp'}"
            f" per object)" if conf["physics"] == "on" else "no physics")
    return (f"depth · {where} · objects: {objs} · {conf['width']} x {conf['height']} frames, fused at "
            f"{conf['res']}^3 · {conf['sampler']} n {conf['n']} seed {conf['seed']} · fused-planned grasps filtered "
            f"on the {conf.get('filter_mesh', 'true')} surface · {phys} · `{conf['command']}`")


def table(report: dict) -> str:
    rows = summarise(report)
    base = next((s for s in rows if s["condition"] == "mesh"), None)
    lines = ["| condition | objects (fusion failed) | surface median / p95 voxels (mm) | worst p95 voxels "
             "| valid share | lift-shake | six-dir | both | vs mesh | top-1 both | fuse s | s/object (physics) |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for s in rows:
        sf = s["surface"]
        surf = "-" if sf is None else (f"{Q.format_fixed(sf['median_vox'], 2)} / {Q.format_fixed(sf['p95_vox'], 2)} "
                                       f"({Q.format_fixed(sf['median_mm'], 1)} / {Q.format_fixed(sf['p95_mm'], 1)})")
        vk, vn = s["valid"]
        lines.append(f"| {s['condition']} | {s['objects']} ({s['failed']}) | {surf} | "
                     f"{Q.format_fixed(s['worst_p95_vox'], 2)} | "
                     f"{100 * vk / max(vn, 1):.1f} % ({vk}/{vn}) | {Q.rate(s['success'].get('lift-shake'))} | "
                     f"{Q.rate(s['success'].get('six-dir'))} | {Q.rate(s['both'])} | {_pp(s, base)} | "
                     f"{Q.rate(s['top1'])} | {Q.format_fixed(s['fuse_s'], 3)} | {Q.format_fixed(s['wall_s'], 2)} "
                     f"({Q.format_fixed(s['physics_s'], 1)}) |")
    target = ""
    for noisy5 in (s for s in rows if s["condition"].startswith("5 views, noisy")):
        if base and noisy5["tested"] and base["tested"]:
            gap = 100 * (noisy5["both"][0] / noisy5["tested"] - base["both"][0] / base["tested"])
            where = noisy5["condition"].replace("5 views, noisy", "5 noisy views", 1)
            target += (f" Target, {where} within 5 pp of mesh-planned: {gap:+.1f} pp, "
                       f"{'met' if gap >= -5 else 'not met'}.")
    return "\n".join(lines) + (
        "\n\nsurface: distance of the true mesh's surface points to the fused zero level (|fused SDF|), per object "
        "median and p95 in voxels of the fused grid, median over objects (mm in brackets). Grasps planned on the "
        "fused SDF (mesh row: the mesh's own SDF), physics on the true mesh; shares pooled over grasps, 95 % Wilson; "
        "top-1: the best returned grasp passes both protocols (failed fusion or no valid grasp: fails). fuse s: "
        "median `from_depth` fusion time (the first object of a frame size compiles); s/object: median synthesize "
        f"wall time (physics time).{target}\n")


def per_object_table(report: dict) -> str:
    lines = ["| object | condition | surface median / p95 voxels | table z error mm | valid | tips not all touching "
             "(median tip distance mm) | both passed |", "|---|---|---|---|---|---|---|"]
    for r in report["records"]:
        s = r["surface"]
        surf = "-" if s is None else f"{s['median_vox']:.2f} / {s['p95_vox']:.2f}"
        tz = "-" if r["table_err_mm"] is None else f"{r['table_err_mm']:.2f}"
        if r["error"]:
            lines.append(f"| {r['object']} | {r['condition']} | {surf} | {tz} | failed: {r['error']} | - | - |")
            continue
        both = Q.passed_every_protocol(r, report["config"]["protocols"])
        f = r["filters"]
        lines.append(f"| {r['object']} | {r['condition']} | {surf} | {tz} | {r['valid']}/{r['n']} | "
                     f"{f['not all tips touching']} ({f['median |tip distance| mm']:.1f}) | "
                     f"{int(both.sum())}/{len(r['tested'])} |")
    return "\n".join(lines) + "\n"


def speed_table(report: dict) -> str:
    def surf(s):
        return "-" if not s else (f"{s['median_vox']:.2f} / {s['p95_vox']:.2f} "
                                  f"({s['median_mm']:.1f} / {s['p95_mm']:.1f})")

    lines = ["| step | median ms | min ms | first call ms | surface of the SDF: median / p95 voxels (mm) "
             "| surface of the mesh: median / p95 voxels (mm) |", "|---|---|---|---|---|---|"]
    for r in report["records"]:
        if "note" in r:
            lines.append(f"| {r['step']} | {r['note']} | | | | |")
            continue
        lines.append(f"| {r['step']} | {r['median_ms']:.2f} | {r['min_ms']:.2f} | {r['first_ms']:.0f} | "
                     f"{surf(r.get('surface'))} | {surf(r.get('surface_mesh'))} |")
    return "\n".join(lines) + (
        "\n\nTarget: 5 frames of 640 x 480 into 64^3 in <= 5 ms on an H100, <= 150 ms on the 2-core CPU (compile "
        "apart). Open3D gets the object's readings only (no masks in its volume) and its mesh has no underside, so "
        "its p95 includes the unseen bottom; ours closes it on the fitted table.\n")


def write_results(path: Path, name: str, block: str) -> None:
    """Replace the text between this block's markers in `path`, or append the block (as bench/quality.py)."""
    begin, end = f"<!-- {name}:begin -->", f"<!-- {name}:end -->"
    text = path.read_text() if path.exists() else ""
    body = f"{begin}\n{block.rstrip()}\n{end}"
    if begin in text and end in text and text.index(begin) < text.index(end):
        text = text[:text.index(begin)] + body + text[text.index(end) + len(end):]
    else:
        text = (text.rstrip("\n") + "\n\n" if text.strip() else "") + body + "\n"
    files.write_text(path, text)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        if args.report:
            report = json.loads(Path(args.report).read_text())
        else:
            t0 = time.perf_counter()
            with contextlib.redirect_stdout(sys.stderr):  # warp's start-up banner must not land in the table
                report = speed(args) if args.speed else run(args)
            report["config"]["total_s"] = time.perf_counter() - t0
            if args.json:
                files.write_text(args.json, json.dumps(report))
    except FfcgsError as e:
        print(f"{PROG}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted", file=sys.stderr)
        return 130
    conf = report["config"]
    head = header_line(conf)
    if conf["mode"] == "speed":
        main_table, extra = speed_table(report), ""
    else:
        main_table, extra = table(report), "\n" + per_object_table(report)
    print(head + "\n\n" + main_table + extra)
    if "total_s" in conf:
        print(f"{len(report['records'])} {'steps' if conf['mode'] == 'speed' else 'jobs'} in {conf['total_s']:.0f} s")
    if args.results:
        name = f"depth-speed-{conf['machine']['backend']}" if conf["mode"] == "speed" else "depth"  # one per kind
        write_results(Path(args.results), name,
                      head + "\n\n" + main_table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
