"""The package's shape: no import cycles (lazy imports included), no giant modules, tests mirroring the
subpackages, configs beside their code, and a public API that is small, lazy and complete."""

import ast
import dataclasses
import functools
import importlib
import re
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
    shared ffcgs_jax/core/config.py holds only helpers."""
    top = importlib.import_module("ffcgs_jax.core.config")
    assert not [n for n, v in vars(top).items() if dataclasses.is_dataclass(v) and v.__module__ == top.__name__]
    for sub in ("geometry", "synthesis", "physics", "dataset", "learning", "training", "viz"):
        mod = importlib.import_module(f"ffcgs_jax.{sub}.config")
        assert any(dataclasses.is_dataclass(v) and v.__module__ == mod.__name__ for v in vars(mod).values()), sub


def _private(n: str) -> bool:
    return n.startswith("_") and not n.startswith("__")


SCRIPTS = sorted(p for d in ("tests", "bench", "train", "data") for p in (REPO / d).rglob("*.py"))


def _script_names(path) -> set[str]:
    """The names a script of tests/, bench/, train/ or data/ is imported by: its stem (pytest puts tests/ and each
    test file's folder on sys.path, a bench script puts bench/ there), and its dotted path from the repository where
    its folder is a package (`train.sampler`, `train`)."""
    names = set() if path.stem == "__init__" else {path.stem}
    if (path.parent / "__init__.py").is_file():
        names.add(_module_name(path))
    return names


SCRIPT_FILES: dict[str, list] = {}  # name -> the scripts of that name (an ambiguous stem names all of them: one module)
for _p in SCRIPTS:
    for _n in _script_names(_p):
        SCRIPT_FILES.setdefault(_n, []).append(_p)
ALL_MODULES = set(MODULES) | set(SCRIPT_FILES)


def _known_module(dotted: str) -> str | None:
    """The repository module a dotted string names (`ffcgs_jax.x.y`, `quality`, `train.sampler`), or None."""
    return dotted if dotted in ALL_MODULES else None


_LOADING: set[str] = set()


@functools.cache
def module_bindings_of(name: str) -> dict[str, str]:
    """The names script `name` binds to repository modules (`module_bindings`): what `from name import n` can bring
    in, such as a pytest fixture that returns a bench script."""
    if name not in SCRIPT_FILES or name in _LOADING:
        return {}
    _LOADING.add(name)
    try:
        out = {}
        for path in SCRIPT_FILES[name]:
            out.update(module_bindings(ast.parse(path.read_text()))[0])
        return out
    finally:
        _LOADING.discard(name)


def module_of(expr: ast.AST, modules: dict[str, str]) -> str | None:
    """The repository module an expression such as `m`, `fj.synthesis.grasp` or `bench_script("quality")` evaluates
    to, given the names bound to modules, or None."""
    if isinstance(expr, ast.Name):
        return modules.get(expr.id)
    if isinstance(expr, ast.Attribute) and (above := module_of(expr.value, modules)):
        return _known_module(f"{above}.{expr.attr}")
    if isinstance(expr, ast.Call) and expr.args:
        func, arg = ast.unparse(expr.func).rpartition(".")[2], expr.args[0]
        if func in ("import_module", "bench_script", "spec_from_file_location") and \
                isinstance(arg, ast.Constant) and isinstance(arg.value, str):
            return _known_module(arg.value)
        if func == "module_from_spec":
            return module_of(arg, modules)
    return None


def module_bindings(tree: ast.AST) -> tuple[dict[str, str], list[str]]:
    """(local name -> the repository module it is bound to, private names imported by name) of a parsed source.

    A name is bound by `import m [as x]` (m a package module or a script's bare name), `from p import m`, `from s
    import n` where script s binds n, `x = importlib.import_module("m")`, `x = bench_script("m")` (tests/paths.py),
    `spec = spec_from_file_location("m", ...)` with `x = module_from_spec(spec)`, `x = y` for a bound y, and by a
    function that returns or yields a bound expression (a pytest fixture: its tests' parameter of that name)."""
    modules, imported = {}, []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.asname and a.name in ALL_MODULES:
                    modules[a.asname] = a.name
                elif not a.asname and (top := a.name.split(".")[0]) in ALL_MODULES:
                    modules[top] = top
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module and \
                (node.module in ALL_MODULES or node.module.startswith("ffcgs_jax")):
            for a in node.names:
                if f"{node.module}.{a.name}" in ALL_MODULES:
                    modules[a.asname or a.name] = f"{node.module}.{a.name}"
                elif _private(a.name):
                    imported.append(f"{node.module}.{a.name}")
                elif a.name in (bound := module_bindings_of(node.module)):
                    modules[a.asname or a.name] = bound[a.name]

    while True:  # bindings through assignments and functions, to a fixed point (they may come in any order)
        before = dict(modules)
        for node in ast.walk(tree):
            if isinstance(node, ast.Assign) and (m := module_of(node.value, modules)):
                modules.update({t.id: m for t in node.targets if isinstance(t, ast.Name)})
            elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                for r in ast.walk(node):
                    if isinstance(r, (ast.Return, ast.Yield)) and r.value is not None \
                            and (m := module_of(r.value, modules)):
                        modules[node.name] = m
        if modules == before:
            return modules, imported


def private_uses_in(source: str, own: str | set[str] | None = None) -> list[str]:
    """Private names (`_x`, not dunders) of repository modules other than `own` that the Python `source` uses.

    The modules are the package's (`ffcgs_jax.x`) and the scripts of tests/, bench/, train/ and data/, by the bare
    names they are imported by (`test_runner`, `quality`, `train.sampler`). A private name is used when it is
    imported by name (`from test_runner import _grasps`); read as an attribute of a module bound as
    `module_bindings` says (`m._x`, `ffcgs_jax.m._x`, `fj.m._x`, `Q._x` after `import quality as Q`, `bench._x`
    for a fixture returning a bench script); named by a string beside a module (`getattr(m, "_x")`,
    `monkeypatch.setattr(m, "_x", f)`); or named whole in a string (`monkeypatch.setattr("ffcgs_jax.m._x", f)`,
    `mock.patch("quality._x")`)."""
    tree = ast.parse(source)
    own = {own} if isinstance(own, str) else set(own or ())
    modules, imported = module_bindings(tree)
    out = [u for u in imported if u.rpartition(".")[0] not in own]

    def used(module: str | None, attr: str) -> None:
        if module and module not in own and _private(attr):
            out.append(f"{module}.{attr}")

    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute):
            used(module_of(node.value, modules), node.attr)
        elif isinstance(node, ast.Call) and len(node.args) >= 2 and isinstance(node.args[1], ast.Constant) \
                and isinstance(node.args[1].value, str):
            used(module_of(node.args[0], modules), node.args[1].value)
        elif isinstance(node, ast.Constant) and isinstance(node.value, str) \
                and re.fullmatch(r"\w+(\.\w+)+", node.value):
            above, _, attr = node.value.rpartition(".")
            used(_known_module(above), attr)
    return sorted(set(out))


def private_uses(name: str) -> list[str]:
    """Private names of other repository modules that package module `name` uses (`private_uses_in`)."""
    return private_uses_in(MODULES[name].read_text(), name)


def test_private_uses_are_found():
    assert private_uses("ffcgs_jax.synthesis.grasp") == []
    tree = {m: private_uses(m) for m in MODULES}
    assert not any(tree.values()), {m: u for m, u in tree.items() if u}


def test_private_uses_are_found_in_every_form():
    source = textwrap.dedent("""
        import importlib
        import ffcgs_jax
        import ffcgs_jax.synthesis.grasp as G
        from ffcgs_jax.geometry import tsdf
        from ffcgs_jax.physics.protocols import _angle, evaluate
        fj = ffcgs_jax
        dm = importlib.import_module("ffcgs_jax.evaluation.device_metrics")
        G._a, tsdf._b, ffcgs_jax.hand.kinematics._c, dm._d, fj.viz.render_software._h, G.__name__, tsdf.public
        getattr(tsdf, "_e"), monkeypatch.setattr(G, "_f", None), monkeypatch.setattr("ffcgs_jax.viz.viewer._g", None)
        monkeypatch.setattr(G, "public", None), "ffcgs_jax._API is private but not a dotted name"
    """)
    found = lambda own=None: [u.removeprefix("ffcgs_jax.") for u in private_uses_in(source, own)]  # noqa: E731
    assert found() == ["evaluation.device_metrics._d", "geometry.tsdf._b", "geometry.tsdf._e", "hand.kinematics._c",
                       "physics.protocols._angle", "synthesis.grasp._a", "synthesis.grasp._f",
                       "viz.render_software._h", "viz.viewer._g"]
    assert "synthesis.grasp._a" not in found(own="ffcgs_jax.synthesis.grasp")
    assert len(found(own="ffcgs_jax.synthesis.grasp")) == len(found()) - 2


def test_private_names_of_scripts_are_found_in_every_form():
    """Scripts by bare name (a test helper, a sibling bench script), as train/'s package, loaded by importlib or
    by tests/paths.py's `bench_script`, and through a fixture that returns one, here or imported from a test file."""
    source = textwrap.dedent("""
        import importlib.util
        import quality as Q
        import train.sampler
        from paths import bench_script
        from test_runner import BALL, _a
        from test_quality_script import quality as imported_fixture
        from train import sampler
        Q._b, train.sampler._c, sampler._d, Q.public, Q.__doc__, paths_like._not_a_module

        @pytest.fixture
        def depth():
            return bench_script("depth")

        def first():
            spec = importlib.util.spec_from_file_location("first_compile", BENCH)
            mod = importlib.util.module_from_spec(spec)
            return mod

        def test_it(depth, first, imported_fixture):
            depth._e, first._f, imported_fixture._g, getattr(Q, "_h"), monkeypatch.setattr("eval_grasp._i", None)
            importlib.import_module("eval_physics")._j
    """)
    # (module, name) pairs: "module._name" written out here would itself be a use of that name
    others = [("depth", "_e"), ("eval_grasp", "_i"), ("eval_physics", "_j"), ("first_compile", "_f"),
              ("train.sampler", "_c"), ("train.sampler", "_d")]
    own = [("quality", "_b"), ("quality", "_g"), ("quality", "_h"), ("test_runner", "_a")]
    assert private_uses_in(source) == sorted(f"{m}.{n}" for m, n in others + own)
    assert private_uses_in(source, {"quality", "test_runner"}) == sorted(f"{m}.{n}" for m, n in others)
    assert _script_names(REPO / "train" / "sampler.py") == {"sampler", "train.sampler"}
    assert _script_names(REPO / "tests" / "physics" / "test_runner.py") == {"test_runner"}


def test_no_module_uses_private_names_of_another():
    """A module's private names stay its own: tests, bench scripts, train/ and data/ go through public names of the
    package and of each other (a test helper of tests/, a sibling bench script), with no exceptions."""
    assert len(SCRIPTS) > 50
    uses = {str(p.relative_to(REPO)): u for p in SCRIPTS if (u := private_uses_in(p.read_text(), _script_names(p)))}
    assert not uses, "\n".join(f"{p}: {', '.join(u)}" for p, u in uses.items())


def test_public_api_names_resolve():
    for name in ffcgs_jax.__all__:
        assert getattr(ffcgs_jax, name) is not None, name
    assert set(ffcgs_jax.__all__) <= set(dir(ffcgs_jax))
    from ffcgs_jax.physics.evaluate_physics import evaluate_grasps
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


def test_layers_name_packages_only():
    """Each name of the layers block is a whole subpackage (or `ffcgs_jax`, the public API), each subpackage is named
    exactly once and no module sits at the package's root beside them: a folder is a layer, at one height."""
    names = [n for layer in layers_contract() for group in layer for n in group]
    subpackages = sorted(p.parent.name for p in PACKAGE.glob("*/__init__.py"))
    assert sorted(n for n in names if n != "ffcgs_jax") == subpackages, (names, subpackages)
    assert names.count("ffcgs_jax") == 1
    assert sorted(p.name for p in PACKAGE.glob("*.py")) == ["__init__.py"]


def test_layers_hold():
    """The import order docs/architecture.md states holds for every module: no exceptions."""
    contract = layers_contract()
    assert len(contract) >= 8
    assert not layer_violations(contract), "\n".join(layer_violations(contract))


def test_constraints_pin_every_dependency_by_version():
    """constraints.txt (what README and CI install with) pins each dependency and test extra as name==version: no
    local file or URL, which would not install on another machine, and nothing of pyproject's left to float."""
    import re
    import tomllib

    pins = {}
    for line in (REPO / "constraints.txt").read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            m = re.fullmatch(r"([A-Za-z0-9_.-]+)==([A-Za-z0-9_.+!-]+)", line.strip())
            assert m, f"constraints.txt: {line!r} is not name==version"
            pins[m.group(1).lower().replace("_", "-")] = m.group(2)
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    wanted = project["dependencies"] + project["optional-dependencies"]["test"]
    names = {re.match(r"[A-Za-z0-9_.-]+", d).group(0).lower().replace("_", "-") for d in wanted}
    assert names <= set(pins), names - set(pins)
