"""README's Python API section runs as written, using only the public API."""

import ast
import json
import os
import re
import subprocess
import sys

import pytest

import ffcgs_jax

from paths import REPO


def api_block() -> str:
    text = (REPO / "README.md").read_text()
    section = text.split("\n## Python API\n", 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"```python\n(.*?)```", section, re.S)
    assert len(blocks) == 1, "README's Python API section should hold one python block"
    return blocks[0]


def test_readme_api_uses_only_the_public_names():
    tree = ast.parse(api_block())
    used = {n.attr for n in ast.walk(tree)
            if isinstance(n, ast.Attribute) and isinstance(n.value, ast.Name) and n.value.id == "fj"}
    assert used and used <= set(ffcgs_jax.__all__), used - set(ffcgs_jax.__all__)
    imported = {a.name for n in ast.walk(tree) if isinstance(n, (ast.Import, ast.ImportFrom)) for a in n.names}
    assert "..." not in api_block() and imported <= {"numpy", "ffcgs_jax"}, imported


def test_readme_python_imports_only_the_package():
    """Every python block of README: `import ffcgs_jax [as fj]`, never a submodule or a name from one."""
    blocks = re.findall(r"```python\n(.*?)```", (REPO / "README.md").read_text(), re.S)
    assert blocks
    for code in blocks:
        for node in ast.walk(ast.parse(code)):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names if a.name.startswith("ffcgs_jax.")]
                assert not names, f"README imports {names}: use fj.<name>"
            elif isinstance(node, ast.ImportFrom):
                assert (node.module or "").split(".")[0] != "ffcgs_jax", f"README imports from {node.module}"


@pytest.mark.e2e  # README's Python block end to end
def test_readme_api_runs_as_written(tmp_path):
    env = dict(os.environ, JAX_PLATFORMS="cpu", FFCGS_JAX_CACHE="off")
    r = subprocess.run([sys.executable, "-c", api_block()], capture_output=True, text=True, cwd=tmp_path, env=env,
                       timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    valid = re.search(r"^(\d+) valid of 8", r.stdout, re.M)
    assert valid and int(valid.group(1)) >= 1, r.stdout
    assert re.search(r"^six-dir success: \[\s*(True|False)\s+(True|False)\]$", r.stdout, re.M), r.stdout


def test_readme_and_notebooks_name_only_public_names_in_their_prose():
    """Outside the code blocks too: every `fj.NAME` is public, and no `ffcgs_jax.sub.module` path is offered to a
    user (a file path such as `ffcgs_jax/physics/` says where code lives, not what to call)."""
    texts = {"README.md": (REPO / "README.md").read_text()}
    for nb in sorted((REPO / "notebooks").glob("*.ipynb")):
        cells = json.loads(nb.read_text())["cells"]
        texts[nb.name] = "\n".join("".join(c["source"]) for c in cells)
    for name, text in texts.items():
        used = set(re.findall(r"\bfj\.([A-Za-z_]\w*)", text))
        assert used <= set(ffcgs_jax.__all__), (name, used - set(ffcgs_jax.__all__))
        dotted = sorted(set(re.findall(r"\bffcgs_jax\.[a-z_]+\.[A-Za-z_.]+", text)))
        assert dotted == [], (name, dotted)
