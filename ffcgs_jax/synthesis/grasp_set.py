"""`GraspSet`: the grasps of one object on the host, what `synthesize` returns and a grasp file holds.

Its fields are typed attributes; README's `grasps.npz` table gives their meanings and units. The arrays are read
through `gs.wrist_pose`, `gs["wrist_pose"]` or `gs.arrays["wrist_pose"]` (all read-only mappings: a GraspSet is
never changed in place); `with_arrays` makes a new one with arrays added or replaced, as the physics check and the
CLI's records of provenance do.
"""

from collections.abc import Mapping

import numpy as np

from ffcgs_jax.core.types import Bool, Float, Int
from ffcgs_jax.evaluation import ranking
from ffcgs_jax.synthesis.config import GraspConfig

Host = np.ndarray
_META = ("trace", "config", "object_name")
_TEXT_ROWS = ("channel_names", "joint_names")  # per channel or joint, not per grasp: `select` keeps them whole


class ReadOnlyArrays(dict):
    """A dict that refuses changes: a GraspSet's arrays as the functions typed `dict` read them (`ranking`, the
    physics check), never written through."""

    def _refuse(self, *args, **kwargs):
        raise TypeError("a GraspSet's arrays are read-only: gs.with_arrays(...) makes a new set")

    __setitem__ = __delitem__ = __ior__ = update = pop = popitem = setdefault = clear = _refuse


class GraspSet:
    """Grasps of one object, host arrays. B grasps, Q channels, J joints, C fingertips; object frame, metres.

    Every array `synthesize` computes for every grasp is a typed attribute below; a set built from fewer arrays (a
    dataset record's, a file of an older version, a test's) has None where it lacks one, and `gs[name]` raises
    KeyError there, as for any absent array. The optional arrays (the success predictor's `pred_*`, physics
    outcomes, provenance `object_source` / `object_scale` / `object_sha256`, depth fields, `*_true`) are in `extra`,
    a read-only mapping; `arrays` is every array, typed and optional.
    """

    wrist_pose: Float[Host, "B 4 4"] | None  # hand root pose in the object frame, after wrist refinement
    q: Float[Host, "B Q"] | None  # actuated channels, in `channel_names` order
    channel_names: Host | None  # (Q,) str
    joint_pos: Float[Host, "B J"] | None  # the MJCF joint angles the channels drive (q @ coupling.T)
    joint_names: Host | None  # (J,) str
    contacts: Float[Host, "B C 3"] | None  # fingertip contact points on the fingertips' collision skin
    E: Float[Host, " B"] | None  # the energy at the result, and its terms (E_c in metres)
    E_g: Float[Host, " B"] | None
    E_c: Float[Host, " B"] | None
    E_q: Float[Host, " B"] | None
    E_m: Float[Host, " B"] | None  # the force-closure margin term
    support_min: Float[Host, " B"] | None  # the smallest wrench support the margin's search found
    epsilon: Float[Host, " B"] | None  # Ferrari-Canny epsilon from the mesh's closest points (touching tips)
    force_closure: Bool[Host, " B"] | None
    E_g_mesh: Float[Host, " B"] | None  # E_g and E_c recomputed on the mesh
    E_c_mesh: Float[Host, " B"] | None
    contact_dist: Float[Host, "B C"] | None  # each fingertip's signed distance to the mesh
    n_contacts: Int[Host, " B"] | None  # fingertips within `contact_tol` of the mesh
    squeeze_dir: Float[Host, "B Q"] | None  # channel direction pressing the touching tips in (largest entry 1)
    q_squeeze: Float[Host, "B Q"] | None  # the servo target q + squeeze_angle x squeeze_dir
    penetration: Float[Host, " B"] | None  # deepest hand collision sphere in the object / the table
    table_penetration: Float[Host, " B"] | None
    pose_collides: Bool[Host, " B"] | None  # the filters' verdicts
    palm_up: Bool[Host, " B"] | None
    tips_below_table: Bool[Host, " B"] | None
    lp_ok: Bool[Host, " B"] | None
    iters: Int[Host, " B"] | None  # descent steps before the early stop
    valid: Bool[Host, " B"] | None  # usable: every filter passed, every fingertip touching, force closure
    rank_by: Host | None  # () "predicted" or "energy": the order `order()` gives
    synthesis_s: Float[Host, ""] | None  # seconds: the device part, the evaluation, compilation, the SDF, the call
    evaluation_s: Float[Host, ""] | None
    compile_s: Float[Host, ""] | None
    sdf_s: Float[Host, ""] | None
    total_s: Float[Host, ""] | None
    trace: Mapping[str, np.ndarray]  # per-iteration E, E_g, E_c: (T+1, B); empty for a set loaded from a file
    config: GraspConfig
    object_name: str

    def __init__(self, arrays: Mapping, trace: Mapping | None = None,
                 config: GraspConfig = GraspConfig(), object_name: str = "object"):
        # a copy (the caller's dict may change later; this set does not), numbers as 0-d arrays, as a file holds them
        own = {k: np.asarray(v) for k, v in arrays.items()}
        for name in FIELDS:
            object.__setattr__(self, name, own.get(name))
        object.__setattr__(self, "_arrays", own)
        object.__setattr__(self, "trace", ReadOnlyArrays(trace or {}))
        object.__setattr__(self, "config", config)
        object.__setattr__(self, "object_name", object_name)

    def __setattr__(self, name, value):
        raise AttributeError(f"a GraspSet is read-only ({name}); gs.with_arrays(...) makes a new one")

    def __getstate__(self):  # the read-only trace refuses the item-by-item rebuild of unpickling; a plain copy not
        return {**self.__dict__, "trace": dict(self.trace)}

    def __setstate__(self, state):
        self.__dict__.update(state, trace=ReadOnlyArrays(state["trace"]))

    def __getitem__(self, key: str) -> np.ndarray:
        return self._arrays[key]

    def __contains__(self, key: str) -> bool:
        return key in self._arrays

    def __repr__(self) -> str:
        n = len(self.q) if self.q is not None else len(self.valid) if self.valid is not None else "?"
        return f"GraspSet({self.object_name!r}, {n} grasps, arrays {', '.join(self._arrays)})"

    @property
    def arrays(self) -> Mapping[str, np.ndarray]:
        """Every array of the set, read-only (`with_arrays` adds or replaces)."""
        return ReadOnlyArrays(self._arrays)

    @property
    def extra(self) -> Mapping[str, np.ndarray]:
        """The arrays that are not typed fields (predictions, physics outcomes, provenance, ...), read-only."""
        return ReadOnlyArrays({k: v for k, v in self._arrays.items() if k not in FIELDS})

    def with_arrays(self, arrays: Mapping | None = None, /, **new) -> "GraspSet":
        """A new GraspSet (trace, config and name kept) whose arrays are `arrays` (this set's when not given) with
        `new` added or replaced: `gs.with_arrays(sdf_s=...)` adds; `gs.with_arrays(checked)` replaces all."""
        return GraspSet({**(self._arrays if arrays is None else arrays), **new}, self.trace, self.config,
                        self.object_name)

    def select(self, idx) -> "GraspSet":
        """The grasps at `idx` (per-grasp arrays and trace columns; scalars kept)."""
        n = len(self["valid"])
        arrays = {k: (v[idx] if v.ndim and v.shape[0] == n and k not in _TEXT_ROWS else v)
                  for k, v in self._arrays.items()}
        return GraspSet(arrays, {k: v[:, idx] for k, v in self.trace.items()}, self.config, self.object_name)

    def order(self) -> np.ndarray:
        """Grasp indices in the offered order (`evaluation.ranking.ranked`): those that passed the physics check
        first when it ran (`physics.validate`), then valid ones, each group by decreasing predicted success
        (`pred_success`, `GraspConfig.rank` "auto" or "predicted") or by increasing E ("energy", or no predictor
        for the hand), ties by index: the same grasps give the same order."""
        return ranking.ranked(self._arrays)


FIELDS = tuple(k for k in GraspSet.__annotations__ if k not in _META)
"""The typed arrays of a GraspSet, in the order `synthesize` computes them."""
