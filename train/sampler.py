"""`python -m train.sampler ...`: the old name of `ffcgs train` (same flags, same output), kept for checkouts and
scripts that use it. The code is the installed package's `ffcgs_jax.cli.train_command`."""

import sys

from ffcgs_jax.cli.train_command import main as _main
from ffcgs_jax.cli.train_command import parse_sweep, replace, run_cv, run_one, run_sweep, split_args  # noqa: F401


def main(argv: list[str] | None = None) -> int:
    return _main(sys.argv[1:] if argv is None else argv, prog="python -m train.sampler", name="train.sampler")


if __name__ == "__main__":
    raise SystemExit(main())
