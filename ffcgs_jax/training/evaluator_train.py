"""Training the success predictor, a task of `training.harness`: `ffcgs train --model evaluator` (one run,
`--cv.all`, `--sweep`). Here: its loss, its compiled epoch of AdamW steps, its figures and the weights it exports.

Outputs in `cfg.out`, as the sampler's training writes them:
    config.toml       the resolved config
    metrics.jsonl     one line per epoch: training loss; on the held-out objects loss, pooled AUC and within-object
                      AUC of the "all" head (over the valid grasps: what a user is offered), first-grasp success
    metrics.png       the curves and the reliability curve of the held-out (or training) predictions
    checkpoint.npz    params, Adam state, the standardiser and the epoch reached (each epoch; a run resumes)
    weights.npz       {"net", "norm"} and metadata: what `ffcgs grasp --evaluator` and `GraspSet.order` use
    summary.json      the final figures

Batch order comes from (seed, epoch), so a resumed run computes the same parameters as an uninterrupted one.
"""

import dataclasses
import json
import math
from collections.abc import Callable
from functools import partial
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from ffcgs_jax.core import files
from ffcgs_jax.core.config import check_all
from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.core.version import __version__
from ffcgs_jax.evaluation import rank_metrics
from ffcgs_jax.hand import kinematics as K
from ffcgs_jax.hand.identity import spec_sha256
from ffcgs_jax.kernels.adam import AdamState, adam_update
from ffcgs_jax.learning import checkpoint, evaluator
from ffcgs_jax.learning import layers as nn
from ffcgs_jax.learning.weights import EVALUATOR_FORMAT
from ffcgs_jax.runtime.fixed_shapes import pad_rows
from ffcgs_jax.training import data as cvae_data
from ffcgs_jax.training import evaluator_data, harness
from ffcgs_jax.training.config import EvaluatorOptimConfig, EvaluatorTrainConfig, to_toml
from ffcgs_jax.training.run import dataset_hand, read_metrics, run_folder

def loss_fn(net, norm, x, y):
    return jnp.mean(evaluator.bce(evaluator.logits(net, norm, x), y))


@partial(jax.jit, static_argnames=("optim",), donate_argnames=("net", "opt"))
def train_steps(net, opt: AdamState, norm, x, y, idx, step0, total, optim: EvaluatorOptimConfig):
    """idx (steps, batch) rows of x / y: that many Adam steps in one lax.scan; cosine-decayed step size and
    decoupled weight decay. Returns (net, opt, per-step loss)."""
    def one(carry, xs):
        net, opt = carry
        i, rows = xs
        loss, grads = jax.value_and_grad(loss_fn)(net, norm, x[rows], y[rows])
        lr = optim.lr * 0.5 * (1 + jnp.cos(jnp.pi * jnp.minimum((step0 + i) / total, 1.0)))
        updates, opt = adam_update(grads, opt, lr, optim.b1, optim.b2, optim.eps)
        net = jax.tree.map(lambda p, u: (p * (1 - lr * optim.weight_decay) + u).astype(p.dtype), net, updates)
        return (net, opt), loss

    (net, opt), losses = jax.lax.scan(one, (net, opt), (jnp.arange(idx.shape[0]), idx))
    return net, opt, losses


_logits = jax.jit(evaluator.logits)


def logit_rows(weights: dict, x: np.ndarray, chunk: int = 8192) -> np.ndarray:
    """Logits (N, H) of feature rows `x` (host), in fixed-size chunks (one compilation)."""
    out = []
    for s in range(0, len(x), chunk):
        part = x[s:s + chunk]
        out.append(np.asarray(_logits(weights["net"], weights["norm"], jnp.asarray(pad_rows(part, chunk))))[:len(part)])
    return np.concatenate(out)


def predict_rows(weights: dict, x: np.ndarray) -> np.ndarray:
    """Probabilities (N, H) of feature rows `x`."""
    return np.exp(-np.logaddexp(0.0, -logit_rows(weights, x)))  # sigmoid without overflow


def figures(prob: np.ndarray, data: evaluator_data.LabelData, rows: np.ndarray) -> dict:
    """How `prob` (N, H) of `rows` ranks: per head the pooled AUC, the "all" head's within-object AUC over valid
    grasps and over every candidate, first-grasp success among the valid ones by prediction, by E and at random,
    and the calibration error."""
    out = {}
    heads = data.heads
    hit = evaluator_data.positives(data)[rows]
    for h, name in enumerate(heads):
        out[f"auc_{name}"] = rank_metrics.auc(prob[:, h], hit[:, h])
    p, y, obj, v = prob[:, -1], hit[:, -1], data.objects[rows], data.valid[rows]
    out["within_auc_valid"], out["within_objects"] = rank_metrics.within_auc(p[v], y[v], obj[v])
    out["within_auc_all"], _ = rank_metrics.within_auc(p, y, obj)
    out["within_auc_valid_minus_E"], _ = rank_metrics.within_auc(-data.E[rows][v], y[v], obj[v])
    # NaN without a valid grasp (a small fold): the keys are always there for the log, the picture and cv.md
    out["top1_pred"] = float(rank_metrics.top_k(p[v], y[v], obj[v]).mean()) if v.any() else math.nan
    out["top1_E"] = float(rank_metrics.top_k(-data.E[rows][v], y[v], obj[v]).mean()) if v.any() else math.nan
    out["top1_random"] = float(rank_metrics.random_top1(y[v], obj[v]).mean()) if v.any() else math.nan
    out["ece"] = rank_metrics.reliability(p, data.y[rows, -1])["ece"]  # against the rate: what p estimates
    return out


def weights_meta(cfg: EvaluatorTrainConfig, hand: K.Hand, heads, width: int, extra: dict) -> dict:
    return {"format": EVALUATOR_FORMAT, "version": __version__, "hand": hand.spec.name,
            "hand_sha256": spec_sha256(hand.spec), "heads": list(heads),
            "feature_version": evaluator.FEATURE_VERSION, "feature_width": width,
            "net": dataclasses.asdict(cfg.net), "train": {"config": to_toml(cfg)} | extra}


def train(cfg: EvaluatorTrainConfig, progress: bool = True, until_epoch: int | None = None,
          data: evaluator_data.LabelData | None = None) -> dict | None:
    """Train one configuration (one fold, or every object with cv.fold -1). Returns the summary (also in
    summary.json); None when `until_epoch` stopped it early (checkpointed: the same call continues it)."""
    if not isinstance(cfg, EvaluatorTrainConfig):
        raise FfcgsError(f"train takes an EvaluatorTrainConfig, got {type(cfg).__name__}")
    check_all(cfg)
    run = run_folder(cfg, " --model evaluator")  # the sampler's parser refuses the evaluator's [net] section
    # data handed in (cross-validation folds, tests) comes with its hand named in cfg.hand: no file to ask
    hand = K.load_hand(cfg.hand if data is not None and cfg.hand else dataset_hand(cfg.data.path, cfg.hand))
    if data is None:
        data = evaluator_data.load(cfg.data.path, hand, progress)
    objects = data.objects
    if cfg.cv.fold < 0:
        train_rows, val_rows = np.arange(len(objects)), np.arange(0)
    else:
        fold = cvae_data.fold_of(objects, cfg.cv.folds, cfg.seed)
        held = np.array([fold[o] == cfg.cv.fold for o in objects.tolist()])
        train_rows, val_rows = np.flatnonzero(~held), np.flatnonzero(held)
    task = evaluator_task(cfg, data, train_rows, val_rows)
    fitted = harness.fit(task, run, until_epoch=until_epoch, progress=progress)
    if fitted is None:
        return None
    weights = {"net": fitted.params, "norm": fitted.consts["norm"]}
    train_fig = figures(predict_rows(weights, data.x[train_rows]), data, train_rows)
    row = fitted.last_row or {}
    last = {k[len("val_"):]: v for k, v in row.items() if k.startswith("val_") and k != "val_loss"}
    if len(val_rows) and not last:
        last = figures(predict_rows(weights, data.x[val_rows]), data, val_rows)
    summary = {"heads": list(data.heads), "train_grasps": int(len(train_rows)), "val_grasps": int(len(val_rows)),
               "train_objects": len(set(objects[train_rows].tolist())),
               "val_objects": sorted(set(objects[val_rows].tolist())), "steps": task.steps_per_epoch * task.epochs,
               "params": nn.num_params(weights["net"]), "backend": jax.default_backend(),
               **{f"train_{k}": v for k, v in train_fig.items()}, **{f"val_{k}": v for k, v in last.items()}}
    checkpoint.save(run.out / "weights.npz", weights,
                    weights_meta(cfg, hand, data.heads, data.x.shape[1],
                                 {k: summary[k] for k in ("train_grasps", "train_objects", "steps")}))
    files.write_text(run.out / "summary.json", json.dumps(summary, indent=1, default=float))
    plot_metrics(run.log, run.out / "metrics.png", weights, data, val_rows if len(val_rows) else train_rows)
    return summary


def cost_key(cfg: EvaluatorTrainConfig) -> str:
    """What one predictor step's cost depends on (`step_cost`): its batch and the network's size."""
    return f"evaluator batch {cfg.optim.batch} hidden {cfg.net.hidden} depth {cfg.net.depth}"


def evaluator_task(cfg: EvaluatorTrainConfig, data: evaluator_data.LabelData, train_rows: np.ndarray,
                   val_rows: np.ndarray) -> harness.Task:
    """The predictor's training as a harness task: one compiled call per epoch, the standardiser of the training
    rows saved beside the network, the held-out figures per epoch."""
    o = cfg.optim
    steps = len(train_rows) // o.batch
    if steps == 0:
        raise FfcgsError(f"the training set has {len(train_rows)} grasps, fewer than one batch ({o.batch})")
    total = steps * o.epochs
    x, y = jnp.asarray(data.x), jnp.asarray(data.y)

    def init():
        net = evaluator.init(jax.random.key(cfg.seed), data.x.shape[1], len(data.heads), cfg.net.hidden, cfg.net.depth)
        return net, {"norm": evaluator.standardiser(data.x[train_rows])}

    def chunks(epoch):
        rng = np.random.default_rng([cfg.seed, epoch])
        idx = train_rows[rng.permutation(len(train_rows))[: steps * o.batch]].reshape(steps, o.batch)
        yield harness.Chunk(0, steps, jnp.asarray(idx))

    def step(net, opt, consts, step0, idx):
        net, opt, losses = train_steps(net, opt, consts["norm"], x, y, idx, jnp.asarray(step0), jnp.asarray(total),
                                       optim=o)
        return net, opt, {"loss": losses}

    def validate(net, consts):
        if not len(val_rows):
            return {}
        zv = logit_rows({"net": net, "norm": consts["norm"]}, data.x[val_rows])
        row = {"val_loss": float(jnp.mean(evaluator.bce(jnp.asarray(zv), jnp.asarray(data.y[val_rows]))))}
        return row | {f"val_{k}": v for k, v in figures(np.exp(-np.logaddexp(0.0, -zv)), data, val_rows).items()}

    def postfix(m, row):
        if row is None:
            return {}
        return {"loss": f"{row['loss']:.4f}"} | ({"val_within": f"{row['val_within_auc_valid']:.3f}"}
                                                  if len(val_rows) else {})

    return harness.Task(
        name="evaluator", step_name="the predictor's training step", seed=cfg.seed, epochs=o.epochs,
        steps_per_epoch=steps, init=init, chunks=chunks, step=step, evaluate=validate, epoch_means=("loss",),
        nonfinite_hint="lower optim.lr", postfix=postfix,
        legacy=lambda tree: (tree["net"], {"norm": tree["norm"]}) if {"net", "norm"} <= set(tree) else None,
        cost_key=cost_key(cfg))


def plot_metrics(log_path: Path, png: Path, weights, data, rows) -> Path | None:
    """Loss per epoch, held-out within-object AUC and top-1, and the reliability curve of `rows`."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print(f"matplotlib is not installed: {png} not drawn (pip install 'ffcgs-jax[train]')")
        return None
    epochs = read_metrics(log_path)
    fig, ax = plt.subplots(1, 3, figsize=(13, 3.6))
    e = [r["epoch"] for r in epochs]
    ax[0].plot(e, [r["loss"] for r in epochs], label="train")
    if "val_loss" in epochs[-1]:
        ax[0].plot(e, [r["val_loss"] for r in epochs], "o-", ms=3, label="held-out objects")
        ax[1].plot(e, [r["val_within_auc_valid"] for r in epochs], "o-", ms=3, label="within-object AUC (valid)")
        ax[1].plot(e, [r["val_top1_pred"] for r in epochs], "s-", ms=3, label="top-1, predicted order")
        ax[1].axhline(epochs[-1]["val_top1_E"], ls="--", c="gray", label="top-1, E order")
        ax[1].legend(fontsize=7)
    ax[0].set(xlabel="epoch", ylabel="binary cross-entropy", title="loss")
    ax[0].legend()
    ax[1].set(xlabel="epoch", title="ranking on held-out objects")
    rel = rank_metrics.reliability(predict_rows(weights, data.x[rows])[:, -1], data.y[rows, -1])
    p, r, n = (np.array(v) for v in zip(*rel["bins"]))
    ax[2].plot([0, 1], [0, 1], c="gray", lw=0.8)
    ax[2].scatter(p, r, s=8 + 60 * n / n.max())
    ax[2].set(xlabel="predicted P(pass all)", ylabel="observed pass rate", xlim=(0, 1), ylim=(0, 1),
              title=f"reliability (ECE {rel['ece']:.3f})")
    fig.tight_layout()
    with files.atomic_path(png) as tmp:
        fig.savefig(tmp, dpi=90)
    plt.close(fig)
    return png


def cv_table(rows: list[dict]) -> str:
    """The markdown comparison of the folds of one cross-validation."""
    lines = ["| fold | held-out objects | within-object AUC (valid) | pooled AUC (all) | top-1 predicted | top-1 E | "
             "top-1 random |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['fold']} | {len(r['val_objects'])} | {r['val_within_auc_valid']:.3f} | "
                     f"{r['val_auc_all']:.3f} | {r['val_top1_pred']:.1%} | {r['val_top1_E']:.1%} | "
                     f"{r['val_top1_random']:.1%} |")
    def measured(k):  # the folds that could measure figure k (NaN: no valid grasp among its held-out objects)
        return [r[k] for r in rows if not math.isnan(r[k])] or [math.nan]

    mean = lambda k: float(np.mean(measured(k)))  # noqa: E731
    std = lambda k: float(np.std(measured(k)))  # noqa: E731
    lines.append(f"\nover {len(rows)} folds: within-object AUC {mean('val_within_auc_valid'):.3f} ± "
                 f"{std('val_within_auc_valid'):.3f}, pooled AUC {mean('val_auc_all'):.3f}, top-1 predicted "
                 f"{mean('val_top1_pred'):.1%} (E {mean('val_top1_E'):.1%}, random {mean('val_top1_random'):.1%})")
    return "\n".join(lines)


def summary_columns() -> tuple[list[str], Callable[[dict], list[str]]]:
    """Column names and a row formatter for `ffcgs train --sweep` tables."""
    def fmt(r):
        g = lambda k: "-" if r.get(k) is None or (isinstance(r.get(k), float) and math.isnan(r[k])) \
            else f"{r[k]:.3f}"  # noqa: E731
        return [g("val_within_auc_valid"), g("val_auc_all"), g("val_top1_pred"), g("train_within_auc_valid"),
                f"{r['time_s']:.0f}"]
    return ["val within-object AUC", "val pooled AUC", "val top-1", "train within-object AUC", "time (s)"], fmt
