"""The package's shape: no import cycles (lazy imports included), no giant modules, tests mirroring the
subpackages, configs beside their code, and a public API that is small, lazy and complete."""

import ast
import dataclasses
import functools
import importlib
import subprocess
import sys
import textwrap

import pytest

import ffcgs_jax

from paths import REPO, TESTS

PACKAGE = REPO / "ffcgs_jax"
MAX_LINES = 600


def _module_name(path) -> str:
    parts = path.relative_to(REPO).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {_module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


def _type_checking_only(node: ast.AST, parents: dict) -> bool:
    while node in parents:
        node = parents[node]
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            return True
    return False


@functools.cache
def imports_of(name: str) -> set[str]:
    """The package modules `name` imports anywhere (top level, inside functions, in try blocks), resolved to
    modules: `from ffcgs_jax.x import y` is ffcgs_jax.x.y when that is a module, else ffcgs_jax.x. Imports under
    `if TYPE_CHECKING` never run and are left out."""
    tree = ast.parse(MODULES[name].read_text())
    parents = {c: p for p in ast.walk(tree) for c in ast.iter_child_nodes(p)}
    out = set()
    for node in ast.walk(tree):
        if _type_checking_only(node, parents):
            continue
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names if a.name.startswith("ffcgs_jax")}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and (node.module or "").startswith("ffcgs_jax"):
            for a in node.names:
                sub = f"{node.module}.{a.name}"
                out.add(sub if sub in MODULES else node.module)
    return out & set(MODULES)


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle of `graph` as a list of modules (first == last), or None."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(n):
        state[n] = 1
        stack.append(n)
        for m in sorted(graph.get(n, ())):
            if state.get(m) == 1:
                return stack[stack.index(m):] + [m]
            if m not in state and (c := visit(m)):
                return c
        stack.pop()
        state[n] = 2
        return None

    for n in sorted(graph):
        if n not in state and (c := visit(n)):
            return c
    return None


def test_find_cycle_finds_one():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": set()}) is None


def test_no_import_cycles():
    graph = {m: imports_of(m) - {m} for m in MODULES}
    assert find_cycle(graph) is None, " -> ".join(find_cycle(graph))


def test_the_physics_backends_share_an_interface_not_each_other():
    cpu, mjx = imports_of("ffcgs_jax.physics.backend_cpu"), imports_of("ffcgs_jax.physics.backend_mjx")
    assert "ffcgs_jax.physics.backend_mjx" not in cpu and "ffcgs_jax.physics.backend_cpu" not in mjx
    assert "ffcgs_jax.physics.backend" in cpu & mjx


def test_no_giant_modules():
    sizes = {m: len(p.read_text().splitlines()) for m, p in MODULES.items()}
    assert max(sizes.values()) <= MAX_LINES, {m: n for m, n in sizes.items() if n > MAX_LINES}


def test_tests_mirror_the_subpackages():
    subpackages = {p.parent.name for p in PACKAGE.glob("*/__init__.py")}
    folders = {p.name for p in TESTS.iterdir() if p.is_dir() and any(p.glob("test_*.py"))}
    assert folders <= subpackages, folders - subpackages
    for sub in subpackages:
        assert (TESTS / sub).is_dir(), f"tests/{sub}/ missing for ffcgs_jax/{sub}/"


def test_configs_live_beside_their_code():
    """Every config dataclass is defined in a subpackage (its `config.py` or the module it configures); the
    shared ffcgs_jax/config.py holds only helpers."""
    top = importlib.import_module("ffcgs_jax.config")
    assert not [n for n, v in vars(top).items() if dataclasses.is_dataclass(v) and v.__module__ == top.__name__]
    for sub in ("geometry", "synthesis", "physics", "dataset", "learning", "viz"):
        mod = importlib.import_module(f"ffcgs_jax.{sub}.config")
        assert any(dataclasses.is_dataclass(v) and v.__module__ == mod.__name__ for v in vars(mod).values()), sub


def private_uses(name: str) -> list[str]:
    """Private names (`_x`, not dunders) of other package modules that module `name` uses: imported by name, or read
    as an attribute of a package module it imported."""
    tree = ast.parse(MODULES[name].read_text())
    private = lambda n: n.startswith("_") and not n.startswith("__")  # noqa: E731
    modules, out = {}, []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name in MODULES and a.asname:
                    modules[a.asname] = a.name
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and (node.module or "").startswith("ffcgs_jax"):
            for a in node.names:
                if f"{node.module}.{a.name}" in MODULES:
                    modules[a.asname or a.name] = f"{node.module}.{a.name}"
                elif private(a.name):
                    out.append(f"{node.module}.{a.name}")
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in modules \
                and private(node.attr) and modules[node.value.id] != name:
            out.append(f"{modules[node.value.id]}.{node.attr}")
    return sorted(set(out))


def test_private_uses_are_found():
    assert private_uses("ffcgs_jax.synthesis.grasp") == []
    tree = {m: private_uses(m) for m in MODULES}
    assert not any(tree.values()), {m: u for m, u in tree.items() if u}


def test_public_api_names_resolve():
    for name in ffcgs_jax.__all__:
        assert getattr(ffcgs_jax, name) is not None, name
    assert set(ffcgs_jax.__all__) <= set(dir(ffcgs_jax))
    from ffcgs_jax.physics.runner import evaluate_grasps
    from ffcgs_jax.synthesis.grasp import synthesize

    assert ffcgs_jax.synthesize is synthesize and ffcgs_jax.evaluate_physics is evaluate_grasps
    with pytest.raises(AttributeError, match="public names: load_hand"):
        ffcgs_jax.no_such_name  # noqa: B018


def test_import_is_lazy_and_fast():
    code = textwrap.dedent("""
        import sys, time
        t = time.perf_counter()
        import ffcgs_jax
        dt = time.perf_counter() - t
        heavy = sorted(m for m in ("jax", "mujoco", "trimesh", "numpy") if m in sys.modules)
        print(heavy, dt)
        ffcgs_jax.GraspConfig
        print("jax" in sys.modules)
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split("\n")
    heavy, dt = out[0].rsplit(" ", 1)
    assert heavy == "[]", heavy
    assert float(dt) < 0.5
    assert out[1] == "False"  # the configs are plain dataclasses: no JAX to build one


def layers_contract() -> list[list[set[str]]]:
    """docs/architecture.md's ```layers block: layers highest first, each a list of independent groups of names."""
    text = (REPO / "docs" / "architecture.md").read_text()
    block = text.split("```layers\n", 1)[1].split("```", 1)[0]
    return [[set(g.split()) for g in line.split("|")] for line in block.splitlines() if line.strip()]


def _lazy_api_imports() -> set[str]:
    """The modules the public API's lazy names come from (`ffcgs_jax._API`: strings, not import statements)."""
    tree = ast.parse(MODULES["ffcgs_jax"].read_text())
    return {node.value for node in ast.walk(tree) if isinstance(node, ast.Constant) and isinstance(node.value, str)
            and node.value in MODULES and node.value != "ffcgs_jax"}


def place(module: str, contract) -> tuple[int, int]:
    """(layer, group) of `module`: the longest contract name that is the module or a package above it."""
    short = module.removeprefix("ffcgs_jax.") if module != "ffcgs_jax" else "ffcgs_jax"
    best = None
    for i, layer in enumerate(contract):
        for j, group in enumerate(layer):
            for name in group:
                if short == name or short.startswith(name + "."):
                    if best is None or len(name) > best[0]:
                        best = (len(name), i, j)
    assert best is not None, f"{module} is in no layer of docs/architecture.md"
    return best[1], best[2]


def layer_violations(contract) -> list[str]:
    out = []
    for m in MODULES:
        deps = imports_of(m) | (_lazy_api_imports() if m == "ffcgs_jax" else set())
        lm, gm = place(m, contract)
        for d in sorted(deps - {m}):
            ld, gd = place(d, contract)
            if ld < lm:
                out.append(f"{m} imports {d}, a higher layer")
            elif ld == lm and gd != gm:
                out.append(f"{m} imports {d}, an independent name of its layer")
    return out


def test_layer_violations_are_found():
    contract = [[{"top"}], [{"low"}]]
    assert place("ffcgs_jax.low.x", contract) == (1, 0)
    with pytest.raises(AssertionError, match="in no layer"):
        place("ffcgs_jax.nowhere", contract)


def test_layers_hold():
    """The import order docs/architecture.md states holds for every module: no exceptions."""
    contract = layers_contract()
    assert len(contract) >= 8
    assert not layer_violations(contract), "\n".join(layer_violations(contract))
