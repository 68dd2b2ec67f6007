"""The summary says why grasps are not valid, and a d0 deeper than the touching band is said before the compile."""

import warnings

import numpy as np
import pytest

import ffcgs_jax as fj
from ffcgs_jax.synthesis import grasp


def _arrays(n=4, tips=4):
    return {"valid": np.ones(n, bool), "contacts": np.zeros((n, tips, 3)), "penetration": np.zeros(n),
            "n_contacts": np.full(n, tips), "force_closure": np.ones(n, bool), "E_c": np.zeros(n),
            "pose_collides": np.zeros(n, bool), "palm_up": np.zeros(n, bool), "tips_below_table": np.zeros(n, bool),
            "lp_ok": np.ones(n, bool)}


def test_rejections_count_each_failed_filter_of_the_invalid_grasps():
    a = _arrays()
    a["penetration"][[0, 1, 2]] = 0.02  # three deeper than the 1 cm max_penetration
    a["n_contacts"][1] = 2
    a["palm_up"][3] = True  # valid stays True for grasp 3: a valid grasp's flags are not counted
    a["valid"][[0, 1, 2]] = False
    gs = fj.GraspSet(a, {}, fj.GraspConfig(), "x")
    assert grasp.rejections(gs) == "hand in the object 3, tips not all touching 1"


def test_rejections_of_an_old_file_without_some_flags():
    a = _arrays()
    del a["lp_ok"], a["tips_below_table"]
    a["valid"][:] = False
    a["force_closure"][:2] = False
    gs = fj.GraspSet(a, {}, fj.GraspConfig(), "x")
    assert grasp.rejections(gs) == "no force closure 2"  # the other two fail a filter the file does not record


def test_summary_has_the_reasons_row_only_when_some_grasp_is_not_valid():
    a = _arrays()
    a.update(E=np.ones(4), E_g=np.zeros(4), epsilon=np.ones(4), synthesis_s=np.array(0.1), compile_s=np.array(1.0))
    rows = dict(grasp.summary_rows(fj.GraspSet(dict(a), {}, fj.GraspConfig(), "x")))
    assert not any(k.startswith("not valid") for k in rows)
    a["valid"] = np.array([True, False, False, False])
    a["force_closure"] = a["valid"].copy()
    rows = dict(grasp.summary_rows(fj.GraspSet(a, {}, fj.GraspConfig(), "x")))
    assert rows["not valid, by reason (a grasp may have several)"] == "no force closure 3"


def test_d0_deeper_than_the_touching_band_warns_at_the_check():
    cfg = fj.GraspConfig(energy=fj.EnergyConfig(d0=0.005))
    with pytest.warns(UserWarning, match=r"d0 = 0.005 m plans the fingertips 5 mm inside.*2 mm"):
        cfg.check()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fj.GraspConfig(energy=fj.EnergyConfig(d0=0.001)).check()
