"""A training run's folder: where it writes (config.toml, checkpoint.npz, metrics.jsonl), which folders it may write
to (new, empty, or this configuration's own run, which it then resumes), and the hand its dataset was built for.
Shared by every `ffcgs train` model through `training.harness`."""

import dataclasses
import json
from pathlib import Path

from ffcgs_jax.core import files
from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.training.config import to_toml

RUN_CONFIG_MARK = "# written by ffcgs train: the resolved config of the run in this folder"
"""The first line of the config.toml a run writes: `ffcgs train --out` rewrites only a config.toml that begins with
it (or that stands beside a checkpoint: runs of older versions), never a config the user put there."""


@dataclasses.dataclass(frozen=True)
class RunFolder:
    """The files of one training run in `out`; `text` is its config as written to `config`."""

    out: Path
    text: str
    config: Path
    checkpoint: Path
    log: Path


def run_folder(cfg, model_flag: str = "") -> RunFolder:
    """The run folder of config `cfg` (its `out`), once `check_run_folder` allows the run there. `model_flag` is the
    `ffcgs train` flag that names the model ("" for the sampler, the default), for the advice to resume."""
    out = Path(cfg.out).expanduser()
    text = f"{RUN_CONFIG_MARK} (train --config it to repeat the run)\n{to_toml(cfg)}"
    run = RunFolder(out, text, out / "config.toml", out / "checkpoint.npz", out / "metrics.jsonl")
    check_run_folder(out, run.config, run.checkpoint, text, model_flag)
    return run


def check_run_folder(out: Path, cfg_path: Path, ckpt_path: Path, text: str, model_flag: str = "") -> None:
    """`out` may be new, empty, or this configuration's run (resumed); a file, another configuration's run, or a
    folder of other files is refused before anything is written."""
    if out.exists() and not out.is_dir():
        raise FfcgsError(f"--out {out} is a file, not a folder: a training run writes a folder (config.toml, "
                         "checkpoint.npz, weights.npz, ...)")
    old = _read_config(cfg_path)
    if old is not None and not old.startswith(RUN_CONFIG_MARK) and not ckpt_path.is_file():
        raise FfcgsError(f"--out {out} holds a config.toml that no ffcgs train run wrote ({cfg_path}), which a run "
                         f"would replace with its own; choose another --out (to train from that config: `ffcgs "
                         f"train{model_flag} --config {cfg_path} --out NEW`)")
    if ckpt_path.is_file() and old is not None and _body(old) != _body(text):
        raise FfcgsError(f"{out} holds a run with a different config ({cfg_path}); resume it with `ffcgs "
                         f"train{model_flag} --config {cfg_path}` or choose another --out")
    if out.is_dir() and not cfg_path.is_file() and any(p.is_file() for p in out.iterdir()):
        raise FfcgsError(f"--out {out} holds files but no training run (no config.toml); choose a new or empty "
                         "folder")


def _read_config(path: Path) -> str | None:
    if not path.is_file():
        return None
    try:
        return path.read_text()
    except (OSError, UnicodeDecodeError):
        return ""  # unreadable: no run's config, refused as such


def _body(config_text: str) -> str:
    """A run's config.toml without its first line (`RUN_CONFIG_MARK`), to compare with one of an older version."""
    first, _, rest = config_text.partition("\n")
    return rest if first.startswith(RUN_CONFIG_MARK) else config_text


def truncate_log(path: Path, step: int) -> None:
    """Drop log lines past `step` (written after the checkpoint a resumed run restarts from)."""
    if not path.exists():
        return
    keep = [line for line in path.read_text().splitlines() if line and json.loads(line)["step"] <= step]
    files.write_text(path, "".join(line + "\n" for line in keep))


def read_metrics(path: str | Path) -> list[dict]:
    """The rows of a metrics.jsonl."""
    return [json.loads(line) for line in Path(path).read_text().splitlines() if line]


def dataset_hand(path: str, hand: str = "") -> str:
    """The hand a dataset file was built for (its build config's `hand`; the SVH for files that predate the field),
    or `hand` after checking that it is the same hand."""
    from ffcgs_jax.dataset import mcap_io
    from ffcgs_jax.hand.spec import load_spec

    built = ((mcap_io.read_config(path).get("config") or {}).get("hand") or "svh")
    if hand and load_spec(hand).name != load_spec(built).name:
        raise FfcgsError(f"{path} was built for hand {built!r}, not {hand!r}: train on a dataset of that hand "
                         "(ffcgs dataset build --hand ...)")
    return hand or built
