"""The Q-distance LP, solved by ProxSuite on the host: the package's only solver callback.

The Q-distance of the paper (eq. 9) with the convex-hull reading of eq. 8 (sum alpha = 1, see `quality.py`) is

    E_g = min 1^T rho   s.t.   U rho = W alpha,  1^T alpha = 1,  rho >= 0,  alpha >= 0         (primal)

with U (6, K) the sphere basis and W (6, N) the primitive wrenches. ProxSuite solves its LP dual, which has 7
variables instead of K + N and so factorises a 7 x 7 system instead of a (K + N)-sized one (about 5x faster here):

    E_g = max t   s.t.   U^T lam <= 1,  t <= w_i^T lam  for every primitive wrench w_i            (dual)

lam is the wrench direction that separates the hull from the origin (0 when the origin is inside), and the
multipliers of the constraints t <= w_i^T lam are the primal alpha (they sum to 1). By the envelope theorem the
derivative of the optimal value is dE_g/dW = lam alpha^T, which the backward pass applies in pure JAX.

Batching: `BatchQP` + `solve_in_parallel`. Its `init_qp_in_place` cannot take `HessianType.Zero`; with H = None the
dense type solves the same LP, and a `VectorQP` of Zero-type QPs gave the same values with no faster solve here.

The callback never raises: every instance returns a status, and a failed or inaccurate solve comes back with
`ok = False`, a finite value and a zero gradient, for the caller to mask.
"""

import functools
import os
import warnings

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float
from proxsuite import proxqp

# Absolute KKT accuracy. 1e-7 keeps values within 1e-6 of HiGHS; at 1e-9 a few degenerate instances (origin inside
# the hull, so lam = 0 is optimal but not unique) take thousands of iterations instead of tens.
EPS_ABS = 1e-7
MAX_ITER = 2000
_INF = 1e20
# ProxSuite statuses that mean "solved to the requested accuracy".
_SOLVED = (proxqp.QPSolverOutput.PROXQP_SOLVED,)


def _threads() -> int:
    """Threads for `solve_in_parallel`: FFCGS_LP_THREADS if set, else every core this process may use."""
    env = os.environ.get("FFCGS_LP_THREADS")
    if env and env.isdigit() and int(env) > 0:
        return int(env)
    if env:
        warnings.warn(f"FFCGS_LP_THREADS={env!r} is not a positive integer; using every core", stacklevel=2)
    return max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1))


def solve_batch(W: np.ndarray, U: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Solve one dual LP per (6, N) matrix in W (B, 6, N) with basis U (6, K).

    Returns:
        value (B,) >= 0, lam (B, 6), alpha (B, N) (>= 0, sums to 1), ok (B,) bool. Where ok is False the value is
        the clipped objective of the last iterate (finite) and lam, alpha are zero.
    """
    W = np.asarray(W, np.float64)
    B, _, N = W.shape
    K = U.shape[1]
    C = np.zeros((K + N, 7))
    C[:K, :6] = U.T
    C[K:, 6] = 1.0
    g = np.zeros(7)
    g[6] = -1.0  # minimise -t
    lo = np.full(K + N, -_INF)
    up = np.concatenate([np.ones(K), np.zeros(N)])
    batch = proxqp.dense.BatchQP()
    for b in range(B):
        qp = batch.init_qp_in_place(7, 0, K + N)
        qp.settings.eps_abs = EPS_ABS
        qp.settings.eps_rel = 0.0
        qp.settings.max_iter = MAX_ITER
        qp.settings.verbose = False
        # The dual LP is always feasible (lam = 0, t = 0) and bounded (U spans positively), so ProxSuite's
        # infeasibility tests can only raise false alarms, which they did on about 1 in 5 grasps: switch them off.
        qp.settings.eps_primal_inf = 1e-30
        qp.settings.eps_dual_inf = 1e-30
        C[K:, :6] = -W[b].T
        qp.init(None, g, None, None, C, lo, up)
    if B > 1:
        proxqp.dense.solve_in_parallel(batch, _threads())
    else:
        batch.get(0).solve()
    value = np.zeros(B)
    lam = np.zeros((B, 6))
    alpha = np.zeros((B, N))
    ok = np.zeros(B, bool)
    for b in range(B):
        r = batch.get(b).results
        x, z = np.asarray(r.x), np.asarray(r.z)
        good = r.info.status in _SOLVED and np.isfinite(x).all() and np.isfinite(z).all()
        t = -r.info.objValue if np.isfinite(r.info.objValue) else 0.0
        value[b] = max(t, 0.0)  # t = 0, lam = 0 is always feasible, so the optimum is >= 0
        if good:
            lam[b] = x[:6]
            a = np.maximum(z[K:], 0.0)
            s = a.sum()
            good = s > 0.5  # the multipliers of t <= w_i . lam sum to 1 at an optimum
            alpha[b] = a / s if good else 0.0
        ok[b] = good
        if not good:
            lam[b] = 0.0
    return value, lam, alpha, ok


@functools.lru_cache(maxsize=8)
def host_fn(U_bytes: bytes, K: int):
    U = np.frombuffer(U_bytes, np.float64).reshape(6, K)

    def fn(W):
        W = np.asarray(W)
        lead = W.shape[:-2]
        v, lam, alpha, ok = solve_batch(W.reshape(-1, *W.shape[-2:]), U)
        dt = W.dtype
        return (v.reshape(lead).astype(dt), lam.reshape(*lead, 6).astype(dt),
                alpha.reshape(*lead, W.shape[-1]).astype(dt), ok.reshape(lead))

    return fn


def _call(W, U_key):
    fn = host_fn(*U_key)
    N = W.shape[-1]
    shapes = (jax.ShapeDtypeStruct((), W.dtype), jax.ShapeDtypeStruct((6,), W.dtype),
              jax.ShapeDtypeStruct((N,), W.dtype), jax.ShapeDtypeStruct((), jnp.bool_))
    return jax.pure_callback(fn, shapes, W, vmap_method="broadcast_all")


@functools.partial(jax.custom_vjp, nondiff_argnums=(1,))
def _q_distance(W, U_key):
    value, _, _, ok = _call(W, U_key)
    return value, ok


def _fwd(W, U_key):
    value, lam, alpha, ok = _call(W, U_key)
    return (value, ok), (lam, alpha)


def _bwd(U_key, res, cts):
    lam, alpha = res
    g_value, _ = cts
    return (g_value * lam[:, None] * alpha[None, :],)


_q_distance.defvjp(_fwd, _bwd)


def q_distance(W: Float[Array, "6 N"], U: np.ndarray) -> tuple[Float[Array, ""], Bool[Array, ""]]:
    """Q-distance E_g of one set of primitive wrenches W (6, N) in the gauge of basis U (6, K), and a solve flag.

    Differentiable wrt W (reverse mode) with dE_g/dW = lam alpha^T. vmap batches it into one host call.
    U must be a host (NumPy) array: it is fixed per configuration and baked into the callback.
    """
    U = np.ascontiguousarray(U, np.float64)
    return _q_distance(W, (U.tobytes(), U.shape[1]))
