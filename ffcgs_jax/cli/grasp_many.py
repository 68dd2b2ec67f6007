"""`ffcgs grasp` of several objects or a folder: one grasp file per object in the `--out` folder, resumable.

Each object's `<name>.npz` lands whole as soon as that object is done (named in the folder's manifest first,
`files.add_to_manifest`, then written atomically), so an interrupted run leaves complete files only. Each file
records `run_key`: a hash of contents, not of paths (`settings_text`, `run_key`): every option that shapes the file
(all but the object list and `--out`), the package version, the hand (its spec and compiled model, so an MJCF or
mesh it names counts too), the weights files the synthesis reads (the CVAE sampler's and the success predictor's,
given or shipped), and the object's geometry as loaded and scaled (`mesh_io.mesh_sha256`). Running the command
again skips the objects whose file holds the same key, and does again those written with other settings, another
hand or weights, or from a mesh that changed since, even when edited in place or copied over.
"""

import contextlib
import dataclasses
import hashlib
import json
import sys
import time
import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ffcgs_jax.core import files
from ffcgs_jax.core.version import __version__
from ffcgs_jax.core.errors import FfcgsError

WRITTEN_BY = "ffcgs grasp"  # the folder's manifest: a folder of another command's files is not added to


def run(cmd, validate: Callable) -> int:
    """Grasp every object of `cmd` (a `cli.commands.GraspCmd` with `many`) not yet written; `validate(gs, hand,
    mesh) -> (gs, rows)` physics-checks one object's grasps when `cmd.validate`. The exit status: 0 when every
    object has its file, 1 when any failed (each listed on stderr, one line)."""
    from tqdm import tqdm

    from ffcgs_jax.geometry import mesh_io
    from ffcgs_jax.hand import kinematics as K
    from ffcgs_jax.synthesis import grasp_io
    from ffcgs_jax.synthesis.many import expand_objects, synthesize_many

    objects = expand_objects(cmd.object)
    out = Path(cmd.out_path).expanduser()
    settings = settings_text(cmd)
    files.manifest_by(out, WRITTEN_BY)
    files.remove_left_behind(out)
    done, redo = _written(out, objects, settings, cmd.grasp.sdf.scale)
    todo = [o for o in objects if o.name not in done]
    if done or redo:
        print(f"{cmd.out_path}: {len(done)} of {len(objects)} objects already written with these settings, skipped"
              + (f"; {len(redo)} written with other settings or from a changed mesh, done again" if redo else ""))
    rows = dict(done)
    failed: list[tuple[str, str]] = []
    if todo:
        hand = K.load_hand(cmd.hand)
        # closed on an interrupt here too, so the next object's load is not waited for
        with tqdm(total=len(todo), desc="objects", unit="object", disable=None) as bar, \
                contextlib.closing(synthesize_many(hand, todo, cmd.grasp)) as results:
            for r in results:
                t0 = time.perf_counter()
                gs, error = r.grasps, r.error
                if gs is not None and cmd.validate:
                    try:
                        gs, _ = validate(gs, hand, r.mesh)
                    except FfcgsError as e:
                        gs, error = None, str(e)
                if gs is None:
                    failed.append((r.name, error))
                    rows[r.name] = _row(None, r.seconds, "failed")
                else:
                    identity = mesh_io.identity(r.source, cmd.grasp.sdf.scale, r.mesh)
                    gs = gs.with_arrays(**identity, run_key=np.array(run_key(settings, str(identity["object_sha256"]))))
                    out.mkdir(parents=True, exist_ok=True)
                    files.add_to_manifest(out, f"{r.name}.npz", WRITTEN_BY)
                    grasp_io.save_npz(gs, out / f"{r.name}.npz")
                    rows[r.name] = _row(gs.arrays, r.seconds + time.perf_counter() - t0, "done")
                bar.set_postfix_str(f"{r.name}{f', {len(failed)} failed' if failed else ''}", refresh=False)
                bar.update(1)
    _print_table([(o.name, rows[o.name]) for o in objects], cmd.validate)
    for name, error in failed:
        print(f"ffcgs: error: {name}: {error}", file=sys.stderr)
    written = len(todo) - len(failed)
    files.announce(f"wrote {written} grasp file(s) to {cmd.out_path}" + (f"; {len(failed)} object(s) failed"
                                                                         if failed else ""))
    return 1 if failed else 0


def settings_text(cmd) -> str:
    """What shapes an object's grasp file besides its mesh, as text: every option but the object list and --out
    (the physics ones only with --validate), the package version, and the contents (never the paths) of the hand
    (`hand_sha256`) and of the weights files the synthesis reads (`weights_sha256`). FfcgsError when the hand
    cannot be loaded."""
    from ffcgs_jax.hand.spec import load_spec

    spec = load_spec(cmd.hand)
    d = dataclasses.asdict(dataclasses.replace(cmd, object=(), out=None, hand=""))
    if not cmd.validate:
        for k in ("protocol", "need", "physics"):
            d.pop(k)
    d["grasp"]["sampling"].pop("weights")  # paths: their files' contents stand in below
    d["grasp"].pop("evaluator")
    return json.dumps({"version": __version__, **d, "hand_sha256": hand_sha256(spec),
                       "weights_sha256": weights_sha256(cmd.grasp, spec.name)}, sort_keys=True, default=str)


def hand_sha256(spec) -> str:
    """SHA-256 of a hand as the synthesis sees it: the spec's fields (not where its MJCF lies) and the compiled
    MuJoCo model (`mj_saveModel`'s bytes: every body, joint, geom and mesh the MJCF and its includes define)."""
    import mujoco

    fields = {k: v for k, v in dataclasses.asdict(spec).items() if k != "mjcf_path"}
    m = spec.mj_model()
    model = np.zeros(mujoco.mj_sizeModel(m), np.uint8)
    mujoco.mj_saveModel(m, None, model)
    h = hashlib.sha256(json.dumps(fields, sort_keys=True).encode())
    h.update(model.tobytes())
    return h.hexdigest()


def weights_sha256(cfg, hand_name: str) -> dict[str, str]:
    """{"cvae": ..., "evaluator": ...}: SHA-256 of each weights file `cfg` (a `GraspConfig`) reads for hand
    `hand_name`, the one given or the one installed or shipped; "none" where there is none (a sampler other than the
    CVAE, no such file), "missing" for a given file that is not there (the synthesis then says so)."""
    from ffcgs_jax.learning.weights import default_weights

    def digest(given: str, default: Path) -> str:
        path = Path(given).expanduser() if given else default
        if not path.is_file():
            return "missing" if given else "none"
        h = hashlib.sha256()
        with open(path, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
        return h.hexdigest()

    cvae = cfg.sampler in ("auto", "cvae")
    return {"cvae": digest(cfg.sampling.weights, default_weights("cvae", hand_name)) if cvae else "none",
            "evaluator": digest(cfg.evaluator, default_weights("evaluator", hand_name))}


def run_key(settings: str, mesh_sha256: str) -> str:
    """The hash of `settings` (`settings_text`) and of the object's geometry `mesh_sha256` (`mesh_io.mesh_sha256`
    of the mesh as loaded and scaled); "" when the geometry is unknown ("": the mesh does not load)."""
    if not mesh_sha256:
        return ""
    return hashlib.sha256(f"{settings}\n{mesh_sha256}".encode()).hexdigest()


def mesh_key(source: str, scale: float) -> str:
    """`mesh_io.mesh_sha256` of the mesh `source` (a built-in name or a file) loaded with `scale`, as the synthesis
    loads it; "" when it does not load (its synthesis then fails, and says why). Its warnings are left to the
    synthesis's load, which says them once."""
    from ffcgs_jax.geometry import mesh_io

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return mesh_io.mesh_sha256(mesh_io.load_mesh(source, scale=scale))
    except Exception:  # noqa: BLE001 - any failure to read the caller's file: the object is done again
        return ""


def _written(out: Path, objects, settings: str, scale: float) -> tuple[dict[str, dict], list[str]]:
    """({name: table row} of the objects whose file in `out` holds their key, [names whose file holds another]);
    a file that cannot be read counts as another (it is written again). Only the objects with a file there are
    loaded, for their geometry."""
    done, redo = {}, []
    for o in objects:
        path = out / f"{o.name}.npz"
        if not path.is_file():
            continue
        try:
            arrays = files.read_npz(path, "grasp file", "grasp .npz")
        except FfcgsError:
            arrays = {}
        key = run_key(settings, mesh_key(o.source, scale)) if "run_key" in arrays else ""
        if key and str(arrays["run_key"]) == key:
            done[o.name] = _row(arrays, None, "skipped")
        else:
            redo.append(o.name)
    return done, redo


def _row(arrays: dict | None, seconds: float | None, status: str) -> dict:
    """One object's line of the table: counts and E figures of its grasps (`arrays`, None for a failed object)."""
    from ffcgs_jax.evaluation import ranking

    row = {"valid": 0, "total": 0, "passed": 0, "median_E": np.nan, "first_E": np.nan, "seconds": seconds,
           "status": status}
    if arrays:
        valid, E = np.asarray(arrays["valid"], bool), np.asarray(arrays["E"], float)
        first = ranking.ranked(arrays)[0] if len(valid) else None
        row.update(valid=int(valid.sum()), total=len(valid), median_E=np.median(E[valid]) if valid.any() else np.nan,
                   first_E=E[first] if first is not None and valid[first] else np.nan,
                   passed=int(np.sum(arrays.get("physics_passed", 0))))
    return row


def _print_table(rows: list[tuple[str, dict]], physics: bool) -> None:
    """Per object: valid / total grasps (and those that passed the physics check), median E of the valid ones, E
    of the first grasp offered (when valid), seconds this run spent on it; then the totals."""
    num = lambda x, f="{:.4g}": "-" if x is None or np.isnan(x) else f.format(x)  # noqa: E731
    width = max([len("object"), len("total")] + [len(n) for n, _ in rows])
    head = f"{'object':<{width}}  {'valid / total':>13}" + (f"  {'passed':>6}" if physics else "") + \
        f"  {'median E':>9}  {'first E':>9}  {'seconds':>8}  status"
    print(head)
    for name, r in rows:
        counts = f"{r['valid']} / {r['total']}" if r["status"] != "failed" else "-"
        print(f"{name:<{width}}  {counts:>13}" + (f"  {r['passed']:>6}" if physics else "")
              + f"  {num(r['median_E']):>9}  {num(r['first_E']):>9}  {num(r['seconds'], '{:.2f}'):>8}  {r['status']}")
    tally = {s: sum(r["status"] == s for _, r in rows) for s in ("done", "skipped", "failed")}
    seconds = sum(r["seconds"] or 0.0 for _, r in rows)
    counts = f"{sum(r['valid'] for _, r in rows)} / {sum(r['total'] for _, r in rows)}"
    print(f"{'total':<{width}}  {counts:>13}" + (f"  {sum(r['passed'] for _, r in rows):>6}" if physics else "")
          + f"  {'':>9}  {'':>9}  {seconds:>8.2f}  " + ", ".join(f"{n} {s}" for s, n in tally.items() if n))
