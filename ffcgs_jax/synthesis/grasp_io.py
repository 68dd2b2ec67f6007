"""Grasp files: `grasps.npz` (arrays, no pickles) and an MCAP log of a run (JSON messages with JSON schemas).

MCAP topics (message encoding "json", schema encoding "jsonschema"; schemas below, also in README):
    /config      one message: the resolved configuration, object name, hand name, package version.
    /iteration   one message per descent iteration t = 0..T: {"iteration": t, "E": [B], "E_g": [B], "E_c": [B]}
                 (the energies of every pose before step t; t = T is the result).
    /grasp       one message per grasp: {"index", "valid", "wrist_pose" (4x4), "q", "contacts" (Cx3), "E", "E_g",
                 "E_c", "E_q", "epsilon", "penetration"}, in the object frame, metres and radians.
    /summary     one message: the table `ffcgs grasp` prints.
Read it back with `mcap.reader.make_reader(open(path, "rb")).iter_messages()` and `json.loads(message.data)`.
"""

import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from ffcgs_jax import __version__, files

NUMBERS = {"type": "array", "items": {"type": "number"}}
SCHEMAS = {
    "/config": {"title": "ffcgs.Config", "type": "object",
                "properties": {"object": {"type": "string"}, "hand": {"type": "string"},
                               "version": {"type": "string"}, "config": {"type": "object"}},
                "required": ["object", "hand", "version", "config"]},
    "/iteration": {"title": "ffcgs.Iteration", "type": "object",
                   "properties": {"iteration": {"type": "integer"}, "E": NUMBERS, "E_g": NUMBERS, "E_c": NUMBERS},
                   "required": ["iteration", "E", "E_g", "E_c"]},
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


def save_npz(gs, path: str | Path) -> None:
    """Write a GraspSet's arrays (and its config as JSON text) to an .npz file."""
    save_arrays({"object_name": np.array(gs.object_name),
                 "config_json": np.array(json.dumps(dataclasses.asdict(gs.config))), **gs.arrays}, path)


def save_arrays(arrays: dict[str, np.ndarray], path: str | Path) -> None:
    """Write named arrays to a compressed .npz file (no pickles), atomically: a failed write leaves an existing
    file as it was. FfcgsError naming the path."""
    files.atomic_write(files.check_output(path, "grasp file"), lambda f: np.savez_compressed(f, **arrays))


def load_npz(path: str | Path) -> dict[str, np.ndarray]:
    return files.read_npz(path, "grasp file", "grasp .npz")


def write_mcap(gs, path: str | Path, hand_name: str, summary: list[tuple[str, str]]) -> None:
    """Write the run log (config, per-iteration energies of every pose, final grasps, summary) as MCAP."""
    files.atomic_write(files.check_output(path, "MCAP log"), lambda f: _write_log(f, gs, hand_name, summary))


def _write_log(f, gs, hand_name: str, summary: list[tuple[str, str]]) -> None:
    from mcap.writer import Writer

    w = Writer(f)
    w.start(profile="", library=f"ffcgs-jax {__version__}")
    ch = {}
    for topic, schema in SCHEMAS.items():
        sid = w.register_schema(name=schema["title"], encoding="jsonschema",
                                data=json.dumps(schema).encode())
        ch[topic] = w.register_channel(topic=topic, message_encoding="json", schema_id=sid)
    t = time.time_ns()

    def put(topic, msg, i):
        w.add_message(ch[topic], log_time=t + i, publish_time=t + i, sequence=i, data=json.dumps(msg).encode())

    put("/config", {"object": gs.object_name, "hand": hand_name, "version": __version__,
                    "config": dataclasses.asdict(gs.config)}, 0)
    for it in range(gs.trace["E"].shape[0]):
        put("/iteration", {"iteration": it, **{k: gs.trace[k][it].tolist() for k in ("E", "E_g", "E_c")}}, it)
    a = gs.arrays
    for i in range(len(a["valid"])):
        put("/grasp", {"index": i, "valid": bool(a["valid"][i]), "wrist_pose": a["wrist_pose"][i].tolist(),
                       "q": a["q"][i].tolist(), "contacts": a["contacts"][i].tolist(),
                       **{k: float(a[k][i]) for k in ("E", "E_g", "E_c", "E_q", "epsilon", "penetration")},
                       **({"force_closure": bool(a["force_closure"][i]), "n_contacts": int(a["n_contacts"][i]),
                           "contact_dist": a["contact_dist"][i].tolist()} if "n_contacts" in a else {})}, i)
    put("/summary", dict(summary), 0)
    w.finish()


def read_mcap(path: str | Path) -> dict[str, list[dict]]:
    """All messages of a log written by `write_mcap`, by topic, decoded from JSON."""
    from mcap.reader import make_reader

    out: dict[str, list[dict]] = {}
    with open(path, "rb") as f:
        for _, channel, message in make_reader(f).iter_messages():
            out.setdefault(channel.topic, []).append(json.loads(message.data))
    return out
