"""`ffcgs bench`: how fast grasp synthesis runs on this machine, as a table written into bench/RESULTS.md.

The rows time the compiled device part of `synthesize` (sample B wrist poses, T descent steps, the filters) once the
object's Gradient-SDF exists, and the same with the device evaluation after it (contacts, force closure, epsilon on
the mesh: `evaluation.device_metrics`), which is the throughput a user gets. The whole call (`time_whole_call`: the
smallest batch, 32 by default, from a mesh to ranked grasps on the host: SDF build, device part, evaluation and the
copy back) is timed apart, in parts, because that is what a user waits for: once as if the mesh were new (the grid
and triangle caches cleared), once with its grid cached. Each row is one compilation, reported apart, one warm-up
call, then the median of `repeats` calls. JAX's persistent compilation cache is off while timing, so compile times
are real compilations.

CLI start: `ffcgs grasp OBJECT --n 32 --iters T` run twice in fresh processes that share a new, empty compilation
cache: cold (nothing cached) and warm (the executables the first run stored). Wall time of the whole process and
the compile time it reported.
"""

import dataclasses
import datetime
import json
import os
import platform
import re
import statistics
import subprocess
import sys
import tempfile
import time
from importlib import metadata
from pathlib import Path

import numpy as np

from ffcgs_jax.core import files
from ffcgs_jax.core.errors import FfcgsError

DEFAULT_BATCHES = {"gpu": (32, 1024, 8192, 65536), "cpu": (32, 256, 1024)}


@dataclasses.dataclass
class Row:
    solver: str
    batch: int
    devices: int
    compile_s: float
    median_s: float
    min_s: float
    lp_ok: float  # fraction of poses whose every LP solved
    with_eval_s: float | None = None  # median of the device part and the device evaluation of its grasps

    @property
    def rate(self) -> float:
        return self.batch / self.median_s


def time_synthesis(hand, target, cfg, repeats: int, surface=None) -> Row:
    """Compile the device part for `cfg` and time it: one warm-up call, then the median of `repeats` calls; with a
    `surface` (`device_metrics.mesh_table`), also the device part followed by the evaluation of its grasps."""
    import jax

    from ffcgs_jax.evaluation import device_metrics
    from ffcgs_jax.synthesis.grasp import metrics_config, compile_device

    run, compile_s = compile_device(hand, target, cfg)
    times, out = [], None
    for i in range(repeats + 1):
        t0 = time.perf_counter()
        out = jax.block_until_ready(run(jax.random.PRNGKey(i)))
        times.append(time.perf_counter() - t0)
    devices = cfg.devices or len(jax.local_devices())
    with_eval = []
    for i in range(repeats + 1 if surface is not None else 0):
        t0 = time.perf_counter()
        o = run(jax.random.PRNGKey(i))
        jax.block_until_ready(device_metrics.evaluate(surface, o.opt.final.contacts, o.opt.q, hand.lower, hand.upper,
                                                      target.centre, target.radius, metrics_config(cfg)))
        with_eval.append(time.perf_counter() - t0)
    return Row(cfg.energy.lp_solver, cfg.n, devices, compile_s, statistics.median(times[1:]), min(times[1:]),
               float(np.mean(np.asarray(out.opt.lp_ok))), statistics.median(with_eval[1:]) if with_eval else None)


def time_whole_call(hand, mesh, cfg, repeats: int) -> dict:
    """What a user waits for, from a mesh to ranked grasps: `synthesize` whole (SDF build, device part, evaluation,
    the copy back) and the ranking, compiled beforehand; medians of `repeats` calls, each with the mesh's grid and
    triangle table built anew ("first": a mesh seen for the first time) and again with them cached ("cached")."""
    from ffcgs_jax.evaluation import device_metrics
    from ffcgs_jax.geometry import sdf
    from ffcgs_jax.synthesis.grasp import synthesize

    parts = ("sdf_s", "synthesis_s", "evaluation_s", "total_s")
    synthesize(hand, mesh, cfg).order()  # compiles what the calls below reuse
    runs = {"first": [], "cached": []}
    for i in range(repeats):
        sdf.clear_cache()
        device_metrics.clear_cache()
        for kind in runs:
            t0 = time.perf_counter()
            gs = synthesize(hand, mesh, dataclasses.replace(cfg, seed=i))
            gs.order()
            wall = time.perf_counter() - t0
            runs[kind].append({**{k: float(gs[k]) for k in parts}, "wall_s": wall})
    return {"batch": cfg.n, "faces": int(len(mesh.faces)),
            **{kind: {k: statistics.median(r[k] for r in rs) for k in (*parts, "wall_s")} for kind, rs in runs.items()}}


def machine() -> dict:
    """Where the figures come from: devices, host, versions, date."""
    import jax

    devs = jax.local_devices()
    cpu = platform.processor() or platform.machine()
    try:
        names = re.findall(r"^model name\s*:\s*(.+)$", Path("/proc/cpuinfo").read_text(), re.M)
        cpu = names[0].strip() if names else cpu
    except OSError:
        pass
    import ffcgs_jax

    versions = {"python": platform.python_version(), "ffcgs-jax": f"{ffcgs_jax.__version__} ({_git_commit()})"}
    for pkg in ("jax", "jaxlib", "mujoco", "mujoco-mjx", "proxsuite"):
        try:
            versions[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            versions[pkg] = "-"
    return {"backend": jax.default_backend(), "device": devs[0].device_kind, "device_count": len(devs),
            "host_cpu": cpu, "host_cores": os.cpu_count(), "versions": versions,
            "date": datetime.date.today().isoformat()}


def _git_commit() -> str:
    """The checkout's commit (+ "-dirty" with local changes), when the package runs from one (a wheel has none)."""
    try:
        r = subprocess.run(["git", "describe", "--always", "--dirty"], capture_output=True, text=True, timeout=10,
                           cwd=Path(__file__).parent)
        return r.stdout.strip() if r.returncode == 0 and r.stdout.strip() else "no git"
    except (OSError, subprocess.SubprocessError):
        return "no git"


def machine_key(m: dict, hand: str = "svh") -> str:
    """One line naming the machine (and the hand, if not the SVH): a RESULTS.md block per key, replaced when the
    bench runs there again."""
    tail = "" if hand == "svh" else f" · hand {hand}"
    if m["backend"] == "cpu":
        return f"cpu · {m['host_cpu']} · {m['host_cores']} cores{tail}"
    return f"{m['backend']} · {m['device']} × {m['device_count']}{tail}"


def cli_start(obj: str, iters: int, backend: str, n: int = 32, hand: str = "svh") -> dict:
    """Cold and warm `ffcgs grasp` in fresh processes sharing a new compilation cache; seconds."""
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        env = {**os.environ, "FFCGS_JAX_CACHE": str(Path(tmp) / "xla")}
        if backend == "cpu":  # a CPU bench on a GPU machine; "gpu" is not set: it would also demand ROCm
            env["JAX_PLATFORMS"] = "cpu"
        for kind in ("cold", "warm"):
            npz = Path(tmp) / f"{kind}.npz"
            cmd = [sys.executable, "-m", "ffcgs_jax.cli", "grasp", obj, "--n", str(n), "--iters", str(iters),
                   "--hand", hand, "--out", str(npz)]
            t0 = time.perf_counter()
            r = subprocess.run(cmd, capture_output=True, text=True, env=env)
            wall = time.perf_counter() - t0
            if r.returncode != 0:
                raise FfcgsError(f"`{' '.join(cmd[2:])}` failed during the CLI start benchmark: {last_error(r.stderr)}")
            with np.load(npz) as z:
                out[kind] = {"wall_s": wall, "compile_s": float(z["compile_s"]),
                             "synthesis_s": float(z["synthesis_s"])}
    return out


def last_error(stderr: str) -> str:
    """The line that names the exception (JAX's traceback note comes after it), else the last line."""
    lines = [ln.strip() for ln in stderr.strip().splitlines() if ln.strip()]
    named = [ln for ln in lines if re.match(r"^([\w.]+(Error|Exception)|ffcgs: error):", ln)]
    return (named or lines or ["no message"])[-1]


def markdown(report: dict) -> str:
    m, p = report["machine"], report["params"]
    v = m["versions"]
    lines = [
        f"### {machine_key(m, p.get('hand', 'svh'))}",
        "",
        f"`{report['command']}`, {m['date']}. Host: {m['host_cpu']}, {m['host_cores']} cores. "
        + ", ".join(f"{k} {v[k]}" for k in v) + ".",
        f"Object `{p['object']}` (Gradient-SDF {p['res']}^3), {p['sampler']} sampler, {p['iters']} descent steps, "
        f"float32; median of {p['repeats']} warm calls; compile is the one-off compilation of that row.",
        "",
    ]
    lat = [r for r in report["rows"] if r["batch"] == p["latency_batch"] and r["devices"] == 1]
    if lat:
        lines += [f"Latency, {p['latency_batch']} grasps × {p['iters']} steps: "
                  + ", ".join(f"**{r['median_s'] * 1e3:.1f} ms** ({r['solver']} LP)" for r in lat), ""]
    lines += ["| LP solver | devices | poses B | compile (s) | median (ms) | min (ms) | grasps/s "
              "| with evaluation (ms) | grasps/s with evaluation | LP ok |",
              "|---|---|---|---|---|---|---|---|---|---|"]
    for r in report["rows"]:
        ev = r.get("with_eval_s")
        ev_cells = f"{ev * 1e3:.1f} | {r['batch'] / ev:,.0f}" if ev else "- | -"
        lines.append(f"| {r['solver']} | {r['devices']} | {r['batch']} | {r['compile_s']:.1f} | "
                     f"{r['median_s'] * 1e3:.1f} | {r['min_s'] * 1e3:.1f} | {r['batch'] / r['median_s']:,.0f} | "
                     f"{ev_cells} | {r['lp_ok']:.3f} |")
    for b in sorted({r["batch"] for r in report["rows"] if r["devices"] > 1}):
        rows = {r["devices"]: r for r in report["rows"] if r["batch"] == b and r["solver"] == "jax"}
        if 1 in rows and len(rows) > 1:
            n = max(rows)
            lines += ["", f"Scaling at B = {b}: {n} devices run {rows[1]['median_s'] / rows[n]['median_s']:.2f}× "
                          f"as fast as one."]
    if report.get("whole"):
        w = report["whole"]
        lines += ["", f"Whole call, `{w.get('object', p['object'])}` ({w['faces']} faces) to {w['batch']} ranked "
                      "grasps (`synthesize` and the ranking, compiled beforehand, jax LP; median ms):", "",
                  "| grid | total | SDF build | device part | evaluation and copy back | wall |",
                  "|---|---|---|---|---|---|"]
        for kind, label in (("first", "mesh seen for the first time"), ("cached", "grid cached")):
            if kind in w:
                t = {k: v * 1e3 for k, v in w[kind].items()}
                lines.append(f"| {label} | **{t['total_s']:.1f}** | {t['sdf_s']:.1f} | {t['synthesis_s']:.1f} | "
                             f"{t['evaluation_s']:.1f} | {t['wall_s']:.1f} |")
    if report.get("cli"):
        c = report["cli"]
        lines += ["", f"CLI start, `ffcgs grasp {p['object']} --n 32 --iters {p['iters']}` in a fresh process:", "",
                  "| compilation cache | wall (s) | compile (s) | synthesis (s) |", "|---|---|---|---|"]
        for kind in ("cold", "warm"):
            lines.append(f"| {kind} | {c[kind]['wall_s']:.1f} | {c[kind]['compile_s']:.1f} | "
                         f"{c[kind]['synthesis_s']:.3f} |")
    return "\n".join(lines) + "\n"


SECTION = "## `ffcgs bench`: synthesis speed per machine"  # the heading `write_results` adds once


def write_results(path: str | Path, report: dict) -> None:
    """Put the report's block into RESULTS.md: replace the block of the same machine, or append it."""
    path = Path(path)
    key = machine_key(report["machine"], report["params"].get("hand", "svh"))
    start, end = f"<!-- ffcgs bench: {key} -->", f"<!-- /ffcgs bench: {key} -->"
    block = f"{start}\n{markdown(report)}{end}\n"
    text = path.read_text() if path.exists() else "# Benchmark results\n"
    if start in text and end in text:
        text = text[:text.index(start)] + block + text[text.index(end) + len(end) + 1:]
    else:
        if SECTION not in text:
            text = text.rstrip("\n") + f"\n\n{SECTION}\n\nWritten by `ffcgs bench` (`ffcgs_jax/benchmark.py`); " \
                "one block per machine, replaced when the bench runs there again.\n"
        text = text.rstrip("\n") + "\n\n" + block
    files.write_text(path, text)


def _print(line: str) -> None:
    print(line, flush=True)  # rows take tens of seconds each: show them as they come, also into a log file


def run(cmd, progress=_print) -> dict:
    """Everything `ffcgs bench` measures, as a JSON-able report (see `BenchCmd` in commands.py for the fields)."""
    import jax

    from ffcgs_jax.geometry import mesh_io, sdf
    from ffcgs_jax.geometry.config import SDFConfig
    from ffcgs_jax.hand import kinematics as K
    from ffcgs_jax.synthesis import grasp
    from ffcgs_jax.synthesis.config import EnergyConfig, GraspConfig, OptimConfig
    from ffcgs_jax.synthesis.energy import make_target

    jax.config.update("jax_enable_compilation_cache", False)  # compile times must be compilations, not loads
    backend = jax.default_backend()
    batches = cmd.batches or DEFAULT_BATCHES["cpu" if backend == "cpu" else "gpu"]
    n_local = len(jax.local_devices())
    counts = cmd.devices or ((1, n_local) if n_local > 1 else (1,))
    if max(counts) > n_local:
        raise FfcgsError(f"--devices {max(counts)} asked for, but this machine has {n_local} {backend} device(s)")
    from ffcgs_jax.evaluation import device_metrics

    hand = K.load_hand(cmd.hand)
    mesh = mesh_io.load_mesh(cmd.object)
    grid = sdf.build_sdf(mesh, SDFConfig(res=cmd.res))
    target = make_target(grid)
    surface = device_metrics.mesh_table(mesh)
    rows = []
    for solver in cmd.lp_solvers:
        for b in batches:
            if solver == "proxsuite" and b > cmd.max_proxsuite_batch:
                continue
            for d in counts if solver == "jax" else (1,):  # the host LP does not scale with devices
                cfg = GraspConfig(n=b, sampler=cmd.sampler, devices=d, sdf=SDFConfig(res=cmd.res),
                                  energy=EnergyConfig(lp_solver=solver), optim=OptimConfig(iters=cmd.iters))
                row = time_synthesis(hand, target, cfg, cmd.repeats, surface if solver == "jax" else None)
                rows.append(dataclasses.asdict(row))
                ev = f"  with evaluation {row.batch / row.with_eval_s:10,.0f} grasps/s" if row.with_eval_s else ""
                progress(f"{solver:>9} LP  B = {b:>6}  devices {d}:  compile {row.compile_s:6.1f} s  "
                         f"median {row.median_s * 1e3:9.1f} ms  {row.rate:10,.0f} grasps/s{ev}")
    whole = None
    if "jax" in cmd.lp_solvers:
        cfg = GraspConfig(n=min(batches), sampler=cmd.sampler, devices=1, sdf=SDFConfig(res=cmd.res),
                          optim=OptimConfig(iters=cmd.iters))  # the latency row's executable (32 by default)
        whole_mesh = mesh_io.load_mesh(cmd.whole_object) if cmd.whole_object else mesh
        whole = {"object": Path(cmd.whole_object).name if cmd.whole_object else cmd.object,
                 **time_whole_call(hand, whole_mesh, cfg, cmd.repeats)}
        for kind in ("first", "cached"):
            t = {k: v * 1e3 for k, v in whole[kind].items()}
            progress(f"whole call ({kind}), B = {cfg.n}: {t['total_s']:.1f} ms (SDF {t['sdf_s']:.1f}, device "
                     f"{t['synthesis_s']:.1f}, evaluation {t['evaluation_s']:.1f})")
    cli = None
    if cmd.cli_start:
        progress("CLI start: cold and warm `ffcgs grasp` ...")
        cli = cli_start(cmd.object, cmd.iters, backend, hand=cmd.hand)
    sampler = grasp.for_hand(GraspConfig(sampler=cmd.sampler), hand).sampler
    params = {"object": cmd.object, "res": int(grid.grid.shape[0]), "sampler": sampler, "iters": cmd.iters,
              "repeats": cmd.repeats, "latency_batch": 32, "hand": cmd.hand}
    return {"command": command_line(cmd), "machine": machine(), "params": params, "rows": rows, "cli": cli,
            "whole": whole}


def command_line(cmd) -> str:
    """`ffcgs bench` with the options that differ from the defaults: the command that reproduces the block."""
    parts = ["ffcgs bench"]
    default = type(cmd)()
    for f in dataclasses.fields(cmd):
        v = getattr(cmd, f.name)
        if f.name in ("results", "json") or v == getattr(default, f.name):
            continue
        flag = "--" + f.name.replace("_", "-")
        if isinstance(v, bool):
            parts.append(flag if v else "--no-" + f.name.replace("_", "-"))
        elif isinstance(v, tuple):
            parts.append(f"{flag} {' '.join(map(str, v))}")
        else:
            parts.append(f"{flag} {v}")
    return " ".join(parts)


def save_json(report: dict, path: str | Path) -> None:
    files.write_text(files.check_output(path, "JSON report"), json.dumps(report, indent=1))
