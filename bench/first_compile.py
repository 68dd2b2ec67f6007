"""Where a process's first grasp waits: every executable's tracing, lowering and XLA compile of one `fj.synthesize`
call, and the evaluation's pivots unrolled against rolled on this backend, side by side.

    python bench/first_compile.py                 # the built-in mug, defaults (n 32, cvae), a fresh process
    python bench/first_compile.py --object OBJ.stl --repeats 20

Part 1 runs `synthesize` once in this process, with JAX's compile log on and no persistent cache, and prints the
seconds of each stage per executable (the largest first), their sums and the number of executables: what a cold
`ffcgs grasp` pays before its first grasp. Part 2 compiles the epsilon search of the device evaluation
(`evaluation.epsilon_search`) over the grasps of part 1 twice: with the simplex pivots of a trip unrolled (the GPU
default) and rolled in a loop (the CPU's form), and prints compile seconds and the median of `--repeats` warm
calls of each (`search_epsilon(..., unroll=...)`, on any backend).
"""

import argparse
import collections
import logging
import re
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np

import ffcgs_jax as fj
from ffcgs_jax.evaluation import epsilon_search
from ffcgs_jax.kernels.directions import sphere_basis
from ffcgs_jax.kernels import quality

_LINE = re.compile(r"Finished (tracing|jaxpr to MLIR module conversion|XLA compilation)(?: of)? (\S+?)(?: for jit)?"
                   r" in ([0-9.e-]+) sec")
_STAGE = {"tracing": "trace", "jaxpr to MLIR module conversion": "lower", "XLA compilation": "compile"}


class CompileStageLog(logging.Handler):
    def __init__(self):
        super().__init__(logging.DEBUG)
        self.rows = []

    def emit(self, record):
        m = _LINE.search(record.getMessage())
        if m:
            name = m.group(2).removeprefix("jit(").removesuffix(")")
            self.rows.append((_STAGE[m.group(1)], name, float(m.group(3))))


def first_call(obj: str) -> tuple[fj.GraspSet, float]:
    log = CompileStageLog()
    loggers = [logging.getLogger(n) for n in ("jax._src.dispatch", "jax._src.interpreters.pxla",
                                              "jax._src.compiler", "jax._src.pjit")]
    for lg in loggers:
        lg.addHandler(log)
    jax.config.update("jax_log_compiles", True)
    t0 = time.perf_counter()
    gs = fj.synthesize(fj.load_hand("svh"), fj.load_mesh(obj))
    wall = time.perf_counter() - t0
    jax.config.update("jax_log_compiles", False)
    for lg in loggers:
        lg.removeHandler(log)
    per = collections.defaultdict(lambda: collections.Counter())
    for stage, name, s in log.rows:
        per[name][stage] += s
    total = collections.Counter()
    for c in per.values():
        total.update(c)
    n_exec = sum(1 for stage, _, _ in log.rows if stage == "compile")
    print(f"part 1: first `synthesize` of {obj}: {wall:.1f} s wall, compile_s {float(gs['compile_s']):.1f} s; "
          f"{n_exec} executables")
    print("| executable | trace (s) | lower (s) | XLA compile (s) |\n|---|---|---|---|")
    for name, c in sorted(per.items(), key=lambda kv: -sum(kv[1].values()))[:8]:
        print(f"| {name} | {c['trace']:.2f} | {c['lower']:.2f} | {c['compile']:.2f} |")
    rest = len(per) - 8
    print(f"| all {len(per)} ({rest} more not shown) | {total['trace']:.2f} | {total['lower']:.2f} | "
          f"{total['compile']:.2f} |")
    return gs, wall


def pivots(gs: fj.GraspSet, obj: str, repeats: int) -> None:
    mesh = fj.load_mesh(obj)
    pts = np.asarray(gs["contacts"]).reshape(-1, 3)
    closest, _, tri = mesh.nearest.on_surface(pts)  # outward normals of the nearest faces: the evaluation's rule
    contacts = jnp.asarray(closest.reshape(gs["contacts"].shape), jnp.float32)
    normals = jnp.asarray(mesh.face_normals[tri].reshape(gs["contacts"].shape), jnp.float32)
    centre = jnp.asarray(mesh.bounding_box.centroid, jnp.float32)
    radius = float(np.max(np.linalg.norm(mesh.vertices - mesh.bounding_box.centroid, axis=1)))
    cfg = fj.GraspConfig()
    W = jax.vmap(lambda p, n: quality.primitive_wrenches(p, n, centre, radius, cfg.energy.lp_friction,
                                                         cfg.energy.cone_edges))(contacts, normals)
    starts = jnp.asarray(sphere_basis(epsilon_search.EPS_STARTS).T, jnp.float32)
    print(f"\npart 2: the epsilon search of {W.shape[0]} grasps on {jax.devices()[0].device_kind} "
          f"({jax.default_backend()}); median of {repeats} warm calls")
    print("| pivots of a trip | compile + first call (s) | warm call (ms) | epsilon equal to the default's |\n"
          "|---|---|---|---|")
    ref = None
    for unroll in (True, False):
        fn = jax.jit(jax.vmap(lambda w, unroll=unroll: epsilon_search.search_epsilon(w, starts, unroll=unroll)))
        t0 = time.perf_counter()
        eps = np.asarray(jax.block_until_ready(fn(W)))
        first = time.perf_counter() - t0
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            jax.block_until_ready(fn(W))
            times.append(time.perf_counter() - t0)
        ref = eps if ref is None else ref
        same = np.mean(np.isclose(eps, ref, rtol=1e-5, atol=1e-7))
        label = "unrolled (GPU default)" if unroll else "rolled (CPU form)"
        print(f"| {label} | {first:.2f} | {1e3 * statistics.median(times):.2f} | {same:.0%} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--object", default="mug")
    ap.add_argument("--repeats", type=int, default=20)
    a = ap.parse_args()
    if a.repeats < 1:
        ap.error(f"--repeats must be >= 1, got {a.repeats}")
    print(f"{jax.devices()[0].device_kind} ({jax.default_backend()}), jax {jax.__version__}")
    gs, _ = first_call(a.object)
    pivots(gs, a.object, a.repeats)


if __name__ == "__main__":
    main()
