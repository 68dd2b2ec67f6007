"""The `ffcgs` subcommands: one frozen dataclass of options and one run function per job (`COMMANDS`).

Parsing and the entry point are `cli.main`'s.
"""

import dataclasses
import json
import math
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Annotated

import numpy as np
import tyro

from ffcgs_jax.core import files
from ffcgs_jax.cli.dataset_commands import (DatasetExportCmd, DatasetInfoCmd, DatasetMergeCmd, run_dataset_build,
                                             run_dataset_export, run_dataset_info, run_dataset_merge)
from ffcgs_jax.cli.depth_commands import FuseCmd, RenderDepthCmd, run_fuse, run_render_depth
from ffcgs_jax.cli.grasp_object import not_the_recorded_object, recorded_object
from ffcgs_jax.cli.hand_command import HandCmd, run_hand
from ffcgs_jax.cli.learn_command import run_learn
from ffcgs_jax.cli.show_command import ShowCmd, run_show
from ffcgs_jax.dataset.config import DatasetConfig
from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.geometry.config import SDFConfig
from ffcgs_jax.learn.config import LearnConfig
from ffcgs_jax.cli.output_plan import Input, Output, Plan
from ffcgs_jax.physics.config import ALL_PROTOCOLS, PROTOCOLS, PhysicsConfig
from ffcgs_jax.synthesis.config import GraspConfig


@dataclasses.dataclass(frozen=True)
class ObjectsCmd:
    """List the built-in objects (usable by name wherever an object is asked for)."""


@dataclasses.dataclass(frozen=True)
class SdfCmd:
    """Write the Gradient-SDF of an object (built-in name or mesh file) to an .npz file.

    Attributes:
        object: built-in name (see `ffcgs objects`) or a mesh file (obj, stl, ply, off, glb).
        out: output .npz (grid (R,R,R,4): distance and gradient; origin; voxel_size; table_z).
        png: also draw mid-slices of the distance field to this PNG.
        sdf: grid settings.
    """

    object: tyro.conf.Positional[str] = tyro.MISSING
    out: str = "sdf.npz"
    png: str | None = None
    sdf: SDFConfig = SDFConfig()


@dataclasses.dataclass(frozen=True)
class BenchCmd:
    """Time grasp synthesis on this machine (latency, throughput, compile, CLI start) and print the report.

    Attributes:
        object: built-in name or mesh file; its Gradient-SDF is built first and not timed.
        res: the Gradient-SDF's resolution (the paper's 32).
        iters: descent steps per grasp (the issue's figures: 50).
        batches: poses per batch, one row each; default 32 1024 8192 65536 on a GPU, 32 256 1024 on a CPU.
        lp_solvers: LP paths to time ("jax", "proxsuite").
        max_proxsuite_batch: skip larger batches for the host LP (it is host-bound: about 0.4 ms per LP).
        devices: device counts to time the "jax" rows with (scaling); default 1, and all local devices when
            there are several.
        repeats: warm calls per row; the median is reported.
        sampler: wrist-pose sampler (auto, cvae, geometric, random; auto: cvae where weights ship for the hand).
        hand: built-in hand name (svh, allegro) or a hand-spec TOML; a hand other than the SVH gets its own
            RESULTS.md block.
        backend: "default" (JAX's choice: the GPU when there is one), "cpu" or "gpu".
        cli_start: also time a cold and a warm `ffcgs grasp` in fresh processes.
        whole_object: the mesh whose whole `synthesize` call is timed, from the mesh to ranked grasps, each time as
            if seen for the first time (grid and triangle caches cleared) and with its grid cached; "" = `object`.
        results: also put this machine's block into this Markdown file, e.g. bench/RESULTS.md (replaced when
            run there again); default: print only, so that a bench run never rewrites a tracked file unasked.
        json: also write the report as JSON here.
    """

    object: str = "mug"
    res: int = 32
    iters: int = 50
    batches: tuple[int, ...] = ()
    lp_solvers: tuple[str, ...] = ("jax", "proxsuite")
    max_proxsuite_batch: int = 256
    devices: tuple[int, ...] = ()
    repeats: int = 5
    sampler: str = "auto"
    hand: str = "svh"
    backend: str = "default"
    cli_start: bool = True
    whole_object: str = ""
    results: str | None = None
    json: str | None = None

    def check(self) -> None:
        from ffcgs_jax.core.config import check_choice
        from ffcgs_jax.synthesis.config import LP_SOLVERS, SAMPLERS

        if self.backend not in ("default", "cpu", "gpu"):
            raise FfcgsError(f"--backend must be default, cpu or gpu, got {self.backend!r}")
        check_choice("sampler", self.sampler, ("auto", *SAMPLERS))
        for s in self.lp_solvers:
            if s not in LP_SOLVERS:
                raise FfcgsError(f"unknown LP solver {s!r}; solvers: {', '.join(LP_SOLVERS)}")
        if not self.lp_solvers:
            raise FfcgsError("--lp-solvers needs at least one solver")
        for name, values, hi in (("batches", self.batches, 1_000_000), ("devices", self.devices, 4096)):
            if any(isinstance(v, bool) or not 1 <= v <= hi for v in values):
                raise FfcgsError(f"--{name} must be integers in [1, {hi}], got {' '.join(map(str, values))}")
        SDFConfig(res=self.res).check()
        if not 1 <= self.iters <= 100_000 or not 1 <= self.repeats <= 1000:
            raise FfcgsError(f"--iters and --repeats must be >= 1, got {self.iters} and {self.repeats}")


def run_bench(cmd: BenchCmd) -> None:
    import jax

    from ffcgs_jax.cli import benchmark

    if cmd.backend == "cpu":  # before JAX starts a backend
        jax.config.update("jax_platforms", "cpu")
    elif cmd.backend == "gpu" and jax.default_backend() != "gpu":
        raise FfcgsError(f"--backend gpu: JAX found no GPU (its backend is {jax.default_backend()})")
    report = benchmark.run(cmd)
    print()
    print(benchmark.markdown(report))
    if cmd.results:
        benchmark.write_results(cmd.results, report)
        files.announce(f"wrote {cmd.results} (block '{benchmark.machine_key(report['machine'], cmd.hand)}')")
    if cmd.json:
        benchmark.save_json(report, cmd.json)
        files.announce(f"wrote {cmd.json}")


def run_objects(cmd: ObjectsCmd) -> None:
    from ffcgs_jax.geometry import objects

    print(f"{'name':<10} {'faces':>6} {'extents (cm)':>20} {'volume (cm3)':>13} {'watertight':>10}")
    for o in objects.describe():
        ext = " x ".join(f"{e * 100:.1f}" for e in o["extents"])
        print(f"{o['name']:<10} {o['faces']:>6} {ext:>20} {o['volume'] * 1e6:>13.1f} {str(o['watertight']):>10}")


def run_sdf(cmd: SdfCmd) -> None:
    from ffcgs_jax.geometry import mesh_io, sdf

    mesh = mesh_io.load_mesh(cmd.object, scale=cmd.sdf.scale)
    t0 = time.perf_counter()
    grid = sdf.build_sdf(mesh, cmd.sdf)
    dt = time.perf_counter() - t0
    sdf.save(grid, cmd.out)
    r = cmd.sdf.res
    files.announce(f"wrote {cmd.out}: {r}^3 Gradient-SDF of {cmd.object}, voxel {float(grid.voxel_size) * 1e3:.2f} mm, "
          f"built in {dt:.2f} s")
    if cmd.png:
        from ffcgs_jax.viz.render import save_png
        from ffcgs_jax.viz.sdf_plot import slices_image

        save_png(slices_image(grid), cmd.png)
        files.announce(f"wrote {cmd.png}")


@dataclasses.dataclass(frozen=True)
class GraspCmd:
    """Synthesise force-closure grasps of an object: sample wrist poses, optimise the fingers, filter, evaluate.

    Several objects or a folder of meshes (`ffcgs grasp meshes/ mug`) run one after another, the next one loading
    while the current one is on the device (`ffcgs_jax.synthesize_many`), and each lands as `<name>.npz` in the
    `--out` folder as soon as it is done. Run the same command again after an interruption: objects already written
    with the same settings are skipped. A mesh that fails is one line at the end, the others are still done, and
    the exit status is then 1. With several objects `--validate` checks each; `--png`, `--mcap`, `--show`,
    `--poses` and `--depth` are about one object and are refused.

    Attributes:
        object: built-in name (see `ffcgs objects`) or a mesh file (obj, stl, ply, off, glb), metres, z up; or
            several, or folders of mesh files (their obj, stl, ply, off, glb and gltf files, not subfolders; two
            files of one name are refused). With `--depth`, one, optional (also as `--object`): the true object, in
            the cameras' world frame: the grasps, filtered on the fused surface, are also measured on it (the fields
            `*_true`) and `--validate` simulates it.
        depth: plan on an object seen by depth cameras instead of a mesh: a depth folder or .npz (README: "Depth
            input"), fused into the grid of `--res` voxels; the object frame is the cameras' world frame.
        table_z: with `--depth`: the table height in metres; default: fitted to the readings.
        bounds: with `--depth`: workspace box XMIN YMIN ZMIN XMAX YMAX ZMAX (metres): readings outside are ignored.
        out: grasp arrays (.npz; fields in README); default grasps.npz. With several objects or a folder: the
            folder of `<object>.npz` files, default grasps/ (the one-object name without its suffix, so a folder run
            and a one-object run beside it do not collide); it may hold only files of earlier such runs.
        mcap: also write an MCAP log of the run (config, per-iteration energies, grasps).
        png: also draw the best grasps to this PNG.
        show: then open the grasps in the interactive 3D view in the browser until Ctrl-C (`ffcgs show`).
        poses: optimise these wrist poses instead of sampling: .npy of shape (B, 4, 4), or .npz with
            `wrist_pose` (e.g. a previous grasps.npz), object frame.
        hand: built-in hand name or a hand-spec TOML.
        validate: physics-check the valid grasps right after synthesis and rank those that pass every protocol
            of `--protocol` first (`ffcgs_jax.validate`); every grasp is kept, with its results and what checked it
            (physics_protocols, physics_backend, physics_config_json) in the grasp file.
        protocol: the protocols `--validate` asks for: lift-shake, six-dir, both (the two), dexgraspbench or
            dexgraspbench-bodex.
        need: with `--validate`: 0 simulates every valid grasp with every protocol; k > 0 stops once k grasps
            pass (candidates in the analytic order, a chunk at a time, six-dir first), for the best grasp sooner.
        grasp: synthesis settings (flags without prefix: --n, --sampler, --iters, --res, --d0, ...).
        physics: physics settings for `--validate` (flags without prefix: --backend, --sim-friction, ...).
    """

    object: tyro.conf.Positional[Annotated[tuple[str, ...], tyro.conf.arg(metavar="[OBJECT ...]")]] = ()
    depth: str | None = None
    table_z: float | None = None
    bounds: tuple[float, float, float, float, float, float] | None = None
    out: str | None = None
    mcap: str | None = None
    png: str | None = None
    show: bool = False
    poses: str | None = None
    hand: str = "svh"
    validate: bool = False
    protocol: str = "both"
    need: int = 0
    grasp: GraspConfig = GraspConfig()
    physics: PhysicsConfig = PhysicsConfig()

    def check(self) -> None:
        from ffcgs_jax.core.config import check_integer

        _protocols(self.protocol)
        check_integer("--need", self.need, 0, 1_000_000)

    @property
    def many(self) -> bool:
        """Several objects, or a folder: one grasp file each in the `--out` folder (`cli.grasp_many`)."""
        from ffcgs_jax.geometry import objects  # not at import: trimesh would slow `ffcgs --help`

        return len(self.object) > 1 or any(o not in objects.names() and Path(o).is_dir() for o in self.object)

    @property
    def one_object(self) -> str | None:
        """The object of a one-object run, or None (from depth frames alone)."""
        return self.object[0] if self.object else None

    @property
    def out_path(self) -> str:
        return self.out if self.out is not None else "grasps/" if self.many else "grasps.npz"

    def check_inputs(self) -> None:
        """What the command line must combine (a config file may hold any part of it, so not in `check`)."""
        if self.many:
            for flag, given in (("--depth", self.depth), ("--poses", self.poses), ("--png", self.png),
                                ("--mcap", self.mcap), ("--show", self.show or None)):
                if given is not None:
                    raise FfcgsError(f"{flag} is about one object; with several objects or a folder, grasp one "
                                     "object at a time for it")
            if Path(self.out_path).suffix.lower() == ".npz":
                raise FfcgsError(f"--out {self.out}: with several objects or a folder, --out names a folder (one "
                                 ".npz per object), e.g. grasps/")
        if not self.object and self.depth is None:
            raise FfcgsError("ffcgs grasp needs an object (a built-in name or a mesh file) or --depth FRAMES")
        if self.depth is None and (self.table_z is not None or self.bounds is not None):
            raise FfcgsError("--table-z and --bounds belong to --depth (a mesh's table is at its lowest point)")
        if self.depth is not None and self.validate and not self.object:
            raise FfcgsError("--validate with --depth needs --object: the physics test simulates the true mesh")
        # against the defaults: a value given without --validate would be ignored without a word
        physics_only = [flag for flag, given in (("--need", self.need != GraspCmd.need),
                                                 ("--protocol", self.protocol != GraspCmd.protocol)) if given]
        if physics_only and not self.validate:
            raise FfcgsError(f"{' and '.join(physics_only)} take{'s' * (len(physics_only) == 1)} effect only with "
                             "--validate: add --validate to physics-check the grasps, or leave "
                             f"{'it' if len(physics_only) == 1 else 'them'} out")
        if self.show:
            _needs("viser", "--show needs viser for the 3D view: pip install -e \".[viz]\" (or pip install viser)")


def _needs(module: str, line: str) -> None:
    """Refuse with `line` now, before any work, when an optional module the options need is not installed."""
    import importlib.util

    if importlib.util.find_spec(module) is None:
        raise FfcgsError(line)


def _protocols(name: str) -> tuple[str, ...]:
    if name == "both":
        return PROTOCOLS
    if name not in ALL_PROTOCOLS:
        raise FfcgsError(f"unknown protocol {name!r}; protocols: {', '.join(ALL_PROTOCOLS)}, both")
    return (name,)


def _print_rows(rows: list[tuple[str, str]]) -> None:
    width = max(len(k) for k, _ in rows)
    for k, v in rows:
        print(f"{k:<{width}}  {v}")


def run_grasp(cmd: GraspCmd) -> int:
    """The command; its exit status: 0, or with several objects 1 when any failed (`cli.grasp_many`)."""
    from ffcgs_jax.geometry import mesh_io
    from ffcgs_jax.hand import kinematics as K
    from ffcgs_jax.synthesis import grasp_io
    from ffcgs_jax.viz import grasp_log
    from ffcgs_jax.synthesis.grasp import check_on_mesh, summary_rows, synthesize

    cmd.check_inputs()
    if cmd.many:
        from ffcgs_jax.cli import grasp_many

        return grasp_many.run(cmd, lambda gs, hand, mesh: _validate(gs, hand, mesh, cmd))
    obj, out = cmd.one_object, cmd.out_path
    hand = K.load_hand(cmd.hand)
    mesh = None if obj is None else mesh_io.load_mesh(obj, scale=cmd.grasp.sdf.scale)
    poses = None if cmd.poses is None else grasp_io.load_poses(cmd.poses)
    grid, rows = None, []
    if cmd.depth is not None:
        from ffcgs_jax.cli.depth_commands import bounds_box, fuse_rows, true_mesh_rows
        from ffcgs_jax.geometry import depth_object

        t0 = time.perf_counter()
        fused = depth_object.from_depth(cmd.depth, cmd.grasp.sdf.res, cmd.table_z, bounds_box(cmd.bounds),
                                        margin=cmd.grasp.sdf.margin, min_margin=cmd.grasp.sdf.min_margin)
        depth_s = time.perf_counter() - t0  # frames on disk to the Gradient-SDF: this object's "SDF build"
        grid = fused.grid
        rows = fuse_rows(fused, cmd.depth) + [("evaluation surface", "the fused SDF (filters, epsilon, "
                                               "contacts); --object adds the true mesh's figures")]
    name = Path(obj if obj is not None else cmd.depth).stem
    # From depth, the filters and epsilon read the fused surface, as a robot without the mesh would: which grasps
    # are returned must not depend on whether a mesh was also given. The true mesh adds the *_true figures.
    gs = synthesize(hand, mesh if cmd.depth is None else fused.grid, cmd.grasp, name, grid=grid, poses=poses)
    # where the object came from (`object_source`, `_scale`, `_sha256`) is recorded by `synthesize`, and from depth
    # frames by `check_on_mesh` below: load_mesh hashed the mesh once
    if cmd.depth is not None:
        gs = gs.with_arrays(sdf_s=np.asarray(depth_s, np.float64), total_s=np.asarray(gs["total_s"] + depth_s))
    rows += summary_rows(gs)
    if cmd.depth is not None:
        gs = gs.with_arrays(depth_source=np.array(str(Path(cmd.depth).expanduser().resolve())),
                            evaluation_surface=np.array("fused"), table_z=np.asarray(fused.table_z, np.float64),
                            fuse_s=np.asarray(fused.fuse_s, np.float64))
        if mesh is not None:
            gs = gs.with_arrays(**check_on_mesh(hand, mesh, gs, grid))
            rows += true_mesh_rows(gs)
    if cmd.validate:
        gs, physics_rows = _validate(gs, hand, mesh, cmd)
        rows += physics_rows
    grasp_io.save_npz(gs, out)
    _print_rows(rows)
    files.announce(f"wrote {out}")
    if cmd.mcap:
        grasp_log.write_mcap(gs, cmd.mcap, hand, rows, mesh=mesh if mesh is not None else fused.mesh)
        files.announce(f"wrote {cmd.mcap}")
    if cmd.png:
        from ffcgs_jax.viz import grasp_plot, render

        image, _ = grasp_plot.grasps_image(hand, mesh if mesh is not None else fused.mesh, gs)
        render.save_png(image, cmd.png)
        files.announce(f"wrote {cmd.png}")
    if cmd.show:
        from ffcgs_jax.cli.show_command import serve
        from ffcgs_jax.viz import viewer

        files.commit_outputs()  # the view is served until Ctrl-C, which ends the process at once

        serve(viewer.show_grasps(hand, mesh if mesh is not None else fused.mesh, gs), 0.0)
    return 0


def _validate(gs, hand, mesh, cmd: GraspCmd):
    """The grasps physics-checked and ranked, those that pass every protocol asked for first
    (`physics.validate`)."""
    from ffcgs_jax.physics import validate as physics_validate

    protocols = _protocols(cmd.protocol)
    gs = gs.with_arrays(_physics_check(hand.spec, mesh, gs.arrays, gs["valid"], cmd.physics, protocols, cmd.need))
    return gs, physics_validate.summary_rows(gs, protocols)


def _physics_check(spec, mesh, arrays: dict, tested: np.ndarray, cfg: PhysicsConfig, protocols,
                   need: int = 0) -> dict:
    """`physics.validate.check` with a progress bar, `cfg.backend` resolved here so that a fallback from "auto" is
    said on stderr."""
    from tqdm import tqdm

    from ffcgs_jax.physics import validate as physics_validate

    n = int(np.sum(tested))
    cfg = dataclasses.replace(cfg, backend=physics_backend(cfg, n, protocols))
    total = n * len(protocols) * cfg.robust.trials  # the runner ticks once per grasp, protocol and trial
    with tqdm(total=total, desc="physics", unit="trial", disable=None, leave=False) as bar:
        return physics_validate.check(spec, mesh, arrays, tested, protocols, cfg, progress=bar.update, need=need)


def physics_backend(cfg: PhysicsConfig, n: int, protocols) -> str:
    """`cfg.backend` resolved for `n` grasps under `protocols` on this machine; when "auto" falls back to the CPU,
    one line on stderr says why."""
    from ffcgs_jax.physics import runner as physics

    backend, note = physics.resolve_backend(cfg.backend, n, protocols, cfg)
    if note:
        print(f"ffcgs: {note}", file=sys.stderr)
    return backend


@dataclasses.dataclass(frozen=True)
class EvalCmd:
    """Physics test of grasps in MuJoCo (lift-shake, six-dir): success rates with 95 % Wilson intervals.

    Attributes:
        grasps: a grasps.npz from `ffcgs grasp` (wrist_pose, q). Per-grasp results are added to it (or `--out`).
        object: the object to simulate: built-in name or mesh file; default the one the grasp file records (its
            source, scale and content hash). Another object is refused unless `--other-object`.
        other_object: simulate `--object` even though it is not the object the grasps were made for; the output
            then records what was simulated (physics_object_source, _scale, _sha256).
        protocol: lift-shake, six-dir or both (the two), or DexGraspBench's test: dexgraspbench (100 g, kp 5) or
            dexgraspbench-bodex (BODex's 30 g, kp 1), which fix their own contacts, mass, gains and bounds
            (`ffcgs_jax/physics/dexgraspbench.py`; CPU MuJoCo only).
        out: write the npz with results here instead of updating `grasps`.
        video: also record one trial of the first protocol to this .gif or .mp4.
        video_index: which grasp the video shows; default the first valid grasp that passed (else the first).
        all: test every grasp, not only those marked valid by the synthesis.
        hand: built-in hand name or a hand-spec TOML.
        scale: multiplies the object's coordinates (0.001 for millimetre meshes); default the scale the grasp file
            records (1 for files without one).
        physics: simulator and success-rule settings (flags without prefix: --backend, --sim-friction, --mass, ...).
    """

    grasps: tyro.conf.Positional[str] = tyro.MISSING
    object: str | None = None
    other_object: bool = False
    protocol: str = "both"
    out: str | None = None
    video: str | None = None
    video_index: int | None = None
    all: bool = False
    hand: str = "svh"
    scale: float | None = None
    physics: PhysicsConfig = PhysicsConfig()

    def check(self) -> None:
        _protocols(self.protocol)
        if self.scale is not None and not (math.isfinite(self.scale) and self.scale > 0):
            raise FfcgsError(f"--scale must be a finite number > 0, got {self.scale}")
        if self.video_index is not None and self.video is None:
            raise FfcgsError("--video-index chooses the grasp of --video; give --video FILE.gif too")
        if self.video is not None and self.video.lower().endswith(".mp4"):
            _needs("imageio_ffmpeg", "--video .mp4 needs imageio-ffmpeg: pip install imageio-ffmpeg (or write a .gif)")


def run_eval(cmd: EvalCmd) -> None:
    from ffcgs_jax.geometry import mesh_io, objects
    from ffcgs_jax.hand import spec as hand_spec
    from ffcgs_jax.physics import protocols as physics_protocols  # scipy.stats: 0.7 s of every command's start
    from ffcgs_jax.physics import runner as physics
    from ffcgs_jax.synthesis import grasp_io

    # read under the file's lock when it is updated in place (`Plan.outputs_together` locks an updated input until
    # the results land): a second eval of the file waits here and adds to the first's results, not over them
    data = grasp_io.load_npz(cmd.grasps)
    missing = [k for k in ("wrist_pose", "q") if k not in data]
    if missing:
        raise FfcgsError(f"{cmd.grasps} has no {' or '.join(missing)} array: is it a grasps.npz from ffcgs grasp?")
    out = cmd.out or cmd.grasps
    if cmd.video_index is not None and not 0 <= cmd.video_index < len(data["q"]):  # before the physics run
        raise FfcgsError(f"--video-index must be in [0, {len(data['q']) - 1}] ({cmd.grasps} holds "
                         f"{len(data['q'])} grasps), got {cmd.video_index}")
    name, scale = recorded_object(cmd, data, objects.names())
    spec = hand_spec.load_spec(cmd.hand)
    grasp_io.check_hand(data, cmd.grasps, spec)
    mesh = mesh_io.load_mesh(name, scale=scale)
    simulated = mesh_io.identity(name, scale, mesh)
    recorded = str(data.get("object_sha256", ""))
    if recorded and recorded != str(simulated["object_sha256"]) and not cmd.other_object:
        raise FfcgsError(not_the_recorded_object(name, scale, simulated, data))
    protocols = _protocols(cmd.protocol)
    valid = np.asarray(data["valid"], bool) if "valid" in data else np.ones(len(data["q"]), bool)
    idx = np.arange(len(valid)) if cmd.all else np.flatnonzero(valid)
    if len(idx) == 0:
        raise FfcgsError(f"{cmd.grasps} has no grasps" if cmd.all else
                         f"{cmd.grasps} has no valid grasps to test (use --all to test them anyway)")
    # files from before squeeze_dir was recorded: the physics test derives it from the fingertips near the mesh
    squeeze = data.get("squeeze_dir")
    data = _physics_check(spec, mesh, data, np.isin(np.arange(len(valid)), idx), cmd.physics, protocols)
    seconds, backend = float(data["physics_s"]), str(data["physics_backend"])
    n = len(valid)
    res = {k: data[k][idx] for k in data if k.endswith(("_success", "_reason", "_trials")) and np.ndim(data[k])}
    data.update({f"physics_{k}": v for k, v in simulated.items()})
    grasp_io.save_arrays(data, out)
    rows = physics_protocols.summary_rows(res, protocols)
    rows.append(("grasps tested", f"{len(idx)} ({'all' if cmd.all else 'valid'}) in {seconds:.1f} s, "
                 f"{len(idx) * len(protocols) * cmd.physics.robust.trials / seconds:.2f} trials/s, backend {backend}"))
    _print_rows(rows)
    files.announce(f"wrote {out}")
    if cmd.video:
        from ffcgs_jax.viz import physics_video

        first = res[physics_protocols.result_key(protocols[0], "success")]
        pick = cmd.video_index
        if pick is None:
            pick = int(idx[np.argmax(first)]) if first.any() else int(idx[0])
        scene = physics.scenes(spec, mesh, cmd.physics, protocols[:1])[protocols[0]]
        batch, _, _ = physics.prepare(scene, mesh, data["wrist_pose"][pick:pick + 1], data["q"][pick:pick + 1],
                                      cmd.physics, None if squeeze is None else squeeze[pick:pick + 1])
        frames = physics_video.record(scene, batch, 0, cmd.physics, protocols[0], cmd.video,
                                      title=f"{protocols[0]}  grasp {pick}")
        files.announce(f"wrote {cmd.video} (grasp {pick}, {protocols[0]}, {frames} frames)")


def _weights(g: GraspConfig) -> Input:
    return Input("--sampling.weights", g.sampling.weights or None)


# What each command reads and writes (`output_plan`), checked before it runs.
PLANS: dict[str, Callable[..., Plan]] = {
    "grasp": lambda c: Plan((*(Input("object", o, folder=Path(o).is_dir()) for o in c.object),
                             Input("--depth", c.depth, folder=True), Input("--poses", c.poses), Input("--hand", c.hand),
                             _weights(c.grasp)),
                            (Output("--out", c.out_path, "files" if c.many else "npz"),
                             Output("--mcap", c.mcap, "mcap"), Output("--png", c.png, "png"))),
    "eval": lambda c: Plan((Input("grasps", c.grasps, updated=True), Input("--object", c.object),
                            Input("--hand", c.hand)),
                           (Output("--out", c.out or c.grasps, "npz"), Output("--video", c.video, "video"))),
    "bench": lambda c: Plan((Input("--object", c.object), Input("--whole-object", c.whole_object or None),
                             Input("--hand", c.hand)),
                            (Output("--results", c.results or None, "markdown"), Output("--json", c.json, "json"))),
    "objects": lambda c: Plan(),
    "sdf": lambda c: Plan((Input("object", c.object),), (Output("--out", c.out, "npz"), Output("--png", c.png, "png"))),
    "hand": lambda c: Plan((Input("--object", c.object), Input("--hand", c.hand)), (Output("--png", c.png, "png"),)),
    "render-depth": lambda c: Plan((Input("object", c.object),),
                                   (Output("--out", c.out, "folder"), Output("--png", c.png, "png")), c.overwrite),
    "fuse": lambda c: Plan((Input("frames", c.frames, folder=True),),
                           (Output("--out", c.out, "npz"), Output("--png", c.png, "png"),
                            Output("--mesh", c.mesh, "mesh"))),
    "show": lambda c: Plan((Input("grasps", c.grasps), Input("--object", c.object), Input("--hand", c.hand))),
    "dataset build": lambda c: Plan((Input("--objects", c.objects or None, folder=True), Input("--hand", c.hand)),
                                    (Output("--out", c.out, "mcap"),)),
    "dataset info": lambda c: Plan((Input("dataset", c.dataset), Input("--objects", c.objects, folder=True)),
                                   (Output("--json", c.json, "json"), Output("--png", c.png, "folder")), c.overwrite),
    "dataset export": lambda c: Plan((Input("dataset", c.dataset),),
                                     (Output("--out", c.out, "npz" if c.out.lower().endswith(".npz") else "folder"),),
                                     c.overwrite),
    "dataset merge": lambda c: Plan((), (Output("out", c.out, "mcap"),)),
    "learn": lambda c: Plan((Input("hand", c.hand), Input("--objects", c.objects or None, folder=True))),
}

COMMANDS: dict[str, tuple[type, Callable]] = {
    "grasp": (GraspCmd, run_grasp),
    "eval": (EvalCmd, run_eval),
    "bench": (BenchCmd, run_bench),
    "objects": (ObjectsCmd, run_objects),
    "sdf": (SdfCmd, run_sdf),
    "hand": (HandCmd, run_hand),
    "render-depth": (RenderDepthCmd, run_render_depth),
    "fuse": (FuseCmd, run_fuse),
    "show": (ShowCmd, run_show),
    "dataset build": (DatasetConfig, run_dataset_build),
    "dataset info": (DatasetInfoCmd, run_dataset_info),
    "dataset export": (DatasetExportCmd, run_dataset_export),
    "dataset merge": (DatasetMergeCmd, run_dataset_merge),
    "learn": (LearnConfig, run_learn),
}
