"""Foxglove messages: the schemas are JSON Schema and the messages built for them validate; the hand is posed as the
package's kinematics poses it (the SVH's reference fingertip table); poses and times convert exactly."""

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ffcgs_jax.viz import foxglove_scene as fx
from ffcgs_jax.viz.foxglove_schemas import SCHEMAS

from paths import DATA

TABLE_TOL = 1e-3  # m, as tests/hand/test_kinematics.py against the same table
FINGERS = ("thumb", "index", "middle", "ring", "little")


def test_schemas_are_json_schema_and_messages_validate(svh):
    jsonschema = pytest.importorskip("jsonschema")
    assert set(SCHEMAS) == {"foxglove.SceneUpdate", "foxglove.FrameTransform", "foxglove.FrameTransforms"}
    for name, schema in SCHEMAS.items():
        jsonschema.Draft202012Validator.check_schema(schema)
        assert schema["title"] == name
    geo = fx.HandGeometry(svh)
    hand = fx.entity(1_500_000_000_123, "wrist_0", "hand", frame_locked=True, metadata={"grasp": 0},
                     texts=[fx.text((0, 0, 0), "#0")], **geo.primitives(np.zeros(9)))
    box = fx.entity(0, "world", "table", cubes=[fx.cube(np.eye(4), (1, 1, 0.01), fx.TABLE_RGBA)])
    update = fx.scene_update([hand, box])
    jsonschema.validate(json.loads(json.dumps(update)), SCHEMAS["foxglove.SceneUpdate"])
    tf = {"transforms": [fx.frame_transform(5, "world", "object", np.eye(4))]}
    jsonschema.validate(tf, SCHEMAS["foxglove.FrameTransforms"])
    with pytest.raises(jsonschema.ValidationError):  # an entity without its primitive lists is refused
        jsonschema.validate({"deletions": [], "entities": [{k: v for k, v in box.items() if k != "models"}]},
                            SCHEMAS["foxglove.SceneUpdate"])
    with pytest.raises(ValueError, match="unknown primitive"):
        fx.entity(0, "world", "x", boxes=[])


def test_time_and_pose_convert_exactly():
    assert fx.stamp(1_700_000_000_123_456_789) == {"sec": 1_700_000_000, "nsec": 123_456_789}
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", [0.3, -1.2, 2.5]).as_matrix()
    T[:3, 3] = [0.1, -0.2, 0.3]
    p = fx.pose(T)
    q = [p["orientation"][k] for k in "xyzw"]
    np.testing.assert_allclose(Rotation.from_quat(q).as_matrix(), T[:3, :3], atol=1e-12)
    assert [p["position"][k] for k in "xyz"] == [0.1, -0.2, 0.3] and abs(np.linalg.norm(q) - 1) < 1e-12


CASES = [c for c in json.loads((DATA / "svh_reference_fk.json").read_text())["cases"]
         if not c["j5_fixed"]]  # not the table's alternative model with the palm fold held at 0


@pytest.mark.parametrize("case", CASES, ids=lambda c: c["name"])
def test_hand_is_posed_as_the_package_poses_it(svh, case):
    """The drawn hand's kinematics (MuJoCo on the hand's MJCF, channels through the coupling, root frame) puts the
    fingertip sites where the SVH's reference table does; its geoms follow the same bodies."""
    q = np.array([case["channels"][n] for n in svh.spec.channel_names])
    geo = fx.HandGeometry(svh)
    tips = geo.site_positions(q, svh.contact_site_ids)
    np.testing.assert_allclose(tips, [case["contact_points"][f] for f in FINGERS], atol=TABLE_TOL)
    poses = geo.geom_poses(q)
    # rigid transforms, and one primitive centred on each box and capsule
    assert np.allclose(poses[:, :3, :3] @ poses[:, :3, :3].transpose(0, 2, 1), np.eye(3), atol=1e-9)
    prims = geo.primitives(q)
    assert len(prims["cubes"]) + len(prims["cylinders"]) == len(geo.geoms) == 27
    centres = np.array([[c["pose"]["position"][k] for k in "xyz"] for c in prims["cubes"] + prims["cylinders"]])
    np.testing.assert_allclose(np.sort(centres, 0), np.sort(poses[:, :3, 3], 0), atol=1e-12)
