"""Import MuJoCo MJX once, quietly.

MJX tries its optional Warp backend at import and prints "Failed to import warp" to stdout when it is absent.
ffcgs-jax uses the JAX backend only, and CLI users (and pipes reading our stdout) should not see that line.
"""

import contextlib
import io

with contextlib.redirect_stdout(io.StringIO()):
    from mujoco import mjx

__all__ = ["mjx"]
