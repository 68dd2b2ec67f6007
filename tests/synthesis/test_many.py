"""`synthesize_many`: which objects a list names, their order, the next object's host work overlapping the current
one's synthesis, and failures that stay one object's. The loader, the triangle table and `synthesize` are stand-ins
here (no compile); tests/cli/test_grasp_many.py runs the real pipeline through the CLI."""

import threading
import time

import pytest
import trimesh

from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.geometry import objects
from ffcgs_jax.synthesis import many
from ffcgs_jax.synthesis.config import GraspConfig
from ffcgs_jax.synthesis.many import ObjectSource, expand_objects, synthesize_many

WAIT_S = 10.0  # how long a stand-in synthesis waits for the next object's load to start (it starts at once)


def _mesh_files(folder, *names):
    folder.mkdir(exist_ok=True)
    for n in names:
        (folder / n).write_text("v 0 0 0\n")
    return folder


def test_expand_objects_reads_folders_in_name_order_and_keeps_the_given_order(tmp_path):
    _mesh_files(tmp_path / "m", "c.obj", "a.STL", "b.ply", ".hidden.obj", "notes.txt")
    (tmp_path / "m" / "sub").mkdir()
    _mesh_files(tmp_path / "m" / "sub", "deep.obj")
    box = trimesh.creation.box()
    got = expand_objects(["mug", tmp_path / "m", str(tmp_path / "x.stl"), ("given", box)])
    assert [o.name for o in got] == ["mug", "a", "b", "c", "x", "given"]
    assert got[1].source == str(tmp_path / "m" / "a.STL") and got[5].source is box
    assert expand_objects(got) == got  # expanded once, filtered, passed again


@pytest.mark.parametrize("make, message", [
    (lambda t: [_mesh_files(t / "m", "mug.obj"), "mug"], r"two objects are named 'mug' \(.*mug.obj and mug\)"),
    (lambda t: [_mesh_files(t / "m", "a.obj", "a.stl")], "two objects are named 'a'"),
    (lambda t: [_mesh_files(t / "m", "notes.txt")], "holds no mesh files"),
    (lambda t: [3], "got int"),
], ids=["file-and-built-in", "two-formats", "empty-folder", "not-an-object"])
def test_expand_objects_refuses_with_one_line(tmp_path, make, message):
    with pytest.raises(FfcgsError, match=message):
        expand_objects(make(tmp_path))


class _Stand:
    """Stand-ins for the host work and the synthesis that record what ran where, in which order."""

    def __init__(self, monkeypatch, broken=(), unsynthesizable=()):
        self.events: list[tuple[str, str, str]] = []  # (what, object, thread)
        self.loading = {}  # object -> Event set when its load starts
        self.saw_next_load: dict[str, bool] = {}
        self.broken, self.unsynthesizable = set(broken), set(unsynthesizable)
        self.order: list[str] = []
        monkeypatch.setattr(many, "load_mesh", self.load)
        monkeypatch.setattr(many, "mesh_table", lambda mesh: self.events.append(
            ("table", mesh.metadata["name"], threading.current_thread().name)))
        monkeypatch.setattr(many, "build_sdf", lambda mesh, cfg: self.events.append(
            ("sdf", mesh.metadata["name"], threading.current_thread().name)))
        monkeypatch.setattr(many, "synthesize", self.synthesize)

    def load(self, source, scale):
        name = str(source)
        self.loading.setdefault(name, threading.Event()).set()
        self.events.append(("load", name, threading.current_thread().name))
        if name in self.broken:
            raise FfcgsError(f"mesh file {name} holds no triangles")
        mesh = trimesh.creation.box()
        mesh.metadata["name"] = name
        return mesh

    def synthesize(self, hand, mesh, cfg, object_name):
        self.events.append(("synthesize", object_name, threading.current_thread().name))
        if object_name in self.unsynthesizable:
            raise FfcgsError(f"{object_name}: the batch would not fit")
        i = self.order.index(object_name)
        if i + 1 < len(self.order):  # the next object's load must start while this one is on the device
            nxt = self.loading.setdefault(self.order[i + 1], threading.Event())
            self.saw_next_load[object_name] = nxt.wait(WAIT_S)
        return f"grasps of {object_name}"


def _names(*names):
    return [ObjectSource(n, n) for n in names]  # sources that are neither built-ins nor files: the stand-in loads


def test_the_next_object_loads_in_a_thread_while_the_current_one_synthesises(monkeypatch, svh):
    stand = _Stand(monkeypatch)
    stand.order = ["a", "b", "c"]
    results = list(synthesize_many(svh, _names(*stand.order), GraspConfig(n=2)))
    assert [r.name for r in results] == stand.order and [r.grasps for r in results] == [
        "grasps of a", "grasps of b", "grasps of c"]
    assert all(r.error is None and r.seconds >= 0 and r.mesh.metadata["name"] == r.name for r in results)
    assert stand.saw_next_load == {"a": True, "b": True}  # b's load began while a was synthesising, c's during b
    main = threading.current_thread().name
    assert all(t != main for what, _, t in stand.events if what in ("load", "table", "sdf"))
    assert all(t == main for what, _, t in stand.events if what == "synthesize")
    # the triangle table and the SDF are built with the mesh, before that object's synthesis
    for name in stand.order:
        kinds = [what for what, n, _ in stand.events if n == name]
        assert kinds == ["load", "table", "sdf", "synthesize"], (name, kinds)


def test_without_prefetch_each_object_loads_in_turn_on_the_calling_thread(monkeypatch, svh):
    stand = _Stand(monkeypatch)
    stand.order = ["a", "b"]
    monkeypatch.setattr(many, "synthesize", lambda hand, mesh, cfg, object_name: stand.events.append(
        ("synthesize", object_name, threading.current_thread().name)) or object_name)
    list(synthesize_many(svh, _names("a", "b"), GraspConfig(n=2), prefetch=0))
    main = threading.current_thread().name
    assert [(w, n) for w, n, _ in stand.events] == [("load", "a"), ("table", "a"), ("sdf", "a"), ("synthesize", "a"),
                                                     ("load", "b"), ("table", "b"), ("sdf", "b"), ("synthesize", "b")]
    assert {t for _, _, t in stand.events} == {main}


def test_a_broken_object_is_one_error_and_the_others_are_done(monkeypatch, svh):
    stand = _Stand(monkeypatch, broken={"b"}, unsynthesizable={"c"})
    stand.order = ["a", "b", "c", "d"]
    results = list(synthesize_many(svh, _names(*stand.order), GraspConfig(n=2)))
    assert [(r.name, r.grasps is not None) for r in results] == [("a", True), ("b", False), ("c", False),
                                                                 ("d", True)]
    assert results[1].error == "mesh file b holds no triangles" and results[1].mesh is None
    assert results[2].error == "c: the batch would not fit" and results[2].mesh is not None
    assert ("synthesize", "b", threading.current_thread().name) not in stand.events


def test_an_unexpected_loader_failure_is_that_objects_line(monkeypatch, svh):
    def crash(source, scale):
        raise ValueError("buffer is too small")

    monkeypatch.setattr(many, "load_mesh", crash)
    monkeypatch.setattr(many, "synthesize", lambda *a, **k: pytest.fail("nothing to synthesise"))
    (r,) = synthesize_many(svh, ["part.stl"], GraspConfig(n=2))
    assert r.error == "cannot load part.stl: ValueError: buffer is too small" and r.source == "part.stl"


def test_an_interrupt_ends_the_loop_without_waiting_for_the_next_load(monkeypatch, svh):
    stand = _Stand(monkeypatch)
    release = threading.Event()

    def slow_load(source, scale):
        if str(source) == "b":
            release.wait(WAIT_S)  # a load still running when the consumer stops
        return stand.load(source, scale)

    def interrupted(hand, mesh, cfg, object_name):
        raise KeyboardInterrupt

    monkeypatch.setattr(many, "load_mesh", slow_load)
    monkeypatch.setattr(many, "synthesize", interrupted)
    it = synthesize_many(svh, _names("a", "b", "c"), GraspConfig(n=2))
    t0 = time.perf_counter()
    with pytest.raises(KeyboardInterrupt):
        next(it)
    waited = time.perf_counter() - t0
    loads = [n for w, n, _ in stand.events if w == "load"]
    release.set()
    assert "b" not in loads and waited < WAIT_S / 2  # b was still loading, and the loop did not wait for it


def test_bad_arguments_raise_at_the_call_not_per_object(tmp_path, svh):
    with pytest.raises(FfcgsError, match=r"n must be an integer in \[1, 1000000\]"):
        synthesize_many(svh, ["mug"], GraspConfig(n=0))
    with pytest.raises(FfcgsError, match="prefetch must be an integer >= 0"):
        synthesize_many(svh, ["mug"], prefetch=-1)
    with pytest.raises(FfcgsError, match="two objects are named 'box'"):
        synthesize_many(svh, ["box", str(objects.path("box"))])


def test_the_public_name():
    import ffcgs_jax as fj

    assert fj.synthesize_many is synthesize_many and "synthesize_many" in fj.__all__
