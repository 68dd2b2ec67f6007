"""Reading an MCAP file raw and checking messages against the JSON Schemas stored in it, for the tests of
`viz.grasp_log` and `ffcgs grasp --mcap`."""

import json

from mcap.reader import make_reader

_TYPES = {"object": dict, "array": list, "string": str, "boolean": bool, "number": (int, float), "integer": int}


def schema_errors(value, schema, where="$") -> list[str]:
    """The subset of JSON Schema that synthesis.grasp_log.SCHEMAS uses: type, properties, required, items,
    additionalProperties. (JSON booleans are not numbers.)"""
    errors = []
    t = schema.get("type")
    if t is not None:
        ok = isinstance(value, _TYPES[t]) and not (t in ("number", "integer") and isinstance(value, bool))
        if not ok:
            return [f"{where}: expected {t}, got {type(value).__name__}"]
    if isinstance(value, dict):
        errors += [f"{where}: missing {k!r}" for k in schema.get("required", []) if k not in value]
        props = schema.get("properties", {})
        for k, v in value.items():
            if k in props:
                errors += schema_errors(v, props[k], f"{where}.{k}")
            elif isinstance(schema.get("additionalProperties"), dict):
                errors += schema_errors(v, schema["additionalProperties"], f"{where}.{k}")
    if isinstance(value, list) and "items" in schema:
        for i, v in enumerate(value):
            errors += schema_errors(v, schema["items"], f"{where}[{i}]")
    return errors


def read_raw(path):
    """(topic -> list of decoded messages, topic -> (schema encoding, schema dict, message encoding))."""
    msgs, meta = {}, {}
    with open(path, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages():
            msgs.setdefault(channel.topic, []).append(json.loads(message.data))
            meta[channel.topic] = (schema.encoding, json.loads(schema.data), channel.message_encoding)
    return msgs, meta


def read_timed(path):
    """Every message in file order as (topic, schema name, log time ns, decoded message)."""
    with open(path, "rb") as f:
        return [(channel.topic, schema.name, message.log_time, json.loads(message.data))
                for schema, channel, message in make_reader(f).iter_messages(log_time_order=False)]


def check_run_log(path, arrays, order, iterations: int, hand_drawn: bool = True, mesh: bool = True) -> dict:
    """What every `ffcgs grasp --mcap` log must hold to play in Foxglove (viz.grasp_log's docstring): the
    schemas by name, every message valid against its schema, the scene entities and transforms, and /energy on a
    real timeline. `arrays`: the run's grasp arrays; `order`: its ranking (`GraspSet.order()`); `iterations`: T + 1.
    Returns the messages by topic."""
    import numpy as np
    from scipy.spatial.transform import Rotation

    from ffcgs_jax.viz import grasp_log
    from ffcgs_jax.viz.foxglove_schemas import SCHEMAS as FOXGLOVE

    timed = read_timed(path)
    msgs, meta = read_raw(path)
    names = {topic: name for topic, name, _, _ in timed}
    hand_topics = [f"/hand/{k}" for k in range(min(grasp_log.HANDS, len(order)))]
    assert set(msgs) == {"/config", "/scene", "/tf", "/energy", "/grasp", "/summary", *hand_topics}, set(msgs)
    for topic, (encoding, schema, message_encoding) in meta.items():
        assert encoding == "jsonschema" and message_encoding == "json", topic
        if topic in grasp_log.SCHEMAS:
            assert names[topic] == schema["title"] and schema == grasp_log.SCHEMAS[topic], topic
        else:
            want = "foxglove.FrameTransforms" if topic == "/tf" else "foxglove.SceneUpdate"
            assert names[topic] == want and schema == FOXGLOVE[want], topic
        for m in msgs[topic]:
            assert schema_errors(m, schema) == [], (topic, m)
    try:  # not a dependency; a second opinion where it is installed
        import jsonschema
    except ImportError:
        pass
    else:
        for topic, (_, schema, _) in meta.items():
            jsonschema.Draft202012Validator.check_schema(schema)
            validator = jsonschema.Draft202012Validator(schema)
            for m in msgs[topic]:
                validator.validate(m)

    # the timeline: one iteration every STEP_NS (> 1 ms), strictly increasing, the rest at its ends
    times = {topic: [t for tp, _, t, _ in timed if tp == topic] for topic in msgs}
    e_times = np.array(times["/energy"], np.int64)
    assert len(e_times) == iterations and [m["iteration"] for m in msgs["/energy"]] == list(range(iterations))
    steps = np.diff(e_times)
    assert (steps > 0).all() and (steps == grasp_log.STEP_NS).all() and grasp_log.STEP_NS > 1_000_000
    assert e_times[-1] - e_times[0] > 1_000_000 * (iterations - 1)
    assert times["/config"] == times["/scene"] == [e_times[0]] and times["/tf"][0] == e_times[0]
    assert set(times["/grasp"]) == set(times["/summary"]) == {e_times[-1]}
    assert [t for _, _, t, _ in timed] == sorted(t for _, _, t, _ in timed)  # written in log-time order

    entities = {e["id"]: e for e in msgs["/scene"][0]["entities"]}
    assert set(entities) == ({"object", "table"} if mesh else {"table"})
    if mesh:
        tri = entities["object"]["triangles"][0]
        assert entities["object"]["frame_id"] == "object" and len(tri["points"]) >= 4
        assert len(tri["indices"]) % 3 == 0 and 0 < max(tri["indices"]) < len(tri["points"])
    assert entities["table"]["frame_id"] == "world" and len(entities["table"]["cubes"]) == 1

    tf = {(x["parent_frame_id"], x["child_frame_id"]): x for x in msgs["/tf"][0]["transforms"]}
    assert set(tf) == {("world", "object")} | {("object", f"wrist_{i}") for i in range(len(arrays["valid"]))}
    for i, H in enumerate(arrays["wrist_pose"]):
        x = tf[("object", f"wrist_{i}")]
        r = x["rotation"]
        np.testing.assert_allclose([x["translation"][k] for k in "xyz"], H[:3, 3], atol=1e-12)
        np.testing.assert_allclose(Rotation.from_quat([r[k] for k in "xyzw"]).as_matrix(), H[:3, :3], atol=1e-6)

    for k, topic in enumerate(hand_topics):
        i = int(order[k])
        last = {e["id"]: e for e in msgs[topic][-1]["entities"]}
        assert set(last) == ({"hand", "contacts"} if hand_drawn else {"contacts"}), topic
        if hand_drawn:
            hand = last["hand"]
            assert hand["frame_id"] == f"wrist_{i}" and hand["frame_locked"]
            assert len(hand["cubes"]) + len(hand["cylinders"]) >= 10 and hand["spheres"] and hand["texts"]
            assert {m["key"]: m["value"] for m in hand["metadata"]}["grasp"] == str(i)
        got = [[s["pose"]["position"][c] for c in "xyz"] for s in last["contacts"]["spheres"]]
        assert last["contacts"]["frame_id"] == "object"
        np.testing.assert_allclose(got, arrays["contacts"][i], atol=1e-12)
    return msgs
