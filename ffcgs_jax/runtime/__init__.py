"""How compiled work is kept and timed, for every stage: the persistent compilation cache (`jax_cache`), traced
programs kept beside it (`traced_store`) and the compile clock (`compile_clock`)."""
