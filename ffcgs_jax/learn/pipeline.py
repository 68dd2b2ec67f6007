"""`learn_hand`: from a hand spec to its learned sampler and ranker, in stages that a rerun resumes.

    check          the spec, the MJCF and its physics scene (one line on any problem)
    held_geometric the held-out objects' candidates from the geometric sampler, labelled (robust verdicts, three
                   protocols): the report's baseline, and the time per object that sizes the run to its budget
    plan           the training object count that fits the budget (said in one line)
    labels         the training objects' candidates, labelled (the data engine: `dataset.build`)
    cvae           the CVAE trained on the robust successes (`training.train`)
    predictor      the success predictor trained on every label (`training.evaluator_train`)
    held_learned   the held-out objects' candidates from the new CVAE, labelled
    report         report.md, report.json, report.png: held-out first grasps, learned against geometric + E
    install        the parts that beat the geometric sampler copied to the user folder (`weights.installed_dir`)

Each stage records its result and its seconds in OUT/state.json when it ends, and a stage interrupted (Ctrl-C, a
`timeout` or a job scheduler's SIGTERM) records the seconds it had run: the budget counts both, so a resumed run
plans with the time its earlier processes spent, and a stage's seconds are its whole time over them. The builds
keep every finished object in their parts folders and the trainings checkpoint every epoch, so a killed run,
started again with the same command, ends where an uninterrupted one would. A folder started for another version
of the hand, or with other settings, is refused in one line.
"""

import dataclasses
import errno
import json
import shutil
import statistics
import time
from pathlib import Path

from ffcgs_jax.core import files
from ffcgs_jax.core.config import check_all
from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.dataset import build as dataset_build
from ffcgs_jax.dataset.objects import sources
from ffcgs_jax.hand import kinematics as K
from ffcgs_jax.hand.identity import spec_sha256
from ffcgs_jax.learn import plan, report
from ffcgs_jax.learn.config import LearnConfig
from ffcgs_jax.learning.config import ModelConfig
from ffcgs_jax.learning.weights import installed_dir

STAGES = ("check", "held_geometric", "plan", "labels", "cvae", "predictor", "held_learned", "report", "install")
READS = {"cvae": ("labels",), "predictor": ("labels",), "held_learned": ("cvae",),  # earlier stages' files
         "report": ("held_geometric", "cvae", "predictor", "held_learned"), "install": ("report",)}


class State:
    """OUT/state.json: the hand's identity, the settings, and each finished stage's result."""

    def __init__(self, work: Path, hand_sha: str, settings: dict):
        self.work = work
        self.path = work / "state.json"
        self.data = {"hand_sha256": hand_sha, "settings": settings, "stages": {}}
        if self.path.is_file():
            old = json.loads(self.path.read_text())
            if old.get("hand_sha256") != hand_sha:
                raise FfcgsError(f"{work} was started for another version of this hand (its spec or MJCF changed); "
                                 "use another --out, or remove the folder to start again")
            if old.get("settings") != settings:
                diff = sorted(k for k in set(settings) | set(old.get("settings", {}))
                              if settings.get(k) != old.get("settings", {}).get(k))
                raise FfcgsError(f"{work} was started with other settings ({', '.join(diff)}); run with the same "
                                 "settings to resume it, or use another --out")
            self.data = old

    def done(self, stage: str) -> dict | None:
        """`stage`'s result, its files named from this folder wherever it is now (None: not finished)."""
        result = self.data["stages"].get(stage)
        return None if result is None else _paths(result, lambda p: str(self.work / p))

    def stages(self) -> dict:
        return {stage: self.done(stage) for stage in self.data["stages"]}

    def finish(self, stage: str, result: dict, seconds: float) -> dict:
        """Record `stage` done; its seconds are these and those of its interrupted earlier processes."""
        earlier = self.data.get("interrupted", {}).pop(stage, 0.0)
        result = result | {"seconds": round(seconds + earlier, 1)}
        self.data["stages"][stage] = _paths(result, self.inside)
        self.save()
        return result

    def inside(self, path: str) -> str:
        """`path` relative to the folder when it is in it: a folder moved (or copied off a cluster) resumes."""
        for p, root in ((Path(path), self.work), (Path(path).resolve(), self.work.resolve())):
            if p.is_relative_to(root):
                return str(p.relative_to(root))
        return path

    def check_files(self) -> None:
        """One line if a finished stage's file that a stage still to run reads is gone: that stage would fail deep
        inside. A file no stage will read again (labels.mcap after the trainings) may go."""
        pending = [s for s in STAGES if self.done(s) is None]
        for stage in sorted({n for s in pending for n in READS.get(s, ())} - set(pending)):
            result = self.done(stage)
            for key in ("out", "files", "weights"):
                for path in _flat(result.get(key)):
                    if not Path(path).exists():
                        raise FfcgsError(f"{self.work}: stage {stage} is done, but its file {path} is missing; put "
                                         "it back to resume, or use another --out to start again")

    def interrupted(self, stage: str, seconds: float) -> None:
        runs = self.data.setdefault("interrupted", {})
        runs[stage] = round(runs.get(stage, 0.0) + seconds, 1)
        self.save()

    def save(self) -> None:
        files.write_text(self.path, json.dumps(self.data, indent=1, default=str))


PATH_KEYS = ("out", "timing", "weights", "files")  # the result keys that name files


def _paths(result: dict, to) -> dict:
    """`result` with `to` applied to each file it names (a string, a list of them, a dict of them, or None)."""
    def each(v):
        if isinstance(v, str):
            return to(v)
        if isinstance(v, list):
            return [each(x) for x in v]
        return {k: each(x) for k, x in v.items()} if isinstance(v, dict) else v
    return {k: each(v) if k in PATH_KEYS else v for k, v in result.items()}


def _flat(v) -> list[str]:
    if isinstance(v, str):
        return [v]
    return [p for x in (v.values() if isinstance(v, dict) else v or []) for p in _flat(x)]


def settings_of(cfg: LearnConfig) -> dict:
    """The settings a folder is resumed with: everything but the folder, the budget and whether to install."""
    d = json.loads(json.dumps(dataclasses.asdict(cfg), default=str))
    for k in ("out", "install", "minutes"):
        d.pop(k)
    return d


def learn_hand(cfg: LearnConfig = LearnConfig(), progress: bool = True, stop_after: str | None = None) -> dict:
    """Run (or resume) the stages; returns the report's figures (`report.json`) and where the weights went."""
    if not isinstance(cfg, LearnConfig):
        raise FfcgsError(f"learn_hand takes a LearnConfig, got {type(cfg).__name__}")
    check_all(cfg)
    if stop_after is not None and stop_after not in STAGES:
        raise FfcgsError(f"stop_after must be one of {', '.join(STAGES)}, got {stop_after!r}")
    hand = K.load_hand(cfg.hand)
    work = Path(cfg.folder(hand.spec.name)).expanduser()
    files.check_folder(work, "--out folder")
    work.mkdir(parents=True, exist_ok=True)
    state = State(work, spec_sha256(hand.spec), settings_of(cfg))
    say = (lambda m: print(f"ffcgs learn: {m}", flush=True)) if progress else (lambda m: None)
    runs = {
        "check": lambda: check(cfg, hand),
        "held_geometric": lambda: held_labels(cfg, scaled(state), work, "geometric", progress),
        "plan": lambda: planned(cfg, state),
        "labels": lambda: labels(cfg, scaled(state), work, state.done("plan")["objects"], progress),
        "cvae": lambda: train_cvae(cfg, hand, work, spent(state), progress),
        "predictor": lambda: train_predictor(cfg, hand, work, spent(state), progress),
        "held_learned": lambda: held_learned(cfg, work, state, progress),
        "report": lambda: report.write(cfg, hand, work, state.stages()),
        "install": lambda: install(cfg, hand, work, state.done("report")),
    }
    state.check_files()
    for i, stage in enumerate(STAGES):
        if state.done(stage) is None:
            say(f"stage {i + 1}/{len(STAGES)}: {stage}")
            t0 = time.perf_counter()

            def record_interrupted(stage=stage, t0=t0):
                state.interrupted(stage, time.perf_counter() - t0)

            try:  # the CLI's Ctrl-C and SIGTERM end the process at once: the record goes with its last words
                with files.last_words(record_interrupted):
                    result = runs[stage]()
            except BaseException as e:  # an error, or Ctrl-C in Python (KeyboardInterrupt)
                record_interrupted()
                if isinstance(e, OSError) and e.errno == errno.ENOSPC:
                    raise FfcgsError(f"the disk is full (stage {stage}, in {work}); free some space and run the "
                                     "same command again: it resumes") from None
                raise
            result = state.finish(stage, result, time.perf_counter() - t0)
            if result.get("say"):
                say(result["say"])
        if stage == stop_after:
            break
    return (state.done("report") or {}) | {"installed": (state.done("install") or {}).get("installed")}


def check(cfg: LearnConfig, hand: K.Hand) -> dict:
    """The physics scene of the hand beside a built-in box: actuators, contacts, the MJCF compiling with an object."""
    from ffcgs_jax.geometry import mesh_io
    from ffcgs_jax.physics import convex, scene

    mesh = mesh_io.load_mesh("box")
    scene.build(hand.spec, mesh, convex.decompose(mesh, cfg.physics), cfg.physics, table_z=0.0)
    scale = plan.scale(hand)
    return {"hand": hand.spec.name, "scale": scale, "say": f"hand {hand.spec.name}: spec, MJCF and physics scene "
            f"checked; objects scaled by {scale:.2f} x the SVH's"}


def _build(dc, progress: bool) -> dict:
    out = dataset_build.build(dc, show_progress=progress)
    if out.get("out") is None:
        raise FfcgsError(f"the build {dc.out} is missing {out.get('missing')} records (another shard's?)")
    return {"out": str(out["out"]), "built": out["built"], "timing": out["timing"]}


def held_labels(cfg: LearnConfig, scale: float, work: Path, sampler: str, progress: bool, grasp=None) -> dict:
    builds = plan.held_out(cfg, scale, str(work / f"held_{sampler}.mcap"), sampler, grasp)
    done = [_build(dc, progress) for dc in builds]
    rows = [json.loads(line) for d in done for line in Path(d["timing"]).read_text().splitlines() if line.strip()]
    # the first object of a process pays the compiles: the others say what one more object costs
    per_object = statistics.median(r["total_s"] for r in (rows[1:] or rows)) if rows else 0.0
    return {"files": [d["out"] for d in done], "seconds_per_object": per_object,
            "objects": sorted({r["object"] for r in rows})}


def scaled(state: State) -> float:
    """The object scale the check stage chose: every later stage, in any process, builds with this one number (a
    rerun of the forward kinematics would cost a resumed process its compiles, and could differ in the last bit)."""
    return float(state.done("check")["scale"])


def spent(state: State) -> float:
    """Seconds the stages took, finished or interrupted, in this process and the earlier ones of the same folder."""
    return sum(r["seconds"] for r in state.data["stages"].values()) + sum(state.data.get("interrupted", {}).values())


def planned(cfg: LearnConfig, state: State) -> dict:
    folder = plan.folder_training(cfg)
    n, why = plan.fitting_objects(cfg, state.done("held_geometric")["seconds_per_object"], spent(state), folder)
    return {"objects": n, "folder_objects": folder, "say": why}


def epochs(cfg: LearnConfig, work: Path, stage: str, most: int, steps_per_epoch: int, cost_key: str,
           spent_s: float, progress: bool) -> int:
    """A training stage's epochs (`plan.fitting_epochs`), said once and kept in runs/STAGE.epochs.json before it
    trains: a stage killed and started again goes on with the epochs its checkpoint was made for."""
    from ffcgs_jax.training import step_cost

    path = work / "runs" / f"{stage}.epochs.json"
    if path.is_file():
        return int(json.loads(path.read_text())["epochs"])
    n, why = plan.fitting_epochs(cfg, stage, most, steps_per_epoch, spent_s, *step_cost.seconds_per_step(cost_key))
    if progress:
        print(f"ffcgs learn: {why}", flush=True)
    path.parent.mkdir(parents=True, exist_ok=True)
    files.write_text(path, json.dumps({"epochs": n, "why": why}))
    return n


def labels(cfg: LearnConfig, scale: float, work: Path, count: int, progress: bool) -> dict:
    dc = plan.training(cfg, scale, str(work / "labels.mcap"), count)
    held = {s.sha256 for h in plan.held_out(cfg, scale, str(work / "held_geometric.mcap")) for s in sources(h)}
    shared = [s.name for s in sources(dc) if s.sha256 in held]
    if shared:  # the report would measure objects the networks learned
        raise FfcgsError(f"training objects {shared[:3]} are also held out; use another --seed or --objects folder")
    return _build(dc, progress)


def train_cvae(cfg: LearnConfig, hand: K.Hand, work: Path, spent_s: float, progress: bool) -> dict:
    from ffcgs_jax.training import data as cvae_data
    from ffcgs_jax.training import train
    from ffcgs_jax.training.config import CVConfig, DataConfig, TrainConfig, TrainOptimConfig

    path = work / "labels.mcap"
    try:
        data = cvae_data.load(path)
    except FfcgsError as e:  # no record holds a robust success: nothing to learn a sampler from
        return {"weights": None, "say": f"no CVAE: {e}"}
    tc = TrainConfig(out=str(work / "runs" / "cvae"), hand=cfg.hand, data=DataConfig(path=str(path)),
                     model=dataclasses.replace(ModelConfig(), res=cfg.grasp.sdf.res), cv=CVConfig(fold=-1))
    train_recs, _ = cvae_data.split(data, tc.cv.folds, tc.cv.fold, tc.seed)
    spe = cvae_data.steps_per_epoch(data, train_recs, tc.optim.batch, tc.data.grasps_per_sdf)
    n = epochs(cfg, work, "cvae", cfg.cvae_epochs, spe, train.cost_key(tc), spent_s, progress)
    tc = dataclasses.replace(tc, optim=TrainOptimConfig(epochs=n))
    summary = train.train(tc, progress=progress, data=data)
    return {"weights": str(Path(tc.out) / "weights.npz"), "train_grasps": summary["train_grasps"], "epochs": n,
            "say": f"CVAE trained on {summary['train_grasps']} robust successes, {n} epochs"}


def train_predictor(cfg: LearnConfig, hand: K.Hand, work: Path, spent_s: float, progress: bool) -> dict:
    from ffcgs_jax.training import evaluator_data, evaluator_train
    from ffcgs_jax.training.config import (CVConfig, EvaluatorDataConfig, EvaluatorOptimConfig,
                                           EvaluatorTrainConfig)

    data = evaluator_data.load(work / "labels.mcap", hand, progress)
    # a small build (a short budget, a test) still trains: at least 4 steps an epoch
    batch = max(1, min(EvaluatorOptimConfig().batch, len(data.x) // 4))
    ec = EvaluatorTrainConfig(out=str(work / "runs" / "predictor"), hand=cfg.hand,
                              data=EvaluatorDataConfig(str(work / "labels.mcap")), cv=CVConfig(fold=-1),
                              optim=EvaluatorOptimConfig(batch=batch))
    n = epochs(cfg, work, "predictor", cfg.predictor_epochs, len(data.x) // batch, evaluator_train.cost_key(ec),
               spent_s, progress)
    ec = dataclasses.replace(ec, optim=dataclasses.replace(ec.optim, epochs=n))
    summary = evaluator_train.train(ec, progress=progress, data=data)
    return {"weights": str(Path(ec.out) / "weights.npz"), "train_grasps": summary["train_grasps"], "epochs": n,
            "say": f"success predictor trained on {summary['train_grasps']} labels, {n} epochs"}


def held_learned(cfg: LearnConfig, work: Path, state: State, progress: bool) -> dict:
    weights = state.done("cvae")["weights"]
    if weights is None:
        return {"files": [], "say": "no learned sampler to label on the held-out objects"}
    grasp = dataclasses.replace(cfg.grasp, sampling=dataclasses.replace(cfg.grasp.sampling, weights=weights))
    return held_labels(cfg, scaled(state), work, "cvae", progress, grasp)


def install(cfg: LearnConfig, hand: K.Hand, work: Path, rep: dict) -> dict:
    """Copy the parts the report chose into the user folder (both, the predictor alone, or nothing)."""
    parts = rep["install"]
    if not parts or not cfg.install:
        why = "the geometric sampler ranked by E did as well on the held-out objects" if not parts \
            else "--no-install"
        return {"installed": None, "say": f"nothing installed: {why}"}
    folder = installed_dir(hand.spec.name)
    folder.mkdir(parents=True, exist_ok=True)
    for kind in ("cvae", "evaluator"):
        (folder / f"{kind}.npz").unlink(missing_ok=True)  # a part not chosen must not stay from an earlier run
    for kind in parts:
        shutil.copyfile(rep["weights"][kind], folder / f"{kind}.npz")
    return {"installed": str(folder), "parts": parts,
            "say": f"installed {' and '.join(parts)} for hand {hand.spec.name} in {folder}"}
