"""The success predictor's network and weights: network against NumPy, gradients against finite differences,
features batched against single, the shipped weights' use in ranking, and bad weights files (one line each). Its
training is tested in tests/training/test_evaluator_train.py."""

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.evaluation import rank_metrics, ranking
from ffcgs_jax.geometry import mesh_io
from ffcgs_jax.geometry import sdf as sdf_mod
from ffcgs_jax.geometry.config import SDFConfig
from ffcgs_jax.hand import kinematics as K
from ffcgs_jax.learning import checkpoint, evaluator
from ffcgs_jax.learning.weights import EVALUATOR_FORMAT, load_evaluator, shipped_evaluator
from ffcgs_jax.synthesis import prediction
from ffcgs_jax.training import evaluator_train
from ffcgs_jax.training.config import EvaluatorTrainConfig

from evaluator_toy import grasps
from paths import DATA


@pytest.fixture(scope="module")
def box_sdf():
    return sdf_mod.build_sdf(mesh_io.load_mesh("box"), SDFConfig(res=16))


def numpy_logits(net: dict, norm: dict, x: np.ndarray) -> np.ndarray:
    h = (x - np.asarray(norm["mean"])) / np.asarray(norm["scale"])
    for i in range(len(net) - 1):
        z = h @ np.asarray(net[f"l{i}"]["w"]) + np.asarray(net[f"l{i}"]["b"])
        h = z / (1 + np.exp(-z))
    return h @ np.asarray(net["head"]["w"]) + np.asarray(net["head"]["b"])


def random_net(n_in=7, n_out=3, hidden=16, depth=2, seed=0):
    net = evaluator.init(jax.random.key(seed), n_in, n_out, hidden, depth)
    net = jax.tree.map(lambda a: a + 0.1 * jax.random.normal(jax.random.key(seed + 1), a.shape), net)
    rng = np.random.default_rng(seed)
    norm = {"mean": rng.normal(size=n_in), "scale": rng.uniform(0.5, 2, n_in)}
    return net, norm


def test_forward_pass_matches_numpy_float64():
    net, norm = random_net()
    x = np.random.default_rng(3).normal(size=(11, 7))
    got = np.asarray(evaluator.logits(net, jax.tree.map(jnp.asarray, norm), jnp.asarray(x)))
    np.testing.assert_allclose(got, numpy_logits(net, norm, x), rtol=1e-12, atol=1e-12)


def test_gradient_matches_finite_differences():
    net, norm = random_net()
    norm = jax.tree.map(jnp.asarray, norm)
    rng = np.random.default_rng(4)
    x, y = jnp.asarray(rng.normal(size=(9, 7))), jnp.asarray((rng.uniform(size=(9, 3)) < 0.5).astype(float))
    grads = jax.grad(evaluator_train.loss_fn)(net, norm, x, y)
    h = 1e-6
    for path in (("l0", "w", (2, 5)), ("l1", "b", (3,)), ("head", "w", (4, 1))):
        layer, leaf, idx = path

        def at(delta):
            moved = jax.tree.map(lambda a: a, net)
            moved[layer] = dict(moved[layer])
            moved[layer][leaf] = moved[layer][leaf].at[idx].add(delta)
            return float(evaluator_train.loss_fn(moved, norm, x, y))

        fd = (at(h) - at(-h)) / (2 * h)
        assert abs(float(grads[layer][leaf][idx]) - fd) < 1e-7 * max(1.0, abs(fd)), path


@pytest.mark.e2e  # over 20 s on the 2-core CPU: kept out of plain `pytest` (README)
def test_features_have_the_documented_width_and_layout(svh, box_sdf):
    a = grasps(svh, 5, seed=1)
    inputs = evaluator.grasp_inputs(a, 5)
    assert inputs.shape == (5, evaluator.input_width(svh))
    args = [jnp.asarray(a[k]) for k in ("wrist_pose", "q", "contacts")] + [jnp.asarray(inputs)]
    batched = np.asarray(evaluator.batch_features_jit(svh, box_sdf, *args))
    assert batched.shape == (5, evaluator.feature_width(svh)) and np.isfinite(batched).all()
    res = box_sdf.grid.shape[0]
    centre = np.asarray(box_sdf.origin) + float(box_sdf.voxel_size) * (res - 1) / 2
    half = float(box_sdf.voxel_size) * res / 2
    np.testing.assert_allclose(batched[:, :15], ((a["contacts"] - centre) / half).reshape(5, 15), atol=1e-12)
    # a sphere's clearance is its SDF distance minus its radius (through asinh)
    c = len(svh.spec.contact_sites)
    start = c * (3 + 1 + 3 + 27)
    for i in (0, 3):
        centres, radii = K.collision_spheres(svh, args[0][i], args[1][i])
        d, _ = sdf_mod.query(box_sdf, centres)
        np.testing.assert_allclose(batched[i, start:start + len(radii)],
                                   np.arcsinh((np.asarray(d) - np.asarray(radii)) / 0.004), rtol=1e-9, atol=1e-9)
    # the last columns: the metrics through asinh(x / scale), then the object's size and table height
    m = len(evaluator.METRICS)
    np.testing.assert_allclose(batched[:, -2 - evaluator.input_width(svh):-2 - evaluator.input_width(svh) + m],
                               np.arcsinh(inputs[:, :m] / np.array(list(evaluator.METRICS.values()))), atol=1e-12)


def test_grasp_inputs_refuse_missing_metrics(svh):
    a = grasps(svh, 2, seed=2)
    del a["E_m"]
    with pytest.raises(FfcgsError, match="E_m"):
        evaluator.grasp_inputs(a, 5)


def test_ranking_by_prediction_is_deterministic_and_ties_go_by_index():
    a = {"valid": np.array([True, False, True, True, True]), "E": np.array([5.0, 0.0, 1.0, 3.0, 2.0]),
         "pred_success": np.array([0.5, 0.99, 0.9, 0.5, 0.1]), "rank_by": np.array("predicted"),
         "q": np.zeros((5, 9))}
    assert ranking.ranked(a).tolist() == [2, 0, 3, 4, 1]
    assert ranking.ranked(a).tolist() == ranking.ranked(dict(a)).tolist()
    assert ranking.ranked({**a, "rank_by": np.array("energy")}).tolist() == [2, 4, 3, 0, 1]
    old = {k: v for k, v in a.items() if k not in ("pred_success", "rank_by")}  # a file from before the predictor
    assert ranking.ranked(old).tolist() == [2, 4, 3, 0, 1]
    assert ranking.ranked({**old, "rank_by": np.array("predicted")}).tolist() == [2, 4, 3, 0, 1]


def test_rank_predicted_without_a_predictor_is_one_line(tmp_path, monkeypatch):
    monkeypatch.setenv("FFCGS_HOME", str(tmp_path))  # no installed predictor either
    toy = K.load_hand(str(DATA / "toy_hand" / "toy.toml"))  # no predictor ships for the toy hand
    assert not shipped_evaluator(toy.spec.name).is_file()
    assert prediction.resolve("auto", toy) == ("energy", None)
    with pytest.raises(FfcgsError, match="needs a success predictor"):
        prediction.resolve("predicted", toy)
    with pytest.raises(FfcgsError, match="rank must be one of"):
        prediction.resolve("best", toy)


def test_the_allegro_ranks_by_its_shipped_predictor():
    """Built by `ffcgs learn allegro` (bench/RESULTS.md, issue 46), stamped with the Allegro's spec hash."""
    allegro = K.load_hand("allegro")
    assert prediction.resolve("auto", allegro)[0] == "predicted"
    meta = load_evaluator(shipped_evaluator(allegro.spec.name), allegro)[1]
    assert meta["hand"] == "allegro_right" and len(meta["hand_sha256"]) == 64


def good_weights(hand, tmp_path):
    w = evaluator.init(jax.random.key(0), evaluator.feature_width(hand), 3, 8, 1)
    norm = {"mean": np.zeros(evaluator.feature_width(hand), np.float32),
            "scale": np.ones(evaluator.feature_width(hand), np.float32)}
    meta = {"format": EVALUATOR_FORMAT, "hand": hand.spec.name, "heads": ["lift_shake", "six_dir", "all"],
            "feature_version": evaluator.FEATURE_VERSION, "net": {"hidden": 8, "depth": 1}}
    return {"net": w, "norm": norm}, meta


@pytest.mark.parametrize("break_it, message", [
    (lambda t, m: (t, {**m, "format": "ffcgs.cvae.v1"}), "not a success-predictor weights file"),
    (lambda t, m: (t, {**m, "hand": "allegro_right"}), "was trained for hand"),
    (lambda t, m: (t, {**m, "feature_version": 0}), "features v0"),
    (lambda t, m: (t, {k: v for k, v in m.items() if k != "net"}), "lacks the network"),
    (lambda t, m: ({**t, "norm": {"mean": t["norm"]["mean"][:5], "scale": t["norm"]["scale"]}}, m), "do not fit"),
    (lambda t, m: ({**t, "net": {**t["net"], "head": {"w": np.full_like(t["net"]["head"]["w"], np.nan),
                                                     "b": t["net"]["head"]["b"]}}}, m), "NaN"),
])
def test_bad_weights_are_one_line(tmp_path, svh, break_it, message):
    tree, meta = break_it(*good_weights(svh, tmp_path))
    path = checkpoint.save(tmp_path / "w.npz", tree, meta)
    with pytest.raises(FfcgsError, match=message) as e:
        prediction.weights_for(svh, str(path))
    assert "\n" not in str(e.value)
    tree, meta = good_weights(svh, tmp_path)
    prediction.weights_for(svh, str(checkpoint.save(tmp_path / "ok.npz", tree, meta)))  # the unbroken file loads


def test_missing_and_foreign_files_are_one_line(tmp_path, svh):
    with pytest.raises(FfcgsError, match="not found"):
        prediction.weights_for(svh, str(tmp_path / "none.npz"))
    (tmp_path / "text.npz").write_text("hello")
    with pytest.raises(FfcgsError) as e:
        prediction.weights_for(svh, str(tmp_path / "text.npz"))
    assert "\n" not in str(e.value)


def test_rank_metrics_against_brute_force():
    rng = np.random.default_rng(5)
    s, y = rng.integers(0, 4, 40).astype(float), rng.uniform(size=40) < 0.4
    pairs = [(a, b) for a in np.flatnonzero(y) for b in np.flatnonzero(~y)]
    brute = np.mean([1.0 if s[a] > s[b] else 0.5 if s[a] == s[b] else 0.0 for a, b in pairs])
    assert rank_metrics.auc(s, y) == pytest.approx(brute, abs=1e-12)
    g = np.repeat([0, 1, 2, 3], 10)
    top = rank_metrics.top_k(s, y, g, 1)
    for i in range(4):
        idx = np.flatnonzero(g == i)
        assert top[i] == y[idx[np.argmax(s[idx])]]
    rel = rank_metrics.reliability(np.linspace(0, 1, 40), y, bins=4)
    assert sum(n for _, _, n in rel["bins"]) == 40 and 0 <= rel["ece"] <= 1


def test_shipped_weights_load_and_are_small(svh):
    path = shipped_evaluator(svh.spec.name)
    if not path.is_file():
        pytest.skip("no predictor ships for the SVH")
    weights, meta = load_evaluator(path, svh)
    assert path.stat().st_size < 4e6
    assert meta["heads"][-1] == "all" and json.loads(json.dumps(meta))
    assert dataclasses.is_dataclass(EvaluatorTrainConfig())
