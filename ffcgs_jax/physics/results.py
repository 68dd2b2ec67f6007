"""The physics test's outcome as typed results: `PhysicsResult` (what `fj.evaluate_physics` returns) holds one
`ProtocolOutcome` per protocol. `as_arrays` gives the flat per-grasp arrays files and datasets store
(`six_dir_success`, ...: `protocols.result_key`), and `from_arrays` reads them back, so files written before keep
their keys."""

import dataclasses

import numpy as np

from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.physics import protocols as physics_protocols

FIELDS = ("success", "reason", "move", "move_dir", "rot", "rot_dir", "pregrasp_penetration")


@dataclasses.dataclass(frozen=True)
class ProtocolOutcome:
    """One protocol's per-grasp outcome, one row per grasp tested.

    Attributes:
        protocol: its name, e.g. "six-dir".
        success: (B,) bool, the grasp passed.
        reason: (B,) int8, index into `protocols.REASONS` ("ok", "penetration", "lost", "slip", "unstable");
            `reasons` gives the names.
        move, rot: (B,) the object's displacement (m) and turn (degrees) the success rule read; NaN where not
            simulated (penetration at the start) or diverged.
        move_dir, rot_dir: (B, 6) for the six-direction tests (six-dir, DexGraspBench's): per direction
            (`protocols.DIRECTION_NAMES`) the largest move and turn, NaN where not pushed; None otherwise.
        pregrasp_penetration: (B,) for DexGraspBench's: the hand's depth in the object at the pre-grasp (m), what
            its penetration rule reads; None otherwise.
    """

    protocol: str
    success: np.ndarray
    reason: np.ndarray
    move: np.ndarray
    rot: np.ndarray
    move_dir: np.ndarray | None = None
    rot_dir: np.ndarray | None = None
    pregrasp_penetration: np.ndarray | None = None

    @property
    def reasons(self) -> np.ndarray:
        """(B,) the failure reasons by name ("ok" for a grasp that passed)."""
        return np.asarray(physics_protocols.REASONS)[np.asarray(self.reason)]

    def as_arrays(self) -> dict[str, np.ndarray]:
        """The flat per-grasp arrays under their file keys (`six_dir_success`, ...); absent fields are left out."""
        return {physics_protocols.result_key(self.protocol, f): getattr(self, f) for f in FIELDS
                if getattr(self, f) is not None}


@dataclasses.dataclass(frozen=True)
class PhysicsResult:
    """The physics test of B grasps (`fj.evaluate_physics`).

    Attributes:
        protocols: per protocol name, its `ProtocolOutcome` (also as an attribute, '-' written '_':
            `result.six_dir`).
        initial_penetration: (B,) the hand's deepest penetration into the object at the grasp's q (m).
        palm_contact: (B,) the palm touches the object at q.
        index: (B,) the tested grasps' numbers in the grasp set given (`which`).
        rerun_cpu: (B,) on MuJoCo Warp, the grasps run again on the CPU (their worlds overflowed a buffer); None
            on the CPU backends.
    """

    protocols: dict[str, ProtocolOutcome]
    initial_penetration: np.ndarray
    palm_contact: np.ndarray
    index: np.ndarray
    rerun_cpu: np.ndarray | None = None

    def __getattr__(self, name: str) -> ProtocolOutcome:
        # only called for names that are no field: a protocol by its name with '_' for '-'
        outcomes = self.__dict__.get("protocols", {})
        if not name.startswith("_") and name.replace("_", "-") in outcomes:
            return outcomes[name.replace("_", "-")]
        raise AttributeError(f"PhysicsResult has no attribute {name!r}; its protocols: {', '.join(outcomes)}")

    def __getitem__(self, key):
        raise FfcgsError(f"a PhysicsResult is no dict of arrays: result.protocols[name].success (or .reason, .move, "
                         f"...), or result.as_arrays()[{key!r}] for the flat arrays")

    def __len__(self) -> int:
        return len(self.initial_penetration)

    @property
    def passed(self) -> np.ndarray:
        """(B,) the grasp passed every protocol."""
        return np.logical_and.reduce([o.success for o in self.protocols.values()] + [np.ones(len(self), bool)])

    def as_arrays(self) -> dict[str, np.ndarray]:
        """The flat per-grasp arrays as `runner.evaluate` returns them and files store them: initial_penetration,
        palm_contact, per protocol `<protocol>_<field>` ('-' written '_') and, on Warp, physics_rerun_cpu."""
        out = {"initial_penetration": self.initial_penetration, "palm_contact": self.palm_contact}
        for o in self.protocols.values():
            out.update(o.as_arrays())
        if self.rerun_cpu is not None:
            out["physics_rerun_cpu"] = self.rerun_cpu
        return out

    @classmethod
    def from_arrays(cls, arrays, protocols=None, index=None) -> "PhysicsResult":
        """A result from flat arrays (`as_arrays`, `runner.evaluate`'s, a file's): `protocols` those to read
        (default: every registered protocol the arrays hold); `index` the grasps' numbers (default 0..B-1)."""
        names = physics_protocols.names() if protocols is None else (
            (protocols,) if isinstance(protocols, str) else tuple(protocols))
        key = physics_protocols.result_key
        if protocols is None:
            names = tuple(p for p in names if key(p, "success") in arrays)
        missing = [key(p, f) for p in names for f in ("success", "reason", "move", "rot") if key(p, f) not in arrays]
        missing += [k for k in ("initial_penetration", "palm_contact") if k not in arrays]
        if missing:
            raise FfcgsError(f"the physics results have no {missing[0]}"
                             f"{f' (and {len(missing) - 1} more)' if len(missing) > 1 else ''}")
        outcomes = {p: ProtocolOutcome(p, **{f: np.asarray(arrays[key(p, f)]) for f in FIELDS if key(p, f) in arrays})
                    for p in names}
        b = len(arrays["initial_penetration"])
        rerun = arrays.get("physics_rerun_cpu") if hasattr(arrays, "get") else None
        return cls(outcomes, np.asarray(arrays["initial_penetration"]), np.asarray(arrays["palm_contact"]),
                   np.arange(b) if index is None else np.asarray(index), None if rerun is None else np.asarray(rerun))
