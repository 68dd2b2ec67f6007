"""`ffcgs dataset build`'s settings: the annotation planner's and the build's."""

import dataclasses
import typing
from typing import Literal

from ffcgs_jax.core.config import SEED_MAX, check_choice, check_integer, is_finite
from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.physics.config import ALL_PROTOCOLS, PhysicsConfig
from ffcgs_jax.synthesis.config import Sampler, GraspConfig


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
            check_integer(f"planner.{name}", getattr(self, name), 1, 1_000_000)
        if self.refine > self.population:
            raise FfcgsError(f"planner.refine ({self.refine}) must not exceed planner.population ({self.population})")
        for name in ("t0", "t_end", "step_shift", "step_rot", "step_q", "a_c", "a_q", "a_pen", "a_fc", "a_up"):
            v = getattr(self, name)
            if not (is_finite(v) and (v > 0 if name in ("t0", "t_end") else v >= 0)):
                raise FfcgsError(f"planner.{name} must be a finite number "
                                 f"{'> 0' if name in ('t0', 't_end') else '>= 0'}, got {v!r}")
        if self.t_end > self.t0:
            raise FfcgsError(f"planner.t_end ({self.t_end}) must not exceed planner.t0 ({self.t0}): it cools")


Split = Literal["train", "test", "all"]
RotationMode = Literal["yaw", "so3"]
Keep = Literal["passing", "all"]
Engine = Literal["auto", "plain", "ray"]

LABEL_PROTOCOLS = ("lift-shake", "six-dir", "dexgraspbench")


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
            of the dataset's config, nor are physics.workers and physics.backend: none changes a record.
        annotate: False writes records only for objects already annotated (in OUT.parts/annotations, e.g. copied
            from the machines that annotated them) and merges them into a partial OUT, saying how many records
            are missing; the default annotates everything first.
        keep: "passing" (the annotation above: plan, dedupe, physics-select until `per_object` pass both tests; the
            learned sampler's data) or "all" (the data engine: `per_object` candidates per object from the
            `grasp.sampler`, "planner" for the annealing, every one written with its `protocols` outcomes, moves,
            reasons, analytic metrics and features, successes and failures alike; `dataset.label`).
        sampler: where a "keep all" build's candidates start: "planner" (the annealing) or a synthesis sampler
            (cvae, geometric, random); a "keep passing" build always plans.
        protocols: the physics protocols a "keep all" build labels every candidate with (comma-separated).
        complex: also build this many complex generated shapes (`procedural.complex_shape`, train split).
        scale_min, scale_max: every object is scaled by a factor uniform in this range (drawn per object name).
        allow_test: build from test-split files and held-out generated seeds too (refused by default: they are
            what the benchmarks report on).
        engine: "plain" (objects one after another in this process), "ray" (objects as Ray tasks: a local Ray
            instance using every GPU and core of this machine, or the cluster at `address`), or "auto" (ray when
            `address` is given, or the build has more than `ray_from` objects, Ray is installed and the machine
            has 2 cores or more; else plain).
        address: a Ray cluster to join ("auto", "HOST:PORT" or "ray://HOST:PORT"); empty starts a local one.
        task_cpus: CPU cores each Ray task holds for its physics threads, at most half the cluster's (its GPU share
            follows: the GPUs are split evenly over the tasks that fit on the cores).
        cpus, gpus: how much of this machine a local Ray instance takes (0 cores / -1 GPUs: all of them), to share
            a workstation; a cluster joined with `address` has its own.
        ray_from: objects from which "auto" starts Ray (its start-up, a few seconds, dominates smaller builds).
        group: objects per unit of work (a Ray task, one physics run) of a labelled build whose physics runs on
            MuJoCo Warp: their grasps share the GPU's launches; 1 labels one object at a time. Other builds, and
            labelled ones on CPU physics, take one object at a time. Not part of the dataset's config.
        planner, grasp, physics: the planner, the refinement (the grasp pipeline on given poses) and the test.
    """

    objects: str = ""
    out: str = "dataset.mcap"
    split: Split = "train"
    per_object: int = 200
    rotations: int = 5
    rotation_mode: RotationMode = "yaw"
    seed: int = 0
    procedural: int = 0
    noise_trans: float = 0.005
    noise_rot: float = 0.05
    dedupe_trans: float = 0.005
    dedupe_rot: float = 0.1
    physics_chunk: int = 128
    physics_test: Literal["both", "none"] = "both"
    hand: str = "svh"
    shard: str = "0/1"
    annotate: bool = True
    keep: Keep = "passing"
    sampler: Literal["planner", Sampler] = "planner"
    protocols: str = ",".join(LABEL_PROTOCOLS)
    complex: int = 0
    scale_min: float = 1.0
    scale_max: float = 1.0
    allow_test: bool = False
    engine: Engine = "auto"
    address: str = ""
    task_cpus: int = 4
    cpus: int = 0
    gpus: int = -1
    ray_from: int = 8
    group: int = 16
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

    def protocol_list(self) -> tuple[str, ...]:
        out = tuple(p.strip() for p in self.protocols.split(",") if p.strip())
        unknown = [p for p in out if p not in ALL_PROTOCOLS]
        if unknown or not out:
            raise FfcgsError(f"--protocols must name one or more of {', '.join(ALL_PROTOCOLS)}, got "
                             f"{self.protocols!r}")
        return out

    def check(self) -> None:
        hints = typing.get_type_hints(DatasetConfig)
        for name in ("keep", "sampler", "engine", "split", "rotation_mode", "physics_test"):
            check_choice(name.replace("_", "-"), getattr(self, name), hints[name])
        if self.keep == "all" and self.physics_test == "none":
            raise FfcgsError("--keep all labels every candidate with the physics test (--protocols); "
                             "--physics-test none applies to --keep passing only")
        if self.engine == "plain" and self.address:
            raise FfcgsError("--address joins a Ray cluster: it needs --engine ray or auto, not plain")
        self.protocol_list()
        for name, lo, hi in (("complex", 0, 100_000), ("task_cpus", 1, 1024), ("ray_from", 0, 1_000_000),
                             ("cpus", 0, 100_000), ("gpus", -1, 1024), ("group", 1, 4096)):
            check_integer(name.replace("_", "-"), getattr(self, name), lo, hi)
        for name in ("scale_min", "scale_max"):
            v = getattr(self, name)
            if not (is_finite(v) and 0.1 <= v <= 10):
                raise FfcgsError(f"{name.replace('_', '-')} must be a number in [0.1, 10], got {v!r}")
        if self.scale_min > self.scale_max:
            raise FfcgsError(f"scale-min ({self.scale_min}) must not exceed scale-max ({self.scale_max})")
        for name, lo, hi in (("per_object", 1, 1_000_000), ("rotations", 1, 1000), ("procedural", 0, 100_000),
                             ("physics_chunk", 1, 1_000_000), ("seed", 0, SEED_MAX)):
            check_integer(name.replace("_", "-"), getattr(self, name), lo, hi)
        for name in ("noise_trans", "noise_rot", "dedupe_trans", "dedupe_rot"):
            v = getattr(self, name)
            if not (is_finite(v) and 0 <= v <= 10):
                raise FfcgsError(f"{name.replace('_', '-')} must be a number in [0, 10], got {v!r}")
        if not self.out.endswith(".mcap"):
            raise FfcgsError(f"--out must name an .mcap file, got {self.out!r}")
        self.shard_of()
