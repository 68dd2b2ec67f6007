"""What the physics test costs on this machine, and where `auto` runs a batch (`choose`).

Two costs, each measured by the runs themselves and kept in `ffcgs-physics-cost.json` beside the compilation
cache (`runtime.jax_cache`; nothing is kept while that cache is off):
- CPU MuJoCo: core-seconds per grasp, per protocol (`remember_cpu`). A batch of n grasps on c cores takes about
  n x sum(protocols) / c.
- MuJoCo Warp: seconds per step call at each world count (`remember_warp`), and the start-up of the first engine
  of a process (model upload, buffers, graph capture; `remember_setup`). A batch needs the longest program's
  steps in sequence, and all its world-steps (`world_steps`) spread over the worlds: about
  max(sequential, world-steps / worlds) x seconds per step, plus the start-up when no engine is warm.
Each engine kind ("ours": lift-shake and six-dir; DexGraspBench's) steps on its own, one after the other, so their
times add. Until a machine has its own figures, `PRIOR`: the H100 host of bench/RESULTS.md. So `auto` may pick the CPU for a small batch on a many-core host and the GPU for
the same batch on a 2-core one, and says which and why in one line.
"""

from pathlib import Path

from ffcgs_jax.core import files
from ffcgs_jax.physics import dexgraspbench as dgb
from ffcgs_jax.physics import protocols as P
from ffcgs_jax.physics.config import PhysicsConfig

RECORD_NAME = "ffcgs-physics-cost.json"
# measured on one H100 and its 16-core host (bench/RESULTS.md, "GPU physics at the limit"): CPU core-seconds per
# grasp and protocol; seconds per step call of one engine at a world count; engines' start in a new process
PRIOR = {"cpu": {"lift-shake": 0.70, "six-dir": 0.52, "dexgraspbench": 1.33, "dexgraspbench-bodex": 1.33},
         "step_s": {"256": 1.4e-3, "1024": 2.5e-3, "4096": 6.5e-3, "8192": 1.26e-2}, "setup_s": 1.5}
KEEP = 0.5  # weight of a new measurement against the record (an exponential average: machines drift, runs vary)


def record_path() -> Path | None:
    from ffcgs_jax.runtime import jax_cache

    where = jax_cache.cache_dir()
    return None if where is None else Path(where) / RECORD_NAME


def _read() -> dict:
    return files.read_record(record_path())


def _update(change) -> None:
    files.update_record(record_path(), change)


def remember_cpu(protocol: str, core_s_per_grasp: float) -> None:
    def change(d):
        cpu = d.setdefault("cpu", {})
        cpu[protocol] = files.blended(cpu.get(protocol), core_s_per_grasp, KEEP)

    _update(change)


def remember_warp(worlds: int, step_s: float) -> None:
    def change(d):
        steps = d.setdefault("step_s", {})
        steps[str(worlds)] = files.blended(steps.get(str(worlds)), step_s, KEEP)

    _update(change)


def remember_setup(seconds: float) -> None:
    _update(lambda d: d.__setitem__("setup_s", files.blended(d.get("setup_s"), seconds, KEEP)))


def _figures() -> dict:
    rec = _read()
    return {"cpu": {**PRIOR["cpu"], **rec.get("cpu", {})}, "step_s": {**PRIOR["step_s"], **rec.get("step_s", {})},
            "setup_s": rec.get("setup_s", PRIOR["setup_s"])}


def program_steps(cfg: PhysicsConfig, protocol: str) -> tuple[int, int]:
    """(steps in sequence, world-steps) of one grasp's programs: lift-shake one world; six-dir and DexGraspBench's
    a closing world and six push worlds."""
    dt = cfg.timestep
    if P.get(protocol).kind == "dexgraspbench":
        c = P.get(protocol).settings(cfg)
        close, push = 2 * P.steps(dgb.STAGE_TIME, c.timestep), P.steps(c.push_time, c.timestep)
        return close + push, close + 6 * push
    close = P.steps(cfg.close_time, dt) + P.steps(cfg.settle_time, dt)
    if protocol == "lift-shake":
        period = 4 * cfg.shake_amplitude / cfg.shake_speed
        shake = P.steps(cfg.shake_cycles * period, dt) if cfg.shake_cycles else 0
        n = close + P.steps(cfg.lift_height / cfg.lift_speed, dt) + P.steps(P.LIFT_HOLD, dt) + shake
        return n, n
    push = P.steps(cfg.push_time, dt)
    return close + push, close + 6 * push


def _step_s(steps: dict, worlds: int) -> float:
    """Seconds per step call at `worlds` worlds: the nearest recorded count at or above, scaled linearly below
    (the GPU is not full there: a step costs about the same)."""
    known = sorted((int(k), float(v)) for k, v in steps.items())
    above = [v for k, v in known if k >= worlds]
    return above[0] if above else known[-1][1] * worlds / known[-1][0]


def estimate(n: int, protocols, cfg: PhysicsConfig, cores: int, warm: bool, max_worlds: int = 8192
             ) -> tuple[float, float]:
    """(CPU seconds on `cores` cores, MuJoCo Warp seconds) for n grasps under `protocols`; `warm`: an engine is
    already running in this process (no start-up)."""
    f = _figures()
    cpu = n * sum(float(f["cpu"].get(p, 1.0)) for p in protocols) / max(1, cores)
    gpu = 0.0 if warm else float(f["setup_s"])
    for bench in (False, True):
        mine = [p for p in protocols if (P.get(p).kind == "dexgraspbench") == bench]
        if not mine:
            continue
        seq = max(program_steps(cfg, p)[0] for p in mine)
        work = n * sum(program_steps(cfg, p)[1] for p in mine)
        parallel = n * sum(7 if p != "lift-shake" else 1 for p in mine)  # worlds the batch can fill at once
        worlds = 64
        while worlds < min(parallel, max_worlds):
            worlds *= 2
        gpu += max(seq, work / worlds) * _step_s(f["step_s"], worlds)
    return cpu, gpu


def choose(n: int, protocols, cfg: PhysicsConfig, cores: int, warm: bool) -> tuple[str, str | None]:
    """"warp" or "cpu" for n grasps by `estimate`, with the reason for the CPU in one line."""
    cpu, gpu = estimate(n, protocols, cfg, cores, warm)
    if gpu <= cpu:
        return "warp", None
    rec = _read()
    source = (f"as measured on this machine ({RECORD_NAME})" if rec.get("cpu") and rec.get("step_s")
              else "by the default figures until this machine has its own")
    return "cpu", (f"physics on the CPU: {n} grasps take about {cpu:.1f} s on {cores} cores here against "
                   f"{gpu:.1f} s on MuJoCo Warp, {source}")
