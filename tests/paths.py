"""Where the tests find their data, the repository and ../shared, wherever the test module sits in tests/; and
`bench_script`, a script of bench/ imported as a module."""

import importlib.util
import sys
from pathlib import Path

TESTS = Path(__file__).resolve().parent
REPO = TESTS.parent
DATA = TESTS / "data"
SHARED = REPO.parent / "shared"


def bench_script(name: str):
    """bench/NAME.py as a module (`bench_NAME`), its folder on sys.path as when the script runs: its sibling
    scripts import by name."""
    script = REPO / "bench" / f"{name}.py"
    if str(script.parent) not in sys.path:
        sys.path.insert(0, str(script.parent))
    spec = importlib.util.spec_from_file_location(f"bench_{name}", script)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod
