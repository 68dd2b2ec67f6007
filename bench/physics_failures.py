"""Pictures of the physics test's outcomes: one held grasp and the common failure modes, as frames of trials.

    python bench/physics_failures.py --grasps .bench_data/i4/grasps --physics .bench_data/i4/physics.json \
        --ycb ../shared/objects/ycb --out bench/physics_failures.png

From the rows of bench/eval_physics.py (geometric sampler, friction 0.6, valid grasps) it takes the first grasp of
each kind: lift-shake success, lift-shake `lost`, six-dir `slip`, six-dir `lost`; replays each trial
(`viz.physics_video.record`) and puts three frames side by side: fingers closed, halfway through the test, end.
"""

import argparse
import json
import tempfile
from pathlib import Path

import numpy as np
from PIL import Image

from ffcgs_jax.geometry import mesh_io
from ffcgs_jax.hand import spec as hand_spec
from ffcgs_jax.physics import protocols as physics_protocols
from ffcgs_jax.physics import runner as physics
from ffcgs_jax.viz import physics_video
from ffcgs_jax.physics.config import PhysicsConfig
from ffcgs_jax.synthesis import grasp_io

REPO = Path(__file__).resolve().parents[1]
KINDS = [("lift-shake", 0, "held"), ("lift-shake", 2, "lost"), ("six-dir", 3, "slip"), ("six-dir", 2, "lost")]


def pick(rows, protocol: str, reason: int):
    key = physics_protocols.result_key(protocol, "reason")
    for r in rows:
        if r["sampler"] == "geometric" and r["friction"] == 0.6:
            hits = np.flatnonzero(np.asarray(r["valid"], bool) & (np.asarray(r[key]) == reason))
            if len(hits):
                return r, int(hits[0])
    return None, None


def frames_of(gif: Path, closed_s: float, fps: float = 15.0) -> list[Image.Image]:
    """Frames when the fingers have closed, halfway through the test and at its end."""
    im = Image.open(gif)
    count = im.n_frames
    first = min(count - 1, int(closed_s * fps) - 1)
    out = []
    for i in (first, (first + count - 1) // 2, count - 1):
        im.seek(int(i))
        out.append(im.convert("RGB").copy())
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--grasps", required=True)
    ap.add_argument("--physics", required=True)
    ap.add_argument("--ycb", default=str(REPO.parent / "shared" / "objects" / "ycb"))
    ap.add_argument("--out", default="physics_failures.png")
    args = ap.parse_args()
    rows = json.loads(Path(args.physics).read_text())
    spec = hand_spec.load_spec("svh")
    cfg = PhysicsConfig(sim_friction=0.6)
    strips = []
    for protocol, reason, label in KINDS:
        r, i = pick(rows, protocol, reason)
        if r is None:
            continue
        g = grasp_io.load_npz(Path(args.grasps) / f"{r['object']}__{r['method']}__{r['sampler']}.npz")
        src = r["object"] if "_" not in r["object"] else str(Path(args.ycb) / f"{r['object']}.stl")
        mesh = mesh_io.load_mesh(src)
        scene = physics.scenes(spec, mesh, cfg, (protocol,))[protocol]
        batch, _, _ = physics.prepare(scene, mesh, g["wrist_pose"][i:i + 1], g["q"][i:i + 1], cfg)
        with tempfile.TemporaryDirectory() as tmp:
            gif = Path(tmp) / "t.gif"
            physics_video.record(scene, batch, 0, cfg, protocol, gif,
                                 title=f"{protocol} {label}: {r['object']} #{i}")
            strips.append(frames_of(gif, cfg.close_time + cfg.settle_time))
        print(f"{protocol} {label}: {r['object']} grasp {i}")
    w, h = strips[0][0].size
    sheet = Image.new("RGB", (3 * w, len(strips) * h), "white")
    for row, frames in enumerate(strips):
        for col, f in enumerate(frames):
            sheet.paste(f, (col * w, row * h))
    sheet.save(args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
