"""Run tests/cli/test_bad_input.py's table of bad inputs against any tree of the package, one subprocess per case,
and count the outcomes (one line, multi-line message, traceback, ran on with exit 0; files changed or not).

    python bench/bad_input_table.py                      # this checkout
    git worktree add /tmp/old 1235c46 && python bench/bad_input_table.py --tree /tmp/old   # an earlier commit
"""

import argparse
import collections
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(REPO / "tests"), str(REPO / "tests" / "cli")]

import test_bad_input as table  # noqa: E402


def outcome(argv: list[str], folder: Path, env: dict) -> str:
    before = table.snapshot(folder)
    try:
        r = subprocess.run([sys.executable, "-m", "ffcgs_jax.cli", *argv], cwd=folder, env=env, capture_output=True,
                           text=True, timeout=600)
        err, code = r.stderr, r.returncode
    except subprocess.TimeoutExpired:
        err, code = "", "timeout"
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    if "Traceback" in err:
        kind = "traceback"
    elif code == 2 and sum(ln.startswith("ffcgs: error:") for ln in lines) == 1 \
            and all(ln.startswith("ffcgs: ") for ln in lines):
        kind = "one line"
    elif code == 0:
        kind = "ran on, exit 0"
    else:
        kind = f"exit {code}, {len(lines)} stderr lines"
    return kind + (", files changed" if table.snapshot(folder) != before else "")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tree", default=str(REPO), help="repository root whose ffcgs_jax runs the cases")
    args = ap.parse_args()
    env = {**os.environ, "PYTHONPATH": args.tree, "JAX_PLATFORMS": "cpu", "FFCGS_JAX_CACHE": "off"}
    counts = collections.Counter()
    for argv, _ in table.CASES:
        folder = Path(tempfile.mkdtemp())
        table.make_inputs(folder)
        kind = outcome(argv, folder, env)
        shutil.rmtree(folder)
        counts[kind] += 1
        print(f"{kind:36s} ffcgs {' '.join(argv)}", flush=True)
    print()
    for kind, n in counts.most_common():
        print(f"{n:3d}  {kind}")


if __name__ == "__main__":
    main()
