"""The trust report's scoring (bench.trust) on small scenes."""

import argparse

import pytest

from bench import trust
from bench.scenes import make_unrelated_pair
from bench.trust import Case, run_case, summarize


def test_an_unrelated_pair_is_refused_or_unreliable():
    row = run_case(Case("u", "unrelated",
                        lambda: make_unrelated_pair(0, size=(200, 150), supersample=1)))
    assert row["verdict"] in ("refused", "unreliable")


def test_summary_counts_wrong_pairs_by_source_verdict_moves_epipolar_and_mostly_wrong_good():
    rows = [
        {"name": "a", "group": "polyhedral", "status": "successful", "verdict": "good",
         "points": 90, "inserted": 10, "wrong": 1, "wrong_share": 0.01, "epe_mean": 1.0,
         "wrong_by_source": {"matched": [0, 90], "step": [1, 10]},
         "corrected": {"correct": [3, 2, 1]}, "epipolar_p90": 0.4},
        {"name": "b", "group": "polyhedral", "status": "successful", "verdict": "doubtful",
         "points": 10, "wrong": 8, "wrong_share": 0.8, "epe_mean": 30.0,
         "wrong_by_source": {"matched": [8, 10]},
         "corrected": {"correct": [1, 1, 0], "border": [4, 1, 2]}, "epipolar_p90": 6.0},
        {"name": "c", "group": "unrelated", "status": "successful", "verdict": "doubtful",
         "points": 5, "wrong_share": 1.0, "epe_mean": float("nan")},
    ]
    s = summarize(rows)
    assert s["wrong_pairs"] == 9 and s["kept_pairs"] == 110
    assert s["mostly_wrong_called_good"] == 0
    assert s["unrelated_not_unreliable"] == 1
    assert s["verdicts"]["good"]["cases"] == 1
    assert s["wrong_by_source"] == {"matched": [8, 100], "step": [1, 10]}
    assert s["wrong_by_verdict"] == {"good": [1, 100], "doubtful": [8, 10]}
    assert s["corrected"] == {"correct": [4, 3, 1], "border": [4, 1, 2]}
    assert s["epipolar_off"] == [1, 2]
    rows[1]["verdict"] = "good"
    assert summarize(rows)["mostly_wrong_called_good"] == 1


def test_other_seeds_replace_the_scene_seeds_and_keep_the_families():
    default = trust.build_cases()
    other = trust.build_cases(seeds=(2, 3))
    scenes = [c.name for c in other if c.group != "unrelated"]
    assert scenes and all(name.endswith(("-s2", "-s3")) for name in scenes)
    assert len(scenes) == len([c for c in default if c.group != "unrelated"])
    assert [c.name for c in other if c.group == "unrelated"] == [
        c.name for c in default if c.group == "unrelated"]


def test_size_renders_every_case_at_that_size_and_names_it():
    default = trust.build_cases(quick=True, seeds=(0,))
    small = trust.build_cases(quick=True, seeds=(0,), size=(320, 240))
    assert [c.name.replace("-320x240", "") for c in small] == [c.name for c in default]
    assert all("-320x240-s" in c.name for c in small)
    assert small[0].make().reference.shape[:2] == (240, 320)
    assert small[-1].make().reference.shape[:2] == (240, 320)  # an unrelated pair


@pytest.mark.parametrize("text", ["1280", "1280x", "axb", "32x32"])
def test_a_bad_size_is_refused_saying_what_is_expected(text):
    with pytest.raises(argparse.ArgumentTypeError, match="WxH|at least"):
        trust.parse_size(text)
