"""The persistent JAX compilation cache of the command-line tool: a second `ffcgs grasp` loads its executables
from disk instead of compiling them again, and the traces of the device part and the evaluation from
`runtime.traced_store` (the mug's first grasp on a 2-core CPU: about a minute of compile cold, 3-6 s warm).

On by default for the CLI. Where: $FFCGS_JAX_CACHE if set, else $XDG_CACHE_HOME/ffcgs-jax/xla (default
~/.cache/ffcgs-jax/xla). `FFCGS_JAX_CACHE=off` (or 0, false, no) turns it off. Library users opt in with
`enable()`; importing the package changes no JAX setting. Executables that call back to the host (the
"proxsuite" LP path) are not cached by JAX, so that path compiles every time.
"""

import os
import warnings
from pathlib import Path

import jax

_OFF = {"0", "off", "false", "no"}


def cache_dir() -> Path | None:
    """The cache folder the CLI uses, or None when the environment turns the cache off."""
    env = os.environ.get("FFCGS_JAX_CACHE")
    if env is not None:
        return None if env.strip().lower() in _OFF else Path(env).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "ffcgs-jax" / "xla"


def enable(path: str | Path | None = None) -> Path | None:
    """Point JAX's persistent compilation cache at `path` (default `cache_dir()`); returns the folder or None."""
    path = cache_dir() if path is None else Path(path)
    if path is None:
        return None
    try:
        path.mkdir(parents=True, exist_ok=True)
        if not os.access(path, os.W_OK | os.X_OK):
            raise PermissionError("permission denied")
    except OSError as e:  # an unusable folder must not stop the tool: it just compiles, and says so once
        warnings.warn(f"compilation cache {path} cannot be used ({e.strerror or e}); compiling without it "
                      "(set FFCGS_JAX_CACHE to a writable folder, or off)", stacklevel=2)
        return None
    jax.config.update("jax_compilation_cache_dir", str(path))
    # every executable, the small ones too: the ~40 under a second each took ~3 s together to compile again
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    return path
