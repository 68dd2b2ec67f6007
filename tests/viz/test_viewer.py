"""`ffcgs show` / `viz.viewer`: the scene it serves (checked through viser's server API against the package's own
forward kinematics), the ranked stepping, and the page in a real browser (headless Chromium, when installed)."""

import shutil
import subprocess

import jax
import numpy as np
import pytest

from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.geometry import mesh_io
from ffcgs_jax.hand import kinematics as K

pytestmark = pytest.mark.e2e  # the viewer serves a synthesised set (the SVH pipeline compiled)

viser = pytest.importorskip("viser", reason="the viewer needs the viz extra: pip install -e '.[viz]'")
from ffcgs_jax.cli.show_command import ShowCmd, hand_of  # noqa: E402
from ffcgs_jax.viz import viewer  # noqa: E402

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


@pytest.fixture(scope="module")
def grasps():
    """Three SVH poses above the ball (palm down, 3 heights), fingertips at the sites: a grasp file's arrays."""
    hand = K.load_hand("svh")
    poses = []
    for z in (0.12, 0.14, 0.16):
        T = np.eye(4)
        T[:3, :3] = [[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]  # the SVH's palm normal (+y) down
        T[:3, 3] = [0.0, 0.0, z]
        poses.append(T)
    poses = np.stack(poses)
    q = np.zeros((3, hand.n_channels))
    contacts = np.stack([np.asarray(K.contact_points(hand, jax.numpy.asarray(T), jax.numpy.asarray(qq)))
                         for T, qq in zip(poses, q)])
    data = {"wrist_pose": poses, "q": q, "contacts": contacts, "valid": np.array([True, False, True]),
            "E": np.array([0.3, 0.1, 0.2]), "contact_dist": np.full((3, hand.n_contacts), 0.001),
            "channel_names": np.array(hand.spec.channel_names), "lift_shake_success": np.array([True, False, False]),
            "six_dir_success": np.array([True, False, True]), "physics_tested": np.array([True, True, True])}
    return hand, data, mesh_io.load_mesh("ball")


@pytest.fixture(scope="module")
def view(grasps):
    hand, data, mesh = grasps
    v = viewer.show(data, hand, mesh, port=viewer.free_port())
    yield v
    v.stop()


def test_ranked_order_and_outcomes(grasps):
    _, data, _ = grasps
    np.testing.assert_array_equal(viewer.ranked(data), [2, 0, 1])  # valid first, then by E
    assert [viewer.outcome(data, i) for i in range(3)] == ["all", "none", "some"]
    assert viewer.outcome({k: v for k, v in data.items() if "success" not in k}, 0) == "plain"


def test_scene_nodes_and_hand_pose_follow_the_selected_grasp(view, grasps):
    hand, data, _ = grasps
    nodes = set(view.server.scene._handle_from_node_name)
    for name in ("/object", "/table", "/grasp/wrist", "/grasp/contacts", "/grasp/normals", "/grasp/friction_cones"):
        assert name in nodes, name
    assert len(view.handles["geoms"]) == len(view.geoms) > 10
    for rank in (0, 2):
        view.select(rank)
        i = int(view.order[rank])
        frames = K.forward_kinematics(hand, jax.numpy.asarray(data["wrist_pose"][i]), jax.numpy.asarray(data["q"][i]))
        got = np.array([h.position for h in view.handles["geoms"]])
        np.testing.assert_allclose(got, np.asarray(frames.geom_pos)[view.geoms], atol=1e-5)
        colour = viewer.COLOURS[viewer.outcome(data, i)]
        assert all(tuple(h.color) == colour for h in view.handles["geoms"])
        assert f"**grasp {i}**" in view.handles["info"].content


def test_friction_cones_open_by_the_friction_angle():
    p, n = np.zeros(3), np.array([0.0, 0.0, 1.0])
    segs = viewer.cone_segments(p, n, 0.5)
    d = segs[:, 1] - segs[:, 0]
    np.testing.assert_allclose(np.degrees(np.arccos(d @ n / np.linalg.norm(d, axis=1))), np.degrees(np.arctan(0.5)))


def test_bad_input_is_one_line(grasps):
    hand, data, mesh = grasps
    with pytest.raises(FfcgsError, match="channels but hand"):
        viewer.show({**data, "q": np.zeros((3, 4))}, hand, mesh, port=viewer.free_port())
    with pytest.raises(FfcgsError, match="no grasps to show"):
        viewer.show({"q": np.zeros((0, 9))}, hand, mesh, port=viewer.free_port())
    assert hand_of(data, None) == "svh"
    with pytest.raises(FfcgsError, match="match no built-in hand"):
        hand_of({"channel_names": np.array(["a", "b"])}, None)
    with pytest.raises(FfcgsError, match="--port"):
        ShowCmd("x.npz", port=0).check()


@pytest.mark.skipif(CHROMIUM is None, reason="needs Chromium (Debian: apt-get install chromium)")
def test_the_page_renders_in_a_real_browser(view, tmp_path):
    """Headless Chromium loads the page: a client connects, and the screenshot shows the object's colour (the 3D
    scene drew, not only the page around it)."""
    from PIL import Image

    connected = []
    view.server.on_client_connect(lambda client: connected.append(client.client_id))
    shot = tmp_path / "view.png"
    err = ""
    for _ in range(2):  # software WebGL on a loaded 2-core machine: one retry
        try:
            r = subprocess.run([CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader",
                                "--use-angle=swiftshader", "--window-size=800,600", "--virtual-time-budget=10000",
                                f"--screenshot={shot}", view.url], capture_output=True, text=True, timeout=180)
            err = r.stderr[-500:]
        except subprocess.TimeoutExpired:
            err = "chromium timed out"
        if connected and shot.is_file():
            break
    assert connected and shot.is_file(), f"the page never opened its websocket to the viewer: {err}"
    img = np.asarray(Image.open(shot).convert("RGB")).astype(int)
    assert img.std() > 5  # not blank
    obj = np.array(viewer.OBJECT_COLOUR)
    near = (np.abs(img - obj).max(-1) < 60).mean()
    assert near > 0.002, f"object colour on {near:.2%} of the screenshot"


def test_show_command_serves_a_grasp_file(grasps, tmp_path, capsys):
    from ffcgs_jax.cli import main as cli_main
    from ffcgs_jax.synthesis import grasp_io

    _, data, _ = grasps
    path = tmp_path / "g.npz"
    grasp_io.save_arrays({**data, "object_source": np.array("ball")}, path)
    assert cli_main.main(["show", str(path), "--port", str(viewer.free_port()), "--seconds", "0.3"]) in (0, None)
    assert "3D view of the grasps at http://127.0.0.1:" in capsys.readouterr().out
