"""Training the CVAE, a task of `training.harness`: its loss, its compiled multi-step Adam update, its batches,
validation and the weights it exports.

`train(cfg)` is what `ffcgs train` runs for one configuration. Outputs in `cfg.out`:
    config.toml       the resolved config (reload it with --config to repeat the run)
    metrics.jsonl     one line per `log_every` steps (loss, reconstruction in m, KL, beta) and one per epoch
                      (validation reconstruction and KL when a fold is held out)
    metrics.png       the curves
    checkpoint.npz    params, Adam state and the epoch reached, written at the end of every epoch (the harness's)
    weights.npz       the trained params with the model config: what `synthesis.samplers.make_sampler("cvae")` loads

Resumption: a run whose folder already has a checkpoint for the same config continues after the last finished
epoch. Batch order comes from (seed, epoch) and the latent noise from (seed, step), so a resumed run computes the
same parameters as an uninterrupted one.
"""

import dataclasses
import json
from functools import partial
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from ffcgs_jax.core import files
from ffcgs_jax.core.config import check_all
from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.core.version import __version__
from ffcgs_jax.hand import kinematics as K
from ffcgs_jax.hand import sites
from ffcgs_jax.hand.identity import spec_sha256
from ffcgs_jax.kernels.adam import AdamState, adam_update
from ffcgs_jax.learning import checkpoint, cvae
from ffcgs_jax.learning.weights import WEIGHTS_FORMAT
from ffcgs_jax.training import data as cvae_data
from ffcgs_jax.training import harness
from ffcgs_jax.training.config import KLConfig, TrainConfig, TrainOptimConfig, to_toml
from ffcgs_jax.training.run import dataset_hand, read_metrics as read_rows, run_folder

def hand_points(hand_name: str) -> tuple[np.ndarray, np.ndarray, K.Hand]:
    """(palm centre (3,), palm tetrahedron (4, 3)) in the hand's root frame, float32, and the hand."""
    hand = K.load_hand(hand_name)
    return sites.palm_centre_root(hand).astype(np.float32), sites.tetrahedron_root(hand).astype(np.float32), hand


def batch_loss(params, grids, origin, voxel, pose, key, beta_t, palm_root, tet_root):
    """Loss of one batch: grids (S, R, R, R, 4), origin (S, 3), voxel (S,), pose (S, K, 4, 4) -> (loss, aux)."""
    res = grids.shape[1]
    centre, half = jax.vmap(cvae.grid_frame, (0, 0, None))(origin, voxel, res)
    g = jax.vmap(jax.vmap(cvae.pose_to_vector, (0, None, None, None)), (0, None, 0, 0))(pose, palm_root, centre, half)
    keys = jax.random.split(key, grids.shape[0])
    g_hat, mu, logvar = jax.vmap(cvae.apply, (None, 0, 0, 0, 0))(params, grids, half, g, keys)
    pose_hat = jax.vmap(jax.vmap(cvae.vector_to_pose, (0, None, None, None)), (0, None, 0, 0))(
        g_hat, palm_root, centre, half)
    rec = jnp.mean(jax.vmap(jax.vmap(cvae.tetrahedron_error, (0, 0, None)), (0, 0, None))(pose, pose_hat, tet_root))
    kl = jnp.mean(jax.vmap(jax.vmap(cvae.kl_divergence))(mu, logvar))
    return rec + beta_t * kl, {"rec": rec, "kl": kl}


def static_optim(optim: TrainOptimConfig) -> TrainOptimConfig:
    """`optim` without what `train_steps` takes traced (lr) or never reads (epochs): its compile key."""
    return dataclasses.replace(optim, lr=TrainOptimConfig.lr, epochs=TrainOptimConfig.epochs)


def _global_norm(tree):
    return jnp.sqrt(sum(jnp.sum(x * x) for x in jax.tree.leaves(tree)))


@partial(jax.jit, static_argnames=("optim", "kl"), donate_argnames=("params", "opt"))
def train_steps(params, opt: AdamState, step0, live, grids, origin, voxel, pose, rec_idx, grasp_idx, palm_root,
                tet_root, seed, total_steps, lr, optim: TrainOptimConfig, kl: KLConfig):
    """len(rec_idx) Adam steps fused in one lax.scan; steps with live[i] False leave params unchanged (they pad
    an epoch's last chunk to the fixed length, so one compilation serves every chunk, fold and epoch count).
    `lr` is traced, and `optim` (static) is `static_optim`'s: a sweep over the step size or the epochs reuses the
    compile. Returns (params, opt, per-step metrics)."""
    base_key = jax.random.key(seed + 1)
    lr = lr.astype(jax.tree.leaves(params)[0].dtype)  # as a Python float's would be: the same steps as before

    def one(carry, xs):
        i, r, gi, ok = xs
        step = step0 + i
        b = cvae.beta(step, total_steps, kl.beta_max, kl.cycles, kl.ramp)

        def update(carry):
            params, opt = carry
            (loss, aux), grads = jax.value_and_grad(batch_loss, has_aux=True)(
                params, grids[r], origin[r], voxel[r], pose[gi], jax.random.fold_in(base_key, step), b, palm_root,
                tet_root)
            norm = _global_norm(grads)
            if optim.grad_clip > 0:
                scale = jnp.minimum(1.0, optim.grad_clip / (norm + 1e-12))
                grads = jax.tree.map(lambda x: x * scale, grads)
            updates, opt = adam_update(grads, opt, lr, optim.b1, optim.b2, optim.eps)
            params = jax.tree.map(lambda p, u: (p + u).astype(p.dtype), params, updates)  # x64 must not promote
            return (params, opt), {"loss": loss, "rec": aux["rec"], "kl": aux["kl"], "grad_norm": norm}

        def skip(carry):
            z = jnp.zeros((), jnp.result_type(jax.tree.leaves(carry[0])[0], pose))
            return carry, {"loss": z, "rec": z, "kl": z, "grad_norm": z}

        carry, m = jax.lax.cond(ok, update, skip, carry)
        return carry, m | {"beta": b}

    steps = jnp.arange(rec_idx.shape[0])
    (params, opt), metrics = jax.lax.scan(one, (params, opt), (steps, rec_idx, grasp_idx, live))
    return params, opt, metrics


@jax.jit
def _eval_chunk(params, grids, origin, voxel, pose, record, palm_root, tet_root):
    """Per-grasp reconstruction error with z = mu (m) and KL, for grasps (M,) of records `record` (M,)."""
    res = grids.shape[1]

    def one(p, r):
        centre, half = cvae.grid_frame(origin[r], voxel[r], res)
        feats = cvae.features(params, cvae.normalise_grid(grids[r], half))
        g = cvae.pose_to_vector(p, palm_root, centre, half)
        mu, logvar = cvae.encode(params, cvae.fcn_base(params["encoder"], feats), g)
        g_hat = cvae.decode(params, cvae.fcn_base(params["decoder"], feats), mu)
        pose_hat = cvae.vector_to_pose(g_hat, palm_root, centre, half)
        return cvae.tetrahedron_error(p, pose_hat, tet_root), cvae.kl_divergence(mu, logvar)

    return jax.lax.map(lambda xs: one(*xs), (pose, record), batch_size=64)


def evaluate(params, data: cvae_data.TrainData, records: np.ndarray, palm_root, tet_root, dev=None,
             chunk: int = 512) -> dict:
    """Mean reconstruction error (z = mu, metres) and KL over the clean grasps of `records`."""
    sel = np.intersect1d(data.grasps_of(records), np.flatnonzero(~data.noisy))
    recs, kls = [], []
    grids, origin, voxel = dev if dev is not None else (jnp.asarray(a) for a in
                                                        (data.grids, data.origin, data.voxel_size))
    # Fixed shapes (one compilation each): `chunk`, or for fewer grasps the power of two that holds them, so that a
    # small validation set does not pay for `chunk` U-Net calls (20 grasps were padded to 512: ~35 s on 2 cores).
    chunk = min(chunk, max(64, 1 << max(len(sel) - 1, 0).bit_length()))
    for s in range(0, len(sel), chunk):
        idx = sel[s:s + chunk]
        pad = np.resize(idx, chunk)  # padded entries are dropped below
        r, k = _eval_chunk(params, grids, origin, voxel, jnp.asarray(data.pose[pad]), jnp.asarray(data.record[pad]),
                           palm_root, tet_root)
        recs.append(np.asarray(r)[: len(idx)])
        kls.append(np.asarray(k)[: len(idx)])
    rec, kl = np.concatenate(recs), np.concatenate(kls)
    return {"rec": float(rec.mean()), "kl": float(kl.mean()), "grasps": int(len(sel))}


def weights_meta(cfg: TrainConfig, hand: K.Hand, extra: dict) -> dict:
    """The metadata saved beside trained weights: format, version, hand (name and identity), model config and
    training config."""
    return {"format": WEIGHTS_FORMAT, "version": __version__, "hand": hand.spec.name,
            "hand_sha256": spec_sha256(hand.spec), "model": dataclasses.asdict(cfg.model),
            "train": {"config": to_toml(cfg)} | extra}


def train(cfg: TrainConfig, hand: str | None = None, progress: bool = True, until_epoch: int | None = None,
          data: cvae_data.TrainData | None = None) -> dict | None:
    """Train one configuration (one fold); see the module docstring. Returns a summary dict (also in summary.json).

    `data` is `training.data.load(cfg.data.path, cfg.data.noisy)` when a caller already holds it (the folds of a
    cross-validation share one read of the file); None reads it here.

    `until_epoch` stops after that many epochs, checkpointed, as an interruption would (time-boxed sessions,
    tests); returns None then, and a later call with the same config continues."""
    # `fj.train_sampler` lands here with no CLI parsing before it: a wrong config is refused in one line
    if not isinstance(cfg, TrainConfig):
        raise FfcgsError(f"train takes a TrainConfig, got {type(cfg).__name__}")
    check_all(cfg)
    run = run_folder(cfg)
    # Everything that can refuse the run comes before its first write: a failed start leaves an existing run (and
    # a new --out) exactly as it was.
    if data is None:
        data = cvae_data.load(cfg.data.path, cfg.data.noisy)
    if data.res != cfg.model.res:
        raise FfcgsError(f"the dataset's SDFs are {data.res}^3 but model.res is {cfg.model.res}")
    train_recs, val_recs = cvae_data.split(data, cfg.cv.folds, cfg.cv.fold, cfg.seed)
    palm_root, tet_root, the_hand = hand_points(dataset_hand(cfg.data.path, hand or cfg.hand))
    palm_root, tet_root = jnp.asarray(palm_root), jnp.asarray(tet_root)
    grids = (jnp.asarray(data.grids), jnp.asarray(data.origin), jnp.asarray(data.voxel_size))
    task = cvae_task(cfg, data, train_recs, val_recs, grids, palm_root, tet_root)
    fitted = harness.fit(task, run, until_epoch=until_epoch, progress=progress)
    if fitted is None:
        return None

    params = fitted.params
    train_eval = evaluate(params, data, train_recs, palm_root, tet_root, grids)
    row = fitted.last_row
    last_val = {"rec": row["val_rec"], "kl": row["val_kl"]} if row is not None and "val_rec" in row else None
    if len(val_recs) and last_val is None:
        last_val = evaluate(params, data, val_recs, palm_root, tet_root, grids)
    summary = {
        "train_rec": train_eval["rec"], "train_kl": train_eval["kl"],
        "val_rec": None if last_val is None else last_val["rec"],
        "val_kl": None if last_val is None else last_val["kl"],
        "train_objects": sorted(set(data.objects[train_recs].tolist())),
        "val_objects": sorted(set(data.objects[val_recs].tolist())),
        "train_grasps": int(len(data.grasps_of(train_recs))), "steps": task.steps_per_epoch * task.epochs,
        "backend": jax.default_backend(),
    }
    checkpoint.save(run.out / "weights.npz", {"params": params},
                    weights_meta(cfg, the_hand, {k: summary[k] for k in ("train_rec", "val_rec", "steps")}))
    files.write_text(run.out / "summary.json", json.dumps(summary, indent=1))
    plot_metrics(run.log, run.out / "metrics.png")
    return summary


def cost_key(cfg: TrainConfig) -> str:
    """What one CVAE step's cost depends on (`step_cost`): its batch, grasps per SDF and the network's size."""
    m, o = cfg.model, cfg.optim
    return (f"sampler batch {o.batch}x{cfg.data.grasps_per_sdf} res {m.res} width {m.width} features {m.features} "
            f"mlp {m.mlp} calls {cfg.steps_per_call}")


def cvae_task(cfg: TrainConfig, data: cvae_data.TrainData, train_recs, val_recs, grids, palm_root,
              tet_root) -> harness.Task:
    """The CVAE's training as a harness task: `steps_per_call` steps per compiled call, validation per epoch."""
    o, k = cfg.optim, cfg.data.grasps_per_sdf
    steps_per_epoch = cvae_data.steps_per_epoch(data, train_recs, o.batch, k)
    total = jnp.asarray(steps_per_epoch * o.epochs, jnp.int32)
    pose = jnp.asarray(data.pose)
    # always `steps_per_call` steps per call, the ones past the epoch's end masked off (`live`): an executable's
    # shapes then do not depend on the dataset's size, so the folds of a cross-validation, a sweep's points and a
    # resumed run share one compile instead of one each (minutes on a CPU)
    chunk = cfg.steps_per_call
    lr = jnp.asarray(o.lr)

    def chunks(epoch):
        rec_idx, grasp_idx = cvae_data.epoch_batches(data, train_recs, o.batch, k,
                                                     np.random.default_rng([cfg.seed, epoch]))
        for s in range(0, steps_per_epoch, chunk):
            n = min(chunk, steps_per_epoch - s)
            sel = np.arange(s, s + chunk) % steps_per_epoch  # the padding steps are masked off
            yield harness.Chunk(s, n, (jnp.asarray(np.arange(chunk) < n), jnp.asarray(rec_idx[sel]),
                                       jnp.asarray(grasp_idx[sel])))

    def step(params, opt, consts, step0, inputs):
        live, rec_idx, grasp_idx = inputs
        return train_steps(params, opt, jnp.asarray(step0, jnp.int32), live, *grids, pose, rec_idx, grasp_idx,
                           palm_root, tet_root, jnp.asarray(cfg.seed, jnp.int32), total, lr, optim=static_optim(o),
                           kl=cfg.kl)

    def validate(params, consts):
        if not len(val_recs):
            return {}
        val = evaluate(params, data, val_recs, palm_root, tet_root, grids)
        return {"val_rec": val["rec"], "val_kl": val["kl"]}

    return harness.Task(
        name="sampler", step_name="the CVAE's training step", seed=cfg.seed, epochs=o.epochs,
        steps_per_epoch=steps_per_epoch, init=lambda: (cvae.init(jax.random.key(cfg.seed), cfg.model), {}),
        chunks=chunks, step=step, evaluate=validate, log_every=cfg.log_every,
        nonfinite_hint="lower optim.lr or set optim.grad_clip",
        postfix=lambda m, row: {"rec_cm": f"{100 * float(m['rec'][-1]):.2f}", "kl": f"{float(m['kl'][-1]):.2f}"},
        legacy=lambda tree: (tree["params"], {}) if "params" in tree else None, cost_key=cost_key(cfg))


def read_metrics(path: str | Path) -> tuple[list[dict], list[dict]]:
    """(step rows, epoch rows) of a metrics.jsonl."""
    rows = read_rows(path)
    return [r for r in rows if "loss" in r], [r for r in rows if "loss" not in r]


def plot_metrics(log_path: Path, png: Path) -> Path | None:
    """Reconstruction error (cm), KL and beta per step, validation per epoch, as a PNG (needs matplotlib)."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print(f"matplotlib is not installed: {png} not drawn (pip install 'ffcgs-jax[train]')")
        return None
    steps, epochs = read_metrics(log_path)
    fig, ax = plt.subplots(1, 3, figsize=(13, 3.6))
    s = [r["step"] for r in steps]
    ax[0].plot(s, [100 * r["rec"] for r in steps], label="train (z ~ q)")
    val = [r for r in epochs if "val_rec" in r]
    if val:
        ax[0].plot([r["step"] for r in val], [100 * r["val_rec"] for r in val], "o-", label="validation (z = mu)")
    ax[0].set(xlabel="step", ylabel="tetrahedron error (cm)", title="reconstruction")
    ax[0].legend()
    ax[1].plot(s, [r["kl"] for r in steps], label="train")
    if val:
        ax[1].plot([r["step"] for r in val], [r["val_kl"] for r in val], "o-", label="validation")
    ax[1].set(xlabel="step", ylabel="nats", title="KL")
    ax[1].legend()
    ax[2].plot(s, [r["beta"] for r in steps])
    ax[2].set(xlabel="step", title="beta_t")
    fig.tight_layout()
    with files.atomic_path(png) as tmp:
        fig.savefig(tmp, dpi=90)
    plt.close(fig)
    return png
