"""The one training loop (`training.harness`): a toy task resumes bit-identically and logs each row once; the CVAE
and the predictor both run through it (one checkpoint schema); checkpoints of the loops before it still resume to
the same weights; checkpoints it cannot continue are refused in one line that says what to do, before any write."""

import dataclasses
import json
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.kernels.adam import adam_update
from ffcgs_jax.learning import checkpoint
from ffcgs_jax.learning.config import EvaluatorNetConfig, ModelConfig
from ffcgs_jax.training import evaluator_data, evaluator_train, harness
from ffcgs_jax.training import train as cvae_train
from ffcgs_jax.training.config import (CVConfig, DataConfig, EvaluatorDataConfig, EvaluatorOptimConfig,
                                       EvaluatorTrainConfig, TrainConfig, TrainOptimConfig)
from ffcgs_jax.training.run import run_folder

from cvae_toy import make_toy_dataset

X = jnp.asarray(np.random.default_rng(0).normal(size=(40, 3)), jnp.float32)
Y = X @ jnp.array([1.0, -2.0, 0.5], jnp.float32)


@partial(jax.jit, static_argnames=("lr",))
def toy_steps(params, opt, step0, idx, lr):
    def one(carry, rows):
        params, opt = carry
        loss, grads = jax.value_and_grad(lambda p: jnp.mean((X[rows] @ p["w"] - Y[rows]) ** 2))(params)
        updates, opt = adam_update(grads, opt, lr)
        return ({"w": params["w"] + updates["w"]}, opt), loss

    (params, opt), loss = jax.lax.scan(one, (params, opt), idx)
    return params, opt, {"loss": loss}


def toy_task(epochs=4, seed=0, lr=0.05, rows=40) -> harness.Task:
    """Linear regression in batches of 8, in two calls per epoch (2 steps, then the rest)."""
    steps = rows // 8

    def chunks(epoch):
        idx = np.random.default_rng([seed, epoch]).permutation(rows)[: steps * 8].reshape(steps, 8)
        yield harness.Chunk(0, 2, jnp.asarray(idx[:2]))
        yield harness.Chunk(2, steps - 2, jnp.asarray(idx[2:]))

    return harness.Task(
        name="toy", step_name="the toy step", seed=seed, epochs=epochs, steps_per_epoch=steps,
        init=lambda: ({"w": jnp.zeros(3)}, {"scale": np.ones(3)}), chunks=chunks,
        step=lambda p, o, c, s0, idx: toy_steps(p, o, s0, idx, lr), evaluate=lambda p, c: {"w0": float(p["w"][0])},
        log_every=3, epoch_means=("loss",))


def test_a_toy_task_resumes_bit_identically_and_logs_each_row_once(tmp_path):
    cfg = lambda name: EvaluatorTrainConfig(out=str(tmp_path / name))  # noqa: E731  (any config: the run's folder)
    whole = harness.fit(toy_task(), run_folder(cfg("a")), progress=False)
    assert harness.fit(toy_task(), run_folder(cfg("b")), progress=False, until_epoch=3) is None
    # a crash after a checkpoint leaves rows past it in the log: the resumed run drops them
    with open(tmp_path / "b" / "metrics.jsonl", "a") as f:
        f.write(json.dumps({"step": 16, "epoch": 3, "loss": 1.0}) + "\n")
    resumed = harness.fit(toy_task(), run_folder(cfg("b")), progress=False)
    np.testing.assert_array_equal(whole.params["w"], resumed.params["w"])
    rows = lambda name: [{k: v for k, v in json.loads(x).items() if k != "elapsed_s"}  # noqa: E731
                         for x in (tmp_path / name / "metrics.jsonl").read_text().splitlines()]
    assert rows("a") == rows("b")
    epochs = [r for r in rows("a") if "w0" in r]
    assert epochs[-1]["loss"] < 0.5 * epochs[0]["loss"] and epochs[-1]["w0"] == float(whole.params["w"][0])
    assert [r["step"] for r in rows("a") if "w0" not in r] == [3, 5, 6, 9, 10, 12, 15, 18, 20]
    tree, meta = checkpoint.load(tmp_path / "b" / "checkpoint.npz")
    assert meta["format"] == harness.CHECKPOINT_FORMAT and (meta["epoch"], meta["step"], meta["seed"]) == (4, 20, 0)
    assert [r["epoch"] for r in meta["history"]] == [1, 2, 3, 4]  # the history survives the resume
    assert set(tree) == {"params", "opt", "consts"} and int(tree["opt"]["count"]) == 20


def test_a_non_finite_loss_names_its_step(tmp_path):
    with pytest.raises(FfcgsError, match=r"non-finite at step \d+ \(epoch 0\); lower optim.lr"):
        harness.fit(toy_task(lr=1e300), run_folder(EvaluatorTrainConfig(out=str(tmp_path / "r"))), progress=False)


def synthetic(n_obj=6, per=30, seed=0) -> evaluator_data.LabelData:
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n_obj * per, 6)).astype(np.float32)
    y = np.stack([x[:, 0] > 0, x[:, 1] > 0, (x[:, 0] > 0) & (x[:, 1] > 0)], 1).astype(np.float32)
    return evaluator_data.LabelData(x, y, np.repeat([f"o{i}" for i in range(n_obj)], per), np.ones(len(x), bool),
                                    rng.normal(size=len(x)), ("lift_shake", "six_dir", "all"),
                                    np.full(len(x), "train"))


def evaluator_cfg(tmp_path, name) -> EvaluatorTrainConfig:
    return EvaluatorTrainConfig(out=str(tmp_path / name), hand="svh", data=EvaluatorDataConfig("unused.mcap"),
                                net=EvaluatorNetConfig(hidden=16, depth=2),
                                optim=EvaluatorOptimConfig(lr=3e-3, epochs=4, batch=32, weight_decay=0.1),
                                cv=CVConfig(folds=3, fold=0))


def legacy_checkpoint(path, model: str) -> None:
    """Rewrite a checkpoint in the layout the loops before the harness wrote (their `checkpoint.save` calls at
    HEAD before issue 44): the sampler {"params", "opt"}, the predictor {"net", "norm", "opt"}, and in both the
    metadata {"epoch", "config"} only."""
    tree, meta = checkpoint.load(path)
    opt = {"count": tree["opt"]["count"], "mu": tree["opt"]["mu"], "nu": tree["opt"]["nu"]}
    old = ({"params": tree["params"], "opt": opt} if model == "sampler" else
           {"net": tree["params"], "norm": tree["consts"]["norm"], "opt": opt})
    path.unlink()
    checkpoint.save(path, old, {"epoch": meta["epoch"], "config": meta["config"]})


def weights(path):
    tree, _ = checkpoint.load(path)
    return checkpoint.flatten(tree)


def test_a_predictor_checkpoint_of_the_old_loop_resumes_to_the_same_weights(tmp_path):
    data = synthetic()
    whole = evaluator_train.train(evaluator_cfg(tmp_path, "a"), progress=False, data=data)
    assert evaluator_train.train(evaluator_cfg(tmp_path, "b"), progress=False, data=data, until_epoch=2) is None
    legacy_checkpoint(tmp_path / "b" / "checkpoint.npz", "evaluator")
    resumed = evaluator_train.train(evaluator_cfg(tmp_path, "b"), progress=False, data=data)
    wa, wb = weights(tmp_path / "a" / "weights.npz"), weights(tmp_path / "b" / "weights.npz")
    assert wa.keys() == wb.keys()
    for k in wa:
        np.testing.assert_array_equal(wa[k], wb[k], err_msg=k)
    assert whole["val_within_auc_valid"] == resumed["val_within_auc_valid"]
    _, meta = checkpoint.load(tmp_path / "b" / "checkpoint.npz")  # rewritten in the one schema
    assert meta["format"] == harness.CHECKPOINT_FORMAT and [r["epoch"] for r in meta["history"]] == [1, 2, 3, 4]


def test_checkpoints_it_cannot_continue_are_refused_before_any_write(tmp_path):
    data = synthetic()
    assert evaluator_train.train(evaluator_cfg(tmp_path, "r"), progress=False, data=data, until_epoch=1) is None
    run = tmp_path / "r"
    before = {p.name: p.read_bytes() for p in run.iterdir()}
    ckpt = run / "checkpoint.npz"
    tree, meta = checkpoint.load(ckpt)
    cases = [
        ({"params": tree["params"], "opt": tree["opt"]}, {"epoch": 1, "config": meta["config"]},
         "not a training checkpoint of the 'evaluator' model"),  # the old sampler's layout under the predictor's config
        (tree, meta | {"format": "ffcgs-train-checkpoint-9"}, "another ffcgs version"),
        (tree, meta | {"task": "sampler"}, "of the 'sampler' model, not of 'evaluator'"),
        ({"params": tree["params"]}, meta, "lacks the parameters or the Adam state"),
    ]
    for t, m, message in cases:
        ckpt.unlink()
        checkpoint.save(ckpt, t, m)
        before["checkpoint.npz"] = ckpt.read_bytes()
        with pytest.raises(FfcgsError, match=message) as e:
            evaluator_train.train(evaluator_cfg(tmp_path, "r"), progress=False, data=data)
        assert "\n" not in str(e.value) and f"delete {ckpt} to train from the start" in str(e.value)
        assert {p.name: p.read_bytes() for p in run.iterdir()} == before
    ckpt.unlink()
    checkpoint.save(ckpt, tree, meta)
    with pytest.raises(FfcgsError, match="the dataset changed"):  # fewer grasps: fewer steps per epoch
        evaluator_train.train(evaluator_cfg(tmp_path, "r"), progress=False, data=synthetic(n_obj=6, per=20))


@pytest.mark.e2e  # compiles the CVAE's step
def test_both_tasks_share_one_checkpoint_schema_and_old_sampler_checkpoints_resume(tmp_path):
    toy = make_toy_dataset(tmp_path / "toy.mcap", n_objects=5, grasps=8)
    cfg = lambda name: TrainConfig(  # noqa: E731
        out=str(tmp_path / name), log_every=2, steps_per_call=3, model=ModelConfig(res=8, width=2, features=4,
                                                                                   head=4, mlp=8),
        optim=TrainOptimConfig(lr=3e-3, batch=8, epochs=2), data=DataConfig(path=str(toy)), cv=CVConfig(fold=0))
    cvae_train.train(cfg("a"), progress=False)
    assert cvae_train.train(cfg("b"), progress=False, until_epoch=1) is None
    assert evaluator_train.train(evaluator_cfg(tmp_path, "e"), progress=False, data=synthetic(), until_epoch=1) is None
    (ts, ms), (te, me) = (checkpoint.load(tmp_path / r / "checkpoint.npz") for r in ("b", "e"))
    assert ms.keys() == me.keys() and ms["format"] == me["format"] == harness.CHECKPOINT_FORMAT
    assert (ms["task"], me["task"]) == ("sampler", "evaluator") and ms["epoch"] == me["epoch"] == 1
    assert set(ts) == {"params", "opt"} and set(te) == {"params", "opt", "consts"}  # the sampler has no consts
    assert set(ts["opt"]) == set(te["opt"]) == {"count", "mu", "nu"}
    legacy_checkpoint(tmp_path / "b" / "checkpoint.npz", "sampler")
    cvae_train.train(cfg("b"), progress=False)
    wa, wb = weights(tmp_path / "a" / "weights.npz"), weights(tmp_path / "b" / "weights.npz")
    assert wa.keys() == wb.keys()
    for k in wa:
        np.testing.assert_array_equal(wa[k], wb[k], err_msg=k)
    strip = lambda r: [{k: v for k, v in json.loads(x).items() if k != "elapsed_s"}  # noqa: E731
                       for x in (tmp_path / r / "metrics.jsonl").read_text().splitlines()]
    assert strip("a") == strip("b")


def test_fit_records_the_steady_seconds_per_step_it_measured(tmp_path, monkeypatch):
    """The cost `ffcgs learn` sizes its epochs by: the epochs after the first (which paid the compile), per step,
    kept under the task's key beside the compilation cache; a task without a key records nothing."""
    from ffcgs_jax.training import step_cost

    monkeypatch.setenv("FFCGS_JAX_CACHE", str(tmp_path / "cache"))
    cfg = lambda name: EvaluatorTrainConfig(out=str(tmp_path / name))  # noqa: E731
    assert step_cost.seconds_per_step("toy batch 8") == (max(step_cost.PRIOR.values()), False)
    harness.fit(toy_task(), run_folder(cfg("a")), progress=False)
    assert not step_cost.record_path().exists()
    keyed = lambda: dataclasses.replace(toy_task(), cost_key="toy batch 8")  # noqa: E731
    harness.fit(keyed(), run_folder(cfg("b")), progress=False)
    rows = [json.loads(x) for x in (tmp_path / "b" / "metrics.jsonl").read_text().splitlines()]
    elapsed = [r["elapsed_s"] for r in rows if "elapsed_s" in r]
    want = (elapsed[-1] - elapsed[0]) / (3 * 5)
    got, measured = step_cost.seconds_per_step("toy batch 8")
    assert measured and got == pytest.approx(want)
    harness.fit(dataclasses.replace(keyed(), epochs=1), run_folder(cfg("c")), progress=False)
    assert step_cost.seconds_per_step("toy batch 8")[0] == got  # one epoch measures nothing steady
    assert step_cost.measured([{"elapsed_s": 1.0}, {"elapsed_s": 3.0}, {"elapsed_s": 5.0}], 4) == 0.5
    assert step_cost.seconds_per_step("sampler batch 32")[0] == step_cost.PRIOR["sampler"]
