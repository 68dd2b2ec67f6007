"""Reading an MCAP file raw and checking messages against the JSON Schemas stored in it, for the tests of
`synthesis.grasp_io` and `ffcgs grasp --mcap`."""

import json

from mcap.reader import make_reader

_TYPES = {"object": dict, "array": list, "string": str, "boolean": bool, "number": (int, float), "integer": int}


def schema_errors(value, schema, where="$") -> list[str]:
    """The subset of JSON Schema that synthesis.grasp_io.SCHEMAS uses: type, properties, required, items,
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
