"""`ffcgs learn` (`learn.pipeline`): the whole path on the two-finger toy hand, resumption, a changed spec, the
held-out split, the install rule, and the inputs it refuses in one line."""

import dataclasses
import errno
import json
import shutil

import numpy as np
import pytest

from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.dataset import mcap_io
from ffcgs_jax.dataset.objects import sources
from ffcgs_jax.hand import kinematics as K
from ffcgs_jax.hand.identity import spec_sha256
from ffcgs_jax.learn import pipeline, plan, report
from ffcgs_jax.learn.config import LearnConfig
from ffcgs_jax.learning import checkpoint, weights
from ffcgs_jax.physics.config import PhysicsConfig, RobustConfig
from ffcgs_jax.synthesis import prediction
from ffcgs_jax.synthesis.config import GraspConfig, OptimConfig
from ffcgs_jax.training import step_cost
from ffcgs_jax.geometry.config import SDFConfig

from paths import REPO
from test_custom_hand_guide import ACTUATED
from weights_toy import cvae_file, evaluator_file

TOY = REPO / "tests" / "data" / "toy_hand"


def actuated_toy(folder, edit=lambda t: t):
    """The toy hand as the guide makes it: actuated, fingers closing towards the pads (tests/test_custom_hand_guide)."""
    folder.mkdir(parents=True, exist_ok=True)
    xml = edit((TOY / "toy.xml").read_text().replace('axis="1 0 0"', 'axis="-1 0 0"'))
    (folder / "toy.xml").write_text(xml.rstrip()[: -len("</mujoco>")] + ACTUATED + "\n")
    shutil.copyfile(TOY / "toy.toml", folder / "toy.toml")
    return folder / "toy.toml"


def small(spec, out, **kw) -> LearnConfig:
    """The toy run: a few objects, few candidates, one trial, short descents."""
    return LearnConfig(hand=str(spec), out=str(out), minutes=0.0, train_objects=3, held_out=2, per_object=8,
                       cvae_epochs=1, predictor_epochs=2, engine="plain",
                       grasp=GraspConfig(sdf=SDFConfig(res=16), optim=OptimConfig(iters=5)),
                       physics=PhysicsConfig(robust=RobustConfig(trials=1)),
                       **kw)


@pytest.mark.e2e
def test_the_toy_hand_end_to_end_resumed_as_uninterrupted(tmp_path, monkeypatch):
    monkeypatch.setenv("FFCGS_HOME", str(tmp_path / "home"))
    spec = actuated_toy(tmp_path / "hand")
    cfg = small(spec, tmp_path / "a")
    # interrupted after the training labels, moved (as off a cluster), then resumed: the stages before are kept
    pipeline.learn_hand(dataclasses.replace(cfg, out=str(tmp_path / "first")), progress=False, stop_after="labels")
    shutil.move(tmp_path / "first", tmp_path / "a")
    state = json.loads((tmp_path / "a" / "state.json").read_text())
    assert list(state["stages"]) == list(pipeline.STAGES[:4])
    assert state["stages"]["labels"]["out"] == "labels.mcap"  # named from the folder, not where it was
    labels_mtime = (tmp_path / "a" / "labels.mcap").stat().st_mtime_ns
    rep = pipeline.learn_hand(cfg, progress=False)
    assert (tmp_path / "a" / "labels.mcap").stat().st_mtime_ns == labels_mtime
    uninterrupted = pipeline.learn_hand(dataclasses.replace(cfg, out=str(tmp_path / "b")), progress=False)
    assert rep["rows"] == uninterrupted["rows"]
    # the same network (its metadata names its own folder)
    trees = [checkpoint.flatten(checkpoint.load(tmp_path / r / "runs" / "predictor" / "weights.npz")[0]) for r in "ab"]
    assert trees[0].keys() == trees[1].keys()
    assert all(np.array_equal(trees[0][k], trees[1][k]) for k in trees[0])
    for f in ("report.md", "report.png", "report.json"):
        assert (tmp_path / "a" / f).is_file()
    # the two-finger toy finds no grasp that holds: the report says so and nothing is installed
    assert rep["install"] == [] and rep["installed"] is None
    assert "keeps it" in (tmp_path / "a" / "report.md").read_text()
    assert not weights.installed_dir("toy").exists()
    # the held-out objects never reached training: no geometry in common, and the report's files are apart
    trained = {r.mesh_sha256 for r in mcap_io.iter_records(tmp_path / "a" / "labels.mcap")}
    held = {r.mesh_sha256 for f in state["stages"]["held_geometric"]["files"]
            for r in mcap_io.iter_records(tmp_path / "a" / f)}
    assert trained and held and not trained & held
    # a changed spec refuses the folder, and the weights it learned
    changed = actuated_toy(tmp_path / "changed", lambda t: t.replace('size="0.005"', 'size="0.007"'))
    with pytest.raises(FfcgsError, match="another version of this hand"):
        pipeline.learn_hand(dataclasses.replace(cfg, hand=str(changed)), progress=False)
    with pytest.raises(FfcgsError, match="another version of hand 'toy'"):
        weights.load_evaluator(tmp_path / "a" / "runs" / "predictor" / "weights.npz", K.load_hand(str(changed)))


@pytest.mark.e2e  # over 20 s on the 2-core CPU: kept out of plain `pytest` (README)
def test_install_copies_the_winning_parts_where_synthesize_finds_them(tmp_path, monkeypatch):
    monkeypatch.setenv("FFCGS_HOME", str(tmp_path / "home"))
    hand = K.load_hand(str(TOY / "toy.toml"))
    cvae_file(tmp_path / "cvae.npz", hand)
    evaluator_file(tmp_path / "evaluator.npz", hand)
    rep = {"install": ["evaluator"], "weights": {"cvae": str(tmp_path / "cvae.npz"),
                                                 "evaluator": str(tmp_path / "evaluator.npz")}}
    cfg = LearnConfig(hand=str(TOY / "toy.toml"))
    out = pipeline.install(cfg, hand, tmp_path, rep)
    folder = weights.installed_dir("toy")
    assert out["installed"] == str(folder) and (folder / "evaluator.npz").is_file()
    assert not (folder / "cvae.npz").exists()  # the predictor alone won: the sampler stays geometric
    assert prediction.weights_for(hand) is not None
    out = pipeline.install(cfg, hand, tmp_path, rep | {"install": ["cvae", "evaluator"]})
    assert (folder / "cvae.npz").is_file()
    assert pipeline.install(dataclasses.replace(cfg, install=False), hand, tmp_path, rep)["installed"] is None


@pytest.mark.e2e  # over 20 s on the 2-core CPU: kept out of plain `pytest` (README)
def test_objects_are_scaled_to_the_hand_and_held_out_apart():
    svh, allegro = K.load_hand("svh"), K.load_hand("allegro")
    assert plan.scale(svh) == pytest.approx(1.0)
    assert plan.scale(allegro) > 1.2  # the Allegro's fingers are longer: larger objects
    cfg = LearnConfig(hand="svh", train_objects=8, held_out=3)
    train = plan.training(cfg, plan.scale(svh), "t.mcap", 8)
    assert (train.procedural, train.complex) == (2, 6) and not train.allow_test
    held = plan.held_out(cfg, plan.scale(svh), "h.mcap")
    assert [h.complex for h in held] == [3] and held[0].seed != train.seed
    assert not {s.sha256 for s in sources(train)} & {s.sha256 for h in held for s in sources(h)}


def test_the_budget_counts_the_seconds_of_earlier_processes(tmp_path):
    """A resumed run plans with what its stages took, not with how long this process has run."""
    state = pipeline.State(tmp_path, "h", {})
    state.finish("check", {}, 60.0)
    state.finish("held_geometric", {"seconds_per_object": 10.0}, 540.0)
    got = pipeline.planned(LearnConfig(minutes=60.0, train_objects=10_000), state)
    assert got["objects"] == plan.fitting_objects(LearnConfig(minutes=60.0, train_objects=10_000), 10.0, 600.0)[0]
    assert got["objects"] == int(0.6 * (3600 - 600) / 10)


def test_an_interrupted_stage_keeps_its_seconds_for_the_budget(tmp_path, monkeypatch):
    """A stage stopped by Ctrl-C, `timeout` or a scheduler (SIGTERM) records the seconds it ran: the labels of a 60 min
    run on one H200 went in 10 min pieces, and without them the plan would have counted only the last piece."""
    import subprocess
    import sys
    import time

    def interrupted(*a, **k):  # Ctrl-C in Python: KeyboardInterrupt
        time.sleep(0.3)
        raise KeyboardInterrupt

    cfg = LearnConfig(hand=str(TOY / "toy.toml"), out=str(tmp_path / "w"))
    monkeypatch.setattr(pipeline, "check", interrupted)
    for _ in range(2):
        with pytest.raises(KeyboardInterrupt):
            pipeline.learn_hand(cfg, progress=False)
    state = json.loads((tmp_path / "w" / "state.json").read_text())
    assert state["stages"] == {} and state["interrupted"]["check"] >= 0.6
    assert pipeline.spent(pipeline.State(tmp_path / "w", state["hand_sha256"], state["settings"])) == \
        state["interrupted"]["check"]
    monkeypatch.setattr(pipeline, "check", lambda *a: {"say": ""})
    pipeline.learn_hand(cfg, progress=False, stop_after="check")
    state = json.loads((tmp_path / "w" / "state.json").read_text())
    assert state["interrupted"] == {} and state["stages"]["check"]["seconds"] >= 0.6

    # the command line ends at once on SIGTERM (no `finally` runs): the stage's seconds go with its last words
    started, out = tmp_path / "started", tmp_path / "cli"
    script = (f"import pathlib, sys, time\nfrom ffcgs_jax.cli import main\nfrom ffcgs_jax.learn import pipeline\n"
              f"def slow(*a):\n    time.sleep(0.3)\n    pathlib.Path({str(started)!r}).touch()\n    time.sleep(600)\n"
              f"pipeline.check = slow\nsys.exit(main.main(['learn', {str(TOY / 'toy.toml')!r}, '--out', "
              f"{str(out)!r}]))\n")
    proc = subprocess.Popen([sys.executable, "-c", script], stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 300  # a hang guard, not a speed bound
        while not started.exists() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert started.exists(), proc.stderr.read() if proc.poll() is not None else "the stage never started"
        proc.terminate()
        assert proc.wait(timeout=60) == 128 + 15 and "ffcgs: interrupted" in proc.stderr.read()
    finally:
        proc.kill()
    state = json.loads((out / "state.json").read_text())
    assert state["stages"] == {} and state["interrupted"]["check"] >= 0.3


def test_a_resumed_run_builds_with_the_scale_its_check_chose(tmp_path, monkeypatch):
    """The later stages take the object scale from state.json: a resumed process pays no forward-kinematics compile
    (27 of the 38 s that the Allegro's resumed labels stage took to reach its first object on the 2-core CPU), and
    its objects are the ones of the earlier processes to the last bit."""
    cfg = LearnConfig(hand=str(TOY / "toy.toml"), out=str(tmp_path / "w"), held_out=2)
    (tmp_path / "w").mkdir()
    state = pipeline.State(tmp_path / "w", spec_sha256(K.load_hand(cfg.hand).spec), pipeline.settings_of(cfg))
    state.finish("check", {"scale": 0.7}, 1.0)
    state.finish("held_geometric", {"seconds_per_object": 1.0}, 1.0)
    state.finish("plan", {"objects": 4}, 0.0)
    built = []

    def build(dc, show_progress=True):
        built.append(dc)
        return {"out": dc.out, "built": 4, "timing": str(tmp_path / "timing.jsonl")}

    def no_kinematics(hand):
        raise AssertionError("the scale was computed again")

    monkeypatch.setattr(pipeline.dataset_build, "build", build)
    monkeypatch.setattr(plan, "scale", no_kinematics)
    pipeline.learn_hand(cfg, progress=False, stop_after="labels")
    assert [(d.scale_min, d.scale_max) for d in built] == [(0.8 * 0.7, 1.2 * 0.7)]
    assert json.loads((tmp_path / "w" / "state.json").read_text())["stages"]["labels"]["built"] == 4


def test_the_folders_training_objects_count_against_the_budget(tmp_path):
    """The --objects folder's train split is labelled whole beside the generated shapes, so the plan counts it: on
    one H200 a 19 min run planned 65 objects and labelled 101, its folder's 36 unseen (2026-11-29)."""
    import trimesh

    for i in range(10):  # sorted index % 5 == 4 is the test split: 8 train, 2 test
        trimesh.creation.box((0.05, 0.06, 0.07 + 0.01 * i)).export(tmp_path / f"obj_{i:02d}.stl")
    cfg = LearnConfig(minutes=60.0, train_objects=10_000, objects=str(tmp_path))
    assert plan.folder_training(cfg) == 8 and plan.folder_training(LearnConfig()) == 0
    fit = int(0.6 * (3600 - 600) / 10)
    n, why = plan.fitting_objects(cfg, 10.0, 600.0, 8)
    assert n == fit - 8 and f"{fit} training objects (8 of the folder, {fit - 8} generated)" in why
    (tmp_path / "w").mkdir()
    state = pipeline.State(tmp_path / "w", "h", {})
    state.finish("check", {}, 60.0)
    state.finish("held_geometric", {"seconds_per_object": 10.0}, 540.0)
    assert pipeline.planned(cfg, state) | {"say": ""} == {"objects": fit - 8, "folder_objects": 8, "say": ""}
    # a folder larger than the budget holds is labelled whole, and the line says the run will take longer
    n, why = plan.fitting_objects(cfg, 300.0, 600.0, 8)
    assert n == 0 and "longer" in why


def test_a_finished_stages_missing_file_is_named_before_any_work(tmp_path):
    """A resumed run whose labels were deleted before the trainings stops in one line, not in the training's reader;
    after the trainings, and in a finished run, the labels may go."""
    cfg = LearnConfig(hand=str(TOY / "toy.toml"), out=str(tmp_path))
    state = pipeline.State(tmp_path, spec_sha256(K.load_hand(cfg.hand).spec), pipeline.settings_of(cfg))
    (tmp_path / "held.mcap").write_bytes(b"")
    state.finish("check", {"scale": 1.0}, 1.0)
    state.finish("held_geometric", {"files": [str(tmp_path / "held.mcap")], "seconds_per_object": 1.0}, 1.0)
    state.finish("plan", {"objects": 3}, 0.0)
    state.finish("labels", {"out": str(tmp_path / "labels.mcap"), "timing": str(tmp_path / "gone.jsonl")}, 1.0)
    with pytest.raises(FfcgsError, match=r"stage labels is done, but its file .*labels\.mcap is missing") as e:
        pipeline.learn_hand(cfg, progress=False)
    assert "\n" not in str(e.value)
    assert json.loads((tmp_path / "state.json").read_text())["stages"]["held_geometric"]["files"] == ["held.mcap"]
    done = {"cvae": {"weights": None}, "report": {"install": [], "weights": {"cvae": None, "evaluator": None}}}
    for stage in pipeline.STAGES[4:-1]:
        state.finish(stage, done.get(stage, {"files": []}), 0.0)
    got = pipeline.learn_hand(cfg, progress=False)  # the install stage runs: it reads nothing of labels
    assert got["installed"] is None and "labels" not in json.dumps(got)


def test_bad_input_is_one_line(tmp_path, monkeypatch):
    with pytest.raises(FfcgsError, match="too small to train anything"):
        plan.fitting_objects(LearnConfig(minutes=1.0), seconds_per_object=30.0, spent_s=20.0)
    n, why = plan.fitting_objects(LearnConfig(minutes=60.0, train_objects=500), 10.0, 60.0)
    assert n == int(0.6 * (3600 - 60) / 10) and "min left" in why
    with pytest.raises(FfcgsError, match="held-out seed"):
        pipeline.learn_hand(LearnConfig(seed=4600, out=str(tmp_path / "x")), progress=False)
    with pytest.raises(FfcgsError, match="hand spec|not found|unknown built-in hand"):
        pipeline.learn_hand(LearnConfig(hand=str(tmp_path / "nope.toml"), out=str(tmp_path / "x")), progress=False)
    with pytest.raises(FfcgsError, match="held-out objects"):
        plan.held_out(LearnConfig(held_out=0), 1.0, "h.mcap")

    def full(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(pipeline, "check", full)
    with pytest.raises(FfcgsError, match="disk is full") as e:
        pipeline.learn_hand(LearnConfig(hand=str(TOY / "toy.toml"), out=str(tmp_path / "y")), progress=False)
    assert "\n" not in str(e.value)


def test_a_budget_chooses_the_epochs_that_fit_and_says_so(tmp_path, monkeypatch):
    cfg = LearnConfig(minutes=60.0)
    # 3600 - 1800 s left; the CVAE's share of the stages still to run: 0.15 / 0.4
    assert plan.stage_seconds(cfg, "cvae", 1800.0) == pytest.approx(1800 * 0.15 / 0.4)
    n, why = plan.fitting_epochs(cfg, "cvae", 40, 100, 1800.0, 0.5, True)
    assert n == int(1800 * 0.15 / 0.4 // 50) == 13 and "13 epochs of 100 steps" in why and "measured" in why
    slower, _ = plan.fitting_epochs(cfg, "cvae", 40, 100, 1800.0, 1.0, False)
    assert slower == 6
    assert plan.fitting_epochs(cfg, "cvae", 40, 100, 1800.0, 1e-4, True)[0] == 40  # at most --cvae-epochs
    assert plan.fitting_epochs(cfg, "predictor", 30, 100, 3590.0, 1.0, True)[0] == 1  # at least one
    assert plan.fitting_epochs(LearnConfig(minutes=0.0), "cvae", 7, 100, 1e9, 10.0, False)[0] == 7
    # the choice is kept: a stage started again trains for the epochs its checkpoint was made for
    monkeypatch.setenv("FFCGS_JAX_CACHE", str(tmp_path / "cache"))
    first = pipeline.epochs(cfg, tmp_path, "cvae", 40, 20_000, "sampler x", 1800.0, progress=False)
    assert first == int(1800 * 0.15 / 0.4 // (20_000 * step_cost.PRIOR["sampler"])) == 4
    assert pipeline.epochs(cfg, tmp_path, "cvae", 40, 20_000, "sampler x", 3000.0, progress=False) == first


def test_the_report_installs_the_best_parts_and_the_fewest_on_a_tie():
    def rows(*holds):
        return [{"sampler": s, "order": o, "parts": list(p), "first_holds": h, "objects": 48}
                for (s, o, p), h in zip(report.ORDERS, holds)]  # 3 holds: a run without CVAE

    # the Allegro's run of 2026-11-29 (one H200): the CVAE helps E (20 against 9) but not the predictor (24 against 25)
    assert report.choose(rows(9, 25, 20, 24))[0] == ["evaluator"]
    assert report.choose(rows(9, 20, 25, 24))[0] == ["cvae"]
    assert report.choose(rows(9, 25, 20, 25))[0] == ["evaluator"]  # a tie: the part that adds nothing stays out
    assert report.choose(rows(9, 9, 9, 9))[0] == []  # nothing beats the baseline: the hand keeps it
    assert report.choose(rows(9, 5, 8))[0] == []  # no CVAE row when none was learned
