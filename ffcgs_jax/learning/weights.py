"""Weights files of the package's networks: the CVAE's and the success predictor's, the ones shipped per hand and
the ones a user installed for a hand (`installed_dir`, what `synthesize` takes first), loading any `weights.npz`
that `ffcgs train` wrote (`training.train`, `training.evaluator_train`), checked (also against the hand's identity,
`hand.identity`, when the file records it), and the one in-process cache of loaded weights (`cached`): a synthesis
call must not read a weights file again."""

import os
from collections.abc import Callable, Hashable
from importlib import resources
from pathlib import Path
from typing import Literal

import cachetools

import jax
import jax.numpy as jnp
import numpy as np

from ffcgs_jax.core.config import from_dict
from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.hand.identity import spec_sha256
from ffcgs_jax.hand.spec import HandSpec
from ffcgs_jax.learning import checkpoint, cvae
from ffcgs_jax.learning.config import ModelConfig
from ffcgs_jax.runtime import compiled

WEIGHTS_FORMAT = "ffcgs.cvae.v1"
WEIGHTS_MAX = 8
"""Loaded weights the process keeps (`cached`), least recently used dropped first: a few MB each, and a process
uses one sampler and one predictor per hand, so 8 covers a few hands and dtypes without holding stale files."""
_LOADED = cachetools.LRUCache(WEIGHTS_MAX)
compiled.register("learning.weights loaded", _LOADED)


def cached(path: str | Path, key: Hashable, load: Callable[[], object]):
    """`load()` of the weights file `path`, kept per version of the file (its resolved path, modification time and
    size: a file trained again is read again) and `key` (what else the result depends on: the hand, a dtype)."""
    p = Path(path).expanduser().resolve()
    st = p.stat()
    k = (str(p), st.st_mtime_ns, st.st_size, key)
    if (hit := _LOADED.get(k)) is None:
        hit = _LOADED[k] = load()
    return hit


def shipped_weights(hand_name: str) -> Path:
    """Where the package keeps the weights trained for hand `hand_name` (the file may not exist)."""
    return Path(str(resources.files("ffcgs_jax.learning") / "assets" / "weights" / f"cvae_{hand_name}.npz"))


Kind = Literal["cvae", "evaluator"]


def installed_dir(hand_name: str) -> Path:
    """Where a hand's own learned parts are installed (`ffcgs learn`): $FFCGS_HOME/hands/NAME, by default
    $XDG_DATA_HOME/ffcgs (~/.local/share/ffcgs): a user folder, never the package's, so an upgrade keeps them."""
    home = os.environ.get("FFCGS_HOME")
    root = Path(home) if home else Path(os.environ.get("XDG_DATA_HOME") or "~/.local/share") / "ffcgs"
    return root.expanduser() / "hands" / hand_name


def default_weights(kind: Kind, hand_name: str) -> Path:
    """The weights a call uses for `hand_name` when none are named: the installed ones, else the package's (the
    file may not exist: the hand then samples geometrically, or ranks by E)."""
    installed = installed_dir(hand_name) / f"{kind}.npz"
    if installed.is_file():
        return installed
    return shipped_weights(hand_name) if kind == "cvae" else shipped_evaluator(hand_name)


def check_hand(path, meta: dict, spec: HandSpec | None) -> None:
    """Refuse weights learned for another version of the hand (its spec or MJCF changed), in one line. Files
    without the record (written before it existed) pass on the hand's name alone."""
    want = meta.get("hand_sha256")
    if spec is None or want is None:
        return
    now = spec_sha256(spec)
    if want != now:
        raise FfcgsError(f"{path} was learned for another version of hand {spec.name!r} (its spec or MJCF changed "
                         f"since: hand sha256 {want[:12]}, now {now[:12]}); learn it again (`ffcgs learn`) or "
                         "remove the file")


def load_weights(path: str | Path, hand: str | None = None, spec: HandSpec | None = None
                 ) -> tuple[dict, ModelConfig]:
    """(params as jax arrays, ModelConfig) from a weights.npz; checks its format and, if given, the hand (by name,
    and by `spec`'s identity where the file records one)."""
    tree, meta = checkpoint.load(path)
    if meta.get("format") != WEIGHTS_FORMAT or "params" not in tree:
        raise FfcgsError(f"{path} is not a CVAE weights file (format {meta.get('format')!r}, want {WEIGHTS_FORMAT})")
    if hand is not None and meta.get("hand") != hand:
        raise FfcgsError(f"{path} was trained for hand {meta.get('hand')!r}, not {hand!r}")
    check_hand(path, meta, spec)
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


# ----------------------------------------------------------------------------------------------------------------
# The success predictor's weights (`learning.evaluator`, trained by `ffcgs train --model evaluator`)
# ----------------------------------------------------------------------------------------------------------------

EVALUATOR_FORMAT = "ffcgs.evaluator.v1"


def shipped_evaluator(hand_name: str) -> Path:
    """Where the package keeps the success predictor trained for hand `hand_name` (the file may not exist)."""
    return Path(str(resources.files("ffcgs_jax.learning") / "assets" / "weights" / f"evaluator_{hand_name}.npz"))


def load_evaluator(path: str | Path, hand) -> tuple[dict, dict]:
    """({"net", "norm"} as jax arrays, metadata) of a predictor weights file, checked against `hand` (a
    `kinematics.Hand`): format, hand, feature version and width, and every array's shape. One line otherwise."""
    from ffcgs_jax.learning import evaluator

    tree, meta = checkpoint.load(path)
    if meta.get("format") != EVALUATOR_FORMAT:
        raise FfcgsError(f"{path} is not a success-predictor weights file (format {meta.get('format')!r}, want "
                         f"{EVALUATOR_FORMAT})")
    if meta.get("hand") != hand.spec.name:
        raise FfcgsError(f"{path} was trained for hand {meta.get('hand')!r}, not {hand.spec.name!r}")
    check_hand(path, meta, hand.spec)
    if meta.get("feature_version") != evaluator.FEATURE_VERSION:
        raise FfcgsError(f"{path} was trained on predictor features v{meta.get('feature_version')}, this version "
                         f"computes v{evaluator.FEATURE_VERSION}: train it again")
    width = evaluator.feature_width(hand)
    heads = meta.get("heads")
    net_cfg = meta.get("net") or {}
    try:
        hidden, depth = int(net_cfg["hidden"]), int(net_cfg["depth"])
        want = jax.eval_shape(lambda k: evaluator.init(k, width, len(heads), hidden, depth), jax.random.key(0))
    except (KeyError, TypeError, ValueError):
        raise FfcgsError(f"{path}: its metadata lacks the network's heads or shape (net.hidden, net.depth)") from None
    layout = lambda t: jax.tree.map(lambda a: (tuple(a.shape), a.dtype.kind), t)  # noqa: E731
    norm_want = {"mean": ((width,), "f"), "scale": ((width,), "f")}
    got_net, got_norm = tree.get("net"), tree.get("norm")
    if not isinstance(got_net, dict) or not isinstance(got_norm, dict) or layout(got_net) != layout(want) \
            or layout(got_norm) != norm_want:
        raise FfcgsError(f"{path}: its arrays do not fit its metadata (names, shapes or dtypes differ from a "
                         f"{depth} x {hidden} network over {width} features)")
    if not all(np.isfinite(a).all() for a in jax.tree.leaves((got_net, got_norm))):
        raise FfcgsError(f"{path}: its weights contain NaN or inf")
    return jax.tree.map(jnp.asarray, {"net": got_net, "norm": got_norm}), meta
