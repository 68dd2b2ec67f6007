"""The data engine (`ffcgs dataset build --keep all`): plain and Ray engines give the same records, a real
two-node Ray cluster survives losing its worker node mid-build, resume, labels against a re-run of the physics
test, the learned sampler's filter, the object supply's rules, `ffcgs dataset merge`, and bad input.

Builds run as subprocesses sharing one persistent compilation cache: the first (plain) build compiles, the Ray
workers after it load the executables from disk. All Ray tests live in this one module, so the suite never runs
two Ray clusters at once (pytest-xdist keeps a module on one worker).
"""

import errno
import json
import os
import re
import secrets
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import ffcgs_jax as fj
from ffcgs_jax.core import files
from ffcgs_jax.core.config import from_dict
from ffcgs_jax.cli import main as cli_main
from ffcgs_jax.dataset import build as dataset_build
from ffcgs_jax.dataset import engine
from ffcgs_jax.dataset import mcap_io as dataset_io
from ffcgs_jax.dataset import objects as dataset_objects
from ffcgs_jax.dataset.config import DatasetConfig
from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.geometry import objects as builtin_objects
from ffcgs_jax.geometry import procedural
from ffcgs_jax.training import data as learning_data
from ffcgs_jax.physics.config import PhysicsConfig

pytestmark = pytest.mark.e2e  # dataset builds end to end, Ray clusters

ray = pytest.importorskip("ray")

ASSETS = Path(builtin_objects.__file__).parent / "assets" / "objects"
PROTOCOLS = ("lift-shake", "six-dir", "dexgraspbench")
PER_OBJECT = 6
# 4 generated objects (3 simple, 1 complex), every candidate labelled by the three protocols; tiny SDF and descent
ARGS = ["--procedural", "3", "--complex", "1", "--seed", "7", "--keep", "all", "--sampler", "geometric",
        "--per-object", str(PER_OBJECT), "--rotations", "1", "--grasp.sdf.res", "16", "--grasp.optim.iters", "60",
        "--protocols", ",".join(PROTOCOLS), "--task-cpus", "1", "--trials", "3"]
N_OBJECTS = 4


def cli(env, *argv, check=True, timeout=600) -> subprocess.CompletedProcess:
    p = subprocess.run([sys.executable, "-m", "ffcgs_jax.cli", *argv], env=env, capture_output=True, text=True,
                       timeout=timeout)
    if check:
        assert p.returncode == 0, p.stderr[-3000:]
    return p


def parts_of(out: Path) -> dict[str, bytes]:
    parts = dataset_io.parts_dir_for(out)
    return {rid: (parts / f"{rid}.mcap").read_bytes() for rid in dataset_io.done_records(parts)}


@pytest.fixture(scope="module")
def env(tmp_path_factory):
    cache = tmp_path_factory.mktemp("xla")
    # Ray's token authentication, one token for every node and driver of the test cluster (Ray's docs: the
    # same RAY_AUTH_TOKEN everywhere); nothing is written to ~/.ray
    return dict(os.environ, FFCGS_JAX_CACHE=str(cache), JAX_ENABLE_X64="1", JAX_PLATFORMS="cpu",
                RAY_USAGE_STATS_ENABLED="0", PYTHONUNBUFFERED="1", RAY_AUTH_MODE="token",
                RAY_AUTH_TOKEN=secrets.token_hex(16))


@pytest.fixture(scope="module")
def plain(tmp_path_factory, env):
    out = tmp_path_factory.mktemp("plain") / "plain.mcap"
    cli(env, "dataset", "build", *ARGS, "--engine", "plain", "--out", str(out))
    return out


def test_every_candidate_is_written_with_its_labels(plain):
    recs = list(dataset_io.iter_records(plain))
    assert len(recs) == N_OBJECTS and all(r.num_grasps == PER_OBJECT for r in recs)
    config = dataset_io.read_config(plain)
    assert config["config"]["keep"] == "all" and len(config["extra"]["objects"]) == N_OBJECTS
    assert config["extra"]["objects_sha256"] == dataset_objects.objects_sha256(
        dataset_objects.sources(DatasetConfig(procedural=3, complex=1, seed=7)))
    outcomes = []
    for r in recs:
        arrays = r.grasp_arrays()
        for p in PROTOCOLS:
            k = p.replace("-", "_")
            assert arrays[f"{k}_success"].shape == (PER_OBJECT,) and arrays[f"{k}_reason"].dtype == np.int8
            assert np.isin(arrays[f"{k}_reason"], (-1, 0, 1, 2, 3, 4)).all()  # 4: unstable
            # success and reason "ok" agree: a label is one outcome, not two
            np.testing.assert_array_equal(arrays[f"{k}_success"], arrays[f"{k}_reason"] == 0)
            outcomes.append(arrays[f"{k}_success"])
        assert {"valid", "epsilon", "E_c", "penetration", "initial_penetration"} <= set(arrays)
        assert r.info["candidates"] == PER_OBJECT and r.info["passed_all"] == int(r.holds().sum())
    outcomes = np.concatenate(outcomes)
    assert 0 < outcomes.sum() < len(outcomes)  # successes and failures both written
    # the learned sampler trains on the successes only: a filter over the same records
    held = sum(int(r.holds().sum()) for r in recs)
    if held:
        assert len(learning_data.load(plain, noisy=False).pose) == held
    batches = list(dataset_io.batches(plain, 4, seed=0, held_only=True))
    assert sum(len(b["q"]) for b in batches) == held
    assert sum(len(b["q"]) for b in dataset_io.batches(plain, 4, seed=0)) == N_OBJECTS * PER_OBJECT



def test_info_reports_the_labels(plain, capsys):
    from ffcgs_jax.dataset import stats

    s = stats.stats(plain)
    recs = list(dataset_io.iter_records(plain))
    lab = s["labelled"]
    assert lab["candidates"] == N_OBJECTS * PER_OBJECT and lab["all"] == sum(int(r.holds().sum()) for r in recs)
    for k in ("lift_shake_success", "six_dir_success", "dexgraspbench_success"):
        assert lab[k] == sum(int(r.grasp_arrays()[k].sum()) for r in recs)
    assert s["physics"] == {"tested": lab["candidates"], "passed_both": lab["all"],
                            "pass_rate": lab["all"] / lab["candidates"]}
    assert f"labelled candidates (record 0 of each object): {lab['candidates']}" in stats.format_stats(s)


def test_export_carries_the_labels(plain, tmp_path):
    from ffcgs_jax.dataset import export

    export.export(plain, tmp_path / "x.npz")
    recs = list(dataset_io.iter_records(plain))
    with np.load(tmp_path / "x.npz") as z:
        for k in ("six_dir_move_dir", "dexgraspbench_reason", "lift_shake_success", "valid", "contacts"):
            np.testing.assert_array_equal(z[k], np.concatenate([r.grasp_arrays()[k] for r in recs]))
            assert z[f"has_{k}"].all()
        assert z["six_dir_move_dir"].shape == (N_OBJECTS * PER_OBJECT, 6)


def test_labels_match_a_rerun_of_the_physics_test(plain):
    config = dataset_io.read_config(plain)["config"]
    pcfg = from_dict(PhysicsConfig, config["physics"], say_renamed=False)
    srcs = {s.name: s for s in dataset_objects.sources(DatasetConfig(procedural=3, complex=1, seed=7))}
    rec = max(dataset_io.iter_records(plain), key=lambda r: int(r.lift_shake_success.sum()))
    np.testing.assert_array_equal(rec.rotation, np.eye(3))  # record 0 is the object as simulated
    mesh = srcs[rec.object_name].load()
    again = fj.evaluate_physics("svh", mesh, {"wrist_pose": rec.wrist_pose, "q": rec.q,
                                              "squeeze_dir": rec.labels["squeeze_dir"]},
                                pcfg, protocols=PROTOCOLS, backend="cpu").as_arrays()
    arrays = rec.grasp_arrays()
    for p in PROTOCOLS:
        k = p.replace("-", "_")
        np.testing.assert_array_equal(again[f"{k}_success"], arrays[f"{k}_success"], err_msg=p)
        np.testing.assert_array_equal(again[f"{k}_reason"], arrays[f"{k}_reason"], err_msg=p)


def test_ray_engine_gives_the_same_records(plain, env, tmp_path):
    out = tmp_path / "ray.mcap"
    p = cli(env, "dataset", "build", *ARGS, "--engine", "ray", "--out", str(out))
    assert "(ray engine)" in p.stdout
    assert parts_of(out) == parts_of(plain)
    assert out.read_bytes() == plain.read_bytes()


def test_resume_never_redoes_a_written_shard(plain, env, tmp_path):
    out = tmp_path / "resumed.mcap"
    parts = dataset_io.parts_dir_for(out)
    shutil.copytree(dataset_io.parts_dir_for(plain), parts)
    (parts / "timing.jsonl").unlink()
    gone = sorted(parts.glob("*.mcap"))[1]
    name = gone.name.split(".")[0]
    gone.unlink()
    dataset_build.annotation_path(parts, name).unlink()
    before = {p.name: p.stat().st_mtime_ns for p in parts.glob("*.mcap")}
    cli(env, "dataset", "build", *ARGS, "--engine", "plain", "--out", str(out))
    rows = [json.loads(line) for line in (parts / "timing.jsonl").read_text().splitlines()]
    assert [r["object"] for r in rows] == [name]  # only the missing object was built
    assert {p.name: p.stat().st_mtime_ns for p in parts.glob("*.mcap") if p.name in before} == before
    assert out.read_bytes() == plain.read_bytes()


def ray_cli(*argv, env) -> subprocess.CompletedProcess:
    return subprocess.run([str(Path(sys.executable).with_name("ray")), *argv], env=env, capture_output=True,
                          text=True, timeout=120)


def alive_nodes(address: str, env) -> int:
    p = ray_cli("status", "--address", address, env=env)
    return len(re.findall(r"^\s*1 node_", p.stdout, re.M)) if p.returncode == 0 else 0


def test_two_node_cluster_loses_its_worker_mid_build(plain, env, tmp_path):
    """`ray start --head` and a worker node joined to it, both here; the build joins through --address; the worker
    node is killed once the first object is written; the build still finishes, equal to the plain build."""
    port = 6391
    address = f"127.0.0.1:{port}"
    head = ray_cli("start", "--head", "--port", str(port), "--num-cpus", "1", "--disable-usage-stats",
                   "--include-dashboard", "false", env=env)
    assert head.returncode == 0, head.stderr[-2000:]
    worker = None
    try:
        worker = subprocess.Popen([str(Path(sys.executable).with_name("ray")), "start", "--address", address,
                                   "--num-cpus", "1", "--block"], env=env, stdout=subprocess.DEVNULL,
                                  stderr=subprocess.DEVNULL, start_new_session=True)
        deadline = time.monotonic() + 60
        while alive_nodes(address, env) < 2:
            assert time.monotonic() < deadline, "the worker node did not join"
            time.sleep(1)
        out = tmp_path / "cluster.mcap"
        parts = dataset_io.parts_dir_for(out)
        build = subprocess.Popen([sys.executable, "-m", "ffcgs_jax.cli", "dataset", "build", *ARGS,
                                  "--address", address, "--out", str(out)], env=env, stdout=subprocess.PIPE,
                                 stderr=subprocess.PIPE, text=True)
        while not dataset_io.done_records(parts) and build.poll() is None:
            time.sleep(0.05)
        assert build.poll() is None, "the build ended before the worker node could be killed"
        os.killpg(worker.pid, signal.SIGKILL)
        worker.wait()
        killed_with = len(dataset_io.done_records(parts))
        stdout, stderr = build.communicate(timeout=600)
        assert build.returncode == 0, stderr[-3000:]
        assert killed_with < N_OBJECTS
        assert parts_of(out) == parts_of(plain)
        assert out.read_bytes() == plain.read_bytes()
        # the merge command writes the same file from the shared parts folder
        out.unlink()
        code = cli_main.main(["dataset", "merge", str(out)])
        assert code == 0 and out.read_bytes() == plain.read_bytes()
    finally:
        if worker is not None and worker.poll() is None:
            os.killpg(worker.pid, signal.SIGKILL)
        ray_cli("stop", "--force", env=env)


# ----------------------------------------------------------------------------------------------------------------
# bad input: one line, no shard lost
# ----------------------------------------------------------------------------------------------------------------


def run_cli(capsys, *argv):
    code = cli_main.main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def test_broken_mesh_is_one_line_before_anything_is_built(capsys, tmp_path):
    objs = tmp_path / "objs"
    objs.mkdir()
    shutil.copy(ASSETS / "ball.ply", objs)
    (objs / "cracked.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\nend_header\n1 2\n")
    code, _, err = run_cli(capsys, "dataset", "build", "--objects", str(objs), "--out", str(tmp_path / "d.mcap"),
                           "--keep", "all")
    assert code == 2 and err.count("\n") == 1 and "cracked.ply" in err, err
    assert not dataset_io.parts_dir_for(tmp_path / "d.mcap").exists()


def test_unreachable_address_is_one_line(capsys, tmp_path):
    t0 = time.monotonic()
    code, _, err = run_cli(capsys, "dataset", "build", "--procedural", "1", "--out", str(tmp_path / "d.mcap"),
                           "--address", "127.0.0.1:1")
    assert code == 2 and err.count("\n") == 1, err
    assert "cannot reach the Ray cluster at 127.0.0.1:1" in err
    assert time.monotonic() - t0 < 30
    code, _, err = run_cli(capsys, "dataset", "build", "--procedural", "1", "--out", str(tmp_path / "d.mcap"),
                           "--address", "nowhere")
    assert code == 2 and "--address must be auto, HOST:PORT or ray://HOST:PORT" in err


def test_full_disk_is_one_line_and_keeps_the_finished_shards(capsys, plain, tmp_path, monkeypatch):
    """The annotations are there (copied), so the build only writes: the second part hits a full disk."""
    out = tmp_path / "full.mcap"
    parts = dataset_io.parts_dir_for(out)
    shutil.copytree(dataset_io.parts_dir_for(plain), parts)
    for p in parts.glob("*.mcap"):
        p.unlink()
    real = files.atomic_write
    written = []

    def full_after_one(path, write):
        if Path(path).suffix == ".mcap" and Path(path).parent == parts:
            if written:
                def no_space(f):
                    f.write(b"\x89MCAP0\r\n")
                    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
                return real(path, no_space)
            written.append(path)
        return real(path, write)

    monkeypatch.setattr(files, "atomic_write", full_after_one)
    argv = ["dataset", "build", *ARGS, "--engine", "plain", "--out", str(out)]
    code, _, err = run_cli(capsys, *argv)
    # mid-build, after the progress bar: the error is its one last line
    last = err.strip().splitlines()[-1]
    assert code == 2 and err.count("ffcgs: error:") == 1 and "Traceback" not in err, err
    assert last.startswith("ffcgs: error: cannot write") and last.endswith("No space left on device"), err
    assert dataset_io.done_records(parts) == [Path(written[0]).name.removesuffix(".mcap")]
    assert not any(p.name.startswith(".") for p in parts.iterdir() if p.suffix == ".mcap")
    monkeypatch.setattr(files, "atomic_write", real)
    code, _, err = run_cli(capsys, *argv)  # space again: the build resumes and finishes
    assert code == 0, err
    assert out.read_bytes() == plain.read_bytes()


# ----------------------------------------------------------------------------------------------------------------
# the object supply and the engine's choices (no build)
# ----------------------------------------------------------------------------------------------------------------


def test_test_split_and_held_out_seeds_are_refused(tmp_path):
    for i in range(5):
        shutil.copy(ASSETS / "ball.ply", tmp_path / f"m{i}.ply")
    with pytest.raises(FfcgsError, match=r"m4\.ply is in the test split"):
        dataset_objects.sources(DatasetConfig(objects=str(tmp_path), split="all"))
    with pytest.raises(FfcgsError, match="in the test split"):
        dataset_objects.sources(DatasetConfig(objects=str(tmp_path), split="test"))
    both = dataset_objects.sources(DatasetConfig(objects=str(tmp_path), split="all", allow_test=True))
    assert [s.split for s in both] == ["train"] * 4 + ["test"]
    assert len(dataset_objects.sources(DatasetConfig(objects=str(tmp_path)))) == 4
    for seed in procedural.HELD_OUT_SEEDS:
        with pytest.raises(FfcgsError, match=f"seed {seed} generates a held-out set"):
            dataset_objects.sources(DatasetConfig(complex=1, seed=seed))
    # the benchmarks' unseen sets are the ones refused
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench"))
    try:
        import quality
    finally:
        sys.path.pop(0)
    assert {quality.PROCEDURAL_SEED, quality.COMPLEX_SEED} <= set(procedural.HELD_OUT_SEEDS)


def test_generated_supply_is_deterministic_distinct_and_scaled():
    cfg = DatasetConfig(procedural=40, complex=14, seed=11, scale_min=0.8, scale_max=1.2)
    a, b = dataset_objects.sources(cfg), dataset_objects.sources(cfg)
    assert [s.describe() for s in a] == [s.describe() for s in b]
    assert dataset_objects.objects_sha256(a) == dataset_objects.objects_sha256(b)
    assert len({s.sha256 for s in a}) == len(a) == 54  # distinct geometry
    # thousands of distinct objects from one seed
    many = dataset_objects.sources(DatasetConfig(procedural=2000, complex=100, seed=11))
    assert len({s.sha256 for s in many}) == 2100
    assert {s.family for s in a} == {"procedural", "complex"} and all(s.split == "train" for s in a)
    scales = np.array([s.scale for s in a])
    assert (0.8 <= scales).all() and (scales <= 1.2).all() and scales.std() > 0.05
    s = a[-1]
    raw = procedural.complex_shape(11, s.index)[1]
    np.testing.assert_allclose(s.load().vertices, raw.vertices * s.scale)
    np.testing.assert_allclose(dataset_objects.regenerate(s.name, {"seed": 11, "scale_min": 0.8, "scale_max": 1.2})
                               .vertices, s.load().vertices)
    # adding objects never changes the earlier ones; another seed, other objects
    more = dataset_objects.sources(DatasetConfig(procedural=41, complex=14, seed=11, scale_min=0.8, scale_max=1.2))
    assert [x.sha256 for x in more[:40]] == [x.sha256 for x in a[:40]]
    assert dataset_objects.objects_sha256(more) != dataset_objects.objects_sha256(a)
    other = dataset_objects.sources(DatasetConfig(procedural=40, seed=12))
    assert not {x.sha256 for x in other} & {x.sha256 for x in a}


def test_engine_choice_and_task_resources(monkeypatch):
    import builtins

    real_import = builtins.__import__

    def no_ray(name, *a, **kw):
        if name == "ray":
            raise ModuleNotFoundError("No module named 'ray'", name="ray")
        return real_import(name, *a, **kw)

    with monkeypatch.context() as m:
        m.setattr(builtins, "__import__", no_ray)
        with pytest.raises(FfcgsError, match=r"Ray is not installed: pip install -e \"\.\[scale\]\""):
            engine.choose(DatasetConfig(engine="ray"), 1)
        assert engine.choose(DatasetConfig(), 100)[0] == "plain"
    assert engine.choose(DatasetConfig(engine="plain"), 10_000) == ("plain", None)
    assert engine.choose(DatasetConfig(engine="ray"), 1) == ("ray", None)
    assert engine.choose(DatasetConfig(address="auto"), 1) == ("ray", None)
    assert engine.choose(DatasetConfig(), 3) == ("plain", None)  # few objects: Ray's start-up would dominate
    monkeypatch.setattr(os, "cpu_count", lambda: 16)
    assert engine.choose(DatasetConfig(), 100) == ("ray", None)
    monkeypatch.setattr(os, "cpu_count", lambda: 2)
    assert engine.choose(DatasetConfig(), 100) == ("ray", None)
    monkeypatch.setattr(os, "cpu_count", lambda: 1)
    how, why = engine.choose(DatasetConfig(), 100)
    assert how == "plain" and "one core holds one task" in why
    # 16 cores and one GPU: four tasks of four cores share it; four GPUs on 64 cores likewise
    assert engine.task_resources(DatasetConfig(), {"CPU": 16, "GPU": 1}) == (4, 0.25)
    assert engine.task_resources(DatasetConfig(), {"CPU": 64, "GPU": 4}) == (4, 0.25)
    assert engine.task_resources(DatasetConfig(task_cpus=8), {"CPU": 4}) == (2, 0.0)  # two in flight at least
    assert engine.task_resources(DatasetConfig(), {"CPU": 2}) == (1, 0.0)
    with pytest.raises(FfcgsError, match="needs --engine ray or auto"):
        DatasetConfig(engine="plain", address="auto").check()
    with pytest.raises(FfcgsError, match="applies to --keep passing only"):
        DatasetConfig(keep="all", physics_test="none").check()
    with pytest.raises(FfcgsError, match="--protocols must name one or more of"):
        DatasetConfig(keep="all", protocols="lift-shake,shake").check()


def test_merge_with_missing_records_is_one_line(capsys, plain, tmp_path):
    out = tmp_path / "m.mcap"
    parts = dataset_io.parts_dir_for(out)
    shutil.copytree(dataset_io.parts_dir_for(plain), parts)
    sorted(parts.glob("*.mcap"))[0].unlink()
    code, _, err = run_cli(capsys, "dataset", "merge", str(out))
    assert code == 2 and err.count("\n") == 1 and f"1 of {N_OBJECTS} records are not built yet" in err
    code, _, err = run_cli(capsys, "dataset", "merge", str(tmp_path / "never.mcap"))
    assert code == 2 and "is not a build's parts folder" in err
