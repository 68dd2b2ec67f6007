"""The CVAE's weights files: the ones shipped in the package per hand, and loading any `weights.npz` that
`python -m train.sampler` wrote (`learning.train`)."""

from importlib import resources
from pathlib import Path

import jax
import jax.numpy as jnp

from ffcgs_jax.config import from_dict
from ffcgs_jax.errors import FfcgsError
from ffcgs_jax.learning import checkpoint
from ffcgs_jax.learning.config import ModelConfig

WEIGHTS_FORMAT = "ffcgs.cvae.v1"


def shipped_weights(hand_name: str) -> Path:
    """Where the package keeps the weights trained for hand `hand_name` (the file may not exist)."""
    return Path(str(resources.files("ffcgs_jax.learning") / "assets" / "weights" / f"cvae_{hand_name}.npz"))


def load_weights(path: str | Path, hand: str | None = None) -> tuple[dict, ModelConfig]:
    """(params as jax arrays, ModelConfig) from a weights.npz; checks its format and, if given, the hand."""
    tree, meta = checkpoint.load(path)
    if meta.get("format") != WEIGHTS_FORMAT or "params" not in tree:
        raise FfcgsError(f"{path} is not a CVAE weights file (format {meta.get('format')!r}, want {WEIGHTS_FORMAT})")
    if hand is not None and meta.get("hand") != hand:
        raise FfcgsError(f"{path} was trained for hand {meta.get('hand')!r}, not {hand!r}")
    return jax.tree.map(jnp.asarray, tree["params"]), from_dict(ModelConfig, meta["model"])
