"""mcap's decoder hook for dataset files, so a plain MCAP reader hands out numpy arrays:

    from mcap.reader import make_reader
    from ffcgs_jax.dataset.decoder import DecoderFactory

    with open("train.mcap", "rb") as f:
        for schema, channel, message, decoded in make_reader(
                f, decoder_factories=[DecoderFactory()]).iter_decoded_messages():
            ...  # /config: the config dict; /sdf, /grasps: {"meta": {...}, "arrays": {name: np.ndarray}}

It decodes the /sdf and /grasps messages of both encodings (`schema` module docstring: JSON with base64 arrays, and
the older "ffcgs.arrays.v1") and the /config message; any other channel is left to the reader's other factories.
Imports numpy and mcap only.
"""

import json
from collections.abc import Callable
from typing import Any

from mcap.decoder import DecoderFactory as _McapDecoderFactory
from mcap.records import Schema

from ffcgs_jax.dataset.schema import ARRAYS_ENCODING, LEGACY_ENCODING, SCHEMAS, decode_message

_ARRAY_SCHEMAS = {SCHEMAS["/sdf"]["title"], SCHEMAS["/grasps"]["title"]}


class DecoderFactory(_McapDecoderFactory):
    """Decoders for the dataset's channels, chosen by message encoding and schema name."""

    def decoder_for(self, message_encoding: str, schema: Schema | None) -> Callable[[bytes], Any] | None:
        if schema is None:
            return None
        if schema.name in _ARRAY_SCHEMAS and message_encoding in (ARRAYS_ENCODING, LEGACY_ENCODING):
            def decode(data) -> dict:
                meta, arrays = decode_message(data, message_encoding, f"{schema.name} message")
                return {"meta": meta, "arrays": arrays}

            return decode
        if schema.name == SCHEMAS["/config"]["title"] and message_encoding == "json":
            return json.loads
        return None
