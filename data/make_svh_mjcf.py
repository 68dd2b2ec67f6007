"""Write the Schunk SVH MJCF and hand spec shipped in `ffcgs_jax/hand/assets/svh/` from `shared/svh/`.

Run from the repo root:  python data/make_svh_mjcf.py [--svh ../shared/svh]

This is a developer tool: the package never reads `shared/` at run time, it ships the files written here.
The kinematic numbers come from `kinematics.json`; the STL meshes (GPL-derived, not shipped) are only used to size
the palm's collision boxes, which the bounding boxes alone would make 2 cm too thick in front of the palm plate.

Modelling decisions (also in README):
- URDF joints become MJCF bodies: child frame = parent * Trans(xyz) * Rot(rpy), hinge about `axis` in that frame.
  Links reached through fixed joints are folded into the nearest moving body (their geometry keeps its pose), so
  the tree has 21 bodies: the root `base_link` and one per moving joint.
- Couplings: the 9 channels are the 9 "master" joints (multiplier 1). The other 11 joints follow through joint
  equality constraints (`polycoef="0 m 0 0 0"`), and the 9 position actuators drive the masters. For kinematics
  the package applies the same matrix directly: qpos = coupling @ q.
- Coupled joint ranges are multiplier x channel range, so limits and couplings never fight (shared/svh README).
- Collision geometry: capsules along link +x for phalanges (radius from the bbox y/z half extents), boxes for the
  knuckles and the thumb base, slab boxes fitted to the mesh vertices for the palm parts, a box for the flange.
- Collision classes: hand geoms have contype=2, conaffinity=1, so the hand never collides with itself but does
  with any geom of contype 1 / conaffinity 2 (objects, table) in scenes built later.
"""

import argparse
import json
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

OUT = Path(__file__).resolve().parents[1] / "ffcgs_jax" / "hand" / "assets" / "svh"
FINGER_SITE = {"thumb": "thumb_tip", "index": "index_tip", "middle": "middle_tip", "ring": "ring_tip",
               "little": "little_tip"}
PALM_SLABS = {"e1": 3, "e2": 3}  # palm parts: boxes fitted to vertex slabs along z
TET_SIZE = 0.04  # palm tetrahedron edge scale (m): comparable to the palm so rotation errors weigh like shifts
COLORS = {"palm": "0.25 0.27 0.3 1", "thumb": "0.75 0.75 0.78 1", "index": "0.75 0.75 0.78 1",
          "middle": "0.75 0.75 0.78 1", "ring": "0.75 0.75 0.78 1", "little": "0.75 0.75 0.78 1"}


def tf(xyz, rpy):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", rpy).as_matrix()
    T[:3, 3] = xyz
    return T


def fmt(v):
    return " ".join(f"{x:.9g}" for x in np.asarray(v, float).ravel())


def quat(R):
    x, y, z, w = Rotation.from_matrix(R).as_quat()
    q = np.array([w, x, y, z])
    return q if q[0] >= 0 else -q


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--svh", default=str(Path(__file__).resolve().parents[2] / "shared" / "svh"))
    args = ap.parse_args()
    svh = Path(args.svh)
    kin = json.loads((svh / "kinematics.json").read_text())
    links = {l["name"]: l for l in kin["links"]}
    joints = {j["name"]: j for j in kin["joints"]}
    by_parent: dict[str, list] = {}
    for j in kin["joints"]:
        by_parent.setdefault(j["parent"], []).append(j)
    channels = kin["actuated_channels"]
    cm = kin["coupling_matrix"]
    M = np.array(cm["matrix"])
    ch_names = cm["cols_channels"]
    ch_upper = {c["name"]: c["upper"] for c in channels}
    ch_lower = {c["name"]: c["lower"] for c in channels}
    row = {n: i for i, n in enumerate(cm["rows_joints"])}
    finger_of = {l["name"]: l.get("finger") for l in kin["links"]}

    def joint_range(jname):
        r = M[row[jname]]
        c = int(np.flatnonzero(r)[0])
        return r[c] * ch_lower[ch_names[c]], r[c] * ch_upper[ch_names[c]]

    def geoms_for(link, T_body_link, name_prefix):
        """Collision/visual primitives of one link, posed in its body frame."""
        L = links[link]
        if L.get("bbox_min") is None:
            return []
        lo, hi = np.array(L["bbox_min"]), np.array(L["bbox_max"])
        color = COLORS.get(finger_of[link] or "palm", COLORS["palm"])
        out = []
        if link in PALM_SLABS:
            v = trimesh.load(svh / L["stl"]["file"]).vertices
            edges = np.linspace(lo[2], hi[2], PALM_SLABS[link] + 1)
            for k in range(PALM_SLABS[link]):
                s = v[(v[:, 2] >= edges[k] - 1e-9) & (v[:, 2] <= edges[k + 1] + 1e-9)]
                blo, bhi = s.min(0), s.max(0)
                blo[2], bhi[2] = edges[k], edges[k + 1]
                out.append(("box", (bhi - blo) / 2, (bhi + blo) / 2, np.eye(3), f"{name_prefix}{link}_{k}", color))
        elif link in ("base_link", "z") or link.startswith("virtual_"):
            out.append(("box", (hi - lo) / 2, (hi + lo) / 2, np.eye(3), f"{name_prefix}{link}", color))
        else:  # phalanx: capsule along +x
            c = (hi + lo) / 2
            r = max(hi[1] - lo[1], hi[2] - lo[2]) / 2
            a, b = lo[0] + r, hi[0] - r
            out.append(("capsule", (r, (b - a) / 2), np.array([(a + b) / 2, c[1], c[2]]),
                        Rotation.from_euler("y", np.pi / 2).as_matrix(), f"{name_prefix}{link}", color))
        res = []
        for kind, size, pos, R, name, rgba in out:
            Tg = np.eye(4)
            Tg[:3, :3], Tg[:3, 3] = R, pos
            Tg = T_body_link @ Tg
            res.append(f'<geom name="{name}" type="{kind}" size="{fmt(size)}" pos="{fmt(Tg[:3, 3])}" '
                       f'quat="{fmt(quat(Tg[:3, :3]))}" rgba="{rgba}"/>')
        return res

    lines: list[str] = []
    tips = {t["distal_link"]: t for t in kin["fingertips"]}
    palm = kin["palm"]

    def emit_link(link, T_body_link, depth):
        """Geoms and sites of `link` (posed in the current body), then its children."""
        ind = "  " * depth
        for g in geoms_for(link, T_body_link, ""):
            lines.append(ind + g)
        if link in tips:
            t = tips[link]
            p = (T_body_link @ np.r_[t["contact_point"], 1])[:3]
            lines.append(f'{ind}<site name="{FINGER_SITE[t["finger"]]}" pos="{fmt(p)}" size="0.002" '
                         f'rgba="1 0.2 0.2 1"/>')
        for j in by_parent.get(link, []):
            T_child = T_body_link @ tf(j["origin_xyz"], j["origin_rpy"])
            if j["type"] == "fixed":
                emit_link(j["child"], T_child, depth)
                continue
            lo, hi = joint_range(j["name"])
            lines.append(f'{ind}<body name="{j["child"]}" pos="{fmt(T_child[:3, 3])}" '
                         f'quat="{fmt(quat(T_child[:3, :3]))}">')
            lines.append(f'{ind}  <joint name="{j["name"]}" axis="{fmt(j["axis"])}" range="{lo:.9g} {hi:.9g}"/>')
            emit_link(j["child"], np.eye(4), depth + 1)
            lines.append(f"{ind}</body>")

    root = "base_link"
    lines.append('    <body name="base_link">')
    c = np.array(palm["center_point"])
    lines.append(f'      <site name="palm" pos="{fmt(c)}" size="0.004" rgba="0.2 0.6 1 1"/>')
    n, f, x = np.array(palm["normal"]), np.array(palm["finger_direction"]), np.cross(palm["normal"], palm["finger_direction"])
    tet = [c + TET_SIZE * n, c + TET_SIZE * f, c - 0.5 * TET_SIZE * f + 0.85 * TET_SIZE * x,
           c - 0.5 * TET_SIZE * f - 0.85 * TET_SIZE * x]
    for i, p in enumerate(tet):
        lines.append(f'      <site name="palm_tet_{i}" pos="{fmt(p)}" size="0.003" rgba="0.2 1 0.4 1"/>')
    emit_link(root, np.eye(4), 3)
    lines.append("    </body>")

    masters = [c["joint"] for c in channels]
    eq = []
    for jn, r in zip(cm["rows_joints"], M):
        ci = int(np.flatnonzero(r)[0])
        master = channels[ci]["joint"]
        if jn != master:
            eq.append(f'    <joint joint1="{jn}" joint2="{master}" polycoef="0 {r[ci]:.9g} 0 0 0"/>')
    act = [f'    <position name="{c["name"]}" joint="{c["joint"]}" kp="5" ctrlrange="{c["lower"]:.9g} {c["upper"]:.9g}"/>'
           for c in channels]
    xml = "\n".join([
        '<mujoco model="schunk_svh_right">',
        "  <!-- Generated by data/make_svh_mjcf.py from the SVH kinematic numbers; primitives only (no meshes). -->",
        '  <compiler angle="radian" autolimits="true"/>',
        '  <default>',
        '    <geom contype="2" conaffinity="1" density="1000" friction="0.6 0.005 0.0001"/>',
        '    <joint damping="0.1" armature="0.001"/>',
        '  </default>',
        "  <worldbody>",
        *lines,
        "  </worldbody>",
        "  <!-- Coupled joints follow their channel's master joint: joint1 = m * joint2. -->",
        "  <equality>", *eq, "  </equality>",
        "  <actuator>", *act, "  </actuator>",
        "</mujoco>",
        "",
    ])
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "svh.xml").write_text(xml)

    rows = cm["rows_joints"]
    spec = [
        "# Hand spec: how ffcgs-jax reads the MJCF next to it. Generated by data/make_svh_mjcf.py.",
        'name = "schunk_svh_right"',
        'mjcf = "svh.xml"',
        f'root_body = "{root}"',
        'contact_sites = ["thumb_tip", "index_tip", "middle_tip", "ring_tip", "little_tip"]',
        'palm_site = "palm"',
        f"palm_normal = [{', '.join(map(str, palm['normal']))}]  # in the root body frame",
        'tetrahedron_sites = ["palm_tet_0", "palm_tet_1", "palm_tet_2", "palm_tet_3"]',
        "",
        "[channels]",
        "names = [" + ", ".join('"' + c["name"] + '"' for c in channels) + "]",
        "lower = [" + ", ".join(f"{c['lower']:.9g}" for c in channels) + "]",
        "upper = [" + ", ".join(f"{c['upper']:.9g}" for c in channels) + "]",
        "",
        "[coupling]",
        "# qpos[joint] = sum over channels of matrix[row][col] * q[col]; rows name MJCF joints, cols follow [channels].",
        "joints = [" + ", ".join('"' + r + '"' for r in rows) + "]",
        "matrix = [",
        *["  [" + ", ".join(f"{v:.9g}" for v in r) + f"],  # {name}" for r, name in zip(M, rows)],
        "]",
        "",
    ]
    assert ch_names == [c["name"] for c in channels]
    assert masters == [c["joint"] for c in channels]
    (OUT / "svh.toml").write_text("\n".join(spec))
    print(f"wrote {OUT / 'svh.xml'} and {OUT / 'svh.toml'}")


if __name__ == "__main__":
    main()
