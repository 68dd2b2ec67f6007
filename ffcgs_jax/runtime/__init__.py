"""How compiled work is kept and timed, for every stage: the persistent compilation cache (`jax_cache`), traced
programs kept beside it (`traced_store`), the compile clock (`compile_clock`) and batches padded to one shape
(`fixed_shapes`)."""

COMPILED_MAX = 32
"""Executables each in-process cache keeps (`synthesis.grasp`, `evaluation.device_metrics`), least recently used
dropped first: each holds its code and, on a CPU, hundreds of the process's 65,530 memory mappings."""
