"""Interactive 3D view of a grasp file in the browser (viser, the `viz` extra): `ffcgs show grasps.npz`.

The scene: the object mesh and the table; the hand at the selected grasp (its collision geoms, posed by the package's
own forward kinematics, so the view shows what the optimiser and the filters saw); the fingertip contacts (green where
a fingertip touches, within `contact_tol`, red where it does not) with the mesh's outward normals and friction cones;
a slider that steps through the grasps in ranked order (`evaluation.ranking`, as `GraspSet.order`); the hand's
colour says the physics outcome when the file has one (green: every protocol run held, orange: some, red: none,
grey: not tested; blue without physics). On demand: the SDF's zero level, a horizontal slice of the SDF, and the
wrist poses the sampler drew before the optimisation (the same sampler, seed and grid as the file's config, which
reproduces them exactly). In Jupyter the returned `GraspView` shows the page inline.
"""

import dataclasses
import json

import jax
import mujoco
import numpy as np
import trimesh

from ffcgs_jax.core.errors import FfcgsError, check_grasp_set
from ffcgs_jax.evaluation.ranking import ranked
from ffcgs_jax.hand import kinematics as K

PROTOCOL_KEYS = ("lift_shake_success", "six_dir_success", "dexgraspbench_success")
COLOURS = {"all": (60, 180, 75), "some": (245, 150, 40), "none": (220, 50, 50), "untested": (150, 150, 150),
           "plain": (110, 140, 200)}
OBJECT_COLOUR = (200, 160, 110)
NORMAL_LENGTH, CONE_LENGTH, CONE_EDGES = 0.02, 0.015, 8  # m, m, generator lines per friction cone


def _viser():
    try:
        import viser
    except ImportError:
        raise FfcgsError("the 3D viewer needs viser: pip install -e \".[viz]\" (or pip install viser)") from None
    return viser


def outcome(data: dict, i: int) -> str:
    """'all', 'some', 'none' (physics protocols held), 'untested', or 'plain' for a file without physics."""
    keys = [k for k in PROTOCOL_KEYS if k in data]
    if not keys:
        return "plain"
    if "physics_tested" in data and not bool(data["physics_tested"][i]):
        return "untested"
    held = [bool(data[k][i]) for k in keys]
    return "all" if all(held) else ("some" if any(held) else "none")


def _geom_mesh(m: mujoco.MjModel, g: int) -> trimesh.Trimesh:
    """Geom g in its own frame (MuJoCo's conventions: capsules and cylinders along z, sizes as half-lengths)."""
    t, size = mujoco.mjtGeom(int(m.geom_type[g])), m.geom_size[g]
    if t == mujoco.mjtGeom.mjGEOM_BOX:
        return trimesh.creation.box(extents=2 * size)
    if t == mujoco.mjtGeom.mjGEOM_CAPSULE:
        return trimesh.creation.capsule(height=2 * size[1], radius=size[0], count=[12, 12])
    if t == mujoco.mjtGeom.mjGEOM_CYLINDER:
        return trimesh.creation.cylinder(radius=size[0], height=2 * size[1], sections=16)
    if t == mujoco.mjtGeom.mjGEOM_SPHERE:
        return trimesh.creation.icosphere(subdivisions=2, radius=size[0])
    box = trimesh.creation.box(extents=2 * m.geom_aabb[g, 3:])  # other types: their bounding box
    box.apply_translation(m.geom_aabb[g, :3])
    return box


def _wxyz(R: np.ndarray) -> np.ndarray:
    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, np.asarray(R, np.float64).ravel())
    return q


def cone_segments(p: np.ndarray, n: np.ndarray, mu: float) -> np.ndarray:
    """(CONE_EDGES, 2, 3) generator lines of the friction cone at p about the outward normal n."""
    a = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(n, a)
    phi = np.linspace(0, 2 * np.pi, CONE_EDGES, endpoint=False)
    half = np.arctan(mu)
    d = np.cos(half) * n + np.sin(half) * (np.cos(phi)[:, None] * a + np.sin(phi)[:, None] * b)
    return np.stack([np.broadcast_to(p, d.shape), p + CONE_LENGTH * d], 1)


@dataclasses.dataclass
class GraspView:
    """A running viewer: `url`, `select(rank)` to show the grasp of that rank, `stop()`; inline in Jupyter."""

    server: object
    data: dict
    hand: K.Hand
    mesh: trimesh.Trimesh
    order: np.ndarray
    geoms: list
    handles: dict
    mu: float
    contact_tol: float
    _normals: np.ndarray | None = None

    @property
    def url(self) -> str:
        return f"http://{self.server.get_host()}:{self.server.get_port()}"

    def _repr_html_(self) -> str:
        return f'<iframe src="{self.url}" width="100%" height="560" style="border:0"></iframe>'

    def stop(self) -> None:
        self.server.stop()

    def select(self, rank: int) -> None:
        """Pose the hand and draw the contacts of the grasp at `rank` in the ranked order."""
        i = int(self.order[rank])
        d = self.data
        frames = jax.tree.map(np.asarray, _fk(self.hand, np.asarray(d["wrist_pose"][i]), np.asarray(d["q"][i])))
        colour = COLOURS[outcome(d, i)]
        for g, h in zip(self.geoms, self.handles["geoms"]):
            h.position, h.wxyz, h.color = frames.geom_pos[g], _wxyz(frames.geom_rot[g]), colour
        self.handles["wrist"].position = d["wrist_pose"][i][:3, 3]
        self.handles["wrist"].wxyz = _wxyz(np.asarray(d["wrist_pose"][i][:3, :3]))
        contacts = np.asarray(d["contacts"][i], float)
        dist = np.asarray(d["contact_dist"][i], float) if "contact_dist" in d else np.zeros(len(contacts))
        normals = self.normals()[i]
        touching = np.abs(dist) <= self.contact_tol
        colours = np.where(touching[:, None], [[40, 200, 60]], [[230, 40, 40]]).astype(np.uint8)
        self.handles["contacts"] = self.server.scene.add_point_cloud(
            "/grasp/contacts", contacts, colours, point_size=0.006, point_shape="circle")
        segs = np.stack([contacts, contacts + NORMAL_LENGTH * normals], 1)
        self.handles["normals"] = self.server.scene.add_line_segments(
            "/grasp/normals", segs, (30, 30, 220), thickness=0.0015)
        cones = np.concatenate([cone_segments(p, n, self.mu) for p, n in zip(contacts, normals)])
        self.handles["cones"] = self.server.scene.add_line_segments(
            "/grasp/friction_cones", cones, (250, 200, 40), thickness=0.001)
        self.handles["info"].content = _info(d, i, rank, touching)

    def normals(self) -> np.ndarray:
        """(G, C, 3) outward mesh normals at the fingertips' nearest surface points (`metrics.mesh_contacts`)."""
        if self._normals is None:
            from ffcgs_jax.evaluation.metrics import mesh_contacts

            self._normals = mesh_contacts(self.mesh, np.asarray(self.data["contacts"], float))[1]
        return self._normals


_fk = jax.jit(K.forward_kinematics)


def _info(d: dict, i: int, rank: int, touching: np.ndarray) -> str:
    def val(k, fmt):
        return format(float(d[k][i]), fmt) if k in d else "-"

    rows = [f"**grasp {i}** (rank {rank + 1} of {len(d['q'])})",
            f"valid: {bool(d['valid'][i]) if 'valid' in d else '-'}, fingertips touching: {int(touching.sum())} of "
            f"{len(touching)}",
            f"E {val('E', '.4f')}, E_g {val('E_g', '.4f')}, E_c {val('E_c', '.4f')} m, epsilon {val('epsilon', '.4f')}"]
    for k in PROTOCOL_KEYS:
        if k in d and ("physics_tested" not in d or bool(d["physics_tested"][i])):
            rows.append(f"{k.removesuffix('_success').replace('_', '-')}: {'held' if bool(d[k][i]) else 'failed'}")
    return "  \n".join(rows)


def free_port() -> int:
    """A TCP port nothing listens on now (for a second viewer, or one in a notebook)."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def show_grasps(hand: K.Hand, mesh: trimesh.Trimesh, gs, **kw) -> GraspView:
    """`show` for a `synthesis.grasp.GraspSet` (what `synthesize` returns), e.g. in a notebook: `fj.show`, its
    arguments in `synthesize`'s order."""
    check_grasp_set(gs, "show")
    return show({**gs.arrays, "config_json": json.dumps(dataclasses.asdict(gs.config))}, hand, mesh, **kw)


def _config(data: dict) -> dict:
    from ffcgs_jax.core.config import upgrade_keys
    from ffcgs_jax.synthesis.config import GraspConfig

    try:
        cfg = json.loads(str(data["config_json"])) if "config_json" in data else {}
    except ValueError:
        return {}
    return upgrade_keys(GraspConfig, cfg)  # a file saved before a setting's rename, under the current names


def show(data: dict, hand: K.Hand, mesh: trimesh.Trimesh, host: str = "127.0.0.1", port: int = 8080,
         verbose: bool = False) -> GraspView:
    """Serve the grasps of a grasp file's arrays `data` (`grasp_io.load_npz`) on `mesh` with `hand`; returns at
    once (viser serves from a thread). The grasps must belong to the hand: their channels are checked."""
    n = len(np.asarray(data.get("q", [])))
    if n == 0 or "wrist_pose" not in data or "contacts" not in data:
        raise FfcgsError("the grasp file has no grasps to show (needs wrist_pose, q and contacts)")
    if np.shape(data["q"])[1] != hand.n_channels:
        raise FfcgsError(f"the grasps have {np.shape(data['q'])[1]} channels but hand {hand.spec.name} has "
                         f"{hand.n_channels}: pass the hand they were made with (--hand)")
    viser = _viser()
    server = viser.ViserServer(host=host, port=port, verbose=verbose)
    server.scene.set_up_direction("+z")
    cfg = _config(data)
    lo, hi = mesh.bounds
    span = float(np.max(hi - lo))
    server.scene.add_mesh_simple("/object", np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces),
                                 color=OBJECT_COLOUR)
    centre = (lo + hi) / 2
    server.initial_camera.position = tuple(centre + span * np.array([2.0, -2.0, 1.6]))
    server.initial_camera.look_at = tuple(centre)
    server.scene.add_box("/table", (235, 235, 235), (4 * span, 4 * span, 0.002),
                         position=(*(lo[:2] + hi[:2]) / 2, lo[2] - 0.001), opacity=0.6)
    m = hand.spec.mj_model()
    geoms = K.hand_geoms(m)
    handles = {"geoms": [], "wrist": server.scene.add_frame("/grasp/wrist", axes_length=0.03, axes_radius=0.002)}
    for g in geoms:
        gm = _geom_mesh(m, g)
        handles["geoms"].append(server.scene.add_mesh_simple(
            f"/grasp/hand/geom_{g}", np.asarray(gm.vertices, np.float32), np.asarray(gm.faces), opacity=0.85))
    handles["info"] = server.gui.add_markdown("")
    order = ranked(data)
    view = GraspView(server, data, hand, mesh, order, geoms, handles,
                     mu=float(cfg.get("energy", {}).get("lp_friction", 0.2)),
                     contact_tol=float(cfg.get("contact_tol", 0.002)))
    slider = server.gui.add_slider("grasp (ranked)", min=1, max=n, step=1, initial_value=1)
    slider.on_update(lambda _: view.select(int(slider.value) - 1))
    _on_demand(server, view, cfg)
    view.select(0)
    return view


def _on_demand(server, view: GraspView, cfg: dict) -> None:
    """Checkboxes for the SDF's zero level, an SDF slice and the sampled wrist poses: built on first use."""
    from ffcgs_jax.geometry import sdf as sdf_mod
    from ffcgs_jax.geometry.config import SDFConfig

    res = int(cfg.get("sdf", {}).get("res", 32))
    state: dict = {}

    def grid():
        if "grid" not in state:
            state["grid"] = sdf_mod.build_sdf(view.mesh, SDFConfig(res=res))
        return state["grid"]

    def toggle(name, build):
        box = server.gui.add_checkbox(name, initial_value=False)

        def update(_):
            if box.value and name not in state:
                state[name] = build()
            if name in state:
                state[name].visible = bool(box.value)

        box.on_update(update)

    def zero_level():
        from ffcgs_jax.geometry import surface_nets

        g = grid()
        surf = surface_nets.zero_level_mesh(np.asarray(g.grid[..., 0]), np.asarray(g.origin), float(g.voxel_size))
        return server.scene.add_mesh_simple("/sdf/zero_level", np.asarray(surf.vertices, np.float32),
                                            np.asarray(surf.faces), color=(90, 200, 255), wireframe=True)

    def slice_():
        g = grid()
        d = np.asarray(g.grid[..., 0])
        k = d.shape[2] // 2
        ij = np.stack(np.meshgrid(np.arange(d.shape[0]), np.arange(d.shape[1]), indexing="ij"), -1).reshape(-1, 2)
        pts = np.asarray(g.origin) + float(g.voxel_size) * np.column_stack([ij, np.full(len(ij), k)])
        v = d[ij[:, 0], ij[:, 1], k] / max(float(np.abs(d).max()), 1e-9)
        colours = np.column_stack([255 * (v < 0), 255 * (1 - np.abs(v)), 255 * (v > 0)]).astype(np.uint8)
        return server.scene.add_point_cloud("/sdf/slice", pts.astype(np.float32), colours,
                                            point_size=float(g.voxel_size) * 0.8)

    def samples():
        from ffcgs_jax.hand import sites
        from ffcgs_jax.synthesis import samplers
        from ffcgs_jax.core.config import from_dict
        from ffcgs_jax.synthesis.config import FilterConfig, SamplerConfig

        name = cfg.get("sampler", "geometric")
        # the file's recorded config, checked as any config file is: an edited or older file gets one line
        sampling = from_dict(SamplerConfig, cfg.get("sampling", {}), "sampling.")
        filters = from_dict(FilterConfig, cfg.get("filters", {}), "filters.")
        poses = np.asarray(samplers.make_sampler(name, view.hand, sampling, filters)(
            jax.random.PRNGKey(int(cfg.get("seed", 0))), grid(), len(view.data["q"])))
        palm = sites.palm_centre_root(view.hand)
        centres = poses[:, :3, :3] @ palm + poses[:, :3, 3]
        normals = poses[:, :3, :3] @ np.asarray(view.hand.palm_normal, float)
        segs = np.stack([centres, centres + 0.02 * normals], 1)
        return server.scene.add_line_segments("/samples/palm_normals", segs, (120, 60, 200), thickness=0.001)

    toggle("SDF zero level", zero_level)
    toggle("SDF slice (mid height)", slice_)
    toggle("sampled wrist poses", samples)
