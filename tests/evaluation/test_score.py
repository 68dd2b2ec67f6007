"""The grasp score (evaluation/score.py), its fit (bench/fit_score.py) and the deterministic grasp order."""

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from ffcgs_jax.evaluation import score as S
from ffcgs_jax.synthesis.config import GraspConfig
from ffcgs_jax.synthesis.grasp import GraspSet

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench"))
import fit_score  # noqa: E402


def _arrays(g: int, seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    return {"epsilon": rng.uniform(0, 0.05, g), "E_c": rng.uniform(0, 2e-3, g), "penetration": rng.uniform(0, 3e-3, g),
            "E_q": rng.uniform(0, 0.3, g), "table_penetration": rng.uniform(0, 1e-3, g),
            "contact_dist": rng.uniform(-2e-3, 2e-3, (g, 5))}


def test_score_is_the_shipped_logistic_model():
    a = _arrays(50)
    m = S.model()
    F = np.column_stack([a["epsilon"], np.sqrt(a["epsilon"]), 1e3 * a["E_c"], 1e3 * a["penetration"], a["E_q"],
                         1e3 * a["table_penetration"], 1e3 * np.abs(a["contact_dist"]).max(axis=1)])
    z = ((F - np.array(m["mean"])) / np.array(m["scale"])) @ np.array(m["weights"]) + m["bias"]
    np.testing.assert_allclose(S.score(a), 1 / (1 + np.exp(-z)), rtol=1e-12)
    assert m["objects"] >= 20 and 0.6 < m["auc_leave_one_object_out"] < 1
    a["epsilon"][3] = np.nan
    assert S.score(a)[3] == 0.0


def test_fit_recovers_a_known_logistic_model():
    rng = np.random.default_rng(1)
    F = rng.standard_normal((20000, 3))
    w, b = np.array([1.5, -2.0, 0.0]), 0.3
    y = rng.uniform(size=len(F)) < 1 / (1 + np.exp(-(F @ w + b)))
    m = fit_score.fit(F, y)
    np.testing.assert_allclose(np.array(m["weights"]) / np.array(m["scale"]), w, atol=0.08)
    assert fit_score.auc(F @ w, y) > fit_score.auc(F[:, 2], y)


def test_fit_refuses_records_outside_the_training_split(tmp_path):
    rec = {"group": "ycb-test", "object": "015_peach", "tested": [], "physics": {}}
    path = tmp_path / "q.json"
    path.write_text(json.dumps({"config": {}, "records": [rec]}))
    with pytest.raises(SystemExit, match="ycb-train only"):
        fit_score.dataset([str(path)])


def test_order_is_deterministic_valid_first_then_E_then_index():
    n = 12
    rng = np.random.default_rng(2)
    E = rng.choice([0.1, 0.2, 0.3], n)  # ties on purpose
    valid = rng.uniform(size=n) < 0.6
    gs = GraspSet({"valid": valid, "E": E}, {}, GraspConfig(), "x")
    order = gs.order()
    expected = sorted(range(n), key=lambda i: (not valid[i], E[i], i))
    assert order.tolist() == expected
    assert gs.order().tolist() == order.tolist()  # and again


def test_evaluate_ranks_any_objects_with_the_shipped_score(tmp_path, capsys):
    """--evaluate reads test-split records too (it fits nothing) and prints the pooled and within-call figures."""
    a = _arrays(4, seed=3)
    rec = {"group": "ycb-test", "object": "015_peach", "row": "cvae", "tested": [0, 1, 2, 3],
           "E": [0.1, 0.2, 0.3, 0.4], "physics": {"lift_shake_success": [True, True, False, True],
                                                  "six_dir_success": [True, False, False, True]},
           **{k: np.asarray(v).tolist() for k, v in a.items()}}
    path = tmp_path / "q.json"
    path.write_text(json.dumps({"config": {}, "records": [rec]}))
    assert fit_score.main(["--evaluate", str(path)]) == 0
    out = capsys.readouterr().out
    assert "4 grasps, 50.0% pass both protocols" in out and "top-1 100.0%" in out  # E's best (index 0) passes
