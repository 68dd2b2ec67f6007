"""The depth commands as a user runs them: `ffcgs render-depth` writes a folder that `ffcgs fuse` and
`ffcgs grasp --depth` read back; bad input is one line, exit 2.

The grasp runs use test_cli_grasp's small settings on a 16^3 grid, so in one session they reuse its executable.
"""

import json
import re

import numpy as np
import pytest
import trimesh
from PIL import Image

from ffcgs_jax.core import files
from ffcgs_jax.cli import main as cli_main
from ffcgs_jax.evaluation import metrics
from ffcgs_jax.geometry import depth_io, mesh_io, sdf
from ffcgs_jax.synthesis import grasp_io

SMALL = ["--n", "4", "--iters", "5", "--res", "16"]
W, H = 120, 90


def run(capsys, *argv):
    code = cli_main.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture(scope="module")
def frames_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("depth")
    code = cli_main.main(["render-depth", "box", "--views", "4", "--width", str(W), "--height", str(H),
                          "--out", str(d / "frames"), "--png", str(d / "frames.png")])
    assert code == 0
    return d


def test_render_depth_writes_the_documented_folder(frames_dir):
    folder = frames_dir / "frames"
    names = sorted(p.name for p in folder.iterdir())
    # no masks by default; the manifest names the files of this run (files.write_folder)
    assert names == [files.MANIFEST, "camera.json", "poses.json"] + [f"view_{i:03d}.png" for i in range(4)]
    cam = json.loads((folder / "camera.json").read_text())
    assert (cam["width"], cam["height"]) == (W, H) and cam["depth_scale"] == 0.001
    frames = depth_io.load_frames(folder)
    assert frames.depth.shape == (4, H, W) and frames.mask is None
    # the cameras look at the box's centre: its reading at the image centre is nearer than the camera distance
    centre = frames.depth[:, H // 2, W // 2]
    assert ((centre > 0.3) & (centre < 0.45)).all(), centre
    png = np.asarray(Image.open(frames_dir / "frames.png"))
    assert png.ndim == 3 and png.shape[1] > 3 * png.shape[0] and png.std() > 10


def test_fuse_writes_an_sdf_the_planner_reads(capsys, frames_dir, tmp_path):
    out = tmp_path / "sdf.npz"
    code, text, err = run(capsys, "fuse", frames_dir / "frames", "--res", 24, "--out", out, "--png",
                          tmp_path / "s.png", "--mesh", tmp_path / "fused.ply")
    assert code == 0, err
    assert re.search(r"table height \(m\)\s+-?0\.00\d\d \(fitted\)", text), text
    grid = sdf.load(out)
    assert grid.grid.shape == (24, 24, 24, 4) and abs(float(grid.table_z)) < 0.003
    box = mesh_io.load_mesh("box")
    fused = trimesh.load(tmp_path / "fused.ply")
    np.testing.assert_allclose(fused.bounds, box.bounds, atol=1.5 * float(grid.voxel_size))
    assert (tmp_path / "s.png").stat().st_size > 0


@pytest.mark.e2e  # fusion, synthesis and evaluation end to end
def test_grasp_from_depth_evaluates_on_the_fused_surface(capsys, frames_dir):
    out = frames_dir / "alone.npz"
    code, text, err = run(capsys, "grasp", "--depth", frames_dir / "frames", *SMALL, "--out", out)
    assert code == 0, err
    assert "the fused SDF (filters, epsilon, contacts)" in text and "on the true mesh" not in text
    data = grasp_io.load_npz(out)
    assert str(data["evaluation_surface"]) == "fused" and "object_source" not in data
    assert str(data["depth_source"]) == str((frames_dir / "frames").resolve())
    assert data["wrist_pose"].shape == (4, 4, 4) and abs(float(data["table_z"])) < 0.003
    # `ffcgs eval` cannot guess the object of a depth-planned file: it asks for it
    code, _, err = run(capsys, "eval", out)
    assert code == 2 and "pass --object" in err


@pytest.mark.e2e  # 265 s on the 2-core CPU: a second synthesis and the true mesh's evaluation compiled
def test_grasp_from_depth_with_the_true_object(capsys, frames_dir, tmp_path):
    out = tmp_path / "g.npz"
    code, text, err = run(capsys, "grasp", "--depth", frames_dir / "frames", "--object", "box", *SMALL,
                          "--out", out)
    assert code == 0, err
    data = grasp_io.load_npz(out)
    assert str(data["evaluation_surface"]) == "fused" and str(data["object_source"]) == "box"
    # filtered on the fused surface (the same grasps as without --object), measured on the true mesh too
    alone = grasp_io.load_npz(frames_dir / "alone.npz") if (frames_dir / "alone.npz").exists() else None
    if alone is not None:
        np.testing.assert_array_equal(data["valid"], alone["valid"])
    box = mesh_io.load_mesh("box")
    closest, _, signed = metrics.mesh_contacts(box, data["contacts"])
    np.testing.assert_allclose(data["contact_dist_true"], signed, atol=1e-9)
    assert (data["n_contacts_true"] == (np.abs(signed) <= 0.002).sum(1)).all()
    assert re.search(r"on the true mesh: force closure \(valid\)\s+\d+ / \d+", text), text


@pytest.mark.parametrize("argv, message", [
    (["grasp"], "needs an object"),
    (["grasp", "box", "--table-z", "0"], "--table-z and --bounds belong to --depth"),
    (["grasp", "--depth", "{frames}", "--validate"], "--validate with --depth needs --object"),
    (["grasp", "--depth", "{tmp}/nothing"], "depth input not found"),
    (["fuse", "{tmp}/nothing"], "depth input not found"),
    (["fuse", "{frames}", "--res", "8"], r"--res must be an integer in \[16, 128\]"),
    (["fuse", "{frames}", "--mesh", "{tmp}/m.txt"], "--mesh .*/m.txt: .* must end in .ply or .obj or .stl"),
    (["fuse", "{frames}", "--table-z", "0.5"], "no depth reading left on the object"),
    (["render-depth", "box", "--views", "0"], r"--views must be an integer"),
    (["render-depth", "no_such_object"], "no_such_object"),
], ids=["no-object", "table-z-without-depth", "validate-without-object", "missing-frames", "fuse-missing",
        "fuse-res", "fuse-mesh-suffix", "table-above-object", "views-0", "unknown-object"])
def test_bad_input_is_one_line_exit_2(capsys, frames_dir, tmp_path, argv, message):
    argv = [a.format(frames=frames_dir / "frames", tmp=tmp_path) for a in argv]
    code, _, err = run(capsys, *argv)
    assert code == 2, err
    assert err.startswith("ffcgs: error:") and err.count("\n") == 1, err
    assert re.search(message, err), err
