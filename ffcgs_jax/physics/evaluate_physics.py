"""`fj.evaluate_physics`: the physics test of a grasp set in the public argument order (hand, object, grasps, cfg,
then keywords), its inputs checked in one line each, its result typed (`results.PhysicsResult`)."""

import os
from collections.abc import Callable

import numpy as np
import trimesh

from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.hand.spec import HandSpec, load_spec
from ffcgs_jax.physics import runner
from ffcgs_jax.physics.config import PROTOCOLS, PhysicsConfig
from ffcgs_jax.physics.results import PhysicsResult


# hand, mesh, grasps and cfg unannotated: a wrong type is refused with FfcgsError here, not by a type checker
def evaluate_grasps(hand, mesh, grasps, cfg=PhysicsConfig(), *, protocols=None,
                    progress: Callable[[int], None] | None = None, which=None, backend: str | None = None,
                    table_z: float | None = None, parts=None) -> PhysicsResult:
    """The physics test of a grasp set (`fj.evaluate_physics`), in the public argument order: hand, object, grasps,
    cfg, then keywords.

    Args:
        hand: the `Hand` the grasps were made with (`load_hand`), its `HandSpec`, or a built-in name or spec path.
        mesh: the object, in the grasps' object frame.
        grasps: a `GraspSet` (from `synthesize` or `load_grasps`) or a mapping of arrays with `wrist_pose`
            (B, 4, 4) and `q` (B, Q); its `squeeze_dir` (B, Q), when present, is the squeeze direction.
        cfg: the physics settings.
        protocols: any of `config.ALL_PROTOCOLS`, or one protocol's name; default `config.PROTOCOLS`.
        progress, backend, table_z, parts: as `evaluate`'s.
        which: the grasps to test, as indices or a (B,) boolean mask; default all.

    Returns:
        A `PhysicsResult`, one row per grasp tested, in the order of `which`: per protocol a `ProtocolOutcome`
        (`result.protocols["six-dir"].success`, ...); `result.as_arrays()` gives `evaluate`'s flat arrays.
    """
    spec = _hand_spec(hand)
    if not isinstance(mesh, trimesh.Trimesh):
        raise FfcgsError(f"mesh must be a trimesh.Trimesh (fj.load_mesh), got {type(mesh).__name__}")
    check_cfg(cfg, "evaluate_physics")
    # a GraspSet by its arrays, as `validate` reads it: physics does not import synthesis
    arrays = getattr(grasps, "arrays", grasps)
    if not hasattr(arrays, "keys") or not hasattr(arrays, "__getitem__"):
        raise FfcgsError(f"grasps must be a GraspSet or a dict of arrays with wrist_pose and q, got "
                         f"{type(grasps).__name__}")
    missing = [k for k in ("wrist_pose", "q") if k not in arrays]
    if missing:
        raise FfcgsError(f"grasps have no {' or '.join(missing)} (a GraspSet or a dict with wrist_pose (B, 4, 4) "
                         f"and q (B, Q))")
    pose, q = np.asarray(arrays["wrist_pose"]), np.asarray(arrays["q"])
    nq = len(spec.channel_names)
    if pose.ndim != 3 or pose.shape[1:] != (4, 4):
        raise FfcgsError(f"wrist_pose must have shape (B, 4, 4), got {pose.shape}")
    if q.dtype.kind not in "biuf":
        raise FfcgsError(f"q must hold real numbers, got dtype {q.dtype}")
    if q.shape != (len(pose), nq):
        raise FfcgsError(f"q must have shape ({len(pose)}, {nq}) to match {len(pose)} wrist poses and hand "
                         f"{spec.name}, got {q.shape}")
    idx = _which(which, len(pose))
    if len(idx):
        runner.check_reach(spec, mesh, pose[idx], idx)  # numbered as the caller's grasps, not as the ones tested
    squeeze = arrays.get("squeeze_dir") if hasattr(arrays, "get") else None
    if protocols is None:
        protocols = PROTOCOLS
    elif isinstance(protocols, str):
        protocols = (protocols,)
    arrays = runner.evaluate(spec, mesh, pose[idx], q[idx], cfg, protocols, backend, table_z, progress,
                      None if squeeze is None else np.asarray(squeeze)[idx], parts)
    return PhysicsResult.from_arrays(arrays, protocols, index=idx)


def check_cfg(cfg, function: str) -> None:
    """Refuse a `cfg` that is no `PhysicsConfig` in one line, naming the argument order (protocols a keyword)."""
    if not isinstance(cfg, PhysicsConfig):
        raise FfcgsError(f"cfg must be a PhysicsConfig, got {type(cfg).__name__}: {function}(hand, mesh, grasps, cfg, "
                         f"protocols=...) takes the protocols as a keyword")


def _hand_spec(hand) -> HandSpec:
    if isinstance(hand, HandSpec):
        return hand
    if isinstance(getattr(hand, "spec", None), HandSpec):
        return hand.spec
    if isinstance(hand, (str, os.PathLike)):
        return load_spec(hand)
    raise FfcgsError(f"hand must be a Hand (fj.load_hand), a hand name or a spec path, got {type(hand).__name__}")


def _which(which, n: int) -> np.ndarray:
    """`which` (None, indices or a (n,) boolean mask) as indices into n grasps."""
    if which is None:
        return np.arange(n)
    w = np.asarray(which)
    if w.dtype == bool:
        if w.shape != (n,):
            raise FfcgsError(f"which as a mask must have shape ({n},), got {w.shape}")
        return np.flatnonzero(w)
    if w.ndim > 1 or (w.size and w.dtype.kind not in "iu"):
        raise FfcgsError(f"which must be grasp indices (integers) or a boolean mask, got {w.dtype} {w.shape}")
    w = w.reshape(-1).astype(np.int64)
    if w.size and (w.min() < -n or w.max() >= n):
        raise FfcgsError(f"which holds index {int(w.max() if w.max() >= n else w.min())} out of range for "
                         f"{n} grasps")
    return w
