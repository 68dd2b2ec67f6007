"""Where a build's objects run: one after another in this process ("plain"), or as Ray tasks ("ray").

The unit of work is a group of objects (`build.build_group`: one object, or `group` of a labelled build on MuJoCo
Warp): it writes each object's parts atomically into the build's parts folder and never rewrites a finished one,
so a task that runs twice (Ray retries a task whose worker died) or on two machines gives the same files, and a
build that stops keeps every finished object.

Ray: with no `address` a local Ray instance is started for the build (every GPU and core of this machine) and
stopped after it; with `address` ("auto", "HOST:PORT", "ray://HOST:PORT") the build joins that cluster, and every
node must see the parts folder (a shared file system). Each task holds `task_cpus` cores, which its CPU physics
uses as threads, and an even share of the GPUs (the GPUs split over the tasks that fit on the cores), which its
synthesis (and MuJoCo Warp) uses; so several objects are in flight per GPU, one synthesising while others
simulate. Tasks are named after their group's first object ("ffcgs:<object>", "+N more" for the rest of a group),
which is how Ray's dashboard shows progress.
"""

from __future__ import annotations

import os
import socket
import warnings
from collections.abc import Callable
from pathlib import Path

from ffcgs_jax.dataset.config import DatasetConfig
from ffcgs_jax.core.errors import FfcgsError

INSTALL = 'Ray is not installed: pip install -e ".[scale]" (or pip install ray)'
RETRIES = 3  # a task whose worker or node died is run again this many times (its object only)
# the driver's settings that change what a worker computes or where it caches, passed to every task
PASSED_ENV = ("JAX_PLATFORMS", "XDG_CACHE_HOME")


def ray_missing() -> str | None:
    """None when Ray imports, else why not (one line)."""
    try:
        import ray  # noqa: F401
    except ImportError as e:
        if getattr(e, "name", None) == "ray":
            return INSTALL
        return f"Ray does not import ({e}): reinstall it with its dependencies, pip install -e \".[scale]\""
    return None


def choose(cfg: DatasetConfig, n_objects: int) -> tuple[str, str | None]:
    """("plain" or "ray", and for "auto" a line saying why when it is not the obvious choice)."""
    if cfg.engine == "plain":
        return "plain", None
    if cfg.engine == "ray" or cfg.address:
        missing = ray_missing()
        if missing:
            raise FfcgsError(missing)
        return "ray", None
    if n_objects <= cfg.ray_from:
        return "plain", None
    missing = ray_missing()
    if missing:
        return "plain", f"objects run one after another: {missing}"
    cores = cfg.cpus or os.cpu_count() or 1
    if cores < 2:
        return "plain", "objects run one after another: one core holds one task"
    return "ray", None


def run(how: str, cfg: DatasetConfig, todo: list, parts_dir: Path, finished: Callable, bar=None,
        work: Callable | None = None) -> None:
    """Build every group of objects of `todo` (lists of `Source`) with `work(cfg, group, parts_dir, progress)`
    (`build.build_group`, a timing row or None per object), calling `finished(src, row)` for each object as its
    group ends. Plain stops at the first failure; Ray tries every group and raises the first failure after the
    others ended, as one line naming its objects. Either way the finished objects are kept, and rerunning the
    build resumes."""
    if how == "plain":
        for group in todo:
            if bar is not None:
                bar.set_postfix_str(_name(group))
            for src, row in zip(group, work(cfg, group, parts_dir, None), strict=True):
                finished(src, row)
        return
    _run_ray(cfg, todo, parts_dir, finished, work)


def _name(group: list) -> str:
    return group[0].name + (f" +{len(group) - 1} more" if len(group) > 1 else "")


def reachable(address: str) -> None:
    """One line now, instead of Ray's long retries, when a HOST:PORT address does not answer."""
    if address in ("", "auto"):
        return
    hostport = address.removeprefix("ray://")
    host, _, port = hostport.rpartition(":")
    if not host or not port.isdigit():
        raise FfcgsError(f"--address must be auto, HOST:PORT or ray://HOST:PORT, got {address!r}")
    try:
        socket.create_connection((host, int(port)), timeout=5).close()
    except OSError as e:
        raise FfcgsError(f"cannot reach the Ray cluster at {address}: {e.strerror or e}") from None


def _connect(cfg: DatasetConfig) -> bool:
    """Join or start Ray; True when this build started it (and so stops it)."""
    import ray

    env = {k: os.environ[k] for k in PASSED_ENV if k in os.environ}
    import jax

    env["JAX_ENABLE_X64"] = "1" if jax.config.jax_enable_x64 else "0"  # the records depend on it
    # workers load the executables the driver's process (or an earlier worker) compiled, where it keeps them;
    # else the CLI's default folder, unless FFCGS_JAX_CACHE turns it off
    if jax.config.jax_compilation_cache_dir:
        env["FFCGS_JAX_CACHE"] = jax.config.jax_compilation_cache_dir
    elif "FFCGS_JAX_CACHE" in os.environ:
        env["FFCGS_JAX_CACHE"] = os.environ["FFCGS_JAX_CACHE"]
    # several tasks share a GPU: none may take most of its memory up front
    env |= {"XLA_PYTHON_CLIENT_PREALLOCATE": "false", "OMP_NUM_THREADS": str(cfg.task_cpus)}
    runtime_env = {"env_vars": env}
    if ray.is_initialized():
        return False
    reachable(cfg.address)
    try:
        with warnings.catch_warnings():
            # Ray forks helper processes that exec at once: JAX's threads are not carried into them
            warnings.filterwarnings("ignore", message="os.fork", category=RuntimeWarning)
            if cfg.address:
                ray.init(address=cfg.address, runtime_env=runtime_env, log_to_driver=False)
                return False
            # "local": a new instance of our own, never a cluster that `ray start` left running on this machine
            ray.init(address="local", runtime_env=runtime_env, log_to_driver=False, num_cpus=cfg.cpus or None,
                     num_gpus=None if cfg.gpus < 0 else cfg.gpus)
            return True
    except (ConnectionError, RuntimeError, ValueError) as e:
        where = cfg.address or "a local Ray instance"
        raise FfcgsError(f"cannot start or join {where}: {str(e).splitlines()[0] if str(e) else type(e).__name__}"
                         ) from None


def task_resources(cfg: DatasetConfig, resources: dict) -> tuple[int, float]:
    """(cores, GPU share) each task holds on a cluster with `resources` (`ray.cluster_resources()`): `task_cpus`,
    but at most half the cores, so that at least two objects are in flight (one synthesising while another
    simulates: 1.6x one at a time on a 2-core CPU, bench/RESULTS.md "Data engine")."""
    cpus = max(1, min(cfg.task_cpus, int(resources.get("CPU", 1)) // 2))
    gpus = float(resources.get("GPU", 0))
    if gpus <= 0:
        return cpus, 0.0
    slots = max(1, int(resources.get("CPU", 1)) // cpus)
    share = min(1.0, gpus / slots)
    return cpus, round(share, 4)


def _group_task(cfg: DatasetConfig, group: list, parts_dir: Path, work: Callable, cpus: int):
    import dataclasses

    from ffcgs_jax.runtime import jax_cache

    jax_cache.enable()  # FFCGS_JAX_CACHE, from the driver
    cfg = dataclasses.replace(cfg, physics=dataclasses.replace(cfg.physics, workers=cpus))
    return work(cfg, group, parts_dir, None)


def _run_ray(cfg: DatasetConfig, todo: list, parts_dir: Path, finished: Callable, work: Callable) -> None:
    import ray

    started = _connect(cfg)
    try:
        cpus, gpus = task_resources(cfg, ray.cluster_resources())
        remote = ray.remote(_group_task)
        pending = {}
        for group in todo:
            ref = remote.options(num_cpus=cpus, num_gpus=gpus, max_retries=RETRIES, retry_exceptions=False,
                                 name=f"ffcgs:{_name(group)}").remote(cfg, group, parts_dir, work, cpus)
            pending[ref] = group
        errors = []
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1)
            for ref in ready:
                group = pending.pop(ref)
                try:
                    rows = ray.get(ref)
                except Exception as e:  # noqa: BLE001 - every task failure becomes one line naming its objects
                    errors.append(f"{_name(group)}: {_message(e)}")
                    rows = [None] * len(group)
                for src, row in zip(group, rows, strict=True):
                    finished(src, row)
        if errors:
            more = f" (and {len(errors) - 1} other task(s))" if len(errors) > 1 else ""
            raise FfcgsError(f"{errors[0]}{more}; finished objects are kept: rerun the same command to resume")
    finally:
        if started:
            ray.shutdown()


def _message(e: BaseException) -> str:
    """A task's failure as one line: the FfcgsError it raised, else its exception's type and first line."""
    cause = getattr(e, "cause", None)
    if isinstance(cause, BaseException):
        e = cause
    text = str(e).strip().splitlines()
    if isinstance(e, FfcgsError):
        return text[0] if text else "failed"
    return f"{type(e).__name__}: {text[-1] if text else ''}"
