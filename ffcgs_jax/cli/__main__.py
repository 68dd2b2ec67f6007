"""`python -m ffcgs_jax.cli ...`: the `ffcgs` command without its console script."""

from ffcgs_jax.cli.main import main

raise SystemExit(main())
