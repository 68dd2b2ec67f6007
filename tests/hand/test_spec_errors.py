"""A hand spec that cannot work is refused with one `FfcgsError` line naming the spec file and the problem.

Each case writes the two-finger toy hand (tests/data/toy_hand) with one thing broken into tmp_path. These run on
the host only (MuJoCo C, no JAX compilation), so the whole module takes about a second.
"""

import json
import re
import tomllib

import pytest

from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.hand.spec import load_spec

from paths import DATA

TOY_XML = (DATA / "toy_hand" / "toy.xml").read_text()
TOY_SPEC = tomllib.loads((DATA / "toy_hand" / "toy.toml").read_text())


def write_hand(tmp_path, xml_edits=(), **changes):
    """The toy hand with `xml_edits` ((old, new) string replacements in toy.xml) and spec `changes`
    ("key" or "section__key" = value) written to tmp_path; returns the spec's path."""
    xml = TOY_XML
    for old, new in xml_edits:
        assert old in xml, old
        xml = xml.replace(old, new, 1)
    (tmp_path / "toy.xml").write_text(xml)
    spec = json.loads(json.dumps(TOY_SPEC))  # a deep copy
    for k, v in changes.items():
        section, _, key = k.rpartition("__")
        (spec[section] if section else spec)[key] = v
    lines = [f"{k} = {json.dumps(v)}" for k, v in spec.items() if not isinstance(v, dict)]
    for sec, tab in spec.items():
        if isinstance(tab, dict):
            lines += [f"[{sec}]"] + [f"{k} = {json.dumps(v)}" for k, v in tab.items()]
    path = tmp_path / "hand.toml"
    path.write_text("\n".join(lines) + "\n")
    return path


def refused(path, match: str) -> str:
    """The error message, checked to match, to be one line and to name the spec file."""
    with pytest.raises(FfcgsError, match=match) as e:
        load_spec(path)
    msg = str(e.value)
    assert "\n" not in msg, msg
    assert str(path) in msg, msg
    return msg


# A joint-less body on the palm (welded to the root) carrying a site, and one on a fingertip (moves with it).
WELDED_PAD = ('<site name="t3" pos="-0.02 0.01 -0.01"/>',
              '<site name="t3" pos="-0.02 0.01 -0.01"/>\n      <body name="palm_pad" pos="0 0.01 0">'
              '<body name="palm_pad2"><site name="pad_site"/></body></body>')
TIP_PAD = ('<site name="tip_b" pos="0 0.005 0.02"/>',
           '<site name="tip_b" pos="0 0.005 0.02"/>\n          <body name="fb2_pad" pos="0 0.005 0.02">'
           '<site name="tip_b_pad"/></body>')


def test_toy_hand_passes_every_check(tmp_path):
    spec = load_spec(write_hand(tmp_path))
    assert spec.contact_sites == ("tip_a", "tip_b")


def test_contact_site_on_the_root_body(tmp_path):
    path = write_hand(tmp_path, contact_sites=["tip_a", "palm"])
    refused(path, r"contact site 'palm' is on body 'palm', which no joint moves")


def test_contact_site_welded_to_the_root_through_jointless_bodies(tmp_path):
    path = write_hand(tmp_path, [WELDED_PAD], contact_sites=["pad_site", "tip_b"])
    refused(path, r"contact site 'pad_site' is on body 'palm_pad2', which no joint moves")


def test_contact_site_on_a_jointless_body_of_a_finger_is_fine(tmp_path):
    """A pad body without a joint of its own rides on the finger that carries it."""
    spec = load_spec(write_hand(tmp_path, [TIP_PAD], contact_sites=["tip_a", "tip_b_pad"]))
    assert spec.contact_sites == ("tip_a", "tip_b_pad")


def test_contact_site_on_the_world(tmp_path):
    path = write_hand(tmp_path, [("<worldbody>", '<worldbody>\n    <site name="floor_mark"/>')],
                      contact_sites=["tip_a", "floor_mark"])
    refused(path, r"contact site 'floor_mark' is on body 'world', which no joint moves")


def test_coupling_row_of_zeros_names_the_undriven_joint(tmp_path):
    path = write_hand(tmp_path, coupling__matrix=[[1, 0], [0, 1], [0, 0]])
    refused(path, r"leaves joint\(s\) \['jb2'\] undriven \(all-zero row\)")


def test_coupling_rows_of_zeros_name_every_undriven_joint(tmp_path):
    path = write_hand(tmp_path, coupling__matrix=[[0, 0], [0, 1], [0, 0]])
    # channel a then drives nothing either; the joints are reported first
    refused(path, r"leaves joint\(s\) \['ja', 'jb2'\] undriven")


def test_coupling_column_of_zeros_names_the_idle_channel(tmp_path):
    path = write_hand(tmp_path, channels__names=["a", "b", "spare"], channels__lower=[0, 0, 0],
                      channels__upper=[1.2, 1.0, 1.0], coupling__matrix=[[1, 0, 0], [0, 1, 0], [0, 0.5, 0]])
    refused(path, r"channel\(s\) \['spare'\] drive no joint \(all-zero column")


def test_palm_normal_of_zero_length(tmp_path):
    refused(write_hand(tmp_path, palm_normal=[0, 0, 0]), r"palm_normal must be a non-zero 3-vector")


def test_hand_without_collision_geoms(tmp_path):
    """contype = conaffinity = 0 on every hand geom; a collidable floor on the world body does not count."""
    edits = [("<worldbody>", '<default><geom contype="0" conaffinity="0"/></default>\n  <worldbody>\n'
              '    <geom name="floor" type="plane" size="1 1 0.1" pos="0 0 -1" contype="1" conaffinity="1"/>')]
    msg = refused(write_hand(tmp_path, edits), r"no collision geoms")
    assert "penetration penalty and the physics test need collision geoms" in msg


def test_one_collision_geom_is_enough(tmp_path):
    edits = [("<worldbody>", '<default><geom contype="0" conaffinity="0"/></default>\n  <worldbody>'),
             ('<geom name="palm_box" type="box"', '<geom name="palm_box" contype="2" conaffinity="1" type="box"')]
    load_spec(write_hand(tmp_path, edits))


def test_mjcf_that_does_not_compile_is_one_line(tmp_path):
    path = write_hand(tmp_path, [('axis="1 0 0" range="0 1.2"', 'axis="1 0 0" range="0 1.2" type="bogus"')])
    msg = refused(path, r"toy.xml does not compile: .*bogus")
    assert re.search(r"; Element 'joint', line \d+$", msg), msg  # MuJoCo's second line, joined into the one


def test_the_cli_prints_the_one_line(tmp_path, capsys):
    from ffcgs_jax.cli.main import main

    path = write_hand(tmp_path, coupling__matrix=[[1, 0], [0, 1], [0, 0]])
    assert main(["hand", "--hand", str(path), "--png", str(tmp_path / "hand.png")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("ffcgs: error: hand spec ") and "['jb2'] undriven" in err, err
    assert not (tmp_path / "hand.png").exists()


def test_a_spec_nested_too_deep_is_one_line(tmp_path):
    """tomllib recurses per nesting level: a hand spec of arrays a few thousand deep is refused, not a RecursionError."""
    path = tmp_path / "deep.toml"
    path.write_text("a = " + "[" * 5000 + "]" * 5000 + "\n")
    refused(path, r"hand spec .*deep.toml is not usable: its arrays or tables nest too deep")
