"""Synthetic grasps of the success predictor's tests (tests/learning, tests/training): random poses and joint
angles around an object, their fingertip points and metrics, and a labelled dataset file of them."""

import hashlib

import jax
import jax.numpy as jnp
import numpy as np

from ffcgs_jax.dataset import mcap_io as dio
from ffcgs_jax.dataset import schema
from ffcgs_jax.hand import kinematics as K
from ffcgs_jax.learning import evaluator

CONTACTS = jax.jit(jax.vmap(K.contact_points, (None, 0, 0)))


def grasps(hand, g: int, seed: int) -> dict:
    """Random grasp arrays around the box (poses, channels within limits, their fingertip points, metrics)."""
    rng = np.random.default_rng(seed)
    poses = np.zeros((g, 4, 4))
    for i in range(g):
        qm, r = np.linalg.qr(rng.normal(size=(3, 3)))
        qm = qm * np.sign(np.diag(r))
        qm[:, 2] *= np.sign(np.linalg.det(qm))
        poses[i, :3, :3] = qm
        poses[i, :3, 3] = rng.normal(0, 0.05, 3) + [0, 0, 0.05]
        poses[i, 3, 3] = 1
    lo, hi = np.asarray(hand.lower), np.asarray(hand.upper)
    q = lo + rng.uniform(size=(g, len(lo))) * (hi - lo)
    contacts = np.asarray(CONTACTS(hand, jnp.asarray(poses), jnp.asarray(q)))
    c = contacts.shape[1]
    a = {"wrist_pose": poses, "q": q, "contacts": contacts, "contact_dist": rng.normal(0, 0.003, (g, c)),
         "squeeze_dir": rng.normal(size=q.shape), "n_contacts": rng.integers(0, c + 1, g),
         "valid": rng.uniform(size=g) < 0.7, "force_closure": rng.uniform(size=g) < 0.5}
    for k in evaluator.METRICS:
        a[k] = np.abs(rng.normal(0, evaluator.METRICS[k], g))
    return a


def write_labelled(path, hand, grid, split="train", n_obj=4, per=24):
    """A labelled dataset file of synthetic grasps on one SDF, labels from a rule of the grasp's height."""
    w = dio.DatasetWriter(path, {"hand": "svh", "keep": "all"}, extra={"note": "test"})
    ids = []
    for i in range(n_obj):
        a = grasps(hand, per, seed=10 + i)
        high = a["wrist_pose"][:, 2, 3] > 0.05
        labels = {k: np.asarray(a[k], np.float32) for k in (*evaluator.METRICS, "contact_dist", "contacts")
                  if k not in schema.GRASP_ARRAYS}
        labels |= {"valid": a["valid"], "force_closure": a["force_closure"], "n_contacts": a["n_contacts"],
                   "squeeze_dir": a["squeeze_dir"]}
        name = f"obj{i}"
        rec = schema.Record.create(
            object_name=name, mesh_sha256=hashlib.sha256(name.encode()).hexdigest(), rotation_index=0,
            rotation=np.eye(3), split=split if i == 0 else "train", sdf=grid, wrist_pose=a["wrist_pose"], q=a["q"],
            epsilon=a["epsilon"], E=a["E"], E_g=a["E_g"], E_c=a["E_c"], lift_shake_success=high,
            six_dir_success=high | (a["q"][:, 0] > 0), **labels)
        w.add(rec)
        ids.append(rec.record_id)
    return w.finish(expected=ids)
