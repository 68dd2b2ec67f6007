"""How compiled work is kept and timed, for every stage: the one bounded cache of compiled executables and the
registry of every in-process cache (`compiled`), the persistent compilation cache (`jax_cache`), traced programs
kept beside it (`traced_store`), the compile clock (`compile_clock`) and batches padded to one shape
(`fixed_shapes`)."""

COMPILED_MAX = 64
"""Executables the process keeps (`compiled`: the synthesis's device parts and the evaluation's together, 32 each
when each stage kept its own), least recently used dropped first: each holds its code and, on a CPU, hundreds of the
process's 65,530 memory mappings."""
