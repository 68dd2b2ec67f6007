"""Pictures of a MuJoCo scene: software rasteriser, MuJoCo's OpenGL path when it works, PNG output."""

import mujoco
import numpy as np
import pytest
import trimesh
from PIL import Image

from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.viz import render, render_software

W, H = 120, 100
BOX_HALF = 0.02
SPHERE_POS, SPHERE_R = np.array([-0.085, 0.085, 0.0]), 0.02
CAPSULE_A, CAPSULE_B, CAPSULE_R = np.array([0.07, -0.09, -0.04]), np.array([0.09, -0.07, 0.04]), 0.015
MESH_POS, MESH_R = np.array([0.06, 0.06, 0.0]), 0.02
_TOL = 1e-9  # metres: vertices of analytic shapes are exact up to rounding


def _xml(box_pos: str = "0 0 0") -> str:
    # Laid out so that the bounding box of the non-plane geoms is centred on the box and nothing sits between
    # any camera and the box centre: the box centre then projects to the middle of every view.
    ico = trimesh.creation.icosphere(subdivisions=2, radius=MESH_R)
    verts = " ".join(f"{x:.9f}" for x in ico.vertices.ravel())
    faces = " ".join(str(i) for i in ico.faces.ravel())
    fromto = " ".join(str(x) for x in (*CAPSULE_A, *CAPSULE_B))
    sphere_pos, mesh_pos = (" ".join(map(str, p)) for p in (SPHERE_POS, MESH_POS))
    return f"""
    <mujoco>
      <asset><mesh name="ico" vertex="{verts}" face="{faces}"/></asset>
      <worldbody>
        <geom name="floor" type="plane" pos="0 0 -0.1" size="0 0 1" rgba="0.8 0.8 0.75 1"/>
        <geom name="box" type="box" pos="{box_pos}" size="{BOX_HALF} {BOX_HALF} {BOX_HALF}"
              rgba="0.9 0.1 0.1 1"/>
        <geom name="capsule" type="capsule" fromto="{fromto}" size="{CAPSULE_R}" rgba="0.1 0.7 0.2 1"/>
        <geom name="sphere" type="sphere" pos="{sphere_pos}" size="{SPHERE_R}" rgba="0.2 0.3 0.9 1"/>
        <geom name="object" type="mesh" mesh="ico" pos="{mesh_pos}" rgba="0.9 0.8 0.2 1"/>
      </worldbody>
    </mujoco>"""


def _load(xml: str) -> tuple[mujoco.MjModel, mujoco.MjData]:
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    return model, data


@pytest.fixture(scope="module")
def scene() -> tuple[mujoco.MjModel, mujoco.MjData]:
    return _load(_xml())


def _geom(model: mujoco.MjModel, name: str) -> int:
    return mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, name)


def test_software_image_shape_and_dtype(scene):
    image, used = render.render_scene(*scene, width=W, height=H, backend="software")
    assert used == "software"
    assert image.shape == (H, 3 * W, 3) and image.dtype == np.uint8
    one, _ = render.render_scene(*scene, width=W, height=H, backend="software", views=("top",))
    assert one.shape == (H, W, 3)


@pytest.mark.parametrize("backend", ["software", "auto"])
def test_box_centre_is_red_and_sky_is_background(scene, backend):
    image, used = render.render_scene(*scene, width=W, height=H, backend=backend)
    for k, view in enumerate(("front", "side", "top")):
        centre = image[H // 2 - 1 : H // 2 + 2, k * W + W // 2 - 1 : k * W + W // 2 + 2].astype(int)
        assert np.all(centre[..., 0] > 120) and np.all(centre[..., 1:] < 60), (used, view, centre[1, 1])
    # The top-right corner of the front view looks over the floor's far edge at the background gradient.
    corner = image[1, W - 2].astype(int)
    assert np.all(np.abs(corner - render_software.BG_TOP) <= 3), (used, corner)


def test_moving_the_box_moves_the_red_pixels():
    model, data = _load(_xml("0 0 0.04"))
    image, _ = render.render_scene(model, data, width=W, height=H, backend="software", views=("front",))
    red = (image[..., 0] > 120) & (image[..., 1] < 60) & (image[..., 2] < 60)
    rows = np.nonzero(red)[0]
    assert len(rows) > 20
    assert rows.mean() < H / 2 - 5  # the box went up, so it is drawn above the middle


def test_empty_scene_is_background():
    model, data = _load("<mujoco/>")
    for backend in ("software", "auto"):
        image, used = render.render_scene(model, data, width=W, height=H, backend=backend)
        assert image.shape == (H, 3 * W, 3)
        below_labels = image[H // 2 :].astype(int)
        assert np.all(below_labels == below_labels[:, :1]), used  # each row one background colour


def test_geom_meshes_lie_on_the_geoms(scene):
    model, data = scene
    meshes = render.geom_meshes(model, data)
    assert len(meshes) == 5
    by_geom = dict(zip(range(model.ngeom), meshes))
    for verts, faces, rgba in meshes:
        assert verts.shape[1] == 3 and faces.shape[1] == 3 and rgba.shape == (4,)
        assert faces.min() >= 0 and faces.max() < len(verts)

    sphere, _, _ = by_geom[_geom(model, "sphere")]
    np.testing.assert_allclose(np.linalg.norm(sphere - SPHERE_POS, axis=1), SPHERE_R, atol=_TOL)

    capsule, _, _ = by_geom[_geom(model, "capsule")]
    axis = CAPSULE_B - CAPSULE_A
    s = np.clip((capsule - CAPSULE_A) @ axis / (axis @ axis), 0, 1)
    to_segment = np.linalg.norm(capsule - (CAPSULE_A + s[:, None] * axis), axis=1)
    np.testing.assert_allclose(to_segment, CAPSULE_R, atol=_TOL)
    assert s.min() == 0 and s.max() == 1  # both caps are there

    g = _geom(model, "box")
    box, box_faces, box_rgba = by_geom[g]
    local = (box - data.geom_xpos[g]) @ data.geom_xmat[g].reshape(3, 3)
    np.testing.assert_allclose(np.abs(local), BOX_HALF, atol=_TOL)
    np.testing.assert_allclose(box_rgba, [0.9, 0.1, 0.1, 1.0], atol=1e-6)
    assert len(box_faces) == 12

    mesh, _, _ = by_geom[_geom(model, "object")]
    np.testing.assert_allclose(np.linalg.norm(mesh - MESH_POS, axis=1), MESH_R, atol=1e-6)  # float32 storage

    floor, _, _ = by_geom[_geom(model, "floor")]
    np.testing.assert_allclose(floor[:, 2], -0.1, atol=_TOL)
    assert len(render.geom_meshes(model, data, include_planes=False)) == 4


def test_hidden_and_transparent_geoms_are_skipped():
    model, data = _load(
        """<mujoco><worldbody>
        <geom type="sphere" size="0.1" rgba="1 0 0 1"/>
        <geom type="sphere" size="0.1" pos="1 0 0" rgba="1 0 0 0"/>
        <geom type="sphere" size="0.1" pos="2 0 0" group="3"/>
        </worldbody></mujoco>"""
    )
    meshes = render.geom_meshes(model, data)
    assert len(meshes) == 1 and np.allclose(meshes[0][0].mean(0), 0, atol=1e-9)


def test_mujoco_backend_works_or_says_why(scene):
    try:
        image, used = render.render_scene(*scene, width=W, height=H, backend="mujoco", views=("side",))
    except FfcgsError as e:
        assert "backend='software'" in str(e)
    else:
        assert used == "mujoco" and image.shape == (H, W, 3) and image.dtype == np.uint8


def test_bad_arguments_are_named(scene):
    with pytest.raises(FfcgsError, match="valid backends: auto, mujoco, software"):
        render.render_scene(*scene, backend="vulkan")
    with pytest.raises(FfcgsError, match="'back'.*valid views: front, side, top"):
        render.render_scene(*scene, views=("front", "back"))
    with pytest.raises(FfcgsError, match="width must be in"):
        render.render_scene(*scene, width=0)
    model = scene[0]
    with pytest.raises(FfcgsError, match="mj_kinematics"):
        render.render_scene(model, mujoco.MjData(model), backend="software")


def test_save_png_round_trip(tmp_path, scene):
    image, _ = render.render_scene(*scene, width=W, height=H, backend="software", views=("front", "top"))
    path = tmp_path / "new" / "dir" / "scene.png"
    render.save_png(image, path)
    with Image.open(path) as png:
        assert png.format == "PNG" and png.size == (2 * W, H)
        np.testing.assert_array_equal(np.asarray(png.convert("RGB")), image)

    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    with pytest.raises(FfcgsError, match="cannot write PNG"):
        render.save_png(image, blocker / "scene.png")
