"""Pictures of grasps: the object with the best grasps, one row per grasp, a few views each (host side)."""

import numpy as np
import trimesh
from PIL import Image, ImageDraw

from ffcgs_jax.hand.kinematics import Hand
from ffcgs_jax.core.errors import check_grasp_set
from ffcgs_jax.viz import render, scene


def grasps_image(hand: Hand, mesh: trimesh.Trimesh, gs, k: int = 4, size: int = 320,
                 views: tuple[str, ...] = ("front", "side", "top"), backend: str = "auto",
                 order: np.ndarray | None = None) -> tuple[np.ndarray, str]:
    """(k * size, len(views) * size, 3) image of the k best grasps (valid first, by E; or the grasps at `order`)
    with a caption each."""
    check_grasp_set(gs, "plot_grasps")
    order = gs.order()[:k] if order is None else np.asarray(order)
    rows, used = [], "software"
    coupling = np.asarray(hand.coupling)
    table_z = float(mesh.bounds[0, 2])
    for i in order:
        m, d = scene.build_scene(hand.spec, gs["wrist_pose"][i], mesh, table_z)
        scene.set_channels(m, d, coupling, gs["q"][i])
        img, used = render.render_scene(m, d, size, size, backend, views)
        caption = (f"#{i} {'valid' if gs['valid'][i] else 'invalid'}  E={gs['E'][i]:.3f}  E_g={gs['E_g'][i]:.3f}  "
                   f"E_c={gs['E_c'][i] * 100:.2f} cm  eps={gs['epsilon'][i]:.3f}")
        pil = Image.fromarray(img)
        ImageDraw.Draw(pil).text((6, size - 16), caption, fill=(20, 20, 20))
        rows.append(np.asarray(pil))
    return np.concatenate(rows, 0), used
