"""The configs of grasp synthesis: energy (eq. 5), the descent (Algorithm 1), filters, samplers and the
pipeline's `GraspConfig`, which nests them with the SDF's.
"""

import dataclasses
import math
import typing
import warnings
from typing import ClassVar, Literal

from ffcgs_jax.core.config import (SEED_MAX, check_choice, check_integer, check_range, from_dict, keeps_old_names,
                                   read_toml)
from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.geometry.config import SDFConfig

LpSolver = Literal["jax", "proxsuite"]
LP_SOLVERS = typing.get_args(LpSolver)
# E_c's offset d0 (metres) aims the fingertips d0 inside the surface. Below 0 it would aim them -d0 outside it, a
# hand that hovers and never holds, which the evaluation (`metrics.MetricsConfig`, derived from this config) does not
# measure as a grasp; above 5 cm it would push them through any object this package grasps. The one check of d0.
D0_RANGE = (0.0, 0.05)


@keeps_old_names
@dataclasses.dataclass(frozen=True)
class EnergyConfig:
    """E = E_g + a_c E_c + a_q E_q (+ a_pen P), eq. 5 of the paper.

    Attributes:
        lp_friction: friction coefficient of the linearised cone the quality LP and the evaluation use (paper's mu:
            0.2); the simulator's is `PhysicsConfig.sim_friction`. Formerly `mu`, which still reads.
        cone_edges: m, edges of the polyhedral friction cone (8).
        basis_size: K directions on the 6-D unit sphere for the Q-distance LP (64: +-e_i and 52 spread ones; the
            gauge then stays within a few per cent of the Euclidean distance while the LP stays small).
        d0: E_c offset in [0, 0.05] m (`D0_RANGE`): 0 as in the paper's simulation, 0.005 for its real-robot
            setting (a slight squeeze).
        a_c, a_q: weights of E_c (metres) and E_q (paper: 5 and 0.5).
        closure_margin: delta, the force-closure margin the descent aims for: E_m (`quality.support_margin`) is 0
            once the wrench hull's support reaches delta in each of `margin_dirs` directions searched where the hull
            is thin (Ferrari-Canny epsilon >= delta implies it). Dimensionless, like E_g (forces of unit cone edges,
            torques divided by the object radius).
        a_m: weight of E_m; 0 leaves it out (the paper: E_g alone, whose optimum is the hull's boundary).
            Defaults delta 0.1, a_m 3: chosen on the YCB training objects among a_m 0, (1, 0.03), (3, 0.05),
            (3, 0.1): same physics success (49 %), valid share 44 -> 59 %, median E_c 0.81 -> 0.18 mm
            (bench/RESULTS.md, "Grasp quality").
        margin_dirs, margin_steps: directions the margin searches, and their search steps per descent step.
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

    RENAMED: ClassVar[dict[str, str]] = {"mu": "lp_friction"}

    lp_friction: float = 0.2
    cone_edges: int = 8
    basis_size: int = 64
    d0: float = 0.0
    a_c: float = 5.0
    a_q: float = 0.5
    closure_margin: float = 0.1
    a_m: float = 3.0
    margin_dirs: int = 16
    margin_steps: int = 4
    a_pen: float = 1e4
    normal_grad: bool = True
    lp_solver: LpSolver = "jax"
    lp_pivots: int = 100

    def check(self) -> None:
        check_choice("energy.lp_solver", self.lp_solver, LpSolver)
        check_integer("energy.lp_pivots", self.lp_pivots, 1, 100_000)
        check_range("energy.lp_friction", self.lp_friction, 0.0, 2.0)
        check_integer("energy.cone_edges", self.cone_edges, 3, 64)
        check_integer("energy.basis_size", self.basis_size, 12, 1024)
        check_range("energy.d0", self.d0, *D0_RANGE)
        check_range("energy.closure_margin", self.closure_margin, 0.0, 1.0)
        check_integer("energy.margin_dirs", self.margin_dirs, 1, 1024)
        check_integer("energy.margin_steps", self.margin_steps, 0, 1000)
        for name in ("a_c", "a_q", "a_m", "a_pen"):
            check_range(f"energy.{name}", getattr(self, name), 0.0, 1e6)


OptimMethod = Literal["gd", "adam"]


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
        contact_ramp: the weight of E_c grows linearly from a_c at the first step to contact_ramp x a_c at the
            last (1: constant, as in the paper). 40 brings the median fingertip distance of returned grasps under
            1 mm (bench/RESULTS.md, "Grasp quality scoreboard").
        project_steps: Gauss-Newton steps of the final projection (`synthesis.project`) that back penetrating
            links out of the object by moving the channels (the wrist held), keeping the fingertips touching;
            0 leaves the descent's result as it is (`configs/paper.toml`). 5: on the 6 built-ins and 6 complex
            shapes of seed 7000 the median penetration of returned grasps fell from 1.38 to 0.41 mm (p90 2.86 ->
            2.34 mm), valid 301 -> 304 of 384 (2-core CPU, `python bench/penetration.py`).
        project_allow: metres of overlap per collision sphere the projection leaves free, in [0, 0.01].
    """

    iters: int = 100
    method: OptimMethod = "adam"
    step: float = 0.3
    step_end: float = 0.03
    lr: float = 0.05
    lr_end: float = 0.005
    eps_g: float = 1e-3
    eps_c: float = 1e-3
    wrist: bool = True
    wrist_rot_scale: float = 0.3
    wrist_shift_scale: float = 0.05
    contact_ramp: float = 40.0
    project_steps: int = 5
    project_allow: float = 0.0

    def check(self) -> None:
        check_range("optim.contact_ramp", self.contact_ramp, 1.0, 1e4)
        check_integer("optim.project_steps", self.project_steps, 0, 1000)
        check_range("optim.project_allow", self.project_allow, 0.0, 0.01)
        check_range("optim.wrist_rot_scale", self.wrist_rot_scale, 0.0, 100.0)
        check_range("optim.wrist_shift_scale", self.wrist_shift_scale, 0.0, 100.0)
        check_choice("optim.method", self.method, OptimMethod)
        check_range("optim.lr", self.lr, 0.0, 10.0)
        check_range("optim.lr_end", self.lr_end, 0.0, 10.0)
        check_integer("optim.iters", self.iters, 1, 100000)
        check_range("optim.step", self.step, 0.0, 1e3)
        check_range("optim.step_end", self.step_end, 0.0, 1e3)
        check_range("optim.eps_g", self.eps_g, 0.0, 10.0)
        check_range("optim.eps_c", self.eps_c, 0.0, 1.0)


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
        check_range("filters.palm_up_max", self.palm_up_max, -1.0, 1.0)
        check_range("filters.clearance", self.clearance, 0.0, 1.0)
        check_range("filters.tip_table_margin", self.tip_table_margin, -1.0, 1.0)


Sampler = Literal["cvae", "geometric", "random"]  # the names `samplers.CORES` implements
SAMPLERS = typing.get_args(Sampler)
Rank = Literal["auto", "predicted", "energy"]  # GraspConfig.rank: `synthesis.prediction.resolve`
RANKS = typing.get_args(Rank)


@dataclasses.dataclass(frozen=True)
class SamplerConfig:
    """Options of the wrist-pose samplers.

    Attributes:
        translation_scale: "random": the palm centre is uniform in the object's axis-aligned bounding box scaled by
            this factor about its centre (paper, V.A.1: "two times the size of the object's bounding box").
        standoff: "geometric": metres from the surface point to the palm centre, along the outward normal; 0 (the
            default) derives it from the hand (`hand.sites.default_standoff`): the smallest multiple of 5 mm at
            which the open hand clears a flat face, its farthest collision-box corner along the palm normal. For
            the SVH that corner (the thumb's proximal link) lies 4.5 cm in front of the palm centre, so 5 cm;
            on the built-in box the fraction of candidates passing the box-corner filter rises from 26 % at
            4-4.5 cm to 34 % at 5 cm and stays there. A larger standoff only moves the fingertips away: along the
            palm normal the SVH's reach at most 4.2 cm (fingers, near mid-closure q = (lower + upper) / 2) and
            4.6 cm (thumb, at 30 % closure), and the fingertips' mean distance to the built-in objects at
            mid-closure grows by about 0.7 cm per cm of standoff.
        oversample: "geometric": candidates drawn per requested pose before the collision and palm-up filters.
            About 6 % pass on the built-in mug (its cavity and the table reject most) and 34 % on the box, so
            32 leaves about twice the poses needed on the mug; raise it for objects with little free surface.
        cvae_oversample: "cvae": latent samples decoded per requested pose; the ones passing the pose filters are
            kept first (see `samplers.sample_cvae`).
        weights: "cvae": the weights file (`weights.npz` from `python -m train.sampler`); "" uses the weights
            shipped in the package for the hand.
    """

    translation_scale: float = 2.0
    standoff: float = 0.0
    oversample: int = 32
    cvae_oversample: int = 4
    weights: str = ""

    def check(self) -> None:
        for name, lo, hi in (("translation_scale", 0.0, 100.0), ("standoff", 0.0, 1.0)):
            v = getattr(self, name)
            ok = isinstance(v, (int, float)) and math.isfinite(v) and (lo < v or (name == "standoff" and v == 0))
            if not (ok and v <= hi):
                zero = " (0: derived from the hand)" if name == "standoff" else ""
                raise FfcgsError(f"sampler.{name} must be a number in ({lo}, {hi}]{zero}, got {v!r}")
        check_integer("sampler.oversample", self.oversample, 1, 4096)
        check_integer("sampler.cvae_oversample", self.cvae_oversample, 1, 4096)
        if not isinstance(self.weights, str):
            raise FfcgsError(f"sampler.weights must be a file path (or \"\" for the shipped weights), got "
                             f"{self.weights!r}")


@dataclasses.dataclass(frozen=True)
class SearchConfig:
    """Searching further where the first batch is weak (`synthesis.search`): while the best `n` grasps so far hold
    fewer than `min_valid` valid ones, or (ranked by the success predictor) no valid one predicted to hold with at
    least `min_predicted`, another batch of `n` is drawn with the next seed of the same compiled program, the
    batches are pooled and the best `n` kept. An object whose first batch is good enough gets exactly the first
    batch and costs nothing more. The grasp set records what was done (`search_*`, README's grasps.npz table).

    Attributes:
        min_valid: valid grasps the returned set should hold (1: search where none is valid).
        min_predicted: predicted success (`pred_success`) the best valid grasp should reach; 0.5, "more likely to
            hold than not". Ignored where grasps are ranked by E (no predictor, or `rank = "energy"`).
        max_rounds: batches at most, the first included (1: never search further). 4: at most 3 more batches,
            each costing what the first did.
        budget: seconds the further batches may take together. A batch starts only when the seconds spent so far
            plus the last batch's fit in it, so the budget is passed by at most one batch's variation.
            10 s: on a GPU (a batch of 32 in well under a second) `max_rounds` binds, and the results do not depend
            on the machine; on a 2-core CPU one batch of 32 takes seconds, and this bounds the wait.
    """

    min_valid: int = 1
    min_predicted: float = 0.5
    max_rounds: int = 4
    budget: float = 10.0

    def check(self) -> None:
        check_integer("search.min_valid", self.min_valid, 0, 1_000_000)
        check_range("search.min_predicted", self.min_predicted, 0.0, 1.0)
        check_integer("search.max_rounds", self.max_rounds, 1, 1000)
        check_range("search.budget", self.budget, 0.0, 86_400.0)


@dataclasses.dataclass(frozen=True)
class GraspConfig:
    """Everything `synthesize` needs besides the hand and the object.

    Attributes:
        n: wrist poses sampled and optimised as one batch.
        sampler: "auto" (the default): "cvae" where weights ship for the hand (the SVH) or `sampling.weights`
            names a file, else "geometric". "cvae" (the learned sampler; it beats geometric on E and E_g,
            bench/RESULTS.md "Learned sampler"), "geometric" or "random" (Table I's baselines) choose one.
            `synthesize` resolves "auto" before it runs; its GraspSet's config names the sampler used.
        seed: PRNG seed of the sampler.
        max_penetration: a grasp whose hand collision spheres reach deeper than this into the object (metres) is
            not valid. 1 cm, as the physics test's initial-penetration rule; the paper does not check this.
        max_contact_rms: a grasp whose fingertips are farther than this from the surface, as RMS (E_c, metres), is
            not valid: it does not touch the object. 1 cm lets one finger of five miss by about 2 cm.
        contact_tol: a fingertip touches the object when the mesh is within this distance (metres) of its contact
            point; only touching fingertips count for epsilon, force_closure, E_g_mesh and n_contacts, and a valid
            grasp has every fingertip touching and force closure with them.
        squeeze_angle: radians past q, along `squeeze_dir` (sum_i J_i^T (-n_i) over the touching fingertips, largest
            channel 1), of the servo target a grasp is executed with: `q_squeeze` in the grasp file. 0.2, as the
            physics test's `physics.squeeze`, which presses with the file's `squeeze_dir` too.
        devices: local accelerators the batch of poses is split over (`jax.sharding`, each device optimises its
            share independently): 0 = all local devices of JAX's default backend, k = the first k. The results
            do not depend on it; a batch that does not divide evenly is padded.
        rank: the order grasps are offered in (`GraspSet.order`): "auto" (the default) by the learned success
            predictor's `pred_success` where one exists for the hand (shipped for the SVH and the Allegro, or
            `evaluator`), else by E; "predicted" requires a predictor; "energy" by E, the analytic order
            (predictions still stored).
            On held-out objects the predicted order puts a grasp that holds first far more often than E
            (bench/RESULTS.md, "Success predictor").
        evaluator: a success-predictor weights file (`ffcgs train --model evaluator`); "" = the shipped one.
        search: where the first batch has too few valid grasps or none predicted to hold, more batches within a
            budget (`SearchConfig`); `SearchConfig(max_rounds=1)` returns the first batch whatever it holds.
    """

    n: int = 32
    sampler: Literal["auto", Sampler] = "auto"
    seed: int = 0
    max_penetration: float = 0.01
    max_contact_rms: float = 0.01
    contact_tol: float = 0.002
    squeeze_angle: float = 0.2
    devices: int = 0
    sdf: SDFConfig = SDFConfig()
    energy: EnergyConfig = EnergyConfig()
    optim: OptimConfig = OptimConfig()
    filters: FilterConfig = FilterConfig()
    sampling: SamplerConfig = SamplerConfig()
    rank: Rank = "auto"
    evaluator: str = ""
    search: SearchConfig = SearchConfig()

    def check(self) -> None:
        check_integer("n", self.n, 1, 1_000_000)
        if self.search.min_valid > self.n:  # never met: every call would spend the whole budget
            raise FfcgsError(f"search.min_valid ({self.search.min_valid}) must be at most n ({self.n})")
        check_choice("rank", self.rank, Rank)
        if not isinstance(self.evaluator, str):
            raise FfcgsError(f"evaluator must be a file path (or \"\" for the shipped weights), got {self.evaluator!r}")
        check_choice("sampler", self.sampler, ("auto", *SAMPLERS))
        if not 0 <= self.max_penetration <= 1:
            raise FfcgsError(f"max_penetration must be in [0, 1] m, got {self.max_penetration}")
        if not 0 <= self.max_contact_rms <= 1:
            raise FfcgsError(f"max_contact_rms must be in [0, 1] m, got {self.max_contact_rms}")
        check_range("contact_tol", self.contact_tol, 0.0, 1.0)
        check_range("squeeze_angle", self.squeeze_angle, 0.0, 3.0)
        check_integer("devices", self.devices, 0, 4096)
        check_integer("seed", self.seed, 0, SEED_MAX)
        if self.energy.d0 > self.contact_tol:
            # said before the compile, not discovered as "0 / 32 valid" after it
            warnings.warn(f"energy.d0 = {self.energy.d0:g} m plans the fingertips {1000 * self.energy.d0:g} mm inside "
                          f"the surface, deeper than the {1000 * self.contact_tol:g} mm that counts as touching "
                          "(contact_tol): few or no grasps will be valid. d0 > 0 is the paper's real-robot squeeze "
                          "for a position-controlled hand; the physics test squeezes by itself", stacklevel=2)


def load_config(path) -> GraspConfig:
    """A preset TOML (`configs/*.toml`, what `ffcgs grasp --config` reads) as a GraspConfig: its [grasp] tables, or,
    in a file without one, its GraspConfig tables ([energy], [optim], [sdf], ...). Unknown keys and out-of-range
    values are refused as on the command line."""
    data = read_toml(path)
    if "grasp" in data:
        return from_dict(GraspConfig, data["grasp"], "grasp.")
    fields = {f.name for f in dataclasses.fields(GraspConfig)}
    if data and set(data) <= fields:
        return from_dict(GraspConfig, data)
    tables = sorted(k if k.isprintable() else repr(k) for k in data)  # a quoted TOML key may hold a newline
    raise FfcgsError(f"config file {path} has no [grasp] table (its tables: {', '.join(tables) or 'none'}): "
                     f"it configures another command")
