"""Write the Allegro hand (right) MJCF, hand spec and NOTICE shipped in `ffcgs_jax/hand/assets/allegro/` from
`shared/hands/allegro/kinematics.json`, and the reference FK table of `tests/data/allegro_reference_fk.json`.

Run from the repo root:  python data/make_allegro_mjcf.py [--allegro ../shared/hands/allegro] [--out DIR]

This is a developer tool: the package never reads `shared/` at run time, it ships the files written here. `--out`
writes the four files flat into DIR instead (the test that the shipped files are this script's output uses it).
The numbers come from the MuJoCo Menagerie `wonik_allegro` description, derived from SimLab's `allegro_hand_ros`
URDF: BSD-2-Clause, Copyright (c) 2016, SimLab, which the NOTICE written beside the MJCF carries.

Modelling decisions:
- Bodies, joints and collision primitives are the numbers file's, names kept, so users can match them to the
  Menagerie model and the real hand's joint indices (joint_order = the hand's 16 servo channels).
- Root `palm` hangs from the world with no joint (the wrist pose places it), posed by `root_body_in_world` with the
  quaternion normalised: the file's [0, 1, 0, 1] is not unit, and a spec's FK results are in the palm frame anyway.
- Channels: the 16 joints in joint_order with the identity coupling (one servo per joint, no linkages). Channel
  limits = joint ranges = actuator ctrlranges, so a servo target never lies past a joint limit.
- Actuators: one `position` servo per joint, named like it, in channel order: the physics scene writes channel q
  straight into ctrl (actuator i must drive channel i) and may overwrite every actuator's kp with
  PhysicsConfig.kp. kp = 10 N m/rad (the numbers file's servos).
- Joints: damping 1 N m s/rad (the numbers file's) makes the servos overdamped: a finger reaches its target with a
  damping/kp = 0.1 s time constant and does not ring when it meets the object. armature 0.001 kg m^2, as the SVH:
  the distal phalanges and the spread joints have under 1e-5 kg m^2 about their joints, so damping/inertia would
  be ~1e5 /s, which an explicit integrator cannot take (RK4 diverges at 2 ms without it, converges with it); the
  physics scene's implicitfast integrates damping implicitly and is stable either way. No joint friction (none in
  the numbers file): the servos and the object contacts are the only forces on the fingers.
- Collision classes as the SVH's: hand geoms have contype 2 / conaffinity 1, so the hand never collides with
  itself (2 & 1 = 0) but does with contype-1/conaffinity-2 objects and the contype-1/conaffinity-3 table of the
  physics scene. The numbers file's collision filter is written as `<contact><exclude>` pairs too, so palm and
  knuckles stay apart even in a scene that gives the hand other bits. density 1000 and friction 0.6 as the SVH's:
  the scene compensates the hand's weight and its object and table geoms' friction rules every contact.
- Contact sites (order thumb, index, middle, ring as the SVH's) sit on the fingertip pad, 1 mm under the skin of
  the fingertip capsule, halfway along the distal half of its straight part (the SVH's sit at the distal end of
  theirs; the Allegro's capsule is the whole 4.4 cm fingertip, whose pad rather than its end meets an object in
  a precision grasp). The pad side is computed, not assumed: for ff/mf/rf it is the direction the pad point moves
  when the flexion joints j1..j3 turn together (MuJoCo's point Jacobian at mid-range q), in the tip body frame,
  less its component along the capsule axis. The thumb's j1 twists it about its own long axis, so its pad is the
  direction from its tip towards the other three tips at mid-range q instead, which must lie within 60 degrees of
  its flexion joints' (j2, j3) direction (checked; it is 19 degrees off, towards the fingers).
- Palm: `palm_site` is the centre of the palm box face the fingers flex towards, `palm_normal` that face's outward
  normal in the palm frame: of the box's six face normals, the one nearest the mean displacement of the ff/mf/rf
  tips from the open hand to mid-range q. Checked: all four tips at mid-range q lie on its + side. The four
  `tetrahedron_sites` are placed as the SVH's: 4 cm out along the normal, 4 cm along the finger direction and two
  points back and to either side, all from the palm site.
"""

import argparse
import json
import re
from pathlib import Path

import mujoco
import numpy as np

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "ffcgs_jax" / "hand" / "assets" / "allegro"
REF_OUT = REPO / "tests" / "data" / "allegro_reference_fk.json"
FINGERS = ("th", "ff", "mf", "rf")  # contact-site order: thumb first, as the SVH's
FLEXION = {"ff": (1, 2, 3), "mf": (1, 2, 3), "rf": (1, 2, 3), "th": (2, 3)}  # j0 spreads; the thumb's j1 twists
SKIN_DEPTH = 0.001  # m: contact sites sit this far under the fingertip capsule's skin
KP = 10.0  # N m/rad, the numbers file's servos
TET_SIZE = 0.04  # palm tetrahedron edge scale (m): comparable to the palm so rotation errors weigh like shifts
COLORS = {"palm": "0.2 0.2 0.22 1", "link": "0.25 0.25 0.28 1", "tip": "0.9 0.9 0.9 1"}
NOTICE = """\
The Allegro hand model in this folder (allegro.xml, allegro.toml) is generated by data/make_allegro_mjcf.py from
kinematic and collision numbers (body and joint frames, axes, joint ranges, collision primitives) taken from the
MuJoCo Menagerie description `wonik_allegro` (right_hand.xml), itself derived from SimLab's allegro_hand_ros URDF.
Those numbers are used under the following license:

BSD 2-Clause License

Copyright (c) 2016, SimLab
All rights reserved.

Redistribution and use in source and binary forms, with or without
modification, are permitted provided that the following conditions are met:

1. Redistributions of source code must retain the above copyright notice, this
   list of conditions and the following disclaimer.

2. Redistributions in binary form must reproduce the above copyright notice,
   this list of conditions and the following disclaimer in the documentation
   and/or other materials provided with the distribution.

THIS SOFTWARE IS PROVIDED BY THE COPYRIGHT HOLDERS AND CONTRIBUTORS "AS IS"
AND ANY EXPRESS OR IMPLIED WARRANTIES, INCLUDING, BUT NOT LIMITED TO, THE
IMPLIED WARRANTIES OF MERCHANTABILITY AND FITNESS FOR A PARTICULAR PURPOSE ARE
DISCLAIMED. IN NO EVENT SHALL THE COPYRIGHT HOLDER OR CONTRIBUTORS BE LIABLE
FOR ANY DIRECT, INDIRECT, INCIDENTAL, SPECIAL, EXEMPLARY, OR CONSEQUENTIAL
DAMAGES (INCLUDING, BUT NOT LIMITED TO, PROCUREMENT OF SUBSTITUTE GOODS OR
SERVICES; LOSS OF USE, DATA, OR PROFITS; OR BUSINESS INTERRUPTION) HOWEVER
CAUSED AND ON ANY THEORY OF LIABILITY, WHETHER IN CONTRACT, STRICT LIABILITY,
OR TORT (INCLUDING NEGLIGENCE OR OTHERWISE) ARISING IN ANY WAY OUT OF THE USE
OF THIS SOFTWARE, EVEN IF ADVISED OF THE POSSIBILITY OF SUCH DAMAGE.
"""


def fmt(v):
    # Values are rounded to 1 nm so float noise (1e-17 for an exact 0) never reaches the file; + 0.0
    # turns -0 into 0.
    return " ".join(f"{x + 0.0:.9g}" for x in np.round(np.asarray(v, float).ravel(), 9))


def unit(q):
    q = np.asarray(q, float)
    return q / np.linalg.norm(q)


def mat(quat_wxyz) -> np.ndarray:
    R = np.zeros(9)
    mujoco.mju_quat2Mat(R, unit(quat_wxyz))
    return R.reshape(3, 3)


def parse_filter(text: str) -> tuple[str, list[str]]:
    """'palm excludes contacts with a, b, c' -> ('palm', ['a', 'b', 'c'])."""
    m = re.fullmatch(r"\s*(\w+) excludes contacts with ([\w\s,]+?)\s*", text)
    if m is None:
        raise ValueError(f"collision_filter not understood: {text!r}")
    return m[1], [b.strip() for b in m[2].split(",")]


def mjcf(kin: dict, sites: dict[str, list[str]]) -> str:
    """The MJCF text; `sites`: site elements per body name (written first in the body)."""
    bodies = kin["bodies"]
    joints = {j["body"]: j for j in kin["joints"]}
    geoms: dict[str, list[dict]] = {}
    for g in kin["collision_geoms"]:
        geoms.setdefault(g["body"], []).append(g)
    tip_bodies = set(kin["fingertips"].values())
    root = kin["root_body_in_world"]
    lines: list[str] = []

    def emit(b, depth):
        ind = "  " * depth
        if b["parent"] == "world":
            pos, quat = root.get("pos", b["pos"]), root["quat_wxyz"]
        else:
            pos, quat = b["pos"], b["quat_wxyz"]
        lines.append(f'{ind}<body name="{b["name"]}" pos="{fmt(pos)}" quat="{fmt(unit(quat))}">')
        for s in sites.get(b["name"], []):
            lines.append(f"{ind}  {s}")
        if b["name"] in joints:
            j = joints[b["name"]]
            assert j["type"] == "hinge", j
            lines.append(f'{ind}  <joint name="{j["name"]}" axis="{fmt(j["axis"])}" range="{fmt(j["range"])}"/>')
        for k, g in enumerate(geoms.get(b["name"], [])):
            name = b["name"] if len(geoms[b["name"]]) == 1 else f'{b["name"]}_{k}'
            color = COLORS["palm" if b["parent"] == "world" else "tip" if b["name"] in tip_bodies else "link"]
            assert g["type"] in ("box", "capsule"), g
            lines.append(f'{ind}  <geom name="{name}" type="{g["type"]}" size="{fmt(g["size"])}" '
                         f'pos="{fmt(g["pos"])}" quat="{fmt(unit(g["quat_wxyz"]))}" rgba="{color}"/>')
        for c in bodies:
            if c["parent"] == b["name"]:
                emit(c, depth + 1)
        lines.append(f"{ind}</body>")

    (top,) = [b for b in bodies if b["parent"] == "world"]
    assert top["name"] == root["name"], (top["name"], root["name"])
    emit(top, 2)
    body1, others = parse_filter(kin["collision_filter"])
    excl = [f'    <exclude body1="{body1}" body2="{b}"/>' for b in others]
    jr = {j["name"]: j["range"] for j in kin["joints"]}
    act = [f'    <position name="{n}" joint="{n}" kp="{KP:g}" ctrlrange="{fmt(jr[n])}"/>' for n in kin["joint_order"]]
    return "\n".join([
        "<!-- BSD-2-Clause, Copyright (c) 2016, SimLab: numbers from the MuJoCo Menagerie wonik_allegro model "
        "(SimLab allegro_hand_ros URDF); see NOTICE. -->",
        f'<mujoco model="{kin["name"]}">',
        "  <!-- Generated by data/make_allegro_mjcf.py from the Allegro kinematic numbers; primitives only (no "
        "meshes). -->",
        '  <compiler angle="radian" autolimits="true"/>',
        "  <default>",
        "    <!-- contype 2 / conaffinity 1: no self-collision; objects (1/2) and the table (1/3) still collide. -->",
        '    <geom contype="2" conaffinity="1" density="1000" friction="0.6 0.005 0.0001"/>',
        "    <!-- Overdamped servos (damping / kp = 0.1 s); armature bounds damping / inertia on the light links. -->",
        '    <joint damping="1" armature="0.001"/>',
        "  </default>",
        "  <worldbody>",
        *lines,
        "  </worldbody>",
        "  <!-- The numbers file's filter, kept even though the collision bits already rule these pairs out. -->",
        "  <contact>", *excl, "  </contact>",
        "  <!-- One servo per joint, in channel order: actuator i drives channel i. -->",
        "  <actuator>", *act, "  </actuator>",
        "</mujoco>",
        "",
    ])


class Model:
    """MuJoCo C kinematics of a compiled MJCF text, by body and joint name."""

    def __init__(self, xml: str):
        self.m = mujoco.MjModel.from_xml_string(xml)
        self.d = mujoco.MjData(self.m)

    def body(self, name):
        return mujoco.mj_name2id(self.m, mujoco.mjtObj.mjOBJ_BODY, name)

    def dof(self, name):
        return self.m.jnt_dofadr[mujoco.mj_name2id(self.m, mujoco.mjtObj.mjOBJ_JOINT, name)]

    def set(self, qpos):
        self.d.qpos[:] = qpos
        mujoco.mj_kinematics(self.m, self.d)
        mujoco.mj_comPos(self.m, self.d)  # mj_jac reads the dof frames (cdof) it computes

    def pose(self, body):
        b = self.body(body)
        return self.d.xmat[b].reshape(3, 3).copy(), self.d.xpos[b].copy()

    def point_velocity(self, body, local, joints):
        """World velocity of the body-fixed point `local` when each of `joints` turns at 1 rad/s."""
        R, p = self.pose(body)
        jacp = np.zeros((3, self.m.nv))
        mujoco.mj_jac(self.m, self.d, jacp, None, R @ local + p, self.body(body))
        return jacp[:, [self.dof(j) for j in joints]].sum(1)


def capsule(kin, body):
    (g,) = [g for g in kin["collision_geoms"] if g["body"] == body and g["type"] == "capsule"]
    axis = mat(g["quat_wxyz"])[:, 2]
    return np.asarray(g["pos"], float), axis, g["size"][0], g["size"][1]


def to_local(R, p, world):
    return R.T @ (world - p)


def place_sites(kin: dict) -> tuple[dict[str, list[str]], dict]:
    """Contact, palm and tetrahedron sites per body, and the spec values they imply (module docstring)."""
    model = Model(mjcf(kin, {}))
    order = kin["joint_order"]
    ranges = {j["name"]: j["range"] for j in kin["joints"]}
    lo = np.array([ranges[n][0] for n in order])
    hi = np.array([ranges[n][1] for n in order])
    adr = [model.m.jnt_qposadr[mujoco.mj_name2id(model.m, mujoco.mjtObj.mjOBJ_JOINT, n)] for n in order]
    q_open, q_mid = np.zeros(model.m.nq), np.zeros(model.m.nq)
    q_open[adr] = np.clip(0.0, lo, hi)  # the open hand: where descents start
    q_mid[adr] = (lo + hi) / 2  # mid-range: a half-closed hand
    tips = kin["fingertips"]
    root = kin["root_body_in_world"]["name"]

    def tip_centre(f):  # world position of a tip capsule's centre at the current qpos
        R, p = model.pose(tips[f])
        return R @ capsule(kin, tips[f])[0] + p

    def in_palm(world):
        R, p = model.pose(root)
        return to_local(R, p, world)

    sites: dict[str, list[str]] = {}
    model.set(q_mid)
    for f in FINGERS:
        c, a, r, h = capsule(kin, tips[f])
        pad = c + 0.5 * h * a  # halfway along the distal half of the straight part
        R, p = model.pose(tips[f])
        flex = R.T @ model.point_velocity(tips[f], pad, [f"{f}j{k}" for k in FLEXION[f]])
        if f == "th":
            others = np.mean([tip_centre(o) for o in FINGERS if o != f], axis=0)
            u = to_local(R, p, others) - pad
        else:
            u = flex
        u = u - (u @ a) * a
        u /= np.linalg.norm(u)
        flex_perp = flex - (flex @ a) * a
        assert u @ flex_perp > 0.5 * np.linalg.norm(flex_perp), (f, u, flex_perp)  # the pad faces the flexion
        sites.setdefault(tips[f], []).append(
            f'<site name="{f}_tip_site" pos="{fmt(pad + (r - SKIN_DEPTH) * u)}" size="0.002" rgba="1 0.2 0.2 1"/>')

    # Palm face: the box face of the root body the fingers flex towards.
    (box,) = [g for g in kin["collision_geoms"] if g["body"] == root and g["type"] == "box"]
    Rb, cb, half = mat(box["quat_wxyz"]), np.asarray(box["pos"], float), np.asarray(box["size"], float)
    model.set(q_open)
    open_tips = {f: in_palm(tip_centre(f)) for f in FINGERS}
    model.set(q_mid)
    mid_tips = {f: in_palm(tip_centre(f)) for f in FINGERS}
    flex_dir = np.mean([mid_tips[f] - open_tips[f] for f in FINGERS if f != "th"], axis=0)
    faces = [(s * Rb[:, k], k) for k in range(3) for s in (1.0, -1.0)]
    normal, k = max(faces, key=lambda nk: nk[0] @ flex_dir)
    centre = cb + half[k] * normal
    assert all((mid_tips[f] - centre) @ normal > 0 for f in FINGERS), mid_tips  # tips close over the palm face
    # Finger direction: palm face towards the middle fingertip of the open hand, in the face's plane.
    fdir = open_tips["mf"] - centre
    fdir = fdir - (fdir @ normal) * normal
    fdir /= np.linalg.norm(fdir)
    side = np.cross(normal, fdir)
    S = TET_SIZE
    tet = [centre + S * normal, centre + S * fdir, centre - 0.5 * S * fdir + 0.85 * S * side,
           centre - 0.5 * S * fdir - 0.85 * S * side]
    sites[root] = [f'<site name="palm_site" pos="{fmt(centre)}" size="0.004" rgba="0.2 0.6 1 1"/>'] + [
        f'<site name="palm_tet_{i}" pos="{fmt(p)}" size="0.003" rgba="0.2 1 0.4 1"/>' for i, p in enumerate(tet)]
    return sites, {"palm_normal": normal}


def spec_toml(kin: dict, palm_normal) -> str:
    order = kin["joint_order"]
    ranges = {j["name"]: j["range"] for j in kin["joints"]}
    n = len(order)
    return "\n".join([
        "# Hand spec: how ffcgs-jax reads the MJCF next to it. Generated by data/make_allegro_mjcf.py.",
        f'name = "{kin["name"]}"',
        'mjcf = "allegro.xml"',
        f'root_body = "{kin["root_body_in_world"]["name"]}"',
        "contact_sites = [" + ", ".join(f'"{f}_tip_site"' for f in FINGERS) + "]",
        'palm_site = "palm_site"',
        f"palm_normal = [{', '.join(str(float(v) + 0.0) for v in np.round(palm_normal, 9))}]  # in the root body frame",
        'tetrahedron_sites = ["palm_tet_0", "palm_tet_1", "palm_tet_2", "palm_tet_3"]',
        "",
        "[channels]",
        "# One servo per joint: the channels are the joints, their limits the joint ranges.",
        "names = [" + ", ".join(f'"{j}"' for j in order) + "]",
        "lower = [" + ", ".join(f"{ranges[j][0]:.9g}" for j in order) + "]",
        "upper = [" + ", ".join(f"{ranges[j][1]:.9g}" for j in order) + "]",
        "",
        "[coupling]",
        "# qpos[joint] = sum over channels of matrix[row][col] * q[col]; rows name MJCF joints, cols follow "
        "[channels].",
        "joints = [" + ", ".join(f'"{j}"' for j in order) + "]",
        "matrix = [",
        *["  [" + ", ".join("1" if c == r else "0" for c in range(n)) + f"],  # {order[r]}" for r in range(n)],
        "]",
        "",
    ])


def reference_json(kin: dict) -> str:
    return json.dumps({
        "source": "shared/hands/allegro/kinematics.json reference_fk (numbers from the MuJoCo Menagerie "
                  "wonik_allegro model, derived from SimLab's allegro_hand_ros URDF); written by "
                  "data/make_allegro_mjcf.py",
        "license": kin["license"],
        "what": "centre of the outer end of each fingertip capsule in the palm body frame (m); qpos in joint_order",
        "joint_order": kin["joint_order"],
        "cases": kin["reference_fk"],
    }, indent=1) + "\n"


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--allegro", default=str(REPO.parent / "shared" / "hands" / "allegro"))
    ap.add_argument("--out", default=None, help="write all four files into this folder instead")
    args = ap.parse_args()
    kin = json.loads((Path(args.allegro) / "kinematics.json").read_text())
    assert [j["name"] for j in kin["joints"]] == kin["joint_order"]  # channel order = joint (and actuator) order
    assert "SimLab" in kin["license"] and "BSD-2-Clause" in kin["license"], kin["license"]
    sites, extra = place_sites(kin)
    xml = mjcf(kin, sites)
    out = Path(args.out) if args.out else OUT
    ref = out / REF_OUT.name if args.out else REF_OUT
    out.mkdir(parents=True, exist_ok=True)
    (out / "allegro.xml").write_text(xml)
    (out / "allegro.toml").write_text(spec_toml(kin, extra["palm_normal"]))
    (out / "NOTICE").write_text(NOTICE)
    ref.write_text(reference_json(kin))
    print(f"wrote {out / 'allegro.xml'}, allegro.toml, NOTICE and {ref}")


if __name__ == "__main__":
    main()
