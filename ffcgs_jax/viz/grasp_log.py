"""The MCAP log of a run, which Foxglove plays back (`ffcgs grasp --mcap`).

The log's messages are JSON (message encoding "json") with JSON-Schema schemas (schema encoding "jsonschema"). The
scene topics use Foxglove's well-known schemas (`viz.foxglove_schemas`), so Foxglove's 3D panel draws the object,
the table and the best hands, and its plot panel draws /energy against the log time.

Timeline: the run's start S (ns since the epoch: the time of writing less the run's `total_s`), then one descent
iteration every `STEP_NS` = 10 ms: iteration t is logged at S + t * STEP_NS, so a run of T iterations spans
T * 10 ms. The result (t = T) is at S + T * STEP_NS.

Topics (schema name in brackets):
    /config      [ffcgs.Config] at S: the resolved configuration, object name, hand name, package version.
    /scene       [foxglove.SceneUpdate] at S: entity "object" (the mesh as a TriangleListPrimitive, frame
                 "object") and entity "table" (a thin cube whose top is the table plane, frame "world").
    /tf          [foxglove.FrameTransforms] at S: "world" -> "object" (identity: the object frame is the world's)
                 and "object" -> "wrist_<i>" (grasp i's wrist pose) for every grasp i.
    /hand/<k>    [foxglove.SceneUpdate] for the k-th best grasp (k = 0..K-1, `GraspSet.order`; K = `hands`):
                 entity "hand" (the hand's collision geoms as cubes / spheres / cylinders, posed by forward
                 kinematics, frame "wrist_<i>", frame-locked, with a label and metadata), entity "contacts" (the
                 fingertip contact points as spheres, frame "object"). At S: the result. When the GraspSet's trace
                 also holds per-iteration "q" (T+1, B, Q), "wrist_pose" (T+1, B, 4, 4) or fingertip "tips"
                 (T+1, B, C, 3), the hands, their wrist transforms (on /tf) and the contacts are logged at up to
                 `MAX_FRAMES` iterations instead (`synthesis.grasp` keeps energies only, so a run shows the result).
    /energy      [ffcgs.Energy] one message per descent iteration t = 0..T, at S + t * STEP_NS: {"iteration": t,
                 "E", "E_g", "E_c": [B] (every pose, before step t; t = T is the result), "E_min", "E_median",
                 "E_g_median", "E_c_median"}. Plot `/energy.E_median` or `/energy.E[3]` against the log time.
    /grasp       [ffcgs.Grasp] at S + T * STEP_NS, one message per grasp: {"index", "valid", "wrist_pose" (4x4),
                 "q", "contacts" (Cx3), "E", "E_g", "E_c", "E_q", "epsilon", "penetration", ...}, object frame,
                 metres and radians.
    /summary     [ffcgs.Summary] at S + T * STEP_NS: the table `ffcgs grasp` prints.
Read it back with `read_mcap`, or `mcap.reader.make_reader(open(path, "rb")).iter_messages()` and
`json.loads(message.data)`.
"""

import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from ffcgs_jax.core import files
from ffcgs_jax.core.version import __version__

NUMBERS = {"type": "array", "items": {"type": "number"}}
SCHEMAS = {
    "/config": {"title": "ffcgs.Config", "type": "object",
                "properties": {"object": {"type": "string"}, "hand": {"type": "string"},
                               "version": {"type": "string"}, "config": {"type": "object"}},
                "required": ["object", "hand", "version", "config"]},
    "/energy": {"title": "ffcgs.Energy", "type": "object",
                "description": "Energies of every pose before descent step `iteration` (the last one: the result)",
                "properties": {"iteration": {"type": "integer"}, "E": NUMBERS, "E_g": NUMBERS, "E_c": NUMBERS,
                               **{k: {"type": "number"} for k in ("E_min", "E_median", "E_g_median",
                                                                   "E_c_median")}},
                "required": ["iteration", "E", "E_g", "E_c", "E_min", "E_median", "E_g_median", "E_c_median"]},
    "/grasp": {"title": "ffcgs.Grasp", "type": "object",
               "properties": {"index": {"type": "integer"}, "valid": {"type": "boolean"},
                              "wrist_pose": {"type": "array", "items": NUMBERS}, "q": NUMBERS,
                              "contacts": {"type": "array", "items": NUMBERS},
                              **{k: {"type": "number"} for k in ("E", "E_g", "E_c", "E_q", "epsilon",
                                                                 "penetration")},
                              "force_closure": {"type": "boolean"}, "n_contacts": {"type": "integer"},
                              "contact_dist": NUMBERS},
               "required": ["index", "valid", "wrist_pose", "q", "contacts", "E", "E_g", "E_c"]},
    "/summary": {"title": "ffcgs.Summary", "type": "object", "additionalProperties": {"type": "string"}},
}
"""The package's own topics' JSON schemas; the scene topics use `viz.foxglove_schemas`."""

SCENE_SCHEMAS = {"/scene": "foxglove.SceneUpdate", "/tf": "foxglove.FrameTransforms"}
"""Scene topics and their Foxglove schema names; the /hand/<k> topics are foxglove.SceneUpdate too."""

STEP_NS = 10_000_000
"""Log-time step between descent iterations (10 ms): T iterations span T * 10 ms of Foxglove's timeline."""

HANDS = 4
"""Grasps drawn with their hand, best first."""

MAX_FRAMES = 200
"""At most this many iterations get hand poses when the trace has them (evenly spaced, first and last included)."""


def write_mcap(gs, path: str | Path, hand, summary: list[tuple[str, str]], mesh=None, hands: int = HANDS) -> None:
    """Write the run log (module docstring) as MCAP.

    `hand`: the `hand.kinematics.Hand` the grasps were made with (its name alone draws no hands: wrist frames and
    contacts only). `mesh`: the object's trimesh in the object frame (none: no object entity). The table is at
    `gs["table_z"]` when the run has one (depth input), else at the mesh's lowest point."""
    files.atomic_write(files.check_output(path, "MCAP log"),
                       lambda f: _write_log(f, gs, hand, summary, mesh, hands))


def _hand_name(hand) -> str:
    return hand if isinstance(hand, str) else hand.spec.name


def _log_messages(gs, hand, summary, mesh, hands: int, start: int) -> list[tuple[int, str, dict]]:
    """(log time ns, topic, message) of the whole log, in no particular order."""
    from ffcgs_jax.viz import foxglove_scene as fx

    a, trace = gs.arrays, gs.trace
    T1 = trace["E"].shape[0]
    at = lambda t: start + int(t) * STEP_NS  # noqa: E731
    end = at(T1 - 1)
    out = [(start, "/config", {"object": gs.object_name, "hand": _hand_name(hand), "version": __version__,
                               "config": dataclasses.asdict(gs.config)})]
    scene = []
    if mesh is not None:
        scene.append(fx.object_entity(start, mesh))
    lo, hi = (mesh.bounds if mesh is not None else (a["contacts"].reshape(-1, 3).min(0),
                                                     a["contacts"].reshape(-1, 3).max(0)))
    table_z = float(a["table_z"]) if "table_z" in a else (float(mesh.bounds[0, 2]) if mesh is not None else None)
    if table_z is not None:
        scene.append(fx.table_entity(start, lo, hi, table_z))
    out.append((start, "/scene", fx.scene_update(scene)))
    poses = a["wrist_pose"]
    out.append((start, "/tf", {"transforms": [fx.frame_transform(start, "world", "object", np.eye(4))] + [
        fx.frame_transform(start, "object", f"wrist_{i}", poses[i]) for i in range(len(poses))]}))

    geometry = None if isinstance(hand, str) else fx.HandGeometry(hand)
    frames = (np.unique(np.linspace(0, T1 - 1, min(T1, MAX_FRAMES)).round().astype(int))
              if "q" in trace or "wrist_pose" in trace or "tips" in trace else np.array([0]))
    for k, i in enumerate(gs.order()[:hands]):
        i, valid = int(i), bool(a["valid"][i])
        rgba = fx.HAND_RGBA if valid else fx.INVALID_HAND_RGBA
        meta = {"grasp": i, "rank": k, "valid": valid, **{n: f"{float(a[n][i]):.6g}" for n in
                                                            ("E", "E_g", "E_c", "epsilon") if n in a}}
        label = f"#{k}: grasp {i}, {'valid' if valid else 'invalid'}, E = {float(a['E'][i]):.3f}"
        for t in frames:
            ents = []
            if geometry is not None:
                q = trace["q"][t, i] if "q" in trace else a["q"][i]
                ents.append(fx.entity(at(t), f"wrist_{i}", "hand", frame_locked=True, metadata=meta,
                                      texts=[fx.text((0, 0, 0), label)], **geometry.primitives(q, rgba)))
            if "tips" in trace or t == frames[-1]:
                tips = trace["tips"][t, i] if "tips" in trace else a["contacts"][i]
                ents.append(fx.entity(at(t), "object", "contacts", spheres=fx.contact_spheres(tips),
                                      metadata={"grasp": i}))
            out.append((at(t), f"/hand/{k}", fx.scene_update(ents)))
            if "wrist_pose" in trace:
                out.append((at(t), "/tf", {"transforms": [fx.frame_transform(at(t), "object", f"wrist_{i}",
                                                                             trace["wrist_pose"][t, i])]}))
    for t in range(T1):
        e = {k: np.asarray(trace[k][t], np.float64) for k in ("E", "E_g", "E_c")}
        out.append((at(t), "/energy", {"iteration": t, **{k: v.tolist() for k, v in e.items()},
                                       "E_min": float(e["E"].min()), "E_median": float(np.median(e["E"])),
                                       "E_g_median": float(np.median(e["E_g"])),
                                       "E_c_median": float(np.median(e["E_c"]))}))
    for i in range(len(a["valid"])):
        out.append((end, "/grasp", {
            "index": i, "valid": bool(a["valid"][i]), "wrist_pose": a["wrist_pose"][i].tolist(),
            "q": a["q"][i].tolist(), "contacts": a["contacts"][i].tolist(),
            **{k: float(a[k][i]) for k in ("E", "E_g", "E_c", "E_q", "epsilon", "penetration")},
            **({"force_closure": bool(a["force_closure"][i]), "n_contacts": int(a["n_contacts"][i]),
                "contact_dist": a["contact_dist"][i].tolist()} if "n_contacts" in a else {})}))
    out.append((end, "/summary", dict(summary)))
    return out


def _write_log(f, gs, hand, summary: list[tuple[str, str]], mesh, hands: int) -> None:
    from mcap.writer import Writer

    from ffcgs_jax.viz.foxglove_schemas import SCHEMAS as FOXGLOVE

    start = time.time_ns() - int(round(float(gs.arrays.get("total_s", 0.0)) * 1e9))
    msgs = sorted(_log_messages(gs, hand, summary, mesh, hands, start), key=lambda m: m[0])  # stable
    w = Writer(f)
    w.start(profile="", library=f"ffcgs-jax {__version__}")
    schema_ids, channels, sequence = {}, {}, {}

    def channel(topic: str) -> int:
        if topic not in channels:
            schema = SCHEMAS.get(topic) or FOXGLOVE[SCENE_SCHEMAS.get(topic, "foxglove.SceneUpdate")]
            name = schema["title"]
            if name not in schema_ids:
                schema_ids[name] = w.register_schema(name=name, encoding="jsonschema",
                                                     data=json.dumps(schema).encode())
            channels[topic] = w.register_channel(topic=topic, message_encoding="json", schema_id=schema_ids[name])
        return channels[topic]

    for ns, topic, msg in msgs:
        seq = sequence[topic] = sequence.get(topic, -1) + 1
        w.add_message(channel(topic), log_time=ns, publish_time=ns, sequence=seq, data=_json(msg))
    w.finish()


def _json(msg) -> bytes:
    """Strict JSON (what Foxglove parses): a non-finite number, which JSON cannot hold, is written as null."""
    try:
        return json.dumps(msg, allow_nan=False).encode()
    except ValueError:
        return json.dumps(_finite(msg), allow_nan=False).encode()


def _finite(x):
    if isinstance(x, float):
        return x if np.isfinite(x) else None
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_finite(v) for v in x]
    return x


def read_mcap(path: str | Path) -> dict[str, list[dict]]:
    """All messages of a log written by `write_mcap`, by topic, decoded from JSON."""
    from mcap.reader import make_reader

    out: dict[str, list[dict]] = {}
    with open(path, "rb") as f:
        for _, channel, message in make_reader(f).iter_messages():
            out.setdefault(channel.topic, []).append(json.loads(message.data))
    return out
