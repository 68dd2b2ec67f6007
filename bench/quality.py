"""The grasp-quality scoreboard: synthesis quality and physics success of the returned grasps, one row per sampler.

    python bench/quality.py                                  # ycb-test + builtin + procedural, cvae and geometric
    python bench/quality.py --objects builtin --samplers cvae --n 8 --max-grasps-per-object 2 --json /tmp/q.json
    python bench/quality.py --config default --config configs/paper.toml --json q.json --results bench/RESULTS.md
    python bench/quality.py --report q.json [--results bench/RESULTS.md]   # the tables again, from a JSON

Objects (`--objects`, comma list of groups): `ycb-test` (the YCB test split: the sorted *.stl of `--ycb` with
index % 5 == 4, or every file with `--every-file`), `builtin` (the package's meshes) and `procedural` (`--procedural`
shapes of `geometry.procedural` with seed 1000, not a training seed); `ycb-train` (the other YCB files: what
`bench/fit_score.py` fits the score on, never the test split); `complex` (`--complex` shapes of
`procedural.complex_shape` with seed 2000: many lobes, thin fins, tori, cups with handles, bowls, C-shapes, plates
with holes). Rows: every sampler of `--samplers` under
every `--config` (a GraspConfig TOML as `ffcgs grasp --config` reads it, or `default` for the package defaults;
label `sampler` for the defaults, `STEM:sampler` for a file); `--n`, `--seed` and the sampler always come from the
command line.

Per row, over the object set:
- valid share: valid grasps / sampled poses. "Returned" grasps are the valid ones, what `ffcgs grasp` returns.
- force closure of the returned grasps (`force_closure`, meant to count touching fingertips only) and, when the
  GraspSet has `contact_dist`, the share whose fingertips are all within `--contact-tol` of the surface.
- medians over the returned grasps (pooled over objects) of E, E_g, E_c (mm) and penetration (mm); and Table-II
  style: per object the mean E, E_g, E_c of the 20 lowest-E of all n sampled poses, median over objects.
- physics (protocol: `runner.evaluate` with PhysicsConfig(sim_friction=`--friction`, default 0.6) and its other
  defaults, lift-shake and six-dir; `--protocols` may add DexGraspBench's `dexgraspbench`, `dexgraspbench-bodex`,
  which fix their own friction, mass and gains, in a column each): every returned grasp in `gs.order()` order
  (best first), at most `--max-grasps-per-object` per object (0 = all). Success shares pooled over the tested
  grasps, 95 % Wilson.
- top-1: per object the first returned grasp passes every protocol run (an object without a valid grasp fails).
- yield: objects with at least n/4 returned grasps.
- seconds per object: median wall time of `synthesize` without each row's first (compiling) call, its device part
  (`synthesis_s`), the physics time, and the compile time apart (a load from JAX's persistent cache, as the CLI
  uses, when an earlier run compiled the same executable: `--no-jax-cache` to compile).
Figures from fields a GraspSet may lack (force_closure, contact_dist) print as "-"; n_contacts goes to
the JSON when present (null when not).
"""

import argparse
import contextlib
import dataclasses
import datetime
import json
import math
import os
import shlex
import sys
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ffcgs_jax.core import config as ffcgs_config
from ffcgs_jax.core import files
from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.physics.config import ALL_PROTOCOLS, BACKENDS, PROTOCOLS, PhysicsConfig
from ffcgs_jax.physics.protocols import wilson
from ffcgs_jax.synthesis.config import SAMPLERS, GraspConfig

from eval_grasp import ycb_test  # noqa: E402 - the sibling script's test-split rule

REPO = Path(__file__).resolve().parents[1]
GROUPS = ("ycb-test", "builtin", "procedural", "complex", "ycb-train")
PROCEDURAL_SEED = 1000  # the training shapes use other seeds: these are unseen
COMPLEX_SEED = 2000  # the complex family (`procedural.complex_shape`), unseen likewise; bench/validated_call.py's
TABLE2_K = 20  # the paper's Table II averages the 20 lowest-energy grasps per object
BEGIN, END = "<!-- quality:begin -->", "<!-- quality:end -->"
PROG = "quality.py"


class Parser(argparse.ArgumentParser):
    def error(self, message):  # one line, no usage block: bad input reads like the CLI's `ffcgs: error:`
        sys.stderr.write(f"{PROG}: error: {message} (see {PROG} --help)\n")
        sys.exit(2)


def int_at_least(lo: int):
    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if v < lo:
            raise argparse.ArgumentTypeError(f"must be >= {lo}, got {v}")
        return v
    return parse


def positive_float(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not (math.isfinite(v) and v > 0):
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {text}")
    return v


def split_list(text: str) -> list[str]:
    return [s.strip() for s in text.split(",") if s.strip()]


def parser() -> Parser:
    ap = Parser(prog=PROG, description=__doc__.splitlines()[0],
                formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--objects", default="ycb-test,builtin,procedural", help=f"comma list of {', '.join(GROUPS)}")
    ap.add_argument("--ycb", default=str(REPO.parent / "shared" / "objects" / "ycb"), help="folder of YCB *.stl")
    ap.add_argument("--every-file", action="store_true", help="--ycb holds only the test split: take every file")
    ap.add_argument("--procedural", type=int_at_least(0), default=8, help="procedural shapes (seed 1000)")
    ap.add_argument("--complex", type=int_at_least(0), default=8,
                    help="complex procedural shapes (seed 2000): lobes, fins, holes, cups, bowls")
    ap.add_argument("--samplers", default="cvae,geometric", help=f"comma list of {', '.join(SAMPLERS)}")
    ap.add_argument("--config", action="append", default=[], metavar="PATH",
                    help="GraspConfig TOML (e.g. configs/paper.toml) or 'default'; repeat for several (default: "
                         "the package defaults only)")
    ap.add_argument("--hand", default="svh")
    ap.add_argument("--n", type=int_at_least(1), default=32, help="wrist poses sampled per object")
    ap.add_argument("--seed", type=int_at_least(0), default=0)
    ap.add_argument("--friction", type=positive_float, default=0.6)
    ap.add_argument("--protocols", default=",".join(PROTOCOLS), help="comma list of physics protocols")
    ap.add_argument("--backend", default="auto", choices=BACKENDS, help="physics backend")
    ap.add_argument("--max-grasps-per-object", type=int_at_least(0), default=0, metavar="K",
                    help="physics-test at most the K best returned grasps per object (0: all)")
    ap.add_argument("--contact-tol", type=positive_float, default=0.002, help="m: a fingertip this close touches")
    ap.add_argument("--json", metavar="PATH", help="write the config and every per-object raw figure here")
    ap.add_argument("--results", metavar="PATH", help="replace or append the quality block of this Markdown file")
    ap.add_argument("--report", metavar="JSON", help="no synthesis: print (and --results) the tables of a --json")
    ap.add_argument("--no-jax-cache", action="store_true", help="compile instead of loading from JAX's disk cache")
    ap.add_argument("--save-grasps", metavar="DIR", help="also write each job's grasps, with the physics outcome of "
                    "every tested grasp (`physics_<field>`, -1 / NaN / False where untested), to DIR/ROW/OBJECT.npz: "
                    "what a ranking is fitted or judged on (`bench/rank_quality.py`)")
    return ap


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = parser()
    args = ap.parse_args(argv)
    if args.report:
        if not Path(args.report).is_file():
            ap.error(f"--report: no such file: {args.report}")
        if args.results and not Path(args.results).resolve().parent.is_dir():
            ap.error(f"--results: no such folder: {Path(args.results).parent}")
        return args
    groups = split_list(args.objects)
    unknown = [g for g in groups if g not in GROUPS]
    if unknown or not groups:
        ap.error(f"--objects: unknown group(s) {', '.join(unknown) or '(none given)'}; groups: {', '.join(GROUPS)}")
    args.groups = list(dict.fromkeys(groups))
    for g in ("ycb-test", "ycb-train"):
        if g in groups and not Path(args.ycb).is_dir():
            ap.error(f"--ycb: no such folder: {args.ycb} (needed by the {g} group)")
    samplers = split_list(args.samplers)
    bad = [s for s in samplers if s not in SAMPLERS]
    if bad or not samplers:
        ap.error(f"--samplers: unknown sampler(s) {', '.join(bad) or '(none given)'}; samplers: {', '.join(SAMPLERS)}")
    args.sampler_list = list(dict.fromkeys(samplers))
    protocols = split_list(args.protocols)
    bad = [p for p in protocols if p not in ALL_PROTOCOLS]
    if bad or not protocols:
        ap.error(f"--protocols: unknown protocol(s) {', '.join(bad) or '(none given)'}; "
                 f"protocols: {', '.join(ALL_PROTOCOLS)}")
    args.protocol_list = [p for p in ALL_PROTOCOLS if p in protocols]
    try:
        args.bases = [load_base(c) for c in (args.config or ["default"])]
    except FfcgsError as e:
        ap.error(f"--config: {e}")
    for flag, out in (("--json", args.json), ("--results", args.results)):
        if out and not Path(out).resolve().parent.is_dir():  # found out now, not after an hour of synthesis
            ap.error(f"{flag}: no such folder: {Path(out).parent}")
    try:
        PhysicsConfig(sim_friction=args.friction, backend=args.backend).check()
    except FfcgsError as e:
        ap.error(str(e))
    return args


def load_base(source: str) -> tuple[str, GraspConfig]:
    """(label prefix, GraspConfig) of a --config value: '' for the defaults, the file's stem for a TOML.

    The file may be a command config (the GraspConfig under [grasp], as configs/paper.toml) or a bare one."""
    if source in ("default", "ours"):
        return "", GraspConfig()
    path = Path(source)
    if not path.is_file() and (REPO / "configs" / f"{source}.toml").is_file():
        path = REPO / "configs" / f"{source}.toml"  # `--config paper`
    data = ffcgs_config.read_toml(path)
    if isinstance(data.get("grasp"), dict):
        data = data["grasp"]
    return path.stem, ffcgs_config.from_dict(GraspConfig, data)


def object_sources(args) -> list[tuple[str, str, object]]:
    """(group, name, source) per object; source is what `mesh_io.load_mesh` takes, or a mesh."""
    from ffcgs_jax.geometry import objects, procedural

    out = []
    for group in args.groups:
        if group == "builtin":
            out += [(group, name, name) for name in objects.names()]
        elif group == "ycb-test":
            out += [(group, f.stem, str(f)) for f in ycb_test(Path(args.ycb), args.every_file)]
        elif group == "ycb-train":  # what scores and thresholds are fitted on, never the test split
            test = set(ycb_test(Path(args.ycb)))
            out += [(group, f.stem, str(f)) for f in sorted(Path(args.ycb).glob("*.stl")) if f not in test]
        elif group == "complex":
            out += [(group, *procedural.complex_shape(COMPLEX_SEED, i)) for i in range(args.complex)]
        else:
            for i in range(args.procedural):
                name, mesh = procedural.shape(PROCEDURAL_SEED, i)
                out.append((group, name, mesh))
    return out


# ----------------------------------------------------------------------------------------------------- running


def _opt(a: dict, key: str):
    """A per-grasp field as a JSON list, or None when this GraspSet has no such field."""
    v = a.get(key)
    return None if v is None else np.asarray(v).tolist()


def run_job(hand, mesh, name: str, cfg: GraspConfig, args, save: Path | None = None) -> dict:
    from ffcgs_jax.physics import runner
    from ffcgs_jax.synthesis.grasp import synthesize

    t0 = time.perf_counter()
    gs = synthesize(hand, mesh, cfg, name)
    wall = time.perf_counter() - t0
    a = gs.arrays
    valid = np.asarray(gs["valid"], bool)
    order = np.asarray(gs.order())
    returned = order[:int(valid.sum())]  # order() puts the valid ones first
    cap = args.max_grasps_per_object
    tested = returned[:cap] if cap else returned
    physics, physics_s = {}, 0.0
    if len(tested):
        t1 = time.perf_counter()
        res = runner.evaluate(hand.spec, mesh, gs["wrist_pose"][tested], gs["q"][tested],
                              PhysicsConfig(sim_friction=args.friction, backend=args.backend), args.protocol_list,
                              squeeze_dir=gs["squeeze_dir"][tested])
        physics_s = time.perf_counter() - t1
        physics = {k: np.asarray(v).tolist() for k, v in res.items()}
    if save is not None:
        save_job(gs, tested, physics, save)
    return {
        "n": int(len(valid)), "valid": valid.tolist(), "order": order.tolist(), "tested": tested.tolist(),
        **{k: np.asarray(a[k], float).tolist() for k in ("E", "E_g", "E_c", "penetration", "epsilon")},
        **{k: _opt(a, k) for k in ("force_closure", "n_contacts", "contact_dist", "E_m", "support_min",
                                   "E_q", "table_penetration")},
        "physics": physics, "wall_s": wall, "synthesis_s": float(a["synthesis_s"]),
        "compile_s": float(a["compile_s"]), "physics_s": physics_s,
    }


def save_job(gs, tested: np.ndarray, physics: dict, path: Path) -> None:
    """`gs` as a grasp file plus `physics_<field>` per grasp (the tested ones filled) and `physics_tested`."""
    from ffcgs_jax.synthesis import grasp_io

    n = len(gs["valid"])
    extra = {"physics_tested": np.isin(np.arange(n), tested)}
    for k, v in physics.items():
        v = np.asarray(v)
        full = np.full((n, *v.shape[1:]), False if v.dtype == bool else -1 if v.dtype.kind in "iu" else np.nan,
                       v.dtype if v.dtype.kind in "biu" else np.float64)
        full[tested] = v
        extra[f"physics_{k}"] = full
    path.parent.mkdir(parents=True, exist_ok=True)
    grasp_io.save_npz(type(gs)({**gs.arrays, **extra}, {}, gs.config, gs.object_name), path)


def machine() -> dict:
    import jax

    devs = jax.local_devices()
    return {"backend": jax.default_backend(), "device": devs[0].device_kind, "device_count": len(devs),
            "cpus": os.cpu_count(), "date": datetime.date.today().isoformat()}


def run(args) -> dict:
    from ffcgs_jax.geometry import mesh_io
    from ffcgs_jax.hand import kinematics as K
    from ffcgs_jax.physics import runner

    if not args.no_jax_cache:
        from ffcgs_jax.runtime import jax_cache

        jax_cache.enable()
    objs = []
    for group, name, src in object_sources(args):
        # every mesh before the first compile: a broken file must not end a run an hour in
        objs.append((group, name, src if not isinstance(src, str) else mesh_io.load_mesh(src)))
    if not objs:
        raise FfcgsError(f"no objects in groups {', '.join(args.groups)}")
    hand = K.load_hand(args.hand)
    rows = [(f"{prefix}:{s}" if prefix else s, dataclasses.replace(base, n=args.n, sampler=s, seed=args.seed))
            for prefix, base in args.bases for s in args.sampler_list]
    labels = [r[0] for r in rows]
    if len(set(labels)) != len(labels):
        raise FfcgsError(f"two rows share a label: {', '.join(labels)} (configs with the same file stem?)")
    for _, cfg in rows:
        ffcgs_config.check_all(cfg)
    per_call = min(args.n, args.max_grasps_per_object) if args.max_grasps_per_object else args.n
    conf = {
        "command": command_line(), "machine": machine(), "groups": args.groups,
        "group_counts": {g: sum(o[0] == g for o in objs) for g in args.groups},
        "n": args.n, "seed": args.seed, "friction": args.friction, "protocols": args.protocol_list,
        "physics_backend": runner.resolve_backend(args.backend, per_call)[0], "hand": args.hand,
        "max_grasps_per_object": args.max_grasps_per_object, "contact_tol": args.contact_tol,
        "procedural": args.procedural, "procedural_seed": PROCEDURAL_SEED, "complex": args.complex,
        "complex_seed": COMPLEX_SEED, "ycb": args.ycb,
        "every_file": args.every_file, "rows": {label: dataclasses.asdict(cfg) for label, cfg in rows},
    }
    records, seen = [], set()
    jobs = [(o, r) for o in objs for r in rows]
    bar = tqdm(jobs, desc="quality", unit="job", file=sys.stderr)
    for (group, name, mesh), (label, cfg) in bar:
        bar.set_postfix_str(f"{name} / {label}")
        save = Path(args.save_grasps) / label.replace(":", "_") / f"{name}.npz" if args.save_grasps else None
        rec = run_job(hand, mesh, name, cfg, args, save)
        rec = {"object": name, "group": group, "row": label, "sampler": cfg.sampler, "warm": label in seen, **rec}
        seen.add(label)
        records.append(rec)
        if args.json:  # after every job: a long run cut short keeps what it measured
            files.write_text(args.json, json.dumps({"config": conf, "records": records}))
    return {"config": conf, "records": records}


def command_line() -> str:
    return "python bench/quality.py" + "".join(" " + shlex.quote(a) for a in sys.argv[1:])


# ---------------------------------------------------------------------------------------------------- reporting


def passed_every_protocol(rec: dict, protocols: list[str]) -> np.ndarray:
    """Per tested grasp: passed every protocol that was run."""
    ok = np.ones(len(rec["tested"]), bool)
    for p in protocols:
        ok &= np.asarray(rec["physics"].get(f"{p.replace('-', '_')}_success", []), bool).reshape(-1)
    return ok


def object_figures(rec: dict, protocols: list[str], contact_tol: float) -> dict:
    """What one (object, row) contributes to the table; everything recomputed from the raw record."""
    n = rec["n"]
    valid = np.asarray(rec["valid"], bool)
    order = np.asarray(rec["order"], int)
    returned = order[valid[order]] if n else order
    tested = np.asarray(rec["tested"], int)
    both = passed_every_protocol(rec, protocols)
    arr = {k: np.asarray(rec[k], float) for k in ("E", "E_g", "E_c", "penetration")}
    low = np.argsort(arr["E"], kind="stable")[:TABLE2_K]
    top1 = int(order[0]) if n and valid[order[0]] else None
    top1_ok = top1 is not None and len(tested) > 0 and int(tested[0]) == top1 and bool(both[0])
    out = {
        "n": n, "valid": int(valid.sum()), "returned": returned,
        "returned_vals": {k: v[returned] for k, v in arr.items()},
        "table2": {k: float(arr[k][low].mean()) if len(low) else math.nan for k in ("E", "E_g", "E_c")},
        "fc": None if rec.get("force_closure") is None else np.asarray(rec["force_closure"], bool)[returned],
        "all_touch": None, "tested": len(tested), "both": both, "top1": top1, "top1_ok": top1_ok,
        "success": {p: np.asarray(rec["physics"].get(f"{p.replace('-', '_')}_success", []), bool).reshape(-1)
                    for p in protocols},
    }
    if rec.get("contact_dist") is not None and n:
        d = np.abs(np.asarray(rec["contact_dist"], float)).reshape(n, -1)
        out["all_touch"] = (d <= contact_tol).all(axis=1)[returned]
    return out


def summarise(report: dict) -> list[dict]:
    """One dict per row (in the order the rows were run) of pooled counts, medians and times."""
    conf = report["config"]
    protocols, tol, n = conf["protocols"], conf["contact_tol"], conf["n"]
    rows = list(dict.fromkeys(r["row"] for r in report["records"]))
    out = []
    for label in rows:
        recs = [r for r in report["records"] if r["row"] == label]
        figs = [object_figures(r, protocols, tol) for r in recs]
        cat = lambda k: np.concatenate([f["returned_vals"][k] for f in figs])  # noqa: E731
        med = lambda x: float(np.median(x)) if len(x) else math.nan  # noqa: E731
        fc = [f["fc"] for f in figs]
        touch = [f["all_touch"] for f in figs]
        warm = [r["wall_s"] for r in recs if r["warm"]]
        s = {
            "row": label, "objects": len(recs),
            "valid": (sum(f["valid"] for f in figs), sum(f["n"] for f in figs)),
            "fc": None if any(x is None for x in fc) else (int(sum(x.sum() for x in fc)), sum(len(x) for x in fc)),
            "all_touch": None if any(x is None for x in touch)
            else (int(sum(x.sum() for x in touch)), sum(len(x) for x in touch)),
            "E": med(cat("E")), "E_g": med(cat("E_g")), "E_c_mm": 1000 * med(cat("E_c")),
            "pen_mm": 1000 * med(cat("penetration")),
            "t2_E": med([f["table2"]["E"] for f in figs]), "t2_E_g": med([f["table2"]["E_g"] for f in figs]),
            "t2_E_c_mm": 1000 * med([f["table2"]["E_c"] for f in figs]),
            "success": {p: (int(sum(f["success"][p].sum() for f in figs)), sum(f["tested"] for f in figs))
                        for p in protocols},
            "both": (int(sum(f["both"].sum() for f in figs)), sum(f["tested"] for f in figs))
            if len(protocols) == len(PROTOCOLS) else None,
            "top1": (sum(f["top1_ok"] for f in figs), len(figs)),
            "top1_none": sum(f["top1"] is None for f in figs),
            "yield": (sum(f["valid"] >= n / 4 for f in figs), len(figs)),
            "wall_s": med(warm) if warm else med([r["wall_s"] for r in recs]), "wall_cold": not warm,
            "synthesis_s": med([r["synthesis_s"] for r in recs]),
            "physics_s": med([r["physics_s"] for r in recs if r["tested"]]),
            "compile_s": max(r["compile_s"] for r in recs),
        }
        out.append(s)
    return out


def rate(k_n) -> str:
    """'k / n = p % (lo-hi %)' with the 95 % Wilson interval; '-' when the figure is absent or n = 0."""
    if k_n is None or k_n[1] == 0:
        return "-"
    k, n = k_n
    lo, hi = wilson(int(k), int(n))
    return f"{k} / {n} = {100 * k / n:.1f} % ({100 * lo:.0f}-{100 * hi:.0f} %)"


def format_fixed(x: float, digits: int = 3) -> str:
    return "-" if x is None or not math.isfinite(x) else f"{x:.{digits}f}"


def _g(x: float) -> str:
    """Three significant digits: E_g and E_c of good grasps are orders of magnitude below E."""
    return "-" if x is None or not math.isfinite(x) else f"{x:.3g}"


def header_line(conf: dict) -> str:
    m = conf["machine"]
    objs = ", ".join(f"{g} {c}" for g, c in conf["group_counts"].items())
    cap = conf["max_grasps_per_object"]
    return (f"quality · {m['device']} x{m['device_count']} ({m['backend']}), {m['cpus']} CPUs · {m['date']} · "
            f"objects: {objs} · friction {conf['friction']} · n {conf['n']} · seed {conf['seed']} · "
            f"physics {conf['physics_backend']} ({', '.join(conf['protocols'])}; "
            f"{'all returned grasps' if not cap else f'at most {cap} returned grasp(s) per object'}) · "
            f"`{conf['command']}`")


def table(report: dict) -> str:
    conf = report["config"]
    prot = conf["protocols"]
    tol_mm = 1000 * conf["contact_tol"]
    extra = [p for p in prot if p not in PROTOCOLS]  # DexGraspBench's, a column each after ours
    lines = [
        "| row | objects | valid share | FC touching (returned) | median E / E_g / E_c mm / pen mm (returned) "
        "| Table-II E / E_g / E_c mm | lift-shake | six-dir | " + "".join(f"{p} | " for p in extra)
        + "both | top-1 both | yield >= n/4 | s/object |",
        "|---|---|---|---|---|---|---|---|" + "---|" * len(extra) + "---|---|---|---|",
    ]
    for s in summarise(report):
        fc = rate(s["fc"])
        if s["all_touch"] is not None:
            fc += f"; all tips <= {tol_mm:g} mm: {rate(s['all_touch'])}"
        vk, vn = s["valid"]
        secs = (f"{format_fixed(s['wall_s'], 2)}{' (cold)' if s['wall_cold'] else ''} "
                f"(device {format_fixed(s['synthesis_s'], 2)}) "
                f"+ physics {format_fixed(s['physics_s'], 1)}; compile {format_fixed(s['compile_s'], 0)}")
        lines.append(
            f"| {s['row']} | {s['objects']} | {100 * vk / max(vn, 1):.1f} % ({vk}/{vn}) | {fc} | "
            f"{_g(s['E'])} / {_g(s['E_g'])} / {_g(s['E_c_mm'])} / {_g(s['pen_mm'])} | "
            f"{_g(s['t2_E'])} / {_g(s['t2_E_g'])} / {_g(s['t2_E_c_mm'])} | "
            f"{rate(s['success'].get('lift-shake'))} | {rate(s['success'].get('six-dir'))} | "
            + "".join(f"{rate(s['success'].get(p))} | " for p in extra) + f"{rate(s['both'])} | "
            f"{rate(s['top1'])} | {s['yield'][0]} / {s['yield'][1]} | {secs} |")
    none = {s["row"]: s["top1_none"] for s in summarise(report) if s["top1_none"]}
    lines.append("")
    lines.append(
        f"Physics at friction {conf['friction']} ({', '.join(prot)}) over the returned (valid) grasps, best first"
        + (f", at most {conf['max_grasps_per_object']} per object" if conf["max_grasps_per_object"] else "")
        + "; shares pooled over grasps with 95 % Wilson intervals. top-1: the object's best returned grasp passes "
        "every protocol run; an object without a valid grasp counts as a failure"
        + (f" ({', '.join(f'{k}: {v}' for k, v in none.items())})" if none else "")
        + ". Table-II: per object the mean of the 20 lowest-E of all sampled poses, median over objects. "
        "s/object: median synthesize wall time without each row's first call (device part in brackets), median "
        "physics time, largest compile (or cache load) time.")
    return "\n".join(lines) + "\n"


def validated_first(rec: dict) -> tuple[int | None, dict[str, bool]]:
    """The grasp `fj.validate` with lift-shake and six-dir would offer first for this (object, row), and whether it
    passes each protocol run. Derived from the record's own simulations: validate simulates the same tested grasps
    with the same settings (the physics is deterministic) and ranks them with `evaluation.ranking.ranked`, which
    is called here on the same arrays."""
    from ffcgs_jax.evaluation.ranking import ranked

    n = rec["n"]
    valid = np.asarray(rec["valid"], bool)
    tested = np.asarray(rec["tested"], int)
    if not n or not valid.any():
        return None, {}
    results = {k: np.asarray(v).reshape(len(tested), -1)[:, 0] if len(tested) else np.zeros(0)
               for k, v in rec["physics"].items() if k.endswith("_success")}
    passed = np.zeros(n, bool)
    if len(tested):
        passed[tested] = np.logical_and.reduce([results[f"{p.replace('-', '_')}_success"].astype(bool)
                                                for p in PROTOCOLS])
    first = int(ranked({"q": np.zeros(n), "valid": valid, "E": np.asarray(rec["E"], float),
                        "physics_passed": passed})[0])
    where = np.flatnonzero(tested == first)
    return first, {k[:-len("_success")]: bool(v[where[0]]) if len(where) else False for k, v in results.items()}


def validated_table(report: dict) -> str:
    """Top-1 by object with and without the physics-checked ranking (issue 31): the first grasp a user gets from
    `ffcgs grasp` against the one from `ffcgs grasp --validate` (lift-shake and six-dir checked)."""
    conf = report["config"]
    prot = conf["protocols"]
    if not all(p in prot for p in PROTOCOLS):
        return ""
    extra = [p for p in prot if p not in PROTOCOLS]
    lines = ["| row | objects | top-1 both: offered order | top-1 both: validated | "
             + "".join(f"top-1 {p}: offered | top-1 {p}: validated | " for p in extra)
             + "median penetration of returned grasps (mm) |",
             "|---|---|---|---|" + "---|---|" * len(extra) + "---|"]
    for s in summarise(report):
        recs = [r for r in report["records"] if r["row"] == s["row"]]
        firsts = [validated_first(r) for r in recs]
        figs = [object_figures(r, prot, conf["contact_tol"]) for r in recs]
        def analytic(names):  # the offered first grasp was tested and passed every protocol of `names`
            return sum(f["top1"] is not None and f["tested"] > 0 and int(np.asarray(r["tested"])[0]) == f["top1"]
                       and all(bool(f["success"][p][0]) for p in names) for f, r in zip(figs, recs))

        def validated(names):
            return sum(all(ok.get(p.replace("-", "_"), False) for p in names) for _, ok in firsts)

        cells = []
        for p in extra:
            cells += [rate((analytic([p]), len(recs))), rate((validated([p]), len(recs)))]
        lines.append(f"| {s['row']} | {len(recs)} | {rate((analytic(PROTOCOLS), len(recs)))} | "
                     f"{rate((validated(PROTOCOLS), len(recs)))} | "
                     + "".join(f"{c} | " for c in cells) + f"{_g(s['pen_mm'])} |")
    lines += ["", "top-1 by object: the first grasp offered passes (an object without a valid grasp fails). Offered "
              "order: what `ffcgs grasp` returns first (valid, then predicted success; E with --rank energy or no "
              "predictor for the hand). Validated: the grasps that pass lift-shake and six-dir first "
              "(`ffcgs grasp --validate`, `fj.validate`), from the same simulations as the columns above"
              + (f"; {', '.join(extra)} is an independent check of the validated grasp" if extra else "") + "."]
    return "\n".join(lines) + "\n"


def per_object_table(report: dict) -> str:
    protocols, tol = report["config"]["protocols"], report["config"]["contact_tol"]
    lines = ["| object | row | valid | returned tested | both passed | top-1 ok |", "|---|---|---|---|---|---|"]
    for r in report["records"]:
        f = object_figures(r, protocols, tol)
        top1 = "no valid grasp" if f["top1"] is None else ("yes" if f["top1_ok"] else "no")
        lines.append(f"| {r['object']} | {r['row']} | {f['valid']}/{f['n']} | {f['tested']} of {len(f['returned'])} "
                     f"| {int(f['both'].sum())}/{f['tested']} | {top1} |")
    return "\n".join(lines) + "\n"


def markers(hand: str = "svh") -> tuple[str, str]:
    """The quality block's markers: one block per hand (the SVH's keeps the unnamed markers)."""
    return (BEGIN, END) if hand == "svh" else (BEGIN.replace(" -->", f" {hand} -->"), END.replace(" -->", f" {hand} -->"))


def write_results(path: Path, block: str, hand: str = "svh") -> None:
    """Replace the text between `hand`'s quality markers in `path`, or append the block to it."""
    text = path.read_text() if path.exists() else ""
    begin, end = markers(hand)
    body = f"{begin}\n{block.rstrip()}\n{end}"
    if begin in text and end in text and text.index(begin) < text.index(end):
        text = text[:text.index(begin)] + body + text[text.index(end) + len(end):]
    else:
        text = (text.rstrip("\n") + "\n\n" if text.strip() else "") + body + "\n"
    files.write_text(path, text)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        if args.report:
            report = json.loads(Path(args.report).read_text())
        else:
            t0 = time.perf_counter()
            with contextlib.redirect_stdout(sys.stderr):  # warp's start-up banner must not land in the table
                report = run(args)
            report["config"]["total_s"] = time.perf_counter() - t0
            if args.json:
                files.write_text(args.json, json.dumps(report))
    except FfcgsError as e:
        print(f"{PROG}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted", file=sys.stderr)
        return 130
    head = header_line(report["config"])
    main_table = table(report) + ("\n" + validated_table(report) if validated_table(report) else "")
    print(head + "\n\n" + main_table + "\n" + per_object_table(report))
    if "total_s" in report["config"]:
        print(f"{len(report['records'])} jobs in {report['config']['total_s']:.0f} s")
    if args.results:
        write_results(Path(args.results), head + "\n\n" + main_table, report["config"].get("hand", "svh"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
