"""Searching further on a weak first batch (`synthesis.search`, `GraspConfig.search`): when it searches and why,
the budget's rule, the pool's ranking, the record in the grasp set and its file, and an object whose first batch
is good enough getting exactly that batch. The decision logic runs on made-up batches with a made-up clock (no
compile, no wall-clock); the calls through `fj.synthesize` share one toy-hand compile."""

import dataclasses
from pathlib import Path

import jax
import numpy as np
import pytest

import ffcgs_jax as fj
from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.evaluation import ranking
from ffcgs_jax.geometry.config import SDFConfig
from ffcgs_jax.runtime import compile_clock
from ffcgs_jax.synthesis import grasp as G
from ffcgs_jax.synthesis import search
from ffcgs_jax.synthesis.config import GraspConfig, OptimConfig, SearchConfig
from ffcgs_jax.synthesis.grasp_set import GraspSet

DATA = Path(__file__).parents[1] / "data"
TOY = DATA / "toy_hand" / "toy.toml"
BEFORE = DATA / "grasps_ae66fbd_toy_box.npz"  # a grasp file from before the search (and the typed fields)
N = 4


def batch(valid, pred=None, E=None, seconds=1.0, tag=0.0) -> GraspSet:
    """A made-up batch: `tag` marks its rows (in `q`) so the pool's picks can be traced back."""
    valid = np.asarray(valid, bool)
    n = len(valid)
    arrays = {"wrist_pose": np.tile(np.eye(4), (n, 1, 1)), "q": np.full((n, 2), tag) + np.arange(n)[:, None],
              "channel_names": np.array(["a", "b"]), "valid": valid,
              "E": np.arange(n, dtype=float) if E is None else np.asarray(E, float),
              "synthesis_s": np.asarray(0.75 * seconds), "evaluation_s": np.asarray(0.25 * seconds),
              "rank_by": np.array("energy")}
    if pred is not None:
        arrays |= {"pred_success": np.asarray(pred, float), "rank_by": np.array("predicted")}
    return GraspSet(arrays, {"E": np.zeros((3, n)) + tag}, GraspConfig(n=n), "thing")


class Clock:
    """Seconds that pass only when a batch runs: each `again` call advances it by that batch's `seconds`."""

    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


def runner(clock: Clock, batches: list[GraspSet], keys: list):
    def again(key):
        keys.append(np.asarray(key))
        gs = batches[len(keys) - 1]
        clock.t += float(gs["synthesis_s"]) + float(gs["evaluation_s"])
        return gs
    return again


# ------------------------------------------------------------------------------------------ deciding, no compile


def test_the_shortfall_names_each_unmet_need_and_the_prediction_counts_only_where_it_ranks():
    cfg = SearchConfig(min_valid=2, min_predicted=0.5)
    assert search.shortfall(batch([1, 0, 0, 0], pred=[0.3, 0.9, 0.9, 0.9]), cfg) == \
        "valid 1 < 2; best predicted 0.30 < 0.5"  # invalid grasps' predictions do not count
    assert search.shortfall(batch([1, 1, 0, 0], pred=[0.3, 0.6, 0.1, 0.1]), cfg) == ""
    assert search.shortfall(batch([1, 0, 0, 0]), cfg) == "valid 1 < 2"  # ranked by E: no prediction need
    assert search.shortfall(batch([0, 0, 0, 0], pred=[0.9] * 4), SearchConfig(min_valid=0)) == \
        "no valid grasp predicted >= 0.5"
    assert search.shortfall(batch([0, 0, 0, 0], pred=[0.9] * 4), SearchConfig(min_valid=0, min_predicted=0.0)) == ""


def test_a_good_first_batch_comes_back_unchanged_with_one_round_recorded():
    first = batch([1, 1, 0, 0], pred=[0.2, 0.8, 0.1, 0.1])
    keys = []
    gs = search.further(first, SearchConfig(), 3, runner(Clock(), [], keys), Clock())
    assert keys == []  # nothing more ran
    assert set(gs.arrays) == set(first.arrays) | set(search.RECORD)
    for k, v in first.arrays.items():
        assert np.array_equal(gs[k], v), k
    assert int(gs["search_rounds"]) == 1 and float(gs["search_s"]) == 0.0 and gs["search_round"].tolist() == [0] * 4
    assert str(gs["search_why"]) == "" and str(gs["search_stop"]) == "enough"


def test_a_weak_batch_pools_rounds_until_the_need_is_met_and_keeps_the_best_n_in_the_offered_order():
    first = batch([0, 0, 0, 0], pred=[0.9, 0.1, 0.2, 0.3], tag=0.0)
    more = [batch([0, 1, 0, 0], pred=[0.5, 0.2, 0.4, 0.1], tag=10.0),
            batch([1, 0, 1, 0], pred=[0.7, 0.05, 0.6, 0.1], tag=20.0), batch([1, 1, 1, 1], pred=[0.9] * 4)]
    clock, keys = Clock(), []
    gs = search.further(first, SearchConfig(min_valid=2, min_predicted=0.5), 5, runner(clock, more, keys), clock)
    # round 1 holds one valid grasp (0.2): short; round 2 brings two more, the best at 0.7: enough, round 3 unused
    assert int(gs["search_rounds"]) == 3 and len(keys) == 2 and str(gs["search_stop"]) == "enough"
    assert str(gs["search_why"]) == "valid 0 < 2"  # the first batch's shortfall
    # the best 4 of the 12, by valid then predicted: (r2, 0.7), (r2, 0.6), (r1, 0.2), then the invalid (r0, 0.9)
    picked = sorted(zip(gs["search_round"].tolist(), gs["q"][:, 0].tolist()))
    assert picked == [(0, 0.0), (1, 11.0), (2, 20.0), (2, 22.0)]
    assert gs["valid"].sum() == 3
    # kept in pool order; the offered order is the ranking of the pool restricted to them
    assert gs["search_round"].tolist() == sorted(gs["search_round"].tolist())
    assert gs.order().tolist() == [2, 3, 1, 0]
    assert float(gs["search_s"]) == 2.0 and float(gs["synthesis_s"]) == pytest.approx(0.75 * 3)
    assert gs.trace["E"].shape == (3, 4) and gs.trace["E"][0].tolist() == [0.0, 10.0, 20.0, 20.0]
    assert gs["channel_names"].tolist() == ["a", "b"]
    # each round's key is the seed's key with the round folded in; round 0 is the plain seed's
    assert np.array_equal(keys[0], jax.random.fold_in(jax.random.PRNGKey(5), 1))
    assert np.array_equal(keys[1], jax.random.fold_in(jax.random.PRNGKey(5), 2))
    assert np.array_equal(search.round_key(5, 0), jax.random.PRNGKey(5))


@pytest.mark.parametrize("budget, first_s, round_s, want_rounds", [
    (0.0, 1.0, [1.0] * 5, 1),  # no budget: the first batch alone
    (2.5, 1.0, [1.0] * 5, 3),  # 1 + 1 fit in 2.5, a third would not
    (3.0, 1.0, [1.0] * 5, 4),  # exactly fits: 3 further batches
    (3.0, 1.0, [2.9, 1.0, 1.0], 2),  # the first further batch ran slow: 2.9 + 2.9 > 3, stop
    (3.0, 0.5, [4.0, 1.0, 1.0], 2),  # estimated 0.5 s, took 4 s: over the budget by less than that batch
    (100.0, 1.0, [1.0] * 10, 5),  # max_rounds binds
])
def test_a_batch_starts_only_when_it_is_expected_to_fit_in_the_budget(budget, first_s, round_s, want_rounds):
    first = batch([0] * N, seconds=first_s)
    more = [batch([0] * N, seconds=s, tag=i + 1) for i, s in enumerate(round_s)]
    clock, keys = Clock(), []
    gs = search.further(first, SearchConfig(min_valid=1, max_rounds=5, budget=budget), 0,
                        runner(clock, more, keys), clock)
    rounds, spent = int(gs["search_rounds"]), float(gs["search_s"])
    assert rounds == want_rounds and spent == pytest.approx(sum(round_s[:rounds - 1]))
    # never past the budget by more than the last batch's own time
    assert spent <= budget + (round_s[rounds - 2] if rounds > 1 else 0.0)
    assert str(gs["search_stop"]).startswith("max_rounds" if want_rounds == 5 else "budget")
    assert str(gs["search_why"]) == "valid 0 < 1"


def test_given_poses_search_no_further_and_say_why():
    gs = search.further(batch([0] * N), SearchConfig(), 0, None, Clock())
    assert int(gs["search_rounds"]) == 1 and str(gs["search_stop"]).startswith("given poses")


def test_the_search_settings_are_checked_in_one_line():
    with pytest.raises(FfcgsError, match=r"search.min_valid \(5\) must be at most n \(4\)"):
        GraspConfig(n=4, search=SearchConfig(min_valid=5)).check()
    for bad, msg in ((dict(max_rounds=0), "search.max_rounds must be an integer in"),
                     (dict(min_predicted=1.5), "search.min_predicted must be in"),
                     (dict(budget=-1.0), "search.budget must be in")):
        with pytest.raises(FfcgsError, match=msg):
            SearchConfig(**bad).check()


def test_a_file_from_before_the_search_loads_without_a_record():
    gs = fj.load_grasps(BEFORE)
    # made before the search and the projection existed: its config says it was made without them
    assert "search_round" not in gs and gs.config.search == SearchConfig(max_rounds=1)
    assert gs.config.optim.project_steps == 0


# ------------------------------------------------------------------------------- through fj.synthesize (toy hand)

CFG = GraspConfig(n=N, seed=3, sdf=SDFConfig(res=16), optim=OptimConfig(iters=5))
OFF = dataclasses.replace(CFG, search=SearchConfig(max_rounds=1))


@pytest.fixture(scope="module")
def toy():
    hand, mesh = fj.load_hand(TOY), fj.load_mesh("box")
    return hand, mesh, fj.synthesize(hand, mesh, OFF)  # compiles what every call below reuses


@pytest.mark.e2e  # one toy-hand synthesis compiled: about 30 s on a loaded 2-core CPU
def test_an_object_whose_first_batch_suffices_gets_exactly_todays_grasps(toy):
    hand, mesh, off = toy
    need = SearchConfig(min_valid=int(off["valid"].sum()), budget=60.0)  # met by the first batch, whatever it is
    gs = fj.synthesize(hand, mesh, dataclasses.replace(CFG, search=need))
    assert int(gs["search_rounds"]) == 1 and str(gs["search_stop"]) == "enough"
    timings = {"synthesis_s", "evaluation_s", "compile_s", "sdf_s", "total_s"}
    assert set(gs.arrays) == set(off.arrays)  # the search off (max_rounds 1) records too
    assert gs["search_round"].tolist() == [0] * N
    for k in set(off.arrays) - timings - {"search_s", "search_why", "search_stop"}:
        assert np.array_equal(gs[k], off[k], equal_nan=gs[k].dtype.kind == "f"), k  # bit for bit (NaN: no contact)


@pytest.mark.e2e
def test_a_hard_case_searches_through_the_same_executables_and_round_trips_its_record(toy, tmp_path):
    hand, mesh, off = toy
    before = len(G.compiled_executables())
    hard = dataclasses.replace(CFG, search=SearchConfig(min_valid=N, max_rounds=3, budget=600.0))
    search.round_key(CFG.seed, 1)  # fold_in's own tiny kernel compiles at its first use in a process: not ours
    with compile_clock.compiling() as compiled_s:
        gs = fj.synthesize(hand, mesh, hard)
    assert compiled_s[0] == 0.0 and len(G.compiled_executables()) == before  # no compile: only the key changed
    rounds = int(gs["search_rounds"])
    assert int(off["valid"].sum()) < N and str(gs["search_why"]) == f"valid {int(off['valid'].sum())} < {N}"
    assert rounds == 3 or (rounds < 3 and gs["valid"].all())
    assert gs["search_round"].max() <= rounds - 1 and len(gs["valid"]) == N
    # the pooled best N: at least as many valid as the first batch, and its first batch's rows are that batch's
    assert gs["valid"].sum() >= off["valid"].sum()
    for i in np.flatnonzero(gs["search_round"] == 0):
        row = np.flatnonzero((off["wrist_pose"] == gs["wrist_pose"][i]).all(axis=(1, 2)))
        assert len(row) == 1 and np.array_equal(off["q"][row[0]], gs["q"][i])
    assert ranking.ranked(gs.arrays).tolist() == gs.order().tolist()
    assert 0 < float(gs["search_s"]) <= float(gs["total_s"])
    fj.save_grasps(gs, tmp_path / "g.npz")
    back = fj.load_grasps(tmp_path / "g.npz")
    for k in search.RECORD:
        assert np.array_equal(back[k], gs[k]), k
    assert back.config.search == hard.search and back.order().tolist() == gs.order().tolist()
