"""`ffcgs dataset info --png`: a picture gallery of a dataset file, one PNG per object."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from ffcgs_jax.dataset import mcap_io as dataset_io
from ffcgs_jax.viz import grasp_plot
from ffcgs_jax.viz.render import save_png


def find_mesh(name: str, sha256: str, config: dict, objects_dir: Path | None):
    """The source mesh of an object: regenerated for a procedural shape, else `objects_dir/<name>.*`, checked
    against the hash the record carries; None if not found."""
    from ffcgs_jax.dataset import objects
    from ffcgs_jax.geometry import mesh_io

    mesh = objects.regenerate(name, config)
    if mesh is not None:
        return mesh if mesh_io.mesh_sha256(mesh) == sha256 else None
    if objects_dir is None:
        return None
    for p in sorted(objects_dir.glob(f"{name}.*")):
        if p.suffix.lower() in objects.MESH_SUFFIXES:
            mesh = objects.scaled(mesh_io.load_mesh(p), objects.object_scale(objects.stored_config(config), name))
            # datasets built before the geometry hash recorded the file's bytes
            if sha256 in (mesh_io.mesh_sha256(mesh), hashlib.sha256(p.read_bytes()).hexdigest()):
                return mesh
    return None


def gallery(path: str | Path, out_dir: str | Path, per_object: int = 4, objects_dir: str | Path | None = None
            ) -> tuple[list[Path], list[str]]:
    """One PNG per object, <out_dir>/<object>.png: its first record's `per_object` best grasps by epsilon, with the
    mesh rotated as in that record. The dataset stores SDFs, not meshes: meshes come from `objects_dir` (matched by
    name and SHA-256) or, for procedural shapes, are regenerated. Returns (pictures written, objects skipped for want
    of their mesh)."""
    from ffcgs_jax.dataset.build import rotate_mesh
    from ffcgs_jax.hand import kinematics as K
    from ffcgs_jax.synthesis import grasp as grasp_mod
    from ffcgs_jax.synthesis.config import GraspConfig

    config = dataset_io.read_config(path).get("config") or {}
    hand = K.load_hand(config.get("hand", "svh"))
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    objects_dir = None if objects_dir is None else Path(objects_dir)
    written, skipped, seen = [], [], set()
    for rec in dataset_io.iter_records(path):
        if rec.object_name in seen:
            continue
        seen.add(rec.object_name)
        mesh = find_mesh(rec.object_name, rec.mesh_sha256, config, objects_dir)
        if mesh is None or rec.num_grasps == 0:
            skipped.append(rec.object_name)
            continue
        g = rec.num_grasps
        arrays = {"wrist_pose": rec.wrist_pose, "q": rec.q, "E": rec.E, "E_g": rec.E_g, "E_c": rec.E_c,
                  "epsilon": rec.epsilon, "valid": np.ones(g, bool)}
        gs = grasp_mod.GraspSet(arrays, {}, GraspConfig(), rec.object_name)
        k = min(per_object, g)
        image, _ = grasp_plot.grasps_image(hand, rotate_mesh(mesh, rec.rotation), gs, k=k,
                                           order=np.argsort(-rec.epsilon, kind="stable")[:k])
        target = out_dir / f"{rec.record_id.rsplit('.', 1)[0]}.png"
        save_png(image, target)
        written.append(target)
    return written, skipped
