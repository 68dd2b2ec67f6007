"""Frozen dataclass configs read from TOML, with unknown keys and out-of-range values rejected.

Every command's options are one nested frozen dataclass. `load(cls, path)` reads a TOML file into it; the CLI
then lets any field be overridden (`--sdf.res 64`). Frozen dataclasses hash, so a config can be a static jit
argument.
"""

import dataclasses
import math
import tomllib
import typing
from pathlib import Path
from typing import Any, TypeVar

from ffcgs_jax.errors import FfcgsError

T = TypeVar("T")


@dataclasses.dataclass(frozen=True)
class SDFConfig:
    """How a mesh becomes a Gradient-SDF grid.

    Attributes:
        res: voxels along each axis of the cube (16-128; the paper uses 32).
        margin: free space around the object on each side, as a fraction of its largest extent. 0.15 leaves room
            for fingertips that approach from outside while keeping voxels small.
        min_margin: lower bound on that margin in metres, so tiny objects still get a band of free space.
        scale: multiplies the mesh's coordinates on load (0.001 turns millimetres into metres).
    """

    res: int = 32
    margin: float = 0.15
    min_margin: float = 0.01
    scale: float = 1.0

    def check(self) -> None:
        _range("sdf.res", self.res, 16, 128)
        _range("sdf.margin", self.margin, 0.0, 2.0)
        _range("sdf.min_margin", self.min_margin, 0.0, 1.0)
        if not self.scale > 0:
            raise FfcgsError(f"sdf.scale must be > 0, got {self.scale}")


@dataclasses.dataclass(frozen=True)
class RenderConfig:
    """Pictures of the hand (and object).

    Attributes:
        width, height: size of one view in pixels.
        backend: "auto" tries MuJoCo's OpenGL renderer and falls back to the built-in software rasteriser;
            "mujoco" or "software" force one.
    """

    width: int = 480
    height: int = 480
    backend: str = "auto"

    def check(self) -> None:
        _range("render.width", self.width, 64, 4096)
        _range("render.height", self.height, 64, 4096)
        if self.backend not in ("auto", "mujoco", "software"):
            raise FfcgsError(f"render.backend must be one of auto, mujoco, software; got {self.backend!r}")


LP_SOLVERS = ("jax", "proxsuite")


@dataclasses.dataclass(frozen=True)
class EnergyConfig:
    """E = E_g + a_c E_c + a_q E_q (+ a_pen P), eq. 5 of the paper.

    Attributes:
        mu: friction coefficient of the linearised cone (paper: 0.2).
        cone_edges: m, edges of the polyhedral friction cone (8).
        basis_size: K directions on the 6-D unit sphere for the Q-distance LP (64: +-e_i and 52 spread ones; the
            gauge then stays within a few per cent of the Euclidean distance while the LP stays small).
        d0: E_c offset: 0 as in the paper's simulation, 0.005 for its real-robot setting (a slight squeeze).
        a_c, a_q: weights of E_c (metres) and E_q (paper: 5 and 0.5).
        a_pen: weight of the whole-hand collision penalty (`filters.penetration_penalty`, summed squared depths in
            metres^2, so 1e4 makes a 1 cm deep link cost 1); the paper has none (0): it penalises fingertips only.
        normal_grad: let gradients flow through the contact normals. The paper holds them fixed (dn/dc = 0), which
            leaves E_g only the torques to work with: contacts bunched on one side then cannot spread out.
        lp_solver: who solves the Q-distance LP: "jax" (a revised simplex inside the compiled graph, `lp_jax.py`)
            or "proxsuite" (a host callback, `lp_host.py`, the reference path). Same values to 1e-9 in float64;
            "jax" is the default on every backend because it measured faster on both the 2-core CPU (1.9x at 32
            grasps) and an H200 (22x at 32; `ffcgs bench`, bench/RESULTS.md).
        lp_pivots: the "jax" solver's pivot budget per LP; a solve that needs more is flagged not ok.

    Defaults are this project's method; `configs/paper.toml` sets the paper's (a_pen 0, normal_grad false).
    """

    mu: float = 0.2
    cone_edges: int = 8
    basis_size: int = 64
    d0: float = 0.0
    a_c: float = 5.0
    a_q: float = 0.5
    a_pen: float = 1e4
    normal_grad: bool = True
    lp_solver: str = "jax"
    lp_pivots: int = 100

    def check(self) -> None:
        if self.lp_solver not in LP_SOLVERS:
            raise FfcgsError(f"unknown energy.lp_solver {self.lp_solver!r}; solvers: {', '.join(LP_SOLVERS)}")
        _integer("energy.lp_pivots", self.lp_pivots, 1, 100_000)
        _range("energy.mu", self.mu, 0.0, 2.0)
        _range("energy.cone_edges", self.cone_edges, 3, 64)
        _range("energy.basis_size", self.basis_size, 12, 1024)
        _range("energy.d0", self.d0, -0.05, 0.05)
        for name in ("a_c", "a_q", "a_pen"):
            _range(f"energy.{name}", getattr(self, name), 0.0, 1e6)


@dataclasses.dataclass(frozen=True)
class OptimConfig:
    """Algorithm 1: gradient descent on the channels q from q = 0, with a linearly decaying step.

    Attributes:
        iters: T, descent steps. The paper uses 50; with the wrist free there are 6 more variables and the hand
            travels further, and at 50 steps most fingertips stop 1-2 cm short of the surface, so the default is
            100 (`configs/paper.toml` keeps 50).
        method: "gd", the paper's plain gradient descent q <- q - beta_t dE/dq, or "adam", the same with each
            channel's step scaled by Adam's running gradient moments (see `optim.py` for why).
        step, step_end: gd step size at the first and the last iteration (linear decay in between; rad per unit of
            gradient).
        lr, lr_end: adam's learning rate at the first and the last iteration (linear decay; about rad per step).
        wrist: also move the wrist (beyond the paper, which keeps H fixed): a twist (rotation vector, translation
            in the hand frame) is optimised with q, so fingers that cannot reach the surface from the sampled
            pose can get there. The filters then judge the refined pose.
        wrist_rot_scale, wrist_shift_scale: the wrist twist's step relative to the channels' (rad per rad,
            metres per rad): with adam and lr 0.05, about 0.015 rad and 2.5 mm per step.

    Defaults are this project's method (adam, wrist refinement); `configs/paper.toml` sets Algorithm 1 as published
    (gd, fixed wrist). Measured on both in bench/RESULTS.md.
        eps_g: a pose stops early once E_g < eps_g ...
        eps_c: ... and its fingertips are on the surface (E_c < eps_c metres). The paper stops on E_g alone; with
            normals taken from the SDF away from the surface, E_g can vanish before the fingers touch anything.
    """

    iters: int = 100
    method: str = "adam"
    step: float = 0.3
    step_end: float = 0.03
    lr: float = 0.05
    lr_end: float = 0.005
    eps_g: float = 1e-3
    eps_c: float = 1e-3
    wrist: bool = True
    wrist_rot_scale: float = 0.3
    wrist_shift_scale: float = 0.05

    def check(self) -> None:
        _range("optim.wrist_rot_scale", self.wrist_rot_scale, 0.0, 100.0)
        _range("optim.wrist_shift_scale", self.wrist_shift_scale, 0.0, 100.0)
        if self.method not in ("gd", "adam"):
            raise FfcgsError(f"optim.method must be gd or adam, got {self.method!r}")
        _range("optim.lr", self.lr, 0.0, 10.0)
        _range("optim.lr_end", self.lr_end, 0.0, 10.0)
        _range("optim.iters", self.iters, 1, 100000)
        _range("optim.step", self.step, 0.0, 1e3)
        _range("optim.step_end", self.step_end, 0.0, 1e3)
        _range("optim.eps_g", self.eps_g, 0.0, 10.0)
        _range("optim.eps_c", self.eps_c, 0.0, 1.0)


@dataclasses.dataclass(frozen=True)
class FilterConfig:
    """Thresholds of the pose and grasp filters.

    Attributes:
        palm_up_max: a pose is discarded when the world z component of its unit palm normal exceeds this. 0 keeps
            palms facing sideways or down (the paper's "palm pointing upwards" rule, for an arm above the table);
            1 disables the filter, -1 would keep only palms facing straight down.
        clearance: metres each box corner must stay outside the object and the table (0 = touching is allowed).
        tip_table_margin: metres the cached fingertip positions must stay above the table plane.
    """

    palm_up_max: float = 0.0
    clearance: float = 0.0
    tip_table_margin: float = 0.0

    def check(self) -> None:
        _range("filters.palm_up_max", self.palm_up_max, -1.0, 1.0)
        _range("filters.clearance", self.clearance, 0.0, 1.0)
        _range("filters.tip_table_margin", self.tip_table_margin, -1.0, 1.0)


@dataclasses.dataclass(frozen=True)
class SamplerConfig:
    """Options of the wrist-pose samplers.

    Attributes:
        translation_scale: "random": the palm centre is uniform in the object's axis-aligned bounding box scaled by
            this factor about its centre (paper, V.A.1: "two times the size of the object's bounding box").
        standoff: "geometric": metres from the surface point to the palm centre, along the outward normal.
            0.05 m, the smallest round standoff at which the open hand (q = 0) clears a flat face: its farthest
            collision-box corner along the palm normal (the thumb's proximal link) lies 4.5 cm in front of the
            palm centre, and on the built-in box the fraction of candidates passing the box-corner filter rises
            from 26 % at 4-4.5 cm to 34 % at 5 cm and stays there. A larger standoff only moves the fingertips
            away: along the palm normal they reach at most 4.2 cm (fingers, near mid-closure q = (lower +
            upper) / 2) and 4.6 cm (thumb, at 30 % closure), and the fingertips' mean distance to the built-in
            objects at mid-closure grows by about 0.7 cm per cm of standoff.
        oversample: "geometric": candidates drawn per requested pose before the collision and palm-up filters.
            About 6 % pass on the built-in mug (its cavity and the table reject most) and 34 % on the box, so
            32 leaves about twice the poses needed on the mug; raise it for objects with little free surface.
        cvae_oversample: "cvae": latent samples decoded per requested pose; the ones passing the pose filters are
            kept first (see `samplers.sample_cvae`).
        weights: "cvae": the weights file (`weights.npz` from `python -m train.sampler`); "" uses the weights
            shipped in the package for the hand.
    """

    translation_scale: float = 2.0
    standoff: float = 0.05
    oversample: int = 32
    cvae_oversample: int = 4
    weights: str = ""

    def check(self) -> None:
        for name, lo, hi in (("translation_scale", 0.0, 100.0), ("standoff", 0.0, 1.0)):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and lo < v <= hi):
                raise FfcgsError(f"sampler.{name} must be a number in ({lo}, {hi}], got {v!r}")
        if not (isinstance(self.oversample, int) and 1 <= self.oversample <= 4096):
            raise FfcgsError(f"sampler.oversample must be an integer in [1, 4096], got {self.oversample!r}")
        _integer("sampler.cvae_oversample", self.cvae_oversample, 1, 4096)
        if not isinstance(self.weights, str):
            raise FfcgsError(f"sampler.weights must be a file path (or \"\" for the shipped weights), got "
                             f"{self.weights!r}")


# ----------------------------------------------------------------------------------------------------------------
# Rotations and frames (single item)
# ----------------------------------------------------------------------------------------------------------------


SAMPLERS = ("cvae", "geometric", "random")  # the names `samplers.CORES` implements


@dataclasses.dataclass(frozen=True)
class GraspConfig:
    """Everything `synthesize` needs besides the hand and the object.

    Attributes:
        n: wrist poses sampled and optimised as one batch.
        sampler: "cvae" (the learned sampler, weights shipped; the default since it beats geometric on E and E_g,
            bench/RESULTS.md "Learned sampler"), "geometric" or "random" (Table I's baselines).
        seed: PRNG seed of the sampler.
        max_penetration: a grasp whose hand collision spheres reach deeper than this into the object (metres) is
            not valid. 1 cm, as the physics test's initial-penetration rule; the paper does not check this.
        max_contact_rms: a grasp whose fingertips are farther than this from the surface, as RMS (E_c, metres), is
            not valid: it does not touch the object. 1 cm lets one finger of five miss by about 2 cm.
        devices: local accelerators the batch of poses is split over (`jax.sharding`, each device optimises its
            share independently): 0 = all local devices of JAX's default backend, k = the first k. The results
            do not depend on it; a batch that does not divide evenly is padded.
    """

    n: int = 32
    sampler: str = "cvae"
    seed: int = 0
    max_penetration: float = 0.01
    max_contact_rms: float = 0.01
    devices: int = 0
    sdf: SDFConfig = SDFConfig()
    energy: EnergyConfig = EnergyConfig()
    optim: OptimConfig = OptimConfig()
    filters: FilterConfig = FilterConfig()
    sampling: SamplerConfig = SamplerConfig()

    def check(self) -> None:
        if not 1 <= self.n <= 1_000_000:
            raise FfcgsError(f"n must be >= 1 (and at most 1e6), got {self.n}")
        if self.sampler not in SAMPLERS:
            raise FfcgsError(f"unknown sampler {self.sampler!r}; samplers: {', '.join(SAMPLERS)}")
        if not 0 <= self.max_penetration <= 1:
            raise FfcgsError(f"max_penetration must be in [0, 1] m, got {self.max_penetration}")
        if not 0 <= self.max_contact_rms <= 1:
            raise FfcgsError(f"max_contact_rms must be in [0, 1] m, got {self.max_contact_rms}")
        _integer("devices", self.devices, 0, 4096)


PROTOCOLS = ("lift-shake", "six-dir")  # the physics tests `physics.run_protocol` implements


@dataclasses.dataclass(frozen=True)
class PhysicsConfig:
    """The physics test (`ffcgs eval`): MuJoCo scene, grasp execution and the success rules. Units: SI.

    Attributes:
        friction: tangential Coulomb friction of every hand-object and object-table contact (0.6 default; 0.2 is
            the paper's metric value). Set on the object and table geoms with a higher geom priority, so it wins
            over the hand's own value.
        condim: contact dimensionality: 3 (point contact with friction, the model the LP metric assumes), 4 (adds
            torsional friction), 6 (adds rolling).
        torsional: torsional friction coefficient (metres), used when condim >= 4.
        timestep: simulation step (2 ms: the fingers' position servos and the 5 mm capsules stay stable).
        cone: "elliptic" (the exact Coulomb cone) or "pyramidal" (MuJoCo's default, what MJX runs fastest).
        impratio: ratio of frictional to normal constraint impedance. MuJoCo's soft friction lets a held object
            creep; at 100 the lift-shake results match those with MuJoCo's no-slip solver (which MJX lacks) on
            the built-in mug, where 1 and 10 let half of those grasps slide out.
        mass: object mass in kg (100 g), used when `density` is 0.
        density: object density in kg/m^3; > 0 replaces `mass` with density x mesh volume.
        kp: position-servo gain of the 9 channel actuators (N m/rad); the MJCF's value is 5.
        squeeze: radians the close target goes beyond the grasp's q, along the channel direction that pushes the
            fingertips near the surface into it (sum of J_i^T (-n_i), scaled so its largest channel moves by
            `squeeze`). The servos then press with about kp x squeeze.
        contact_band: fingertips within this distance of the surface (m) count for the squeeze direction.
        open_fraction: the fingers start at (1 - open_fraction) q, on the straight channel path from the open
            hand (q = 0, which the synthesis filters checked) to q; 1 = fully open.
        close_time, settle_time: seconds to ramp the servos from start to target, then to hold before testing.
        lift_height, lift_speed: lift-shake: the wrist rises this far (m) at this speed (m/s).
        shake_amplitude, shake_cycles, shake_speed: lift-shake: then it moves +-amplitude along world x, this
            many full cycles, sinusoidally at this mean speed (m/s): one cycle lasts 4 amplitude / speed.
        max_slip: lift-shake success bound on the object's displacement relative to the palm (m), measured from
            the end of closing to the end of shaking; the object must also be off the table.
        accel: six-dir: the external force is accel x mass (N), gravity off, no table.
        push_time: six-dir: seconds each of +x, -x, +y, -y, +z, -z is applied, each from the grasped state.
        max_move, max_rot_deg: six-dir success bounds on the object's displacement (m) and rotation (degrees) in
            every direction.
        max_initial_penetration: a grasp whose hand reaches deeper than this into the object at the start
            (metres, MuJoCo contact depth against the convex parts) fails without simulating.
        workers: threads for CPU MuJoCo (`mujoco.rollout`); 0 = all cores.
        coacd_threshold: CoACD's concavity threshold for the object's convex decomposition (smaller = more parts).
        max_hulls: at most this many convex parts (CoACD `max_convex_hull`).
        hull_vertices: at most this many vertices per part (CoACD `max_ch_vertex`).
    """

    friction: float = 0.6
    condim: int = 3
    torsional: float = 0.005
    timestep: float = 0.002
    cone: str = "elliptic"
    impratio: float = 100.0
    mass: float = 0.1
    density: float = 0.0
    kp: float = 5.0
    squeeze: float = 0.2
    contact_band: float = 0.01
    open_fraction: float = 1.0
    close_time: float = 0.5
    settle_time: float = 0.5
    lift_height: float = 0.10
    lift_speed: float = 0.10
    shake_amplitude: float = 0.10
    shake_cycles: int = 6
    shake_speed: float = 0.10
    max_slip: float = 0.05
    accel: float = 10.0
    push_time: float = 2.0
    max_move: float = 0.05
    max_rot_deg: float = 15.0
    max_initial_penetration: float = 0.01
    workers: int = 0
    coacd_threshold: float = 0.05
    max_hulls: int = 32
    hull_vertices: int = 64

    def check(self) -> None:
        _range("physics.friction", self.friction, 0.0, 10.0)
        if self.condim not in (1, 3, 4, 6):
            raise FfcgsError(f"physics.condim must be 1, 3, 4 or 6, got {self.condim}")
        if self.cone not in ("elliptic", "pyramidal"):
            raise FfcgsError(f"physics.cone must be elliptic or pyramidal, got {self.cone!r}")
        _range("physics.torsional", self.torsional, 0.0, 1.0)
        _range("physics.timestep", self.timestep, 1e-5, 0.02)
        _range("physics.impratio", self.impratio, 0.1, 1000.0)
        _range("physics.mass", self.mass, 1e-4, 100.0)
        _range("physics.density", self.density, 0.0, 1e5)
        _range("physics.kp", self.kp, 0.0, 1e4)
        _range("physics.squeeze", self.squeeze, 0.0, 3.0)
        _range("physics.contact_band", self.contact_band, 0.0, 1.0)
        _range("physics.open_fraction", self.open_fraction, 0.0, 1.0)
        for name in ("close_time", "settle_time", "push_time"):
            _range(f"physics.{name}", getattr(self, name), 0.0, 60.0)
        for name in ("lift_height", "shake_amplitude", "max_slip", "max_move", "max_initial_penetration"):
            _range(f"physics.{name}", getattr(self, name), 0.0, 10.0)
        for name in ("lift_speed", "shake_speed"):
            _range(f"physics.{name}", getattr(self, name), 1e-4, 100.0)
        _range("physics.shake_cycles", self.shake_cycles, 0, 1000)
        _range("physics.accel", self.accel, 0.0, 1000.0)
        _range("physics.max_rot_deg", self.max_rot_deg, 0.0, 180.0)
        _range("physics.workers", self.workers, 0, 4096)
        _range("physics.coacd_threshold", self.coacd_threshold, 0.01, 1.0)
        _range("physics.max_hulls", self.max_hulls, 1, 1024)
        _range("physics.hull_vertices", self.hull_vertices, 8, 4096)


def _range(name: str, value: int | float, lo: int | float, hi: int | float) -> None:
    if not lo <= value <= hi:
        raise FfcgsError(f"{name} must be in [{lo}, {hi}], got {value}")


def _integer(name: str, value: Any, lo: int, hi: int) -> None:
    """Like `_range`, for a field that must be a true int (not a bool, not a float from a TOML typo)."""
    if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
        raise FfcgsError(f"{name} must be an integer in [{lo}, {hi}], got {value!r}")


def _finite(value: Any) -> bool:
    return isinstance(value, (int, float)) and math.isfinite(value)


def from_dict(cls: type[T], data: Any, where: str = "") -> T:
    """Build dataclass `cls` from a nested dict, naming any unknown key and listing the valid ones."""
    if not isinstance(data, dict):
        raise FfcgsError(f"config section {where.rstrip('.') or '<top>'} must be a table, got {type(data).__name__}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    hints = typing.get_type_hints(cls)
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise FfcgsError(
            f"unknown config key(s) {', '.join(where + k for k in unknown)}; "
            f"valid keys{' in ' + where.rstrip('.') if where else ''}: {', '.join(sorted(fields))}"
        )
    kwargs = {}
    for name, value in data.items():
        hint = hints[name]
        if dataclasses.is_dataclass(hint):
            kwargs[name] = from_dict(hint, value, f"{where}{name}.")
        else:
            kwargs[name] = _coerce(hint, value, where + name)
    obj = cls(**kwargs)
    check_all(obj)
    return obj


def _coerce(hint: Any, value: Any, name: str) -> Any:
    if hint is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if hint in (int, float, str, bool) and not isinstance(value, hint):
        raise FfcgsError(f"config key {name} must be {hint.__name__}, got {value!r}")
    if typing.get_origin(hint) is tuple:
        return tuple(value)
    return value


def check_all(obj: Any) -> None:
    """Run `check()` on a config and on every nested config, so CLI overrides are validated too."""
    for f in dataclasses.fields(obj):
        sub = getattr(obj, f.name)
        if dataclasses.is_dataclass(sub):
            check_all(sub)
    if hasattr(obj, "check"):
        obj.check()


def load(cls: type[T], path: str | Path) -> T:
    """Read a TOML file into config class `cls` (missing keys keep their defaults)."""
    path = Path(path)
    if not path.is_file():
        raise FfcgsError(f"config file not found: {path}")
    try:
        data = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as e:
        raise FfcgsError(f"config file {path} is not valid TOML: {e}") from None
    return from_dict(cls, data)


@dataclasses.dataclass(frozen=True)
class PlannerConfig:
    """The annotation planner's simulated annealing (frozen: a static jit argument). Start poses come from the
    geometric sampler and the palm-up bound from the filters of the `GraspConfig` the planner is given.

    Attributes:
        population: candidates annealed as one batch.
        steps: Metropolis steps per candidate.
        t0, t_end: temperature at the first and the last step (geometric cooling in between), in units of the
            cheap energy: 0.05 accepts a 1 cm RMS fingertip regression (a_c 5) about a third of the time at first.
        step_shift, step_rot, step_q: standard deviation of the proposal's wrist translation (m, hand frame), wrist
            rotation (rad) and channels (rad) at t0. They shrink with sqrt(T / t0), so late steps fine-tune
            instead of jumping out of the basin they cooled into.
        a_c, a_q, a_pen: weights of E_c, E_q and the whole-hand penetration penalty, as in `EnergyConfig`.
        a_fc: weight of the force-closure proxy |sum of inward unit contact normals| / C (0 when opposed).
        a_up: weight of how far the palm normal's z exceeds filters.palm_up_max (that filter would drop it later).
        refine: how many of the lowest-energy annealed candidates go on to the Q-distance optimiser.
    """

    population: int = 2048
    steps: int = 100
    t0: float = 0.05
    t_end: float = 1e-3
    step_shift: float = 0.01
    step_rot: float = 0.1
    step_q: float = 0.2
    a_c: float = 5.0
    a_q: float = 0.5
    a_pen: float = 1e4
    a_fc: float = 0.1
    a_up: float = 1.0
    refine: int = 512

    def check(self) -> None:
        for name in ("population", "steps", "refine"):
            _integer(f"planner.{name}", getattr(self, name), 1, 1_000_000)
        if self.refine > self.population:
            raise FfcgsError(f"planner.refine ({self.refine}) must not exceed planner.population ({self.population})")
        for name in ("t0", "t_end", "step_shift", "step_rot", "step_q", "a_c", "a_q", "a_pen", "a_fc", "a_up"):
            v = getattr(self, name)
            if not (_finite(v) and (v > 0 if name in ("t0", "t_end") else v >= 0)):
                raise FfcgsError(f"planner.{name} must be a finite number "
                                 f"{'> 0' if name in ('t0', 't_end') else '>= 0'}, got {v!r}")
        if self.t_end > self.t0:
            raise FfcgsError(f"planner.t_end ({self.t_end}) must not exceed planner.t0 ({self.t0}): it cools")


SPLITS = ("train", "test", "all")
ROTATION_MODES = ("yaw", "so3")


@dataclasses.dataclass(frozen=True)
class DatasetConfig:
    """`ffcgs dataset build`: annotate every object of a split with the planner and the physics test, then write
    each object under several random rotations (recomputed SDF, grasps rotated with it) to one MCAP file.

    Attributes:
        objects: directory of meshes (stl, obj, ply, off, glb; metres, z up). Files are taken in sorted order; the
            test split is the files at positions where index % 5 == 4, the rest is train.
        out: the dataset file (.mcap). Finished records and per-object annotations are kept in OUT.parts/ (also
            after the merge; delete it yourself), so a rerun of the same command continues an interrupted build.
        split: "train", "test" or "all" of `objects`.
        per_object: grasps kept per object (the best by epsilon among those that pass the physics test).
        rotations: random rotations per object; every rotation is its own record with all the object's grasps.
        rotation_mode: "yaw" (about the vertical axis: the object still rests on the table the same way, so the
            physics results stay true) or "so3" (uniform over all rotations, as a pure shape augmentation).
        seed: seeds everything (per object through its name, so adding objects does not change the others).
        procedural: also annotate this many generated shapes (boxes, cylinders, ellipsoids, capsules, train
            split; named proc_NNN_kind).
        noise_trans, noise_rot: standard deviation (m, rad) of the Gaussian noise on the wrist pose stored as
            `wrist_pose_noisy` per record: translation in the object frame, rotation as a rotation vector applied
            in the wrist frame. The clean pose is kept beside it.
        dedupe_trans, dedupe_rot: a candidate whose wrist is within both this distance (m) and this angle (rad)
            of a better-ranked one is dropped before the physics test (near-duplicates add nothing).
        physics_chunk: candidates sent to the physics test at a time, in ranking order, until per_object pass.
        physics_test: "both" (six-dir, then lift-shake on the survivors; both must pass) or "none" (rank by
            epsilon only; for quick tests).
        hand: built-in hand name or hand-spec TOML.
        shard: "K/N" builds only objects K, K+N, K+2N, ... (0-based, in build order) so N processes or machines
            can share one parts directory; the last to finish merges (or rerun without --shard to merge). Not part
            of the dataset's config, nor is physics.workers: neither changes a record.
        annotate: False writes records only for objects already annotated (in OUT.parts/annotations, e.g. copied
            from the machines that annotated them) and merges them into a partial OUT, saying how many records
            are missing; the default annotates everything first.
        planner, grasp, physics: the planner, the refinement (the grasp pipeline on given poses) and the test.
    """

    objects: str = ""
    out: str = "dataset.mcap"
    split: str = "train"
    per_object: int = 200
    rotations: int = 5
    rotation_mode: str = "yaw"
    seed: int = 0
    procedural: int = 0
    noise_trans: float = 0.005
    noise_rot: float = 0.05
    dedupe_trans: float = 0.005
    dedupe_rot: float = 0.1
    physics_chunk: int = 128
    physics_test: str = "both"
    hand: str = "svh"
    shard: str = "0/1"
    annotate: bool = True
    planner: PlannerConfig = PlannerConfig()
    # The planner draws its own geometric start poses; "geometric" here keeps the stored build config (and so
    # resuming a build) independent of the synthesis default, which is the cvae trained on this very data.
    grasp: GraspConfig = GraspConfig(sampler="geometric")
    physics: PhysicsConfig = PhysicsConfig()

    def shard_of(self) -> tuple[int, int]:
        try:
            k, n = (int(x) for x in self.shard.split("/"))
        except ValueError:
            k, n = -1, 0
        if not 0 <= k < n:
            raise FfcgsError(f"--shard must be K/N with 0 <= K < N, got {self.shard!r}")
        return k, n

    def check(self) -> None:
        if self.split not in SPLITS:
            raise FfcgsError(f"unknown split {self.split!r}; splits: {', '.join(SPLITS)}")
        if self.rotation_mode not in ROTATION_MODES:
            raise FfcgsError(f"unknown rotation_mode {self.rotation_mode!r}; modes: {', '.join(ROTATION_MODES)}")
        if self.physics_test not in ("both", "none"):
            raise FfcgsError(f"physics_test must be 'both' or 'none', got {self.physics_test!r}")
        for name, lo, hi in (("per_object", 1, 1_000_000), ("rotations", 1, 1000), ("procedural", 0, 100_000),
                             ("physics_chunk", 1, 1_000_000), ("seed", 0, 2**63 - 1)):
            _integer(name.replace("_", "-"), getattr(self, name), lo, hi)
        for name in ("noise_trans", "noise_rot", "dedupe_trans", "dedupe_rot"):
            v = getattr(self, name)
            if not (_finite(v) and 0 <= v <= 10):
                raise FfcgsError(f"{name.replace('_', '-')} must be a number in [0, 10], got {v!r}")
        if not self.out.endswith(".mcap"):
            raise FfcgsError(f"--out must name an .mcap file, got {self.out!r}")
        self.shard_of()
