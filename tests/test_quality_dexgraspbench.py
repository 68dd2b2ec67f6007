"""bench/quality.py with DexGraspBench's protocol: `--protocols` accepts it and the table gives it a column."""

import pytest

from test_quality_script import fabricated_report, quality  # noqa: F401 - quality: the script, as a fixture


def test_dexgraspbench_gets_its_own_column(quality):  # noqa: F811
    report = fabricated_report()
    report["config"]["protocols"] = ["six-dir", "dexgraspbench"]
    report["records"][0]["physics"]["dexgraspbench_success"] = [False, True]
    (s,) = quality.summarise(report)
    assert s["success"]["dexgraspbench"] == (1, 2)
    header, rule, row = quality.table(report).splitlines()[:3]
    cols = [c.strip() for c in header.strip("|").split("|")]
    assert cols[6:10] == ["lift-shake", "six-dir", "dexgraspbench", "both"]
    assert rule.count("---") == len(cols) == row.strip("|").count("|") + 1
    assert row.split("|")[9].strip().startswith("1 / 2 = 50.0 %")


@pytest.mark.parametrize("given,expect", [("dexgraspbench-bodex,six-dir", ["six-dir", "dexgraspbench-bodex"])])
def test_protocols_flag_accepts_the_benchmark(quality, given, expect):  # noqa: F811
    args = quality.parse_args(["--objects", "builtin", "--protocols", given])
    assert args.protocol_list == expect
