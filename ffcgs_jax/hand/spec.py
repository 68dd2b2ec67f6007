"""Hand specs: which MJCF sites, joints and channels the grasp pipeline uses (host side, no JAX).

A hand is data, not code: any MJCF hand works given a small TOML spec next to it::

    name = "toy"
    mjcf = "toy.xml"                      # relative to the TOML file
    root_body = "palm"                    # the body the wrist pose moves (must hang from the world, no joint)
    contact_sites = ["tip_a", "tip_b"]    # one site per fingertip contact, in order
    palm_site = "palm"                    # palm frame
    palm_normal = [0, 1, 0]               # the direction the palm faces, in the root body frame
    tetrahedron_sites = ["t0", "t1", "t2", "t3"]   # 4 palm points (the sampler's pose loss)

    [channels]                            # the actuated channels q, in order
    names = ["a", "b"]
    lower = [0, 0]
    upper = [1, 1]

    [coupling]                            # qpos[joints[i]] = sum_k matrix[i][k] * q[k]
    joints = ["ja", "jb", "jb2"]
    matrix = [[1, 0], [0, 1], [0, 0.5]]

Every MJCF hinge/slide joint must appear in `coupling.joints` (a joint left out would have no defined angle), every
joint needs a non-zero row and every channel a non-zero column of the matrix, each contact site must ride on a body
that a joint moves, and the hand needs collision geoms (contype or conaffinity non-zero). A spec that breaks a rule
is refused with one `FfcgsError` line naming the spec file and the problem. docs/custom_hand.md is the user's guide.
"""

import dataclasses
from importlib import resources
from pathlib import Path

import mujoco
import numpy as np

from ffcgs_jax.core.config import read_toml
from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.core.files import read_text

_TOP_KEYS = {"name", "mjcf", "root_body", "contact_sites", "palm_site", "palm_normal", "tetrahedron_sites",
             "channels", "coupling"}
_CHANNEL_KEYS = {"names", "lower", "upper"}
_COUPLING_KEYS = {"joints", "matrix"}
BUILTIN_HANDS = ("svh", "allegro")


@dataclasses.dataclass(frozen=True)
class HandSpec:
    """A validated hand spec. Tuples only, so it hashes and can sit in a jit-static field."""

    name: str
    mjcf_path: str
    root_body: str
    contact_sites: tuple[str, ...]
    palm_site: str
    palm_normal: tuple[float, float, float]
    tetrahedron_sites: tuple[str, ...]
    channel_names: tuple[str, ...]
    lower: tuple[float, ...]
    upper: tuple[float, ...]
    coupling_joints: tuple[str, ...]
    coupling: tuple[tuple[float, ...], ...]

    def mj_model(self) -> mujoco.MjModel:
        """Compile the MJCF (a fresh MjModel each call: callers may edit it)."""
        try:
            return mujoco.MjModel.from_xml_path(self.mjcf_path)
        except ValueError as e:
            detail = "; ".join(line.strip() for line in str(e).splitlines() if line.strip())  # MuJoCo's are 2 lines
            raise FfcgsError(f"MJCF {self.mjcf_path} does not compile: {detail}") from None


def builtin_spec_path(name: str) -> Path:
    if name not in BUILTIN_HANDS:
        raise FfcgsError(f"unknown built-in hand {name!r}; built-in hands: {', '.join(BUILTIN_HANDS)}")
    return Path(str(resources.files("ffcgs_jax.hand") / "assets" / name / f"{name}.toml"))


def load_spec(source: str | Path = "svh") -> HandSpec:
    """Read and validate a hand spec: a built-in name ("svh") or a path to a TOML file."""
    path = Path(source)
    if path.suffix != ".toml":
        path = builtin_spec_path(str(source))
    raw = read_toml(path, "hand spec")
    where = f"hand spec {path}"
    _keys(raw, _TOP_KEYS, where, required=_TOP_KEYS)
    _keys(raw["channels"], _CHANNEL_KEYS, f"{where} [channels]", required=_CHANNEL_KEYS)
    _keys(raw["coupling"], _COUPLING_KEYS, f"{where} [coupling]", required=_COUPLING_KEYS)
    mjcf = (path.parent / _string(raw["mjcf"], f"{where} mjcf")).resolve()
    try:
        read_text(mjcf, "mjcf file")  # MuJoCo's own words for a folder or a binary file are obscure
    except FfcgsError as e:
        raise FfcgsError(f"{where}: {e}") from None
    ch = raw["channels"]
    names = _strings(ch["names"], f"{where} [channels] names")
    lower = _floats(ch["lower"], f"{where} [channels] lower")
    upper = _floats(ch["upper"], f"{where} [channels] upper")
    if not (len(names) == len(lower) == len(upper)) or not names:
        raise FfcgsError(f"{where}: [channels] names/lower/upper must be non-empty and of equal length, "
                         f"got {len(names)}/{len(lower)}/{len(upper)}")
    bad = [n for n, lo, hi in zip(names, lower, upper) if not lo < hi]
    if bad:
        raise FfcgsError(f"{where}: channel(s) {bad} need lower < upper")
    joints = _strings(raw["coupling"]["joints"], f"{where} [coupling] joints")
    matrix = raw["coupling"]["matrix"]
    shape = (len(joints), len(names))
    if not isinstance(matrix, list) or len(matrix) != shape[0] \
            or any(not isinstance(r, list) or len(r) != shape[1] for r in matrix):
        got = (len(matrix), sorted({len(r) if isinstance(r, list) else -1 for r in matrix}))
        raise FfcgsError(f"{where}: [coupling] matrix must be {shape[0]}x{shape[1]} (joints x channels), "
                         f"got {got[0]} rows of lengths {got[1]}")
    normal = _floats(raw["palm_normal"], f"{where} palm_normal")
    if len(normal) != 3 or not np.linalg.norm(normal) > 0:
        raise FfcgsError(f"{where}: palm_normal must be a non-zero 3-vector, got {list(normal)}")
    tet = _strings(raw["tetrahedron_sites"], f"{where} tetrahedron_sites")
    if len(tet) != 4:
        raise FfcgsError(f"{where}: tetrahedron_sites must name exactly 4 sites, got {len(tet)}")
    spec = HandSpec(
        name=_string(raw["name"], f"{where} name"), mjcf_path=str(mjcf),
        root_body=_string(raw["root_body"], f"{where} root_body"),
        contact_sites=_strings(raw["contact_sites"], f"{where} contact_sites"),
        palm_site=_string(raw["palm_site"], f"{where} palm_site"),
        palm_normal=tuple(float(v) / float(np.linalg.norm(normal)) for v in normal),
        tetrahedron_sites=tet, channel_names=names, lower=lower, upper=upper, coupling_joints=joints,
        coupling=tuple(_floats(r, f"{where} [coupling] matrix") for r in matrix),
    )
    try:
        m = spec.mj_model()
    except FfcgsError as e:
        raise FfcgsError(f"{where}: {e}") from None
    _check_names(spec, m, where)
    return spec


def _check_names(spec: HandSpec, m: mujoco.MjModel, where: str) -> None:
    def names(objtype, n):
        return {mujoco.mj_id2name(m, objtype, i) for i in range(n)}

    sites = names(mujoco.mjtObj.mjOBJ_SITE, m.nsite)
    for field in ("contact_sites", "tetrahedron_sites", "palm_site"):
        val = getattr(spec, field)
        unknown = [s for s in ((val,) if isinstance(val, str) else val) if s not in sites]
        if unknown:
            raise FfcgsError(f"{where}: {field} names unknown site(s) {unknown}; sites in the MJCF: "
                             f"{', '.join(sorted(s for s in sites if s))}")
    if not spec.contact_sites:
        raise FfcgsError(f"{where}: contact_sites is empty")
    bodies = names(mujoco.mjtObj.mjOBJ_BODY, m.nbody)
    if spec.root_body not in bodies:
        raise FfcgsError(f"{where}: root_body {spec.root_body!r} is not a body of the MJCF; bodies: "
                         f"{', '.join(sorted(b for b in bodies if b))}")
    root = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, spec.root_body)
    if m.body_parentid[root] != 0 or m.body_jntnum[root] != 0:
        raise FfcgsError(f"{where}: root_body {spec.root_body!r} must be a child of the world with no joint "
                         "(the wrist pose places it)")
    joints = names(mujoco.mjtObj.mjOBJ_JOINT, m.njnt)
    unknown = [j for j in spec.coupling_joints if j not in joints]
    if unknown:
        raise FfcgsError(f"{where}: [coupling] joints names unknown joint(s) {unknown}; joints in the MJCF: "
                         f"{', '.join(sorted(joints))}")
    if len(set(spec.coupling_joints)) != len(spec.coupling_joints):
        raise FfcgsError(f"{where}: [coupling] joints lists a joint twice")
    missing = sorted(joints - set(spec.coupling_joints))
    if missing:
        raise FfcgsError(f"{where}: MJCF joint(s) {missing} are not in [coupling] joints")
    bad_type = [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, j) for j in range(m.njnt)
                if int(m.jnt_type[j]) not in (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE))]
    if bad_type:
        raise FfcgsError(f"{where}: only hinge/slide joints are supported, not {bad_type}")
    _check_structure(spec, m, root, where)


def _check_structure(spec: HandSpec, m: mujoco.MjModel, root: int, where: str) -> None:
    """What the names alone do not show: fingertips that cannot move, joints or channels the coupling leaves out,
    a hand without collision geoms. Runs after `_check_names`, so every name resolves."""
    for s in spec.contact_sites:
        site_body = b = int(m.site_bodyid[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, s)])
        moved = False
        while b not in (0, root):  # up to the root (or the world, for a site off the hand)
            moved = moved or m.body_jntnum[b] > 0
            b = int(m.body_parentid[b])
        if not moved:
            body = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, site_body) or f"#{site_body}"
            raise FfcgsError(f"{where}: contact site {s!r} is on body {body!r}, which no joint moves (the root body, "
                             "the world, or welded to them by joint-less bodies); put it on a fingertip body")
    matrix = np.asarray(spec.coupling, float).reshape(len(spec.coupling_joints), len(spec.channel_names))
    undriven = [j for j, row in zip(spec.coupling_joints, matrix) if not np.any(row)]
    if undriven:
        raise FfcgsError(f"{where}: [coupling] matrix leaves joint(s) {undriven} undriven (all-zero row); give each "
                         "joint a non-zero entry for the channel that moves it")
    idle = [c for c, col in zip(spec.channel_names, matrix.T) if not np.any(col)]
    if idle:
        raise FfcgsError(f"{where}: channel(s) {idle} drive no joint (all-zero column of [coupling] matrix); "
                         "remove them from [channels] or give them a non-zero entry")
    if not any(m.geom_bodyid[g] != 0 and (m.geom_contype[g] or m.geom_conaffinity[g]) for g in range(m.ngeom)):
        raise FfcgsError(f"{where}: the hand has no collision geoms (no geom with contype or conaffinity on a "
                         "non-world body); the penetration penalty and the physics test need collision geoms")


def _keys(table: dict, valid: set[str], where: str, required: set[str]) -> None:
    if not isinstance(table, dict):
        raise FfcgsError(f"{where} must be a table")
    unknown = sorted(set(table) - valid)
    if unknown:
        raise FfcgsError(f"{where}: unknown key(s) {unknown}; valid keys: {', '.join(sorted(valid))}")
    missing = sorted(required - set(table))
    if missing:
        raise FfcgsError(f"{where}: missing key(s) {missing}")


def _string(value, where: str) -> str:
    if not isinstance(value, str):
        raise FfcgsError(f"{where} must be a string, got {value!r}")
    return value


def _strings(values, where: str) -> tuple[str, ...]:
    if not isinstance(values, list) or not all(isinstance(v, str) for v in values):
        raise FfcgsError(f"{where} must be a list of strings, got {values!r}")
    return tuple(values)


def _floats(values, where: str) -> tuple[float, ...]:
    if not isinstance(values, list) or any(isinstance(v, bool) or not isinstance(v, (int, float)) for v in values):
        raise FfcgsError(f"{where} must be a list of numbers, got {values!r}")
    try:
        out = tuple(float(v) for v in values)
    except (TypeError, ValueError, OverflowError):
        raise FfcgsError(f"{where} must be a list of numbers, got {values!r}") from None
    if not all(np.isfinite(out)):
        raise FfcgsError(f"{where} must be finite, got {list(out)}")
    return out
