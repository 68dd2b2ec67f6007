"""How README's command blocks are run as written (`test_readme_commands.py`, `test_readme_command_reference.py`):
every `bash` block outside the quick start (which `.ci/run` runs verbatim), line by line in a fresh folder, with
`FFCGS_SMOKE=1` cutting the long commands down (`cli/smoke.py`).

What a user brings is made first: `my_part.stl` (a mesh in millimetres) and `meshes/` (a folder of meshes), and
the names README leaves to the user are set (`HEAD`, the Ray head host: this machine; `SHARED`, a folder every host
sees). A command that serves a web page until Ctrl-C (`ffcgs show`, `--show`) must print its address; it is then
interrupted. A block that starts Ray nodes runs as one script in a PID namespace of its own (`unshare`, root), so
its nodes end with it. Nothing here is skipped: a README line that cannot run as written is a README bug.
"""

import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from paths import REPO

QUICK_START = 2  # the first two blocks: the quick start, run by .ci/run as written
REFERENCE = 0  # the first block after it: README's "Commands", the longest (about half of the blocks' time)


def command_blocks() -> list[tuple[int, list[str]]]:
    """(README line, [command lines with continuations joined and comments dropped]) per bash block after the quick
    start."""
    text = (REPO / "README.md").read_text()
    blocks = []
    for m in re.finditer(r"```bash\n(.*?)```", text, re.S):
        lines, pending = [], ""
        for raw in m.group(1).splitlines():
            line = pending + raw
            if line.rstrip().endswith("\\"):
                pending = line.rstrip()[:-1] + " "
                continue
            pending = ""
            code = strip_comment(line).strip()
            if code:
                lines.append(code)
        blocks.append((text[: m.start()].count("\n") + 1, lines))
    return blocks[QUICK_START:]


def strip_comment(line: str) -> str:
    """`line` without its `# ...` comment (a # inside quotes stays)."""
    quote = None
    for i, c in enumerate(line):
        if quote:
            quote = None if c == quote else quote
        elif c in "'\"":
            quote = c
        elif c == "#" and (i == 0 or line[i - 1].isspace()):
            return line[:i].rstrip()
    return line.rstrip()


def _user_files(folder: Path) -> None:
    import ffcgs_jax as fj

    part = fj.load_mesh("banana")
    part.apply_scale(1000.0)  # a mesh in millimetres, as `--scale 0.001` in README expects
    part.export(folder / "my_part.stl")
    (folder / "meshes").mkdir()
    for name in ("box", "can"):
        fj.load_mesh(name).export(folder / "meshes" / f"{name}.ply")
    (folder / "shared").mkdir()


def env_for(folder: Path, cache: Path) -> dict:
    env = dict(os.environ, FFCGS_SMOKE="1", JAX_PLATFORMS="cpu", FFCGS_JAX_CACHE=str(cache), HEAD="127.0.0.1",
               SHARED=str(folder / "shared"), FFCGS_CACHE_DIR=str(cache / "convex"), RAY_ADDRESS="")
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env['PATH']}"  # this environment's `ffcgs`, `ray`
    return env


def shared_cache(tmp_path_factory) -> Path:
    """One compilation cache for every block of this run, on every test worker: a block reuses what another compiled,
    as one user's commands do. Concurrent writers are safe (JAX's cache and `runtime.traced_store` write atomically,
    as a Ray build's workers rely on)."""
    base = tmp_path_factory.getbasetemp()
    return (base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base) / "readme-cache"


def _line_env(line: str, env: dict) -> dict:
    """`--devices 2` on a machine without two GPUs: two virtual CPU devices, as the sharding tests use. Only for
    the lines that ask for devices: on the 2-core CI machine, XLA's CPU collectives between two virtual devices
    can starve each other under a labelled build's load (a rendezvous that timed out once, 2026-11-28)."""
    if "--devices" not in line.split():
        return env
    return dict(env, XLA_FLAGS=(env.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2").strip())


def _serves(line: str) -> bool:
    return line.startswith("ffcgs show") or " --show" in f" {line} "


def _run_served(line: str, folder: Path, env: dict) -> str:
    """Start `line`, wait for the page's address, then Ctrl-C it; what it printed."""
    p = subprocess.Popen(line, shell=True, cwd=folder, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                         text=True, start_new_session=True)
    out, deadline = [], time.monotonic() + 900
    try:
        for text in p.stdout:
            out.append(text)
            if "http://" in text or time.monotonic() > deadline:
                break
    finally:
        os.killpg(p.pid, signal.SIGINT)
        try:
            rest, _ = p.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)
            rest, _ = p.communicate()
    said = "".join(out) + (rest or "")
    assert "http://" in said, f"{line!r} served no page:\n{said[-3000:]}"
    return said


def run_block(lines: list[str], tmp_path: Path, tmp_path_factory) -> None:
    """Every line of one block in a fresh folder under `tmp_path`, as a user's shell would run them one after the
    other, with the run's shared compilation cache; each must exit 0 without a traceback."""
    folder = tmp_path / "work"
    folder.mkdir()
    env = env_for(folder, shared_cache(tmp_path_factory))
    _user_files(folder)
    os.symlink(REPO / "configs", folder / "configs")  # README's paths into the checkout (`--config configs/...`)
    if any(line.startswith("ray ") for line in lines):
        _run_cluster_block(lines, folder, env)
        return
    for line in lines:
        if _serves(line):
            _run_served(line, folder, _line_env(line, env))
            continue
        r = subprocess.run(line, shell=True, cwd=folder, env=_line_env(line, env), capture_output=True, text=True,
                           timeout=1800)
        assert r.returncode == 0, f"README's {line!r} failed ({r.returncode}):\n{r.stdout[-2000:]}\n{r.stderr[-3000:]}"
        assert "Traceback" not in r.stderr, f"{line!r}:\n{r.stderr[-3000:]}"


def _run_cluster_block(lines: list[str], folder: Path, env: dict) -> None:
    """A block that starts Ray nodes (`ray start`): as one script in a PID namespace of its own, so that the nodes
    it starts end with it and no other Ray instance of the machine (the data engine's tests) is touched, with
    Ray's files in a folder of its own (a short path: Ray's sockets live there)."""
    ray_tmp = tempfile.mkdtemp(prefix="ray", dir="/tmp")
    try:
        script = "set -e\n" + "\n".join(lines) + "\n"
        r = subprocess.run(["unshare", "--pid", "--fork", "--mount-proc", "--kill-child", "bash", "-c", script],
                           cwd=folder, env=dict(env, RAY_TMPDIR=ray_tmp), capture_output=True, text=True,
                           timeout=1800)
        assert r.returncode == 0, f"README's Ray block failed ({r.returncode}):\n{r.stdout[-3000:]}\n" \
                                  f"{r.stderr[-4000:]}"
        assert "Traceback" not in r.stderr, r.stderr[-4000:]
    finally:
        shutil.rmtree(ray_tmp, ignore_errors=True)
