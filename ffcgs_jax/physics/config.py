"""The physics test's settings: `PhysicsConfig` and the built-in protocols' names.

The protocols themselves are registered objects (`protocols.get`, `registry.Protocol`); their names are here too so
that the CLI and the dataset config can check a name without importing the simulation (`protocols` imports MuJoCo
and SciPy, and this module). `protocols` refuses to load when its built-ins and these names differ.
"""

import dataclasses
import typing
from typing import ClassVar, Literal

from ffcgs_jax.core.config import check_choice, check_integer, check_range, keeps_old_names
from ffcgs_jax.core.errors import FfcgsError

PROTOCOLS = ("lift-shake", "six-dir")  # our physics tests: what `--protocol both` and `evaluate` run by default
# DexGraspBench's MuJoCo test in its two published versions (`dexgraspbench.VERSIONS`: object mass and servo gain)
DEXGRASPBENCH = ("dexgraspbench", "dexgraspbench-bodex")
ALL_PROTOCOLS = PROTOCOLS + DEXGRASPBENCH  # the built-in protocols `protocols` registers, in its order

Backend = Literal["auto", "cpu", "mjx", "warp"]
BACKENDS = typing.get_args(Backend)
# the object's collision geometry (`collision.parts`): the default first
Collision = Literal["voxel-hulls", "coacd", "vhacd", "voxel-boxes", "patch-hulls"]
COLLISIONS = typing.get_args(Collision)
Cone = Literal["elliptic", "pyramidal"]


@dataclasses.dataclass(frozen=True)
class RobustConfig:
    """The robust verdict (`physics.robust`): every grasp is tried `trials` times under perturbations drawn from
    one distribution, and per protocol it gets a pass rate with its Wilson interval. Units: SI, angles in degrees
    (pose) and radians (joints).

    The distribution, per trial k of grasp g (reproducible from `trial_seed`; a grasp's draws depend on its own wrist
    pose and q, not on the other grasps of the call):
    - the object's collision geometry: `geometries[k % len(geometries)]`, "method@cells" (cells: the voxel
      methods' `voxel_cells`), what a millimetre of other geometry does to contacts (bench/RESULTS.md, issue 45);
    - the object's sliding friction, uniform in `sim_friction` x friction_factors (0.4-0.8 at the default 0.6),
      and its mass, uniform in `mass` x mass_factors (0.05-0.3 kg at the default 100 g; with `density` > 0, the
      density scales instead): the unknown object a robot meets. Stratified over the K trials (each of K equal
      bins once) and shared by every grasp of the call in trial k, so grasps are compared under the same
      conditions;
    - the wrist pose: a shift uniform in the ball of radius `pose_mm` millimetres and a turn about the wrist's
      origin uniform in the ball of rotation vectors of radius `rot_deg` degrees (a robot arm's placement error);
    - the finger channels: each q_i + uniform(-joint_rad, joint_rad) (servo and calibration error).
    DexGraspBench's protocols keep the friction and mass they fix (their definition); the rest applies.

    Attributes:
        trials: trials per grasp and protocol. 1 = today's single trial at the nominal grasp and settings, no
            perturbation (the verdict before issue 45). 8 (the default): a grasp holds at 7 or 8 passes of 8, and
            on MuJoCo Warp eight trials of a validated call are worlds of the same launches (bench/RESULTS.md).
        trial_seed: the draws' seed.
        pose_mm, rot_deg, joint_rad, friction_factors, mass_factors, geometries: the distribution.
        confidence: level of the two-sided Wilson interval of each pass rate (0.9: its lower bound is a one-sided
            95 % bound).
        threshold: a grasp holds (`<protocol>_success`, and `physics_passed` for all protocols of a check) when the
            interval's lower bound is at least this: with 95 % confidence it holds in more executions than not.
    """

    trials: int = 8
    trial_seed: int = 0
    pose_mm: float = 2.0
    rot_deg: float = 2.0
    joint_rad: float = 0.02
    friction_factors: tuple[float, float] = (2 / 3, 4 / 3)
    mass_factors: tuple[float, float] = (0.5, 3.0)
    geometries: tuple[str, ...] = ("voxel-hulls@64", "voxel-hulls@48")
    confidence: float = 0.9
    threshold: float = 0.5

    def check(self) -> None:
        check_integer("physics.robust.trials", self.trials, 1, 1024)
        check_integer("physics.robust.trial_seed", self.trial_seed, 0, 2**63 - 1)
        check_range("physics.robust.pose_mm", self.pose_mm, 0.0, 100.0)
        check_range("physics.robust.rot_deg", self.rot_deg, 0.0, 180.0)
        check_range("physics.robust.joint_rad", self.joint_rad, 0.0, 1.0)
        for name in ("friction_factors", "mass_factors"):
            lo, hi = getattr(self, name)
            check_range(f"physics.robust.{name}[0]", lo, 1e-3, 100.0)
            check_range(f"physics.robust.{name}[1]", hi, lo, 100.0)
        if not self.geometries:
            raise FfcgsError("physics.robust.geometries needs at least one geometry, e.g. [\"voxel-hulls@64\"]")
        for g in self.geometries:
            geometry_settings(g)
        check_range("physics.robust.confidence", self.confidence, 0.5, 0.9999)
        check_range("physics.robust.threshold", self.threshold, 0.0, 1.0)
        least = fewest_trials(self.confidence, self.threshold)
        if 1 < self.trials < least:
            raise FfcgsError(f"physics.robust.trials {self.trials} can never show a grasp holds: at confidence "
                             f"{self.confidence:g} and threshold {self.threshold:g} even {self.trials} passes of "
                             f"{self.trials} leave the interval's lower bound below it; use 1 (one nominal trial) or "
                             f">= {least}")


def fewest_trials(confidence: float, threshold: float) -> int:
    """The fewest trials after which a grasp that passed all of them holds: the Wilson lower bound of n passes in
    n, n / (n + z^2), reaches `threshold` (`protocols.wilson`; 3 at the defaults)."""
    import math

    from statistics import NormalDist

    z = NormalDist().inv_cdf(0.5 + confidence / 2)
    if threshold >= 1.0:
        return 10**9
    return max(1, math.ceil(z * z * threshold / (1.0 - threshold) - 1e-12))


def geometry_settings(text: str) -> dict:
    """The `PhysicsConfig` fields of a geometry variant "method" or "method@cells" (`RobustConfig.geometries`)."""
    method, _, cells = str(text).partition("@")
    if method not in COLLISIONS or (cells and not (cells.isdigit() and 8 <= int(cells) <= 256)):
        raise FfcgsError(f"physics.robust.geometries: {text!r} is no geometry; write a method of "
                         f"{', '.join(COLLISIONS)}, optionally @cells (8-256), e.g. \"voxel-hulls@48\"")
    return {"collision": method, **({"voxel_cells": int(cells)} if cells else {})}


@keeps_old_names
@dataclasses.dataclass(frozen=True)
class PhysicsConfig:
    """The physics test (`ffcgs eval`): MuJoCo scene, grasp execution and the success rules. Units: SI.

    DexGraspBench's protocols (`DEXGRASPBENCH`) replace the contact, solver, mass, gain, force and bound fields
    with the benchmark's values (the protocol's `fixed`, `dexgraspbench.fixed`; a value you set otherwise is
    named in one warning line); they keep `squeeze`, `contact_band`, the convex decomposition and `workers`.

    Attributes:
        backend: the simulator: "auto" (MuJoCo Warp when a CUDA device and the `[warp]` extra are present, else
            CPU MuJoCo), "cpu" (MuJoCo, threads), "warp" (MuJoCo Warp: grasps as worlds on a CUDA GPU,
            `pip install -e ".[warp]"`) or "mjx" (MuJoCo MJX on the JAX device; far slower). Where the grasps are
            simulated, not what: the success rules are the same (bench/RESULTS.md gives the measured agreement).
        sim_friction: MuJoCo's sliding (tangential Coulomb) friction of every hand-object and object-table contact
            (0.6 default; the quality LP's cone is `EnergyConfig.lp_friction`, 0.2). Set on the object and table
            geoms with a higher geom priority, so it wins over the hand's own value. Formerly `friction`, which
            still reads.
        condim: contact dimensionality: 3 (point contact with friction, the model the LP metric assumes), 4 (adds
            torsional friction), 6 (adds rolling).
        torsional: torsional friction coefficient (metres), used when condim >= 4.
        timestep: simulation step. 4 ms (2 ms until the GPU-physics issue): on 271 valid grasps of the YCB test
            split and the built-ins, 99.3 % of outcomes equal 2 ms's in both protocols at half the cost
            (bench/RESULTS.md, "Faster physics defaults").
        cone: "elliptic" (the exact Coulomb cone) or "pyramidal" (MuJoCo's default, what MJX runs fastest).
        impratio: ratio of frictional to normal constraint impedance. MuJoCo's soft friction lets a held object
            creep; at 100 the lift-shake results match those with MuJoCo's no-slip solver (which MJX lacks) on
            the built-in mug, where 1 and 10 let half of those grasps slide out.
        mass: object mass in kg (100 g), used when `density` is 0.
        density: object density in kg/m^3; > 0 replaces `mass` with density x mesh volume.
        kp: position-servo gain of the channel actuators (N m/rad); 0 (the default) keeps the hand MJCF's own
            gains (the SVH's 5, the Allegro's 10).
        squeeze: radians the close target goes beyond the grasp's q, along the channel direction that pushes the
            fingertips near the surface into it (sum of J_i^T (-n_i), scaled so its largest channel moves by
            `squeeze`). The servos then press with about kp x squeeze.
        contact_band: fingertips within this distance of the surface (m) count for the squeeze direction.
        open_fraction: the fingers start at q_open + (1 - open_fraction) (q - q_open), on the straight channel
            path from the open hand (q_open: q = 0 clamped into the limits, which the synthesis filters checked) to
            q; 1 = fully open.
        close_time, settle_time: seconds to ramp the servos from start to target, then to hold before testing.
        lift_height, lift_speed: lift-shake: the wrist rises this far (m) at this speed (m/s).
        shake_amplitude, shake_cycles, shake_speed: lift-shake: then it moves +-amplitude along world x, this
            many full cycles, sinusoidally at this mean speed (m/s): one cycle lasts 4 amplitude / speed. 3 cycles
            (6 until the GPU-physics issue): the later cycles repeat the same accelerations; 3 % of grasps that
            hold 3 cycles drop in cycles 4 to 6.
        max_slip: lift-shake success bound on the object's displacement relative to the palm (m), measured from
            the end of closing to the end of shaking; the object must also be off the table.
        accel: six-dir: the external force is accel x mass (N), gravity off, no table.
        push_time: six-dir: seconds each of +x, -x, +y, -y, +z, -z is applied, each from the grasped state
            (1 s; 2 s until the GPU-physics issue gave the same outcome for 99.6 % of grasps).
        max_move, max_rot_deg: six-dir success bounds on the object's displacement (m) and rotation (degrees) in
            every direction.
        max_initial_penetration: a grasp whose hand reaches deeper than this into the object at the start
            (metres, MuJoCo contact depth against the convex parts) fails without simulating.
        workers: threads for CPU MuJoCo (`mujoco.rollout`); 0 = all cores.
        collision: how the object becomes convex parts for MuJoCo (`COLLISIONS`, `physics.collision`):
            "voxel-hulls" (hulls of voxel clusters, bounded by its grid), "coacd" (CoACD, bounded search), "vhacd",
            "voxel-boxes", "patch-hulls". bench/RESULTS.md, "Collision geometry", compares them.
        collision_budget: wall-clock seconds the decomposition may take; past it the object gets a coarser
            voxel-hull geometry and a one-line warning.
        voxel_cells: voxels along the object's longest side for the voxel methods.
        voxel_tol: voxel-hulls: metres a part may reach out of the solid beyond the voxel layer next to it.
        coacd_threshold: CoACD's concavity threshold for the object's convex decomposition (smaller = more parts).
        max_hulls: at most this many convex parts (CoACD `max_convex_hull`, V-HACD's, voxel-hulls').
        hull_vertices: at most this many vertices per part (CoACD `max_ch_vertex`).
        robust: the robust verdict's trials and perturbations (`RobustConfig`); `trials` 1 is one nominal trial.
    """

    RENAMED: ClassVar[dict[str, str]] = {"friction": "sim_friction"}

    backend: Backend = "auto"
    sim_friction: float = 0.6
    condim: int = 3
    torsional: float = 0.005
    timestep: float = 0.004
    cone: Cone = "elliptic"
    impratio: float = 100.0
    mass: float = 0.1
    density: float = 0.0
    kp: float = 0.0
    squeeze: float = 0.2
    contact_band: float = 0.01
    open_fraction: float = 1.0
    close_time: float = 0.5
    settle_time: float = 0.5
    lift_height: float = 0.10
    lift_speed: float = 0.10
    shake_amplitude: float = 0.10
    shake_cycles: int = 3
    shake_speed: float = 0.10
    max_slip: float = 0.05
    accel: float = 10.0
    push_time: float = 1.0
    max_move: float = 0.05
    max_rot_deg: float = 15.0
    max_initial_penetration: float = 0.01
    workers: int = 0
    collision: Collision = "voxel-hulls"
    collision_budget: float = 20.0
    voxel_cells: int = 64
    voxel_tol: float = 0.002
    coacd_threshold: float = 0.05
    max_hulls: int = 32
    hull_vertices: int = 64
    robust: RobustConfig = RobustConfig()

    def check(self) -> None:
        check_choice("physics.backend", self.backend, Backend)
        check_range("physics.sim_friction", self.sim_friction, 0.0, 10.0)
        if self.condim not in (1, 3, 4, 6):
            raise FfcgsError(f"physics.condim must be 1, 3, 4 or 6, got {self.condim}")
        check_choice("physics.cone", self.cone, Cone)
        check_range("physics.torsional", self.torsional, 0.0, 1.0)
        check_range("physics.timestep", self.timestep, 1e-5, 0.02)
        check_range("physics.impratio", self.impratio, 0.1, 1000.0)
        check_range("physics.mass", self.mass, 1e-4, 100.0)
        check_range("physics.density", self.density, 0.0, 1e5)
        check_range("physics.kp", self.kp, 0.0, 1e4)
        check_range("physics.squeeze", self.squeeze, 0.0, 3.0)
        check_range("physics.contact_band", self.contact_band, 0.0, 1.0)
        check_range("physics.open_fraction", self.open_fraction, 0.0, 1.0)
        for name in ("close_time", "settle_time", "push_time"):
            check_range(f"physics.{name}", getattr(self, name), 0.0, 60.0)
        for name in ("lift_height", "shake_amplitude", "max_slip", "max_move", "max_initial_penetration"):
            check_range(f"physics.{name}", getattr(self, name), 0.0, 10.0)
        for name in ("lift_speed", "shake_speed"):
            check_range(f"physics.{name}", getattr(self, name), 1e-4, 100.0)
        check_integer("physics.shake_cycles", self.shake_cycles, 0, 1000)
        check_range("physics.accel", self.accel, 0.0, 1000.0)
        check_range("physics.max_rot_deg", self.max_rot_deg, 0.0, 180.0)
        check_integer("physics.workers", self.workers, 0, 4096)
        check_choice("physics.collision", self.collision, Collision)
        check_range("physics.collision_budget", self.collision_budget, 0.0, 3600.0)
        check_integer("physics.voxel_cells", self.voxel_cells, 8, 256)
        check_range("physics.voxel_tol", self.voxel_tol, 0.0, 0.05)
        check_range("physics.coacd_threshold", self.coacd_threshold, 0.01, 1.0)
        check_integer("physics.max_hulls", self.max_hulls, 1, 1024)
        check_integer("physics.hull_vertices", self.hull_vertices, 8, 4096)
        self.robust.check()
