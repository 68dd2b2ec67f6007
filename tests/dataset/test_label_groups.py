"""A labelled build's groups of objects (`DatasetConfig.group`, `build.build_group`, `label.label_many`): labels equal
to one object at a time, the same parts as a per-object build, resume, a synthesis failure inside a group, and the
field's check.

Groups are taken where the physics runs on MuJoCo Warp; here `resolve_backend` is made to say "warp" for the
build's choice only, so the groups run, but their physics runs on CPU MuJoCo (`--physics.backend cpu`), as cheap
as a per-object build's. Three generated objects in groups of 2 give a group of two and a group of one.
"""

import json
import re
import shutil

import numpy as np
import pytest

from ffcgs_jax.cli import main as cli_main
from ffcgs_jax.dataset import build as dataset_build
from ffcgs_jax.dataset import engine, label
from ffcgs_jax.dataset import mcap_io as dataset_io
from ffcgs_jax.dataset import objects as dataset_objects
from ffcgs_jax.dataset.config import DatasetConfig
from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.hand import kinematics as K
from ffcgs_jax.hand import spec as hand_spec
from ffcgs_jax.physics import runner as physics_runner

pytestmark = pytest.mark.e2e  # dataset builds end to end (synthesis, physics, MCAP)

# tiny synthesis (16^3 SDF, 60 descent steps, 4 candidates) and the fast physics program, all three protocols
ARGS = ["--procedural", "3", "--seed", "7", "--keep", "all", "--sampler", "geometric", "--per-object", "4",
        "--rotations", "2", "--grasp.sdf.res", "16", "--grasp.optim.iters", "60",
        "--protocols", "lift-shake,six-dir,dexgraspbench", "--engine", "plain", "--group", "2",
        "--physics.backend", "cpu", "--physics.sim-friction", "1.0", "--physics.close-time", "0.2",
        "--physics.settle-time", "0.1", "--physics.lift-height", "0.03", "--physics.shake-cycles", "1",
        "--physics.shake-amplitude", "0.02", "--physics.push-time", "0.2"]
N_OBJECTS = 3


def parse(*argv: str) -> DatasetConfig:
    return cli_main.parse(["dataset", "build", *ARGS, *argv])[1]


def run_build(monkeypatch, out, warp: bool) -> list[list[str]]:
    """`build` of ARGS into `out`; the names of each unit of work `engine.run` was given. `warp`: the build's
    backend choice says "warp" (every later choice, the physics' own, is the real one: the CPU)."""
    units = []
    real_run, real_resolve = engine.run, physics_runner.resolve_backend
    answers = iter([("warp", None)] if warp else [])

    def run(how, cfg, todo, *a, **kw):
        units.extend([s.name for s in group] for group in todo)
        return real_run(how, cfg, todo, *a, **kw)

    monkeypatch.setattr(engine, "run", run)
    monkeypatch.setattr(physics_runner, "resolve_backend",
                        lambda *a, **kw: next(answers, None) or real_resolve(*a, **kw))
    dataset_build.build(parse("--out", str(out)), show_progress=False)
    return units


def arrays_of(out) -> dict[str, dict[str, np.ndarray]]:
    return {r.record_id: r.grasp_arrays() for r in dataset_io.iter_records(out)}


def parts_of(out) -> dict[str, bytes]:
    parts = dataset_io.parts_dir_for(out)
    return {rid: (parts / f"{rid}.mcap").read_bytes() for rid in dataset_io.done_records(parts)}


def timing(out) -> list[dict]:
    path = dataset_io.parts_dir_for(out) / "timing.jsonl"
    return [json.loads(line) for line in path.read_text().splitlines()]


@pytest.fixture(scope="module")
def builds(tmp_path_factory):
    """The same build one object at a time (CPU physics, as chosen) and in groups (the choice made "warp")."""
    d = tmp_path_factory.mktemp("groups")
    with pytest.MonkeyPatch.context() as mp:
        single = run_build(mp, d / "single.mcap", warp=False)
    with pytest.MonkeyPatch.context() as mp:
        grouped = run_build(mp, d / "grouped.mcap", warp=True)
    return {"single": d / "single.mcap", "grouped": d / "grouped.mcap", "units": (single, grouped)}


def test_group_build_writes_the_same_parts(builds):
    single, grouped = builds["units"]
    assert [len(u) for u in single] == [1] * N_OBJECTS  # CPU physics: one object at a time, as before groups
    assert [len(u) for u in grouped] == [2, 1]
    a, b = arrays_of(builds["single"]), arrays_of(builds["grouped"])
    assert sorted(a) == sorted(b) and len(a) == 2 * N_OBJECTS
    for rid in a:
        assert sorted(a[rid]) == sorted(b[rid]), rid
        for k in a[rid]:
            np.testing.assert_array_equal(a[rid][k], b[rid][k], err_msg=f"{rid} {k}")
    outcomes = np.concatenate([a[rid][k] for rid in a for k in a[rid] if k.endswith("_success")])
    assert len(outcomes) == 3 * 4 * 2 * N_OBJECTS  # three protocols, 4 candidates, two records per object
    assert 0 < outcomes.sum() < len(outcomes)  # successes and failures both: equal labels are no accident
    assert parts_of(builds["grouped"]) == parts_of(builds["single"])
    assert builds["grouped"].read_bytes() == builds["single"].read_bytes()
    rows = timing(builds["grouped"])
    assert sorted(r["object"] for r in rows) == sorted(n for u in grouped for n in u)
    for r in rows:  # every object's own row: its synthesis and a share of its group's physics
        assert r["synthesis_s"] > 0 and r["physics_s"] >= 0 and r["total_s"] >= r["synthesis_s"]


def test_group_build_resumes_only_what_is_missing(builds, tmp_path, monkeypatch):
    out = tmp_path / "resumed.mcap"
    parts = dataset_io.parts_dir_for(out)
    shutil.copytree(dataset_io.parts_dir_for(builds["grouped"]), parts)
    (parts / "timing.jsonl").unlink()
    name = timing(builds["grouped"])[0]["object"]  # in the group of two
    for p in parts.glob(f"{name}.*.mcap"):
        p.unlink()
    dataset_build.annotation_path(parts, name).unlink()
    before = {p.name: p.stat().st_mtime_ns for p in parts.glob("*.mcap")}
    synthesised = []
    real = label.candidates
    monkeypatch.setattr(label, "candidates", lambda hand, mesh, cfg, n, grid: synthesised.append(n) or
                        real(hand, mesh, cfg, n, grid))
    # run_build patches too: monkeypatch undoes both
    units = run_build(monkeypatch, out, warp=True)
    assert synthesised == [name]
    assert [r["object"] for r in timing(out)] == [name]  # only the missing object was built
    assert sum(len(u) for u in units) == 1
    assert {p.name: p.stat().st_mtime_ns for p in parts.glob("*.mcap") if p.name in before} == before
    assert out.read_bytes() == builds["grouped"].read_bytes()

    # one group of every object, two of them unfinished: one to label again, one with its annotation kept
    cfg = parse("--out", str(out))
    srcs = dataset_objects.sources(cfg)
    relabel, cached = srcs[1].name, srcs[2].name
    for n in (relabel, cached):
        for p in parts.glob(f"{n}.*.mcap"):
            p.unlink()
    dataset_build.annotation_path(parts, relabel).unlink()
    rows = dataset_build.build_group(cfg, srcs, parts)
    assert synthesised == [name, relabel]
    assert rows[0] is None and (rows[1]["object"], rows[1]["cached"]) == (relabel, False)
    assert (rows[2]["object"], rows[2]["cached"]) == (cached, True)
    assert parts_of(out) == parts_of(builds["grouped"])
    # a group of objects all done does nothing: no synthesis, no row
    assert dataset_build.build_group(cfg, srcs, parts) == [None] * N_OBJECTS
    assert synthesised == [name, relabel]


def test_label_many_equals_label_per_object(builds, monkeypatch):
    cfg = parse()
    hand, spec = K.load_hand(cfg.hand), hand_spec.load_spec(cfg.hand)
    objects = [(s.load(), s.name) for s in dataset_objects.sources(cfg)[:2]]
    done = []
    many = label.label_many(hand, spec, objects, cfg, lambda i, t: done.append(i))
    assert done == [0, 1] and len(many) == 2
    for (mesh, name), (grasps, counts, seconds) in zip(objects, many):
        g1, c1, _ = label.label(hand, spec, mesh, cfg, name)
        assert counts == c1 and sorted(grasps) == sorted(g1)
        for k in g1:
            np.testing.assert_array_equal(grasps[k], g1[k], err_msg=f"{name} {k}")
        assert set(seconds) == {"synthesis", "physics"} and seconds["synthesis"] > 0
    assert many[0][2]["physics"] == many[1][2]["physics"]  # the group's physics, shared evenly

    # a synthesis failure ends the group: the objects before it are labelled and handed over, then it is raised
    real = label.candidates

    def candidates(hand, mesh, cfg, name, grid):
        if name == objects[1][1]:
            raise FfcgsError(f"no candidates for {name}")
        return real(hand, mesh, cfg, name, grid)

    monkeypatch.setattr(label, "candidates", candidates)
    kept = []
    with pytest.raises(FfcgsError, match=f"no candidates for {objects[1][1]}"):
        label.label_many(hand, spec, objects, cfg, lambda i, t: kept.append((i, t)))
    assert [i for i, _ in kept] == [0]
    np.testing.assert_array_equal(kept[0][1][0]["lift_shake_success"], many[0][0]["lift_shake_success"])


@pytest.mark.parametrize("value", [0, -3, 4097])
def test_group_field_is_checked(value, capsys, tmp_path):
    with pytest.raises(FfcgsError, match=re.escape(f"group must be an integer in [1, 4096], got {value!r}")):
        DatasetConfig(group=value).check()
    code = cli_main.main(["dataset", "build", "--procedural", "1", f"--group={value}",
                          "--out", str(tmp_path / "never.mcap")])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("ffcgs: error:") and err.count("\n") == 1, err
    assert "group must be an integer in [1, 4096]" in err
    assert not (tmp_path / "never.mcap").exists()


def test_group_is_not_part_of_the_dataset_config():
    # a build resumed with another group size writes the same records: it must not be refused as a new config
    assert "group" not in dataset_build.record_config(DatasetConfig(group=3))
