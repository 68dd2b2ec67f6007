"""Test-wide JAX settings: float64 references and no silent rank promotion (set at import, before any test).

The CLI's persistent compilation cache is off for the suite (tests must not write to the user's home);
tests/cli/test_jax_cache.py turns it on in a folder of its own."""

import os

import jax

os.environ.setdefault("FFCGS_JAX_CACHE", "off")
jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")


import pytest  # noqa: E402

MAPS_LIMIT = 45_000  # of the kernel's 65,530 per process (vm.max_map_count)


def _maps() -> int:
    try:
        with open(f"/proc/{os.getpid()}/maps") as f:
            return sum(1 for _ in f)
    except OSError:  # not Linux
        return 0


@pytest.fixture(autouse=True, scope="module")
def _release_executables():
    """Drop compiled executables between test modules once the process holds many memory mappings.

    On a CPU every kernel of an XLA executable is a mapping of its own; the whole suite in one process compiles
    enough (SDF builds, evaluations, descents) to pass the kernel's limit, and XLA's compiler then segfaults. A
    module-scoped check keeps the executables that tests of one module share."""
    yield
    if _maps() > MAPS_LIMIT:
        import ffcgs_jax

        ffcgs_jax.clear_compiled()


@pytest.fixture(scope="session")
def svh():
    """The SVH, loaded once per test process: a `Hand` holds no state a test can change (frozen arrays, an MJX
    model), so the tests share one."""
    from ffcgs_jax.hand.kinematics import load_hand

    return load_hand("svh")


# The longest files first (`--dist loadfile`, `--no-loadscope-reorder` in pyproject's addopts): each test worker
# starts on a long one and the short ones fill in behind, instead of a half-hour file starting last (xdist's own
# order, by test count, started README's blocks near the end). Measured in `.ci/run` on a 2-core CPU (2026-11-29),
# longest first; a file missing here runs in collection order after these.
LONGEST_FIRST = (
    "test_readme_command_reference.py",  # 27 min
    "test_readme_commands.py",  # 32 min, in four blocks: the other worker takes files meanwhile
    "dataset/test_engine.py",  # 8 min
    "test_custom_hand_guide.py",
    "dataset/test_label_groups.py",
    "test_readme.py",
    "test_notebooks.py",
    "learn/test_learn.py",
    "dataset/test_build.py",
)


def pytest_collection_modifyitems(items):
    def rank(item):
        path = item.path.as_posix()
        return next((k for k, name in enumerate(LONGEST_FIRST) if path.endswith("/tests/" + name)), len(LONGEST_FIRST))

    items.sort(key=rank)  # stable: the rest keep their collection order
