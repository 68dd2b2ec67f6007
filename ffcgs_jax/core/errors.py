"""The one exception type users see.

Everything that is the caller's fault (a missing file, a broken mesh, a wrong shape, an unknown config key)
raises `FfcgsError` with a message naming the problem. The CLI prints that message alone, without a traceback.
"""


class FfcgsError(ValueError):
    """Bad input to ffcgs-jax: the message says what was wrong and, where it helps, what would be right."""


def check_grasp_set(gs, caller: str) -> None:
    """FfcgsError unless `gs` is a `synthesis.grasp.GraspSet`, the one line naming `caller`, the public function that
    takes it. Checked by its fields, here below every package, so that physics (which does not import synthesis)
    and synthesis share one rule and one message."""
    if not (isinstance(getattr(gs, "arrays", None), dict) and hasattr(gs, "config") and hasattr(gs, "object_name")):
        raise FfcgsError(f"{caller} needs a GraspSet (from fj.synthesize or fj.load_grasps), got "
                         f"{type(gs).__name__}")
