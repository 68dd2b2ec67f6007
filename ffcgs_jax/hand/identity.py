"""What a hand is, as one hash: the learned parts of a hand (CVAE sampler, success predictor) record it, and
weights learned for another version of the hand are refused in one line instead of sampling grasps for a hand
that no longer exists.

`spec_sha256` covers the spec's fields (the sites, channels, limits and coupling the pipeline reads; not where the
files lie) and the compiled MJCF's kinematic and collision numbers (bodies, joints, sites, collision geoms),
rounded to 6 significant digits (a micrometre of a link, far above float noise and the
compilers of MuJoCo releases): a moved or re-saved file is the same hand, a longer link, a new limit or a larger
fingertip is not. Inertias and other numbers the grasp pipeline never reads are left out.

`cli.grasp_many.hand_sha256` hashes the same hand exactly (`mj_saveModel`'s bytes): a many-object run's resume
key must change with anything the synthesis sees, even a MuJoCo release's compiler; weights must not be refused
for that.
"""

import dataclasses
import functools
import hashlib
import json
from pathlib import Path

import numpy as np

from ffcgs_jax.hand.spec import HandSpec

_MODEL_FIELDS = ("body_parentid", "body_pos", "body_quat", "jnt_type", "jnt_bodyid", "jnt_axis", "jnt_pos",
                 "site_bodyid", "site_pos", "site_quat", "geom_bodyid", "geom_type", "geom_size", "geom_pos",
                 "geom_quat", "geom_contype", "geom_conaffinity")


def spec_sha256(spec: HandSpec) -> str:
    """The hand's identity (module docstring), hex."""
    path = Path(spec.mjcf_path)
    return _hash(spec, path.stat().st_mtime_ns if path.exists() else 0)


@functools.lru_cache(maxsize=16)
def _hash(spec: HandSpec, mtime_ns: int) -> str:  # keyed by the MJCF's mtime: an edited file is hashed again
    fields = {k: v for k, v in dataclasses.asdict(spec).items() if k != "mjcf_path"}
    m = spec.mj_model()
    numbers = {f: _rounded(getattr(m, f)) for f in _MODEL_FIELDS}
    text = json.dumps({"spec": fields, "model": numbers}, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


def _rounded(a) -> list:
    a = np.asarray(a)
    if a.dtype.kind == "f":
        return [float(f"{x:.6g}") + 0.0 for x in a.ravel()]  # + 0.0: -0.0 and 0.0 are one number
    return a.ravel().tolist()
