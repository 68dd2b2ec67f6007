"""docs/custom_hand.md cannot rot: its commands parse, its quotes match the files, and its steps run on the toy hand.

Conventions of the guide (its last section says them to its editors):
- a fenced block right after `<!-- guide-test -->` runs in every test run; after `<!-- guide-test: slow -->` only
  with `-m slow` (dataset build, training, physics: minutes);
- `bash` blocks hold only `ffcgs ...` and `python -m train.sampler ...` lines. Each runs as a subprocess
  (`python -m ffcgs_jax.cli ...`) in a temporary folder, with the small sizes of `TINY` appended (later flags win);
- `python` blocks run with exec, in that folder, one namespace for the whole guide;
- `my_hand.toml` is the two-finger toy hand of tests/data/toy_hand, with the actuators and the joint equality
  that section 1 of the guide asks for, and `my_objects/` holds two built-in meshes;
- every command line of every bash block, marked or not, must parse (flags checked by the real parsers);
- a block after `<!-- guide-quote: FILE -->` quotes FILE: its lines, less `...` lines, appear in FILE in order.
"""

import os
import re
import shlex
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from paths import DATA, REPO

pytestmark = pytest.mark.e2e  # the guide's steps end to end: a hand built, compiled and synthesised

GUIDE = REPO / "docs" / "custom_hand.md"
BLOCK = re.compile(r"(?:<!-- guide-(?P<mark>[^>]*?) -->\n)?```(?P<lang>[\w-]*)\n(?P<body>.*?)^```", re.S | re.M)

# Small sizes per command, appended to the guide's flags (argparse: the last occurrence wins).
GRASP = ["--n", "8", "--iters", "5", "--res", "16"]
TINY = {
    "hand": ["--width", "96", "--height", "96"],
    "grasp": GRASP,
    "eval": ["--all", "--protocol", "six-dir"],
    "dataset build": ["--per-object", "2", "--rotations", "1", "--physics-test", "none", "--grasp.sdf.res", "16",
                      "--planner.population", "16", "--planner.steps", "5", "--planner.refine", "8",
                      "--grasp.optim.iters", "5", "--physics-chunk", "4"],
    "dataset info": [],
    "learn": ["--minutes", "0", "--train-objects", "3", "--held-out", "2", "--per-object", "8", "--cvae-epochs", "1",
              "--predictor-epochs", "2", "--grasp.sdf.res", "16", "--grasp.optim.iters", "5",
              "--physics.robust.trials", "1", "--engine", "plain"],
    "train.sampler": ["--optim.epochs", "1", "--optim.batch", "4", "--model.res", "16", "--model.width", "2",
                      "--model.features", "4", "--model.head", "4", "--model.mlp", "8", "--steps-per-call", "1",
                      "--log-every", "1"],
}
ACTUATED = """  <equality>
    <joint joint1="jb2" joint2="jb" polycoef="0 0.5 0 0 0"/>
  </equality>
  <actuator>
    <position name="a" joint="ja" kp="5" ctrlrange="0 1.2"/>
    <position name="b" joint="jb" kp="5" ctrlrange="0 1.0"/>
  </actuator>
</mujoco>"""


def blocks() -> list[tuple[str | None, str, str]]:
    """(marker or None, language, body) of every fenced block of the guide, in order."""
    return [(m["mark"], m["lang"], m["body"]) for m in BLOCK.finditer(GUIDE.read_text())]


def commands(body: str) -> list[list[str]]:
    """A bash block's command lines as argument lists (continuations joined, comments dropped)."""
    out = []
    for line in body.replace("\\\n", " ").splitlines():
        args = shlex.split(line, comments=True)
        if args:
            out.append(args)
    return out


def split_command(args: list[str]) -> tuple[str, list[str], list[str]]:
    """(TINY key, the command's argv after the program, the argv prefix that runs it with this Python)."""
    if args[0] == "ffcgs":
        key = " ".join(args[1:3]) if args[1] == "dataset" else args[1]
        return key, args[1:], [sys.executable, "-m", "ffcgs_jax.cli"]
    if args[:3] == ["python", "-m", "train.sampler"]:
        return "train.sampler", args[3:], [sys.executable, "-m", "train.sampler"]
    raise AssertionError(f"guide bash blocks may hold only `ffcgs ...` and `python -m train.sampler ...` lines, not "
                         f"{shlex.join(args)!r}")


def test_the_guide_marks_the_steps_it_promises():
    marked = [(mark, lang) for mark, lang, _ in blocks() if mark]
    assert ("test", "bash") in marked and ("test", "python") in marked, marked
    assert all(m in ("test", "test: slow") or m.startswith("quote: ") for m, _ in marked), marked
    text = "\n".join(body for mark, lang, body in blocks() if lang == "bash")
    for step in ("ffcgs hand", "ffcgs grasp", "ffcgs dataset build", "python -m train.sampler"):
        assert step in text and "--hand my_hand.toml" in text, step


def test_every_command_line_of_the_guide_parses():
    """The flags of every command in every bash block, tested or not, exist (nothing runs: parsing only)."""
    from ffcgs_jax.cli.main import parse
    from ffcgs_jax.core.config import with_overrides
    from ffcgs_jax.training.config import TrainConfig
    from train.sampler import split_args

    lines = [args for _, lang, body in blocks() if lang == "bash" for args in commands(body)]
    assert len(lines) >= 6, lines
    for args in lines:
        key, argv, _ = split_command(args)
        if key == "train.sampler":
            path, sweep, rest = split_args(argv)
            with_overrides(TrainConfig, rest if path is None else ["--config", path, *rest], "python -m train.sampler",
                           keep_prefixes=True)
        else:
            parse(argv)


def test_quoted_files_are_quoted_as_they_are():
    quotes = [(mark.split(": ", 1)[1], body) for mark, _, body in blocks() if mark and mark.startswith("quote: ")]
    assert quotes
    for rel, body in quotes:
        path = REPO / rel
        if not path.is_file():
            pytest.skip(f"{rel} does not exist (yet)")
        lines = path.read_text().splitlines()
        i = 0
        for want in body.splitlines():
            if want.strip() == "...":
                continue
            while i < len(lines) and lines[i] != want:
                i += 1
            assert i < len(lines), f"docs/custom_hand.md quotes {rel} with a line it lacks (or out of order): {want!r}"
            i += 1


@pytest.fixture
def workdir(tmp_path, monkeypatch):
    """The toy hand as `my_hand.toml` (actuated as the guide says), two meshes in `my_objects/`; cwd = there."""
    from ffcgs_jax.geometry import objects

    # the toy's fingers close towards -y, away from its +y pads and palm normal (harmless for the loader tests it was
    # made for); the guide's hand closes towards its pads, as the guide's palm check asks
    xml = (DATA / "toy_hand" / "toy.xml").read_text().replace('axis="1 0 0"', 'axis="-1 0 0"')
    assert xml.rstrip().endswith("</mujoco>") and xml.count('axis="-1 0 0"') == 3
    (tmp_path / "toy.xml").write_text(xml.rstrip()[: -len("</mujoco>")] + ACTUATED + "\n")
    shutil.copy(DATA / "toy_hand" / "toy.toml", tmp_path / "my_hand.toml")
    (tmp_path / "my_objects").mkdir()
    for name in ("ball", "box"):
        shutil.copy(objects.path(name), tmp_path / "my_objects")
    monkeypatch.chdir(tmp_path)
    return tmp_path


def grasps_in(dataset: Path) -> int:
    from ffcgs_jax.dataset import mcap_io

    return sum(len(rec.wrist_pose) for rec in mcap_io.iter_records(dataset))


def synthetic_toy_dataset(path: Path, hand: str, res: int = 16, n_objects: int = 5, grasps: int = 8) -> None:
    """A dataset "built" for `hand` (its config names it, as `ffcgs dataset build --hand` writes it): spheres and
    palm poses on a ring around them (tests/cvae_toy.py), 2 channels."""
    import numpy as np
    from cvae_toy import sphere_grid, toy_pose

    from ffcgs_jax.dataset import mcap_io, schema

    path.unlink()
    shutil.rmtree(mcap_io.parts_dir_for(path))  # the build's parts: a writer of another config refuses them
    w = mcap_io.DatasetWriter(path, {"hand": hand, "synthetic": True})
    rng = np.random.default_rng(0)
    for i in range(n_objects):
        size = 0.03 + 0.01 * i
        grid, origin, h = sphere_grid(size, np.array([0.0, 0.0, size]), res)
        poses = np.stack([toy_pose(size, a) for a in rng.uniform(0, 2 * np.pi, grasps)])
        z = np.zeros(grasps)
        w.add(schema.Record.create(object_name=f"sphere{i}", mesh_sha256="0" * 64, rotation_index=0,
                                   rotation=np.eye(3), split="train", grid=grid, origin=origin, voxel_size=h,
                                   table_z=0.0, wrist_pose=poses, q=np.zeros((grasps, 2)), epsilon=z, E=z, E_g=z,
                                   E_c=z, wrist_pose_noisy=poses))
    w.finish()


def follow(workdir: Path, marks: tuple[str, ...]) -> list[tuple[str, float]]:
    """Run the guide's blocks marked with one of `marks`, in order; returns (step, seconds) per step.

    The toy hand has two fingers: two point contacts never reach force closure (nothing resists a torque about the
    line through them), so `ffcgs dataset build` keeps no grasp of it. Before the training step, an empty
    dataset is replaced by a synthetic one of the same hand."""
    env = dict(os.environ, JAX_PLATFORMS="cpu", FFCGS_JAX_CACHE="off", FFCGS_CACHE_DIR=str(workdir / "cache"),
               FFCGS_HOME=str(workdir / "home"),
               PYTHONPATH=os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")])))
    namespace: dict = {"__name__": "__guide__"}
    timings = []
    for mark, lang, body in blocks():
        if mark not in marks:
            continue
        t0 = time.perf_counter()
        if lang == "python":
            exec(compile(body, str(GUIDE), "exec"), namespace)
            timings.append(("python block", time.perf_counter() - t0))
            continue
        assert lang == "bash", lang
        for args in commands(body):
            t0 = time.perf_counter()
            key, argv, prog = split_command(args)
            data = workdir / "my_hand_train.mcap"
            if key == "train.sampler" and data.is_file() and grasps_in(data) == 0:
                synthetic_toy_dataset(data, "my_hand.toml")
            r = subprocess.run([*prog, *argv, *TINY[key]], cwd=workdir, env=env, capture_output=True, text=True,
                               timeout=900)
            assert r.returncode == 0, f"{shlex.join(args)} failed:\n{r.stdout[-2000:]}\n{r.stderr[-3000:]}"
            assert "Traceback" not in r.stderr, r.stderr[-3000:]
            timings.append((shlex.join(args), time.perf_counter() - t0))
    return timings


def test_the_guide_runs_on_the_toy_hand(workdir, capsys):
    timings = follow(workdir, ("test",))
    out = capsys.readouterr().out
    assert "MJX and MuJoCo C agree on 16 configurations of toy" in out, out
    for png in ("hand.png", "hand_half.png", "grasp.png"):
        assert (workdir / png).stat().st_size > 1000, png
    import numpy as np

    with np.load(workdir / "grasps.npz") as g:
        assert g["q"].shape == (8, 2) and g["contacts"].shape == (8, 2, 3)
    # section 7: the toy never holds an object, so its learn run reports that and installs nothing
    report = (workdir / "learn_my_hand" / "report.md").read_text()
    assert "keeps it" in report and (workdir / "learn_my_hand" / "report.png").is_file()
    assert not (workdir / "home" / "hands").exists()
    print("\n".join(f"{s:7.1f} s  {step}" for step, s in timings))


@pytest.mark.slow
def test_the_guide_runs_on_the_toy_hand_with_its_slow_steps(workdir):
    """Physics test, dataset build, training and the trained sampler, with tiny settings."""
    timings = follow(workdir, ("test", "test: slow"))
    assert (workdir / "my_hand_train.mcap").is_file() and (workdir / "runs" / "my_hand" / "weights.npz").is_file()
    assert (workdir / "grasp_cvae.png").is_file()
    print("\n".join(f"{s:7.1f} s  {step}" for step, s in timings))
