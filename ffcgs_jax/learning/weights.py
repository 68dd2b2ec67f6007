"""The CVAE's weights files: the ones shipped in the package per hand, and loading any `weights.npz` that
`python -m train.sampler` wrote (`learning.train`)."""

from importlib import resources
from pathlib import Path

import jax
import jax.numpy as jnp

from ffcgs_jax.config import from_dict
from ffcgs_jax.errors import FfcgsError
from ffcgs_jax.learning import checkpoint, cvae
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
    if "model" not in meta:
        raise FfcgsError(f"{path} is not a CVAE weights file: its metadata has no model config")
    try:
        model = from_dict(ModelConfig, meta["model"])
    except FfcgsError as e:
        raise FfcgsError(f"{path}: model config: {e}") from None
    layout = lambda tree: jax.tree.map(lambda a: (a.shape, a.dtype.kind), tree)  # noqa: E731
    got, want = tree["params"], jax.eval_shape(lambda k: cvae.init(k, model), jax.random.key(0))
    if not isinstance(got, dict) or layout(got) != layout(want):
        raise FfcgsError(f"{path}: its parameters do not fit its model config (array names, shapes or dtypes differ "
                         "from what learning.cvae.init makes for it)")
    return jax.tree.map(jnp.asarray, got), model
