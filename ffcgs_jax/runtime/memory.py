"""Memory known before it is spent: a compiled batch that would not fit on its device is refused before it runs.

XLA's own analysis of the compiled program (arguments, outputs and temporaries, per device) is compared with what
the device has free: a GPU's allocator limit less what is in use, or the host's available memory for the CPU
backend. Memory grows about linearly with the batch, so the refusal names the largest batch that fits.
"""

import jax

from ffcgs_jax.core.errors import FfcgsError

HEADROOM = 0.9  # of the free memory a batch may plan to use: allocator fragmentation and the host's other needs


def free_bytes(device: jax.Device) -> int | None:
    """Bytes `device` can still allocate, or None when it does not say."""
    if device.platform == "cpu":
        try:
            with open("/proc/meminfo") as f:
                info = dict(line.split(":", 1) for line in f)
            return int(info["MemAvailable"].split()[0]) * 1024
        except (OSError, KeyError, ValueError):
            return None
    stats = device.memory_stats() or {}
    if "bytes_limit" not in stats:
        return None
    return int(stats["bytes_limit"]) - int(stats.get("bytes_in_use", 0))


def needed_bytes(compiled) -> int | None:
    """Per-device bytes a compiled executable allocates when it runs (arguments, outputs, temporaries)."""
    stats = compiled.memory_analysis()
    if stats is None:
        return None
    return int(stats.argument_size_in_bytes + stats.output_size_in_bytes + stats.temp_size_in_bytes
               - stats.alias_size_in_bytes)


def check_fits(compiled, n: int, device: jax.Device, free: int | None = None) -> None:
    """FfcgsError naming the largest batch that fits, when the compiled batch of `n` poses needs more than
    `device` has free (`free` overrides the device's own figure)."""
    need = needed_bytes(compiled)
    free = free_bytes(device) if free is None else free
    if need is None or free is None or need <= HEADROOM * free:
        return
    fits = int(n * HEADROOM * free / need)
    advice = f"the largest batch that fits is about {fits} (lower --n or split the run)" if fits else \
        "not even one pose fits"
    raise FfcgsError(f"a batch of {n} poses needs about {need / 1e9:.3g} GB on {device.platform} "
                     f"({device.device_kind}), which has {free / 1e9:.3g} GB free: {advice}")
