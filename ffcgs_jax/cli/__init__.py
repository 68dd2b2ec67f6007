"""The `ffcgs` command line (`main`), its subcommands (`commands`), `ffcgs bench` and the compilation cache."""
