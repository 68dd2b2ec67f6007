"""The depth-input subcommands: `ffcgs render-depth` (synthetic frames of a mesh) and `ffcgs fuse` (frames to a
Gradient-SDF). `ffcgs grasp --depth` lives with `grasp` in `cli.commands`."""

import dataclasses
import time

import numpy as np
import tyro


BOUNDS_HELP = "workspace box XMIN YMIN ZMIN XMAX YMAX ZMAX (metres, world frame): readings outside are background"


@dataclasses.dataclass(frozen=True)
class RenderDepthCmd:
    """Render depth frames of an object on a table from cameras around it, as a depth folder `ffcgs fuse` and
    `ffcgs grasp --depth` read (README: "Depth input").

    Attributes:
        object: built-in name (see `ffcgs objects`) or a mesh file, metres, z up; it rests on a table at its lowest
            point.
        out: the folder to write (camera.json, poses.json, view_000.png, ...; created if missing).
        views: cameras, evenly spaced in azimuth around the object.
        width: image width in pixels (the focal length scales with it: 615 px at 640).
        height: image height in pixels.
        noise: RealSense-like noise (sigma = 0.0015 z^2 per metre, 2 % of readings lost); --no-noise for exact depth.
        masks: also write object masks (<stem>_mask.png); without them `fuse` separates the object by removing the
            table, as with a real camera.
        elevation: camera elevation above the horizontal, degrees.
        distance: camera distance to the object's centre, metres.
        seed: noise seed.
        scale: multiplies the object's coordinates (0.001 for millimetre meshes).
        png: also draw the depth images side by side to this PNG.
        overwrite: replace `out` whole even when it holds files that no `render-depth` run wrote, or another
            command wrote it, such as a folder of `ffcgs grasp` results (without it such a folder is refused; a
            folder an earlier render-depth run wrote is always replaced whole, so no stale frame or mask of that run
            stays behind). A link `out` stays a link: the folder it points to is replaced.
    """

    object: tyro.conf.Positional[str] = tyro.MISSING
    out: str = "frames"
    views: int = 5
    width: int = 640
    height: int = 480
    noise: bool = True
    masks: bool = False
    elevation: float = 35.0
    distance: float = 0.45
    seed: int = 0
    scale: float = 1.0
    png: str | None = None
    overwrite: bool = False

    def check(self) -> None:
        from ffcgs_jax.core.config import SEED_MAX, check_integer, check_range

        check_integer("--views", self.views, 1, 360)
        check_integer("--width", self.width, 8, 4096)
        check_integer("--height", self.height, 8, 4096)
        check_range("--elevation", self.elevation, 1.0, 89.0)
        check_range("--distance", self.distance, 0.05, 10.0)
        check_integer("--seed", self.seed, 0, SEED_MAX)


def run_render_depth(cmd: RenderDepthCmd) -> None:
    from ffcgs_jax.core import files
    from ffcgs_jax.geometry import depth_io, depth_render, mesh_io

    mesh = mesh_io.load_mesh(cmd.object, scale=cmd.scale)
    t0 = time.perf_counter()
    frames = depth_render.render_views(mesh, cmd.views, cmd.width, cmd.height, cmd.noise, cmd.seed,
                                       elevation_deg=cmd.elevation, distance=cmd.distance)
    seconds = time.perf_counter() - t0
    written = frames if cmd.masks else frames._replace(mask=None)
    with files.write_folder(cmd.out, "ffcgs render-depth") as tmp:  # swapped in whole: no stale frame survives
        depth_io.write_frames(written, tmp)
    files.announce(f"wrote {cmd.out}: {cmd.views} depth frames of {cmd.object}, {cmd.width}x{cmd.height}, "
          f"{'noisy' if cmd.noise else 'exact'}, {'with' if cmd.masks else 'without'} masks, table at z = "
          f"{float(mesh.bounds[0, 2]):.4f} m (rendered in {seconds:.1f} s)")
    if cmd.png:
        from ffcgs_jax.viz.depth_plot import frames_image
        from ffcgs_jax.viz.render import save_png

        save_png(frames_image(frames), cmd.png)
        files.announce(f"wrote {cmd.png}")


@dataclasses.dataclass(frozen=True)
class FuseCmd:
    """Fuse depth frames of one object into a Gradient-SDF (TSDF fusion; README: "Depth input").

    Attributes:
        frames: a depth folder (camera.json, poses.json, *.png or *.npy, optional *_mask.png) or an .npz with
            depth (N, H, W), K (3, 3), poses (N, 4, 4).
        res: voxels along each axis of the grid (16-128).
        out: output .npz, the format of `ffcgs sdf` (grid, origin, voxel_size, table_z).
        png: also draw mid-slices of the fused distance field to this PNG.
        mesh: also write the fused zero level as a mesh (.ply, .obj, .stl).
        table_z: the table height in metres; default: fitted to the readings (RANSAC on horizontal planes).
        bounds: workspace box XMIN YMIN ZMIN XMAX YMAX ZMAX (metres, world frame): readings outside it are
            background and the grid is the cube around it.
        trunc: truncation distance in voxels.
    """

    frames: tyro.conf.Positional[str] = tyro.MISSING
    res: int = 64
    out: str = "sdf.npz"
    png: str | None = None
    mesh: str | None = None
    table_z: float | None = None
    bounds: tuple[float, float, float, float, float, float] | None = None
    trunc: float = 4.0

    def check(self) -> None:
        from ffcgs_jax.core.config import check_integer, check_range

        check_integer("--res", self.res, 16, 128)
        check_range("--trunc", self.trunc, 1.0, 16.0)


def bounds_box(bounds) -> np.ndarray | None:
    return None if bounds is None else np.asarray(bounds, np.float64).reshape(2, 3)


def fuse_rows(fo, source: str) -> list[tuple[str, str]]:
    """The lines `fuse` and `grasp --depth` print about a fused object."""
    g = fo.grid
    r = g.grid.shape[0]
    return [("depth frames", f"{len(fo.frames.names)} from {source} ({fo.frames.depth.shape[2]}x"
                             f"{fo.frames.depth.shape[1]})"),
            ("table height (m)", f"{fo.table_z:.4f} ({'fitted' if fo.table_fitted else 'given'})"),
            ("object", _object_row(fo)),
            ("fused grid", f"{r}^3, voxel {float(g.voxel_size) * 1000:.2f} mm, fused in {fo.fuse_s * 1000:.0f} ms"),
            ("fused surface", f"{len(fo.mesh.faces)} triangles, extents (cm) "
                              + " x ".join(f"{e * 100:.1f}" for e in fo.mesh.extents))]


def _object_row(fo) -> str:
    if fo.masks_given:
        return "the given masks (no isolation)"
    if fo.isolation is None:
        return "every reading above the table (not isolated)"
    return "isolated: " + fo.isolation.summary()


def true_mesh_rows(gs) -> list[tuple[str, str]]:
    """The lines `grasp --depth --object` adds: the returned grasps measured on the true mesh."""
    v, n = gs["valid"], int(gs["valid"].sum())
    tips = gs["contacts"].shape[1]
    return [("on the true mesh: force closure (valid)", f"{int(gs['force_closure_true'][v].sum())} / {n}"),
            ("on the true mesh: all tips touching (valid)", f"{int((gs['n_contacts_true'][v] == tips).sum())} / {n}"
                                                            f"  (within {1000 * gs.config.contact_tol:g} mm)"),
            ("on the true mesh: median |tip distance| (mm)",
             f"{np.median(np.abs(gs['contact_dist_true'][v])) * 1000:.2f}" if n else "-")]


def run_fuse(cmd: FuseCmd) -> None:
    from ffcgs_jax.core import files
    from ffcgs_jax.geometry import depth_object, sdf

    fo = depth_object.from_depth(cmd.frames, cmd.res, cmd.table_z, bounds_box(cmd.bounds), cmd.trunc)
    sdf.save(fo.grid, cmd.out)
    for k, v in fuse_rows(fo, cmd.frames):
        print(f"{k:<18} {v}")
    files.announce(f"wrote {cmd.out}")
    if cmd.png:
        from ffcgs_jax.viz.render import save_png
        from ffcgs_jax.viz.sdf_plot import slices_image

        save_png(slices_image(fo.grid), cmd.png)
        files.announce(f"wrote {cmd.png}")
    if cmd.mesh:
        files.atomic_write(cmd.mesh, lambda f: fo.mesh.export(f, file_type=cmd.mesh.rsplit(".", 1)[1].lower()))
        files.announce(f"wrote {cmd.mesh}")
