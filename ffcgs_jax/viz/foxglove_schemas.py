"""Foxglove's well-known message schemas, in the JSON Schema form Foxglove uses for JSON-encoded MCAP channels.

Foxglove's 3D panel renders a channel when its schema *name* is one of its well-known schemas (`foxglove.SceneUpdate`,
`foxglove.FrameTransforms`, ...) and its messages have that schema's fields. For the "json" message encoding the
schema is a JSON Schema (schema encoding "jsonschema"). The schemas below are written from the field tables of
Foxglove's schema reference (docs.foxglove.dev, "Message schemas": SceneUpdate, SceneEntity, SceneEntityDeletion,
the eight primitives, FrameTransform(s), and the built-in types), following the conventions of the JSON schemas
Foxglove generates for them:

* one self-contained object schema per message, nested types written inline (no `$ref`), each titled with its
  Foxglove name (`foxglove.Pose`, ...);
* `time` and `duration` are objects {sec, nsec} (integers; nsec in [0, 1e9); a time's sec >= 0);
* float64 is "number", uint32 is "integer" >= 0, boolean and string as such;
* enums are integers, listed as `oneOf` constants with their names (LineType, SceneEntityDeletionType);
* `bytes` are base64 strings (`contentEncoding: base64`);
* every field of a message is listed as required.

The messages `viz.foxglove_scene` builds carry every field (an empty list where there is nothing): Foxglove's panels
fill no defaults into a JSON message. Checked once, field by field (descriptions aside), against the JSON schemas of
the @foxglove/schemas 2.1.0 npm package: the same titles, types, bounds, enums and required fields.
"""

NUMBER = {"type": "number"}
STRING = {"type": "string"}
BOOLEAN = {"type": "boolean"}
UINT32 = {"type": "integer", "minimum": 0}


def _message(title: str, description: str, fields: dict[str, dict]) -> dict:
    """An object schema with every field required (see the module docstring)."""
    return {"title": title, "description": description, "type": "object",
            "properties": fields, "required": list(fields)}


def _field(schema: dict, description: str) -> dict:
    return {**schema, "description": description}


def _array(items: dict, description: str) -> dict:
    return {"type": "array", "items": items, "description": description}


def _enum(title: str, description: str, values: list[tuple[str, int, str]]) -> dict:
    return {"title": title, "description": description,
            "oneOf": [{"title": name, "const": value, "description": text} for name, value, text in values]}


TIME = {"title": "time", "type": "object",
        "properties": {"sec": {"type": "integer", "minimum": 0, "description": "seconds since the epoch"},
                       "nsec": {"type": "integer", "minimum": 0, "maximum": 999_999_999,
                                "description": "additional nanoseconds"}}}

DURATION = {"title": "duration", "type": "object",
            "properties": {"sec": {"type": "integer", "description": "seconds offset"},
                           "nsec": {"type": "integer", "minimum": 0, "maximum": 999_999_999,
                                    "description": "nanoseconds offset (positive direction)"}}}

VECTOR3 = _message("foxglove.Vector3", "A vector in 3D space that represents a direction only",
                   {"x": _field(NUMBER, "x coordinate length"), "y": _field(NUMBER, "y coordinate length"),
                    "z": _field(NUMBER, "z coordinate length")})

POINT3 = _message("foxglove.Point3", "A point representing a position in 3D space",
                  {"x": _field(NUMBER, "x coordinate position"), "y": _field(NUMBER, "y coordinate position"),
                   "z": _field(NUMBER, "z coordinate position")})

QUATERNION = _message("foxglove.Quaternion", "A quaternion representing a rotation in 3D space",
                      {k: _field(NUMBER, f"{k} value") for k in ("x", "y", "z", "w")})

POSE = _message("foxglove.Pose", "A position and orientation for an object or reference frame in 3D space",
                {"position": _field(VECTOR3, "Point denoting position in 3D space"),
                 "orientation": _field(QUATERNION, "Quaternion denoting orientation in 3D space")})

COLOR = _message("foxglove.Color", "A color in RGBA format",
                 {k: _field(NUMBER, f"{name} value between 0 and 1")
                  for k, name in (("r", "Red"), ("g", "Green"), ("b", "Blue"), ("a", "Alpha"))})

KEY_VALUE_PAIR = _message("foxglove.KeyValuePair", "A key with its associated value",
                          {"key": _field(STRING, "Key"), "value": _field(STRING, "Value")})

ARROW_PRIMITIVE = _message("foxglove.ArrowPrimitive", "A primitive representing an arrow", {
    "pose": _field(POSE, "Position of the arrow's tail and orientation of the arrow. Identity orientation means "
                         "the arrow points in the +x direction."),
    "shaft_length": _field(NUMBER, "Length of the arrow shaft"),
    "shaft_diameter": _field(NUMBER, "Diameter of the arrow shaft"),
    "head_length": _field(NUMBER, "Length of the arrow head"),
    "head_diameter": _field(NUMBER, "Diameter of the arrow head"),
    "color": _field(COLOR, "Color of the arrow")})

CUBE_PRIMITIVE = _message("foxglove.CubePrimitive", "A primitive representing a cube or rectangular prism", {
    "pose": _field(POSE, "Position of the center of the cube and orientation of the cube"),
    "size": _field(VECTOR3, "Size of the cube along each axis"),
    "color": _field(COLOR, "Color of the cube")})

SPHERE_PRIMITIVE = _message("foxglove.SpherePrimitive", "A primitive representing a sphere or ellipsoid", {
    "pose": _field(POSE, "Position of the center of the sphere and orientation of the sphere"),
    "size": _field(VECTOR3, "Size (diameter) of the sphere along each axis"),
    "color": _field(COLOR, "Color of the sphere")})

CYLINDER_PRIMITIVE = _message(
    "foxglove.CylinderPrimitive", "A primitive representing a cylinder, elliptic cylinder, or truncated cone", {
        "pose": _field(POSE, "Position of the center of the cylinder and orientation of the cylinder. The flat "
                             "face(s) are perpendicular to the z-axis."),
        "size": _field(VECTOR3, "Size of the cylinder's bounding box"),
        "bottom_scale": _field(NUMBER, "0-1, ratio of the diameter of the cylinder's bottom face (min z) to the "
                                       "bottom of the bounding box"),
        "top_scale": _field(NUMBER, "0-1, ratio of the diameter of the cylinder's top face (max z) to the top of "
                                    "the bounding box"),
        "color": _field(COLOR, "Color of the cylinder")})

LINE_TYPE = _enum("foxglove.LineType", "An enumeration indicating how input points should be interpreted to "
                                       "create lines", [
                      ("LINE_STRIP", 0, "Connected line segments: 0-1, 1-2, ..., (n-1)-n"),
                      ("LINE_LOOP", 1, "Closed polygon: 0-1, 1-2, ..., (n-1)-n, n-0"),
                      ("LINE_LIST", 2, "Individual line segments: 0-1, 2-3, 4-5, ...")])

LINE_PRIMITIVE = _message("foxglove.LinePrimitive", "A primitive representing a series of points connected by "
                                                    "lines", {
    "type": _field(LINE_TYPE, "Drawing primitive to use for lines"),
    "pose": _field(POSE, "Origin of lines relative to reference frame"),
    "thickness": _field(NUMBER, "Line thickness"),
    "scale_invariant": _field(BOOLEAN, "Indicates whether `thickness` is a fixed size in screen pixels (true), or "
                                       "specified in world coordinates and scales with distance from the camera "
                                       "(false)"),
    "points": _array(POINT3, "Points along the line"),
    "color": _field(COLOR, "Solid color to use for the whole line. One of `color` or `colors` must be provided."),
    "colors": _array(COLOR, "Per-point colors (if specified, must have the same length as `points`)."),
    "indices": _array(UINT32, "Indices into the `points` and `colors` attribute arrays; empty: no indexing")})

TRIANGLE_LIST_PRIMITIVE = _message(
    "foxglove.TriangleListPrimitive", "A primitive representing a set of triangles or a surface tiled by "
                                      "triangles", {
        "pose": _field(POSE, "Origin of triangles relative to reference frame"),
        "points": _array(POINT3, "Vertices to use for triangles, interpreted as a list of triples (0-1-2, 3-4-5, "
                                 "...)"),
        "color": _field(COLOR, "Solid color to use for the whole shape. One of `color` or `colors` must be "
                               "provided."),
        "colors": _array(COLOR, "Per-vertex colors (if specified, must have the same length as `points`)."),
        "indices": _array(UINT32, "Indices into the `points` and `colors` attribute arrays, which can be used to "
                                  "avoid duplicating attribute data; empty: no indexing")})

TEXT_PRIMITIVE = _message("foxglove.TextPrimitive", "A primitive representing a text label", {
    "pose": _field(POSE, "Position of the center of the text box and orientation of the text. Identity "
                         "orientation means the text is oriented in the xy-plane and flows from -x to +x."),
    "billboard": _field(BOOLEAN, "Whether the text should respect `pose.orientation` (false) or always face the "
                                 "camera (true)"),
    "font_size": _field(NUMBER, "Font size (height of one line of text)"),
    "scale_invariant": _field(BOOLEAN, "Indicates whether `font_size` is a fixed size in screen pixels (true), or "
                                       "specified in world coordinates and scales with distance from the camera "
                                       "(false)"),
    "color": _field(COLOR, "Color of the text"),
    "text": _field(STRING, "Text")})

MODEL_PRIMITIVE = _message("foxglove.ModelPrimitive", "A primitive representing a 3D model file loaded from an "
                                                      "external URL or embedded data", {
    "pose": _field(POSE, "Origin of model relative to reference frame"),
    "scale": _field(VECTOR3, "Scale factor to apply to the model along each axis"),
    "color": _field(COLOR, "Solid color to use for the whole model if `override_color` is true."),
    "override_color": _field(BOOLEAN, "Whether to use the color specified in `color` instead of any materials "
                                      "embedded in the original model."),
    "url": _field(STRING, "URL pointing to model file. One of `url` or `data` should be provided."),
    "media_type": _field(STRING, "[Media type](https://developer.mozilla.org/en-US/docs/Web/HTTP/Basics_of_HTTP/"
                                 "MIME_types) of embedded model (e.g. `model/gltf-binary`). Required if `data` is "
                                 "provided instead of `url`. Overrides the inferred media type if `url` is "
                                 "provided."),
    "data": {"type": "string", "contentEncoding": "base64",
             "description": "Embedded model. One of `url` or `data` should be provided. If `data` is provided, "
                            "`media_type` must be set to indicate the type of the data."}})

SCENE_ENTITY = _message("foxglove.SceneEntity", "A visual element in a 3D scene. An entity may be composed of "
                                                "multiple primitives which all share the same frame of reference.", {
    "timestamp": _field(TIME, "Timestamp of the entity"),
    "frame_id": _field(STRING, "Frame of reference"),
    "id": _field(STRING, "Identifier for the entity. A entity will replace any prior entity on the same topic "
                         "with the same `id`."),
    "lifetime": _field(DURATION, "Length of time (relative to `timestamp`) after which the entity should be "
                                 "automatically removed. Zero value indicates the entity should remain visible "
                                 "until it is replaced or deleted."),
    "frame_locked": _field(BOOLEAN, "Whether the entity should keep its location in the fixed frame (false) or "
                                    "follow the frame specified in `frame_id` as it moves relative to the fixed "
                                    "frame (true)"),
    "metadata": _array(KEY_VALUE_PAIR, "Additional user-provided metadata associated with the entity. Keys must "
                                       "be unique."),
    "arrows": _array(ARROW_PRIMITIVE, "Arrow primitives"),
    "cubes": _array(CUBE_PRIMITIVE, "Cube primitives"),
    "spheres": _array(SPHERE_PRIMITIVE, "Sphere primitives"),
    "cylinders": _array(CYLINDER_PRIMITIVE, "Cylinder primitives"),
    "lines": _array(LINE_PRIMITIVE, "Line primitives"),
    "triangles": _array(TRIANGLE_LIST_PRIMITIVE, "Triangle list primitives"),
    "texts": _array(TEXT_PRIMITIVE, "Text primitives"),
    "models": _array(MODEL_PRIMITIVE, "Model primitives")})

SCENE_ENTITY_DELETION_TYPE = _enum("foxglove.SceneEntityDeletionType",
                                   "An enumeration indicating which entities should match a SceneEntityDeletion "
                                   "command", [
                                       ("MATCHING_ID", 0, "Delete the existing entity on the same topic that has "
                                                          "the provided `id`"),
                                       ("ALL", 1, "Delete all existing entities on the same topic")])

SCENE_ENTITY_DELETION = _message("foxglove.SceneEntityDeletion", "Command to remove previously published entities", {
    "timestamp": _field(TIME, "Timestamp of the deletion. Only matching entities earlier than this timestamp will "
                              "be deleted."),
    "type": _field(SCENE_ENTITY_DELETION_TYPE, "Type of deletion action to perform"),
    "id": _field(STRING, "Identifier which must match if `type` is `MATCHING_ID`.")})

SCENE_UPDATE = _message("foxglove.SceneUpdate", "An update to the entities displayed in a 3D scene", {
    "deletions": _array(SCENE_ENTITY_DELETION, "Scene entities to delete"),
    "entities": _array(SCENE_ENTITY, "Scene entities to add or replace")})

FRAME_TRANSFORM = _message("foxglove.FrameTransform", "A transform between two reference frames in 3D space", {
    "timestamp": _field(TIME, "Timestamp of transform"),
    "parent_frame_id": _field(STRING, "Name of the parent frame"),
    "child_frame_id": _field(STRING, "Name of the child frame"),
    "translation": _field(VECTOR3, "Translation component of the transform"),
    "rotation": _field(QUATERNION, "Rotation component of the transform")})

FRAME_TRANSFORMS = _message("foxglove.FrameTransforms", "An array of FrameTransform messages", {
    "transforms": _array(FRAME_TRANSFORM, "Array of transforms")})

SCHEMAS = {s["title"]: s for s in (SCENE_UPDATE, FRAME_TRANSFORM, FRAME_TRANSFORMS)}
"""The top-level schemas a log registers, by their Foxglove name."""
