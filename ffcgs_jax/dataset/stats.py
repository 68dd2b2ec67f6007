"""`ffcgs dataset info`: counts, quality and diversity of a dataset file (its picture gallery: `viz.dataset_gallery`).

Statistics stream over the file (one record at a time). Per object, the annotation counts stored in each record's
`info` (candidates refined, valid, physics-tested, passed) give the planner's yield and the physics pass rate of
the candidates it tested; the kept grasps themselves all passed by construction.

Diversity: the approach direction of a grasp is its palm normal in the object frame. Per object (first record)
we report the mean resultant length |mean of the unit approach vectors| (1: all grasps approach from one side,
0: balanced) and how many of 20 equal-area direction cells (icosahedron faces) hold at least one grasp.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ffcgs_jax.dataset import mcap_io as dataset_io
from ffcgs_jax.dataset.schema import SUCCESS_KEYS
from ffcgs_jax.core.files import check_file


def _icosahedron_face_centres() -> np.ndarray:
    import trimesh

    ico = trimesh.creation.icosahedron()
    c = ico.triangles_center
    return c / np.linalg.norm(c, axis=1, keepdims=True)


def diversity(directions: np.ndarray) -> dict:
    """{"resultant": |mean unit vector|, "cells": occupied icosahedron-face cells of 20} of (G, 3) directions."""
    d = np.asarray(directions, np.float64).reshape(-1, 3)
    if len(d) == 0:
        return {"resultant": None, "cells": 0}
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    cells = np.argmax(d @ _icosahedron_face_centres().T, axis=1)
    return {"resultant": float(np.linalg.norm(d.mean(0))), "cells": int(len(np.unique(cells)))}


def _palm_normal(config: dict) -> np.ndarray:
    from ffcgs_jax.hand import spec as hand_spec

    hand = (config.get("config") or {}).get("hand", "svh")
    return np.asarray(hand_spec.load_spec(hand).palm_normal, np.float64)


def stats(path: str | Path) -> dict:
    """Everything `ffcgs dataset info` prints, as a JSON-ready dict."""
    path = Path(path)
    check_file(path, "dataset file")
    config = dataset_io.read_config(path)
    normal = _palm_normal(config)
    per_object: dict[str, dict] = {}
    eps, E_g, E_c, splits = [], [], [], {}
    n_records = 0
    labelled: dict[str, int] = {}  # a labelled build's record 0 per object: candidates and passes per protocol
    for rec in dataset_io.iter_records(path):
        n_records += 1
        if rec.rotation_index == 0 and "candidates" in rec.info:
            arrays = rec.grasp_arrays()
            labelled["candidates"] = labelled.get("candidates", 0) + rec.num_grasps
            labelled["all"] = labelled.get("all", 0) + int(rec.holds().sum())
            for k in SUCCESS_KEYS:
                if k in arrays:
                    labelled[k] = labelled.get(k, 0) + int(arrays[k].sum())
        s = splits.setdefault(rec.split, {"records": 0, "grasps": 0, "objects": set()})
        s["records"] += 1
        s["grasps"] += rec.num_grasps
        s["objects"].add(rec.object_name)
        eps.append(rec.epsilon)
        E_g.append(rec.E_g)
        E_c.append(rec.E_c)
        o = per_object.get(rec.object_name)
        if o is None:  # the first record of an object: its annotation counts and its diversity
            approach = rec.wrist_pose[:, :3, :3] @ normal
            o = per_object[rec.object_name] = {
                "category": rec.category or "-", "split": rec.split, "records": 0, "grasps": 0,
                "per_record": rec.num_grasps, "epsilon_median": float(np.median(rec.epsilon)) if rec.num_grasps
                else None, "info": rec.info, **diversity(approach)}
        o["records"] += 1
        o["grasps"] += rec.num_grasps
    cat: dict[str, dict] = {}
    for name, o in per_object.items():
        c = cat.setdefault(o["category"], {"objects": 0, "grasps": 0, "tested": 0, "passed": 0, "short": 0})
        c["objects"] += 1
        c["grasps"] += o["grasps"]
        # a labelled build tests every candidate with every protocol: its "passed" is passed_all
        c["tested"] += int(o["info"].get("tested_six_dir", o["info"].get("candidates", 0)))
        c["passed"] += int(o["info"].get("passed_both", o["info"].get("passed_all", 0)))
        c["short"] += int(o["per_record"] < config["config"].get("per_object", 0))
    for c in cat.values():
        c["physics_pass_rate"] = c["passed"] / c["tested"] if c["tested"] else None
    tested = sum(c["tested"] for c in cat.values())
    passed = sum(c["passed"] for c in cat.values())
    cat_all = lambda arrs: np.concatenate(arrs) if arrs else np.zeros(0)  # noqa: E731
    div = [o for o in per_object.values() if o["resultant"] is not None]
    return {
        "file": str(path), "version": config.get("version"), "records": n_records, "objects": len(per_object),
        "grasps": int(sum(o["grasps"] for o in per_object.values())),
        "splits": {k: {**v, "objects": len(v["objects"])} for k, v in sorted(splits.items())},
        "epsilon": dataset_io.quantiles(cat_all(eps)), "epsilon_pos_fraction": float((cat_all(eps) > 0).mean()) if eps else None,
        "E_g": dataset_io.quantiles(cat_all(E_g)), "E_c_cm": dataset_io.quantiles(cat_all(E_c) * 100),
        "physics": {"tested": tested, "passed_both": passed, "pass_rate": passed / tested if tested else None},
        "labelled": labelled or None,
        "categories": dict(sorted(cat.items())),
        "diversity": {"resultant_median": float(np.median([o["resultant"] for o in div])) if div else None,
                      "cells_median": float(np.median([o["cells"] for o in div])) if div else None},
        "per_object": dict(sorted(per_object.items())),
        "config": config.get("config"),
    }


def format_stats(s: dict) -> str:
    """The human-readable report of `stats`."""
    f = lambda v, fmt="{:.4g}": "-" if v is None else fmt.format(v)  # noqa: E731
    lines = [f"{s['file']}: {s['records']} records, {s['objects']} objects, {s['grasps']} grasps "
             f"(ffcgs-jax {s['version']})"]
    for k, v in s["splits"].items():
        lines.append(f"  split {k}: {v['objects']} objects, {v['records']} records, {v['grasps']} grasps")
    if s["epsilon"]:
        e = s["epsilon"]
        lines.append(f"  epsilon: median {f(e['median'])}, q05 {f(e['q05'])}, q95 {f(e['q95'])}, max {f(e['max'])}; "
                     f"> 0 for {100 * s['epsilon_pos_fraction']:.1f} %")
        lines.append(f"  E_g median {f(s['E_g']['median'])}, E_c median {f(s['E_c_cm']['median'])} cm")
    p = s["physics"]
    lines.append(f"  physics (six-dir and lift-shake; a labelled build: every protocol) over tested candidates: {p['passed_both']} / {p['tested']}"
                 f" = {f(p['pass_rate'] and 100 * p['pass_rate'], '{:.1f}')} %")
    lab = s.get("labelled")
    if lab and lab.get("candidates"):
        n = lab["candidates"]
        each = ", ".join(f"{k.removesuffix('_success')} {v} ({100 * v / n:.1f} %)" for k, v in lab.items()
                         if k.endswith("_success"))
        lines.append(f"  labelled candidates (record 0 of each object): {n}; passed {each}; all of them "
                     f"{lab['all']} ({100 * lab['all'] / n:.1f} %)")
    d = s["diversity"]
    lines.append(f"  diversity per object (median): approach resultant {f(d['resultant_median'], '{:.2f}')}, "
                 f"{f(d['cells_median'], '{:.0f}')} of 20 direction cells")
    lines.append("")
    lines.append(f"  {'category':<12} {'objects':>7} {'grasps':>8} {'tested':>7} {'passed':>7} {'rate':>6} {'short':>6}")
    for k, c in s["categories"].items():
        rate = f(c["physics_pass_rate"] and 100 * c["physics_pass_rate"], "{:.1f}")
        lines.append(f"  {k:<12} {c['objects']:>7} {c['grasps']:>8} {c['tested']:>7} {c['passed']:>7} {rate:>6} "
                     f"{c['short']:>6}")
    lines.append("")
    lines.append(f"  {'object':<28} {'split':<6} {'kept':>5} {'valid':>6} {'tested':>7} {'passed':>7} "
                 f"{'eps med':>8} {'resultant':>9} {'cells':>5}")
    for name, o in s["per_object"].items():
        i = o["info"]
        lines.append(f"  {name[:28]:<28} {o['split']:<6} {o['per_record']:>5} {i.get('valid', 0):>6} "
                     f"{i.get('tested_six_dir', 0):>7} {i.get('passed_both', 0):>7} {f(o['epsilon_median']):>8} "
                     f"{f(o['resultant'], '{:.2f}'):>9} {o['cells']:>5}")
    return "\n".join(lines)
