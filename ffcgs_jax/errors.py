"""The one exception type users see.

Everything that is the caller's fault (a missing file, a broken mesh, a wrong shape, an unknown config key)
raises `FfcgsError` with a message naming the problem. The CLI prints that message alone, without a traceback.
"""


class FfcgsError(ValueError):
    """Bad input to ffcgs-jax: the message says what was wrong and, where it helps, what would be right."""
