"""DexGraspBench's MuJoCo test (BODex, ICRA 2025; github.com/JYChen18/DexGraspBench), as its code runs it, for our
hands and grasp files: `--protocol dexgraspbench` (the benchmark's main branch: 100 g, kp 5) and
`--protocol dexgraspbench-bodex` (the BODex paper's original version: 30 g, kp 1).

The benchmark's force-closure test ("FCMocap") of one grasp, and what we run (our implementation, not its code):

- Scene: gravity off, no table; timestep 4 ms, implicit-fast integrator, elliptic friction cones, impratio 10,
  MuJoCo's no-slip solver with 2 iterations. Every hand and object geom has sliding friction 0.6, torsional 0.02,
  condim 4; the hand geoms are stiffened to solref (0.005, 1) and solimp (0.5, 0.99, 0.0001), the object's keep
  MuJoCo's defaults (geoms of equal priority: MuJoCo averages the two per contact, as in the benchmark). The wrist
  is a free joint welded to a mocap target with MuJoCo's default weld softness (solref 0.02), anchored at the hand's
  root with the relative pose of the compiled model, as the benchmark writes its weld (MjSpec's default equality
  data would anchor it 1 m away, and 1 N on the hand would then move it centimetres). The object is a free
  body of CoACD convex parts whose mass is set to the version's (inertia from the mesh), the hand's position servos
  get the version's kp.
- Execution, from the pre-grasp: the hand starts at rest at the pre-grasp (hand and object exactly there), then
  the servo targets (and the wrist target) go pre-grasp -> grasp in 0.4 s and grasp -> squeeze in 0.4 s, each as
  10 equal steps held 40 ms each (the benchmark's 10 x 10 simulation steps).
- Test: a force of 10 x the object's mass (N) on the object's centre of mass along -x, +x, -y, +y, -z, +z (our
  order: +x, -x, +y, -y, +z, -z), each for 2 s from a fresh reset to the pre-grasp (grasp and squeeze again), the
  targets held at the squeeze. Every 0.2 s (50 steps) the object's pose is compared with its pose at the
  pre-grasp (where the grasp was planned): success when it moved < 5 cm and turned < 15 degrees at every check in
  all six directions. The first failing check ends the test (as the benchmark stops).
- A grasp whose hand is more than 1 cm inside the object at the pre-grasp fails without simulating.

What we cannot take over, and what we chose:
- The hands: ours (the SVH: 9 servo channels with 11 coupling constraints; the Allegro: 16 servos), not the
  benchmark's MuJoCo Menagerie Shadow, Allegro and Leap models with their tendons, armatures and force limits. Only
  the kp of the servos is the benchmark's; our MJCFs' servos have no force limit.
- Pre-grasp and squeeze: the benchmark takes both from the grasp data (BODex writes its own; its converters for
  DexGraspNet and SpringGrasp data keep the wrist and scale the joint angles by 0.9 and 1.1). Our grasp files carry
  q, the wrist pose and `squeeze_dir` (the channel direction that presses the fingertips touching the object into
  it: sum_i J_i^T (-n_i), largest entry 1), so: squeeze = q + `PhysicsConfig.squeeze` x squeeze_dir (the squeeze
  of our own protocols, 0.2 rad on the channel that moves most), pre-grasp = q - squeeze x squeeze_dir (the same
  step backwards: the touching fingertips backed off along their normals; fingers that touch nothing stay at q),
  both clipped to the channel limits, with the wrist at the grasp's pose throughout (so the wrist target never
  moves). A 0.9 / 1.1 scaling of q would also move channels that do not close on the object (the SVH's spread, the
  thumb's opposition), and q = 0 is not "open" for every channel of every hand.
- Branching: the six directions start from the squeezed state, simulated once; the benchmark re-simulates
  pre-grasp -> squeeze for each. The simulation is deterministic, so the state is the same (a test checks it).
- Rotation: the smallest angle between the two orientations; the benchmark's 2 acos(w) of the relative
  quaternion differs only beyond 180 degrees, far past the bound.
- "lost" (the failure reason) is a failure with no hand contact left after the squeeze; such grasps are still
  pushed, as in the benchmark (a hand that cages the object without touching it can pass).
- The backends: CPU MuJoCo (the reference) and MuJoCo Warp (`worlds`, its own no-slip solver, float32: 82 % of
  outcomes equal the CPU's on 512 candidates of complex shapes, bench/RESULTS.md); MJX has no no-slip solver and is
  refused.
"""

import dataclasses
from typing import Any


@dataclasses.dataclass(frozen=True)
class Version:
    """One published version of the benchmark: object mass (kg) and the hand servos' kp (N m/rad)."""

    mass: float
    kp: float
    source: str


# the names `--protocol` takes (`protocols` registers one protocol per version)
VERSIONS = {
    "dexgraspbench": Version(0.1, 5.0, "DexGraspBench main branch (the standard benchmark)"),
    "dexgraspbench-bodex": Version(0.03, 1.0, "the BODex paper's version (DexGraspBench's `original` branch)"),
}

TIMESTEP = 0.004  # s
IMPRATIO = 10.0
NOSLIP_ITERATIONS = 2
FRICTION = 0.6  # sliding, every geom
TORSIONAL = 0.02  # m, every geom
CONDIM = 4
HAND_SOLREF = (0.005, 1.0)  # the hand geoms' contact softness: stiffer than MuJoCo's default (0.02, 1)
HAND_SOLIMP = (0.5, 0.99, 0.0001)
WELD_SOLREF = (0.02, 1.0)  # the wrist weld: MuJoCo's default
STAGE_TIME = 0.4  # s: pre-grasp -> grasp, then grasp -> squeeze
WAYPOINTS = 10  # servo (and wrist) targets per stage, each held STAGE_TIME / WAYPOINTS
ACCEL = 10.0  # m/s^2: the external force is ACCEL x mass
PUSH_TIME = 2.0  # s per direction
CHECK_TIME = 0.2  # s: the object's pose is checked this often during a push
MAX_MOVE = 0.05  # m
MAX_ROT_DEG = 15.0
MAX_PENETRATION = 0.01  # m, at the pre-grasp


def fixed(v: Version) -> dict[str, Any]:
    """The `PhysicsConfig` fields the benchmark fixes, with their values for version `v`: the scene, the object's
    mass, the servo gain, the force and the success bounds (the protocol's `fixed`, applied by
    `Protocol.settings`). What stays the user's: the squeeze (`squeeze`, `contact_band` when a file has no
    `squeeze_dir`), the convex decomposition and `workers`."""
    return dict(sim_friction=FRICTION, condim=CONDIM, torsional=TORSIONAL, timestep=TIMESTEP, cone="elliptic",
                impratio=IMPRATIO, mass=v.mass, density=0.0, kp=v.kp, accel=ACCEL, push_time=PUSH_TIME,
                max_move=MAX_MOVE, max_rot_deg=MAX_ROT_DEG, max_initial_penetration=MAX_PENETRATION)
