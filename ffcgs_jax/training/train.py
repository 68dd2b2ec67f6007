"""Training the CVAE: a compiled multi-step Adam update, validation, checkpoints, resumption and metric logs.

`train(cfg)` is what `python -m train.sampler` runs for one configuration. Outputs in `cfg.out`:
    config.toml       the resolved config (reload it with --config to repeat the run)
    metrics.jsonl     one line per `log_every` steps (loss, reconstruction in m, KL, beta) and one per epoch
                      (validation reconstruction and KL when a fold is held out)
    metrics.png       the curves
    checkpoint.npz    params, Adam state and the epoch reached, written at the end of every epoch
    weights.npz       the trained params with the model config: what `synthesis.samplers.make_sampler("cvae")` loads

Resumption: a run whose folder already has a checkpoint for the same config continues after the last finished
epoch. Batch order comes from (seed, epoch) and the latent noise from (seed, step), so a resumed run computes the
same parameters as an uninterrupted one.
"""

import dataclasses
import json
import time
from contextlib import nullcontext
from functools import partial
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from ffcgs_jax.core import files
from ffcgs_jax.core.config import check_all
from ffcgs_jax.core.version import __version__
from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.hand import kinematics as K
from ffcgs_jax.hand import sites
from ffcgs_jax.learning import checkpoint, cvae
from ffcgs_jax.training import data as cvae_data
from ffcgs_jax.learning.config import KLConfig, TrainConfig, TrainOptimConfig, to_toml
from ffcgs_jax.learning.weights import WEIGHTS_FORMAT
from ffcgs_jax.runtime.progress import compiling
from ffcgs_jax.kernels.adam import AdamState, adam_init, adam_update


def hand_points(hand_name: str) -> tuple[np.ndarray, np.ndarray, str]:
    """(palm centre (3,), palm tetrahedron (4, 3)) in the hand's root frame, float32, and the hand's full name."""
    hand = K.load_hand(hand_name)
    return (sites.palm_centre_root(hand).astype(np.float32), sites.tetrahedron_root(hand).astype(np.float32),
            hand.spec.name)


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


def _global_norm(tree):
    return jnp.sqrt(sum(jnp.sum(x * x) for x in jax.tree.leaves(tree)))


@partial(jax.jit, static_argnames=("optim", "kl"), donate_argnames=("params", "opt"))
def train_steps(params, opt: AdamState, step0, live, grids, origin, voxel, pose, rec_idx, grasp_idx, palm_root,
                tet_root, seed, total_steps, optim: TrainOptimConfig, kl: KLConfig):
    """len(rec_idx) Adam steps fused in one lax.scan; steps with live[i] False leave params unchanged (they pad
    an epoch's last chunk to the fixed length, so one compilation serves every chunk, fold and epoch count).
    Returns (params, opt, per-step metrics)."""
    base_key = jax.random.key(seed + 1)

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
            updates, opt = adam_update(grads, opt, optim.lr, optim.b1, optim.b2, optim.eps)
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
    for s in range(0, len(sel), chunk):
        idx = sel[s:s + chunk]
        pad = np.resize(idx, chunk)  # fixed shape: one compilation; padded entries are dropped below
        r, k = _eval_chunk(params, grids, origin, voxel, jnp.asarray(data.pose[pad]), jnp.asarray(data.record[pad]),
                           palm_root, tet_root)
        recs.append(np.asarray(r)[: len(idx)])
        kls.append(np.asarray(k)[: len(idx)])
    rec, kl = np.concatenate(recs), np.concatenate(kls)
    return {"rec": float(rec.mean()), "kl": float(kl.mean()), "grasps": int(len(sel))}


def dataset_hand(path: str, hand: str = "") -> str:
    """The hand a dataset file was built for (its build config's `hand`; the SVH for files that predate the field),
    or `hand` after checking that it is the same hand."""
    from ffcgs_jax.dataset import mcap_io
    from ffcgs_jax.hand.spec import load_spec

    built = ((mcap_io.read_config(path).get("config") or {}).get("hand") or "svh")
    if hand and load_spec(hand).name != load_spec(built).name:
        raise FfcgsError(f"{path} was built for hand {built!r}, not {hand!r}: train on a dataset of that hand "
                         "(ffcgs dataset build --hand ...)")
    return hand or built


def weights_meta(cfg: TrainConfig, hand: str, extra: dict) -> dict:
    """The metadata saved beside trained weights: format, version, hand, model config and training config."""
    return {"format": WEIGHTS_FORMAT, "version": __version__, "hand": hand, "model": dataclasses.asdict(cfg.model),
            "train": {"config": to_toml(cfg)} | extra}


RUN_CONFIG_MARK = "# written by ffcgs train: the resolved config of the run in this folder"
"""The first line of the config.toml a run writes: `ffcgs train --out` rewrites only a config.toml that begins with
it (or that stands beside a checkpoint: runs of older versions), never a config the user put there."""


def run_folder(cfg) -> tuple[Path, str, Path, Path, Path]:
    """(out folder, the config as TOML, its config.toml, checkpoint.npz and metrics.jsonl) of a training run,
    once `check_run_folder` allows the run there. Shared by every `ffcgs train` model."""
    out = Path(cfg.out).expanduser()
    text = f"{RUN_CONFIG_MARK} (train --config it to repeat the run)\n{to_toml(cfg)}"
    cfg_path, ckpt_path, log_path = out / "config.toml", out / "checkpoint.npz", out / "metrics.jsonl"
    # the advice to resume names the model: the sampler's parser refuses the evaluator's [net] section
    check_run_folder(out, cfg_path, ckpt_path, text, "" if isinstance(cfg, TrainConfig) else " --model evaluator")
    return out, text, cfg_path, ckpt_path, log_path


def check_run_folder(out: Path, cfg_path: Path, ckpt_path: Path, text: str, model_flag: str = "") -> None:
    """`out` may be new, empty, or this configuration's run (resumed); a file, another configuration's run, or a
    folder of other files is refused before anything is written."""
    if out.exists() and not out.is_dir():
        raise FfcgsError(f"--out {out} is a file, not a folder: a training run writes a folder (config.toml, "
                         "checkpoint.npz, weights.npz, ...)")
    old = _read_config(cfg_path)
    if old is not None and not old.startswith(RUN_CONFIG_MARK) and not ckpt_path.is_file():
        raise FfcgsError(f"--out {out} holds a config.toml that no ffcgs train run wrote ({cfg_path}), which a run "
                         f"would replace with its own; choose another --out (to train from that config: `ffcgs "
                         f"train{model_flag} --config {cfg_path} --out NEW`)")
    if ckpt_path.is_file() and old is not None and _body(old) != _body(text):
        raise FfcgsError(f"{out} holds a run with a different config ({cfg_path}); resume it with `ffcgs "
                         f"train{model_flag} --config {cfg_path}` or choose another --out")
    if out.is_dir() and not cfg_path.is_file() and any(p.is_file() for p in out.iterdir()):
        raise FfcgsError(f"--out {out} holds files but no training run (no config.toml); choose a new or empty "
                         "folder")


def _read_config(path: Path) -> str | None:
    if not path.is_file():
        return None
    try:
        return path.read_text()
    except (OSError, UnicodeDecodeError):
        return ""  # unreadable: no run's config, refused as such


def _body(config_text: str) -> str:
    """A run's config.toml without its first line (`RUN_CONFIG_MARK`), to compare with one of an older version."""
    first, _, rest = config_text.partition("\n")
    return rest if first.startswith(RUN_CONFIG_MARK) else config_text


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
    out, text, cfg_path, ckpt_path, log_path = run_folder(cfg)
    # Everything that can refuse the run comes before its first write: a failed start leaves an existing run (and
    # a new --out) exactly as it was.
    if data is None:
        data = cvae_data.load(cfg.data.path, cfg.data.noisy)
    if data.res != cfg.model.res:
        raise FfcgsError(f"the dataset's SDFs are {data.res}^3 but model.res is {cfg.model.res}")
    train_recs, val_recs = cvae_data.split(data, cfg.cv.folds, cfg.cv.fold, cfg.seed)
    palm_root, tet_root, hand_name = hand_points(dataset_hand(cfg.data.path, hand or cfg.hand))
    palm_root, tet_root = jnp.asarray(palm_root), jnp.asarray(tet_root)
    o, k = cfg.optim, cfg.data.grasps_per_sdf
    steps_per_epoch = cvae_data.steps_per_epoch(data, train_recs, o.batch, k)
    total = steps_per_epoch * o.epochs
    tree, meta = checkpoint.load(ckpt_path) if ckpt_path.is_file() else (None, None)
    files.check_folder(out, "--out")
    files.write_text(cfg_path, text)

    params = cvae.init(jax.random.key(cfg.seed), cfg.model)
    opt = adam_init(params)
    start_epoch = 0
    if tree is not None:
        params, opt = tree["params"], AdamState(tree["opt"]["count"], tree["opt"]["mu"], tree["opt"]["nu"])
        params, opt = jax.tree.map(jnp.asarray, (params, opt))
        start_epoch = int(meta["epoch"])
        truncate_log(log_path, start_epoch * steps_per_epoch)
    elif log_path.exists():
        log_path.unlink()

    grids = (jnp.asarray(data.grids), jnp.asarray(data.origin), jnp.asarray(data.voxel_size))
    pose = jnp.asarray(data.pose)
    # always `steps_per_call` steps per call, the ones past the epoch's end masked off (`live`): an executable's
    # shapes then do not depend on the dataset's size, so the folds of a cross-validation, a sweep's points and a
    # resumed run share one compile instead of one each (minutes on a CPU)
    chunk = cfg.steps_per_call
    t_start = time.perf_counter()
    # drawn from its first update on (`delay`): before it, the first step's compile has its own line
    bar = tqdm(total=total, initial=start_epoch * steps_per_epoch, desc=f"train {out.name}", unit="step",
               disable=not progress, dynamic_ncols=True, delay=1e-3)
    last_val = None
    first_step = start_epoch * steps_per_epoch
    with open(log_path, "a") as log:
        for epoch in range(start_epoch, o.epochs if until_epoch is None else min(until_epoch, o.epochs)):
            rng = np.random.default_rng([cfg.seed, epoch])
            rec_idx, grasp_idx = cvae_data.epoch_batches(data, train_recs, o.batch, k, rng)
            step = epoch * steps_per_epoch
            acc: dict[str, list] = {}
            for s in range(0, steps_per_epoch, chunk):
                n = min(chunk, steps_per_epoch - s)
                sel = np.arange(s, s + chunk) % steps_per_epoch  # the padding steps are masked off
                # the first call compiles (minutes on a small CPU): a ticker says so; later calls only dispatch
                with compiling("the CVAE's training step", show=progress) if step + s == first_step else nullcontext():
                    params, opt, m = train_steps(
                        params, opt, jnp.asarray(step + s, jnp.int32), jnp.asarray(np.arange(chunk) < n), *grids,
                        pose, jnp.asarray(rec_idx[sel]), jnp.asarray(grasp_idx[sel]), palm_root, tet_root,
                        jnp.asarray(cfg.seed, jnp.int32), jnp.asarray(total, jnp.int32), optim=o, kl=cfg.kl)
                m = {key: np.asarray(v)[:n] for key, v in m.items()}
                if not np.isfinite(m["loss"]).all():
                    raise FfcgsError(f"the loss became non-finite at step {step + s} (epoch {epoch}); lower "
                                     f"optim.lr or set optim.grad_clip")
                for i in range(n):
                    for key, v in m.items():
                        acc.setdefault(key, []).append(float(v[i]))
                    gstep = step + s + i + 1
                    if gstep % cfg.log_every == 0 or gstep == step + steps_per_epoch:
                        log.write(json.dumps({"step": gstep, "epoch": epoch} |
                                             {key: float(np.mean(v)) for key, v in acc.items()}) + "\n")
                        acc = {}
                bar.update(n)
                bar.set_postfix(rec_cm=f"{100 * float(m['rec'][-1]):.2f}", kl=f"{float(m['kl'][-1]):.2f}")
            row = {"epoch": epoch + 1, "step": (epoch + 1) * steps_per_epoch, "elapsed_s": time.perf_counter() - t_start}
            if len(val_recs):
                last_val = evaluate(params, data, val_recs, palm_root, tet_root, grids)
                row |= {"val_rec": last_val["rec"], "val_kl": last_val["kl"]}
            log.write(json.dumps(row) + "\n")
            log.flush()
            checkpoint.save(ckpt_path, {"params": params, "opt": {"count": opt.count, "mu": opt.mu, "nu": opt.nu}},
                            {"epoch": epoch + 1, "config": text})
    bar.close()
    if until_epoch is not None and until_epoch < o.epochs:
        return None

    train_eval = evaluate(params, data, train_recs, palm_root, tet_root, grids)
    if len(val_recs) and last_val is None:
        last_val = evaluate(params, data, val_recs, palm_root, tet_root, grids)
    summary = {
        "train_rec": train_eval["rec"], "train_kl": train_eval["kl"],
        "val_rec": None if last_val is None else last_val["rec"], "val_kl": None if last_val is None else last_val["kl"],
        "train_objects": sorted(set(data.objects[train_recs].tolist())),
        "val_objects": sorted(set(data.objects[val_recs].tolist())),
        "train_grasps": int(len(data.grasps_of(train_recs))), "steps": total, "backend": jax.default_backend(),
    }
    checkpoint.save(out / "weights.npz", {"params": params},
                    weights_meta(cfg, hand_name, {k: summary[k] for k in ("train_rec", "val_rec", "steps")}))
    files.write_text(out / "summary.json", json.dumps(summary, indent=1))
    plot_metrics(log_path, out / "metrics.png")
    return summary


def truncate_log(path: Path, step: int) -> None:
    """Drop log lines past `step` (written after the checkpoint a resumed run restarts from)."""
    if not path.exists():
        return
    keep = [line for line in path.read_text().splitlines() if line and json.loads(line)["step"] <= step]
    files.write_text(path, "".join(line + "\n" for line in keep))


def read_metrics(path: str | Path) -> tuple[list[dict], list[dict]]:
    """(step rows, epoch rows) of a metrics.jsonl."""
    rows = [json.loads(line) for line in Path(path).read_text().splitlines() if line]
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
