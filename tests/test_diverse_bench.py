"""bench/diverse_objects.py: the object set's recipe and builder, and the run's plumbing with a stand-in synthesis
(no compile: the real run is the benchmark's)."""

import json

from types import SimpleNamespace

import numpy as np
import pytest
import trimesh

from paths import SHARED, bench_script

YCB = SHARED / "objects" / "ycb"


@pytest.fixture(scope="module")
def bench():
    return bench_script("diverse_objects")


def test_recipe_spans_the_range_log_uniformly(bench):
    t = bench.targets()
    assert len(t) == bench.COUNT == 100 and t[0] == 1_000 and t[-1] == 200_000
    ratios = t[1:] / t[:-1]
    assert np.allclose(ratios, ratios.mean(), rtol=2e-3)  # one factor between neighbours
    kinds = [s.kind for s in bench.slots()]
    assert (kinds.count("ycb"), kinds.count("complex"), kinds.count("simple")) == (50, 25, 25)
    assert [s.index for s in bench.slots()] == list(range(100)) and bench.slots() == bench.slots()
    assert sorted(bench.run_order(range(100))) == list(range(100)) and bench.run_order(range(100)) != list(range(100))


@pytest.mark.skipif(not YCB.is_dir(), reason="needs the YCB meshes in ../shared/objects/ycb")
def test_built_meshes_land_on_their_targets_distinct_and_watertight(bench, tmp_path):
    from ffcgs_jax.geometry import mesh_io

    wanted = [0, 1, 3, 30]  # YCB decimated, complex, simple refined from 12 faces, YCB refined
    built = bench.build(tmp_path, YCB, wanted)["objects"]
    assert sorted(int(i) for i in built) == wanted
    assert bench.check_set(built, mesh_io.mesh_sha256(mesh_io.load_mesh(bench.WARMUP))) == []
    for e in built.values():
        mesh = mesh_io.load_mesh(tmp_path / e["file"])
        assert abs(len(mesh.faces) / e["target"] - 1) <= bench.HIT and len(mesh.faces) == e["faces"]
        assert mesh.is_watertight == e["watertight"] and (e["watertight"] or not e["source_watertight"])
        assert mesh_io.mesh_sha256(mesh) == e["sha256"]
        assert 0.04 < np.ptp(mesh.vertices, axis=0).max() < 0.35  # metres: the library's scale, no rescaling
    assert built["0"]["faces"] < built["0"]["source_faces"] < built["30"]["faces"]  # down and up from 3,000
    assert len({e["sha256"] for e in built.values()}) == len(built)
    stamps = {p.name: p.stat().st_mtime_ns for p in tmp_path.glob("*.ply")}
    again = bench.build(tmp_path, YCB, wanted)["objects"]  # a second run reuses the cache
    assert again == json.loads(json.dumps(built)) and stamps == {p.name: p.stat().st_mtime_ns
                                                                  for p in tmp_path.glob("*.ply")}


@pytest.mark.skipif(not YCB.is_dir(), reason="needs the YCB meshes in ../shared/objects/ycb")
def test_refining_keeps_the_surface(bench):
    from ffcgs_jax.geometry import mesh_io

    src = mesh_io.load_mesh(YCB / "025_mug.stl")
    fine, tol = bench.resize(src, 12_000)
    assert tol == 0.0 and fine.is_watertight and abs(len(fine.faces) / 12_000 - 1) <= bench.HIT
    pts = fine.vertices[np.random.default_rng(0).choice(len(fine.vertices), 500, replace=False)]
    assert trimesh.proximity.closest_point(src, pts)[1].max() < 1e-6  # no smoothing, no jitter


class FakeSet:
    def __init__(self, n: int):
        self.a = {"valid": np.arange(n) % 2 == 0, "compile_s": 0.0, "sdf_s": 0.01, "synthesis_s": 0.02,
                  "evaluation_s": 0.03}

    def __getitem__(self, k):
        return self.a[k]

    def order(self):
        return np.arange(len(self.a["valid"]))


def test_loop_and_iterator_rows_and_the_target_lines(bench, monkeypatch, tmp_path):
    import ffcgs_jax as fj

    mesh = trimesh.creation.icosphere(2, radius=0.05)
    items = []
    for i in range(3):
        path = tmp_path / f"{i}.ply"
        mesh.export(path)
        items.append((f"o{i}", path, {"file": path.name, "kind": "simple", "faces": len(mesh.faces)}))
    monkeypatch.setattr(fj, "synthesize", lambda hand, m, cfg, name: FakeSet(cfg.n), raising=False)
    monkeypatch.setattr(fj, "synthesize_many", lambda hand, files, cfg: (
        SimpleNamespace(grasps=FakeSet(cfg.n), error=None) for _ in files), raising=False)
    cfg = fj.GraspConfig(n=4)
    counter = bench.Compiles()
    rows = {go.__name__: go(None, cfg, items, counter, lambda line: None) for go in (bench.loop, bench.iterate)}
    for rs in rows.values():
        assert [r["object"] for r in rs] == ["o0", "o1", "o2"] and all(r["valid"] == 2 and r["n"] == 4 for r in rs)
        assert all(r["executables"] == 0 and r["whole_s"] >= r["load_s"] for r in rs)
    assert all(r["load_s"] > 0 for r in rows["loop"])  # the iterator's loads are prefetched, not an object's own

    warm = dict(rows["loop"][0], object="mug", compile_s=25.0)
    full = [dict(rows["loop"][0], whole_s=0.15, object=f"x{i}") for i in range(100)]
    report = {"command": "c", "mode": "loop", "rows": full, "warmup": warm,
              "machine": {"backend": "gpu", "device": "NVIDIA H100 80GB HBM3", "cpus": 16, "jax": "x"},
              "config": {"hand": "svh", "n": 32, "sampler": "cvae", "iters": 100, "defaults": True},
              "set": {"count": 100, "lines": []}, "summary": bench.summary(warm, full, 15.0)}
    text = bench.table(report)
    assert "100 objects in <= 20 s after the first compile: 15.0 s, met" in text
    assert "the first compile <= 30 s: 25.0 s, met" in text
    report["summary"] = bench.summary(dict(warm, compile_s=31.0), full, 21.0)
    assert text.count("missed") == 0 and bench.table(report).count("missed") == 2
    report["set"]["count"] = 6
    assert "not judged (6 of 100 objects)" in bench.table(report)


@pytest.mark.parametrize("argv, message", [
    (["--n", "0"], "--n must be >= 1"),
    (["--limit", "-1"], "--limit must be >= 0"),
    (["--hand", "nohand"], "unknown built-in hand 'nohand'"),
    (["--iterator", "--compare"], "pick one"),
])
def test_bad_input_is_one_line_and_exit_2(bench, capsys, argv, message):
    with pytest.raises(SystemExit) as e:
        bench.parse_args(argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and len(err) == 1 and message in err[0] and err[0].startswith(bench.PROG)
