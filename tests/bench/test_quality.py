"""The quality report machinery on one tiny synthetic case (same code path as the full run)."""

from __future__ import annotations

import json

import numpy as np

from bench import quality
from bench.metrics import disparity_correctness


def test_one_tiny_case_through_the_report(tmp_path):
    case = quality._synthetic("open_book", seed=1, condition=1, size=(200, 150))
    row = quality.run_case(case, tmp_path)
    assert set(row["optimizers"]) == {label for label, _ in quality.OPTIMIZERS}
    for label, o in row["optimizers"].items():
        assert o["endpoint_error"]["n"] > 0
        assert 0.0 <= o["correctness"]["correctness"] <= 1.0
        assert len(o["convergence"]) == o["swaps"] + 1
        if label == "delaunay":
            assert o["swaps"] == 0
    md = quality.write_report([row], tmp_path, elapsed=1.0, quick=True, env=quality._environment())
    assert "## Table 1" in md and "## Quality bar" in md
    assert (tmp_path / "convergence.png").stat().st_size > 0
    data = json.loads((tmp_path / "results.json").read_text())
    assert data["cases"][0]["name"] == case.name
    assert "synthetic" in data["quality_bar"]


def test_disparity_correctness_on_a_step():
    # Two fronto-parallel planes (disparity 5 left of x = 50, 15 right): an edge crossing the
    # step is incompatible, edges on one side are compatible.
    disparity = np.where(np.arange(100)[None, :] < 50, 5.0, 15.0).repeat(60, axis=0)
    ref = np.array([[10.0, 10], [40, 10], [10, 50], [40, 50], [70, 10], [70, 50]])
    mov = ref - np.where(ref[:, :1] < 50, 5.0, 15.0) * np.array([[1.0, 0.0]])
    on_left = np.array([[0, 1, 2], [1, 3, 2]])
    across = np.array([[1, 4, 3], [4, 5, 3]])
    r = disparity_correctness(ref, mov, np.vstack([on_left, across]), disparity)
    # Internal edges: (1, 2) on the left plane, (1, 3) on the step's left side, (3, 4) across.
    assert r["internal_edges"] == 3
    assert r["incompatible_internal"] == 1


def test_draws_repeat_the_synthetic_scenes_with_other_seeds():
    own = [c for c in quality.build_cases() if c.kind == "synthetic"]
    both = [c for c in quality.build_cases(draws=(0, 2)) if c.kind == "synthetic"]
    assert [c.name for c in both[:len(own)]] == [c.name for c in own]
    again = both[len(own):]
    assert len(again) == len(own)
    step = 2 * len(quality.CONDITIONS)
    for a, b in zip(own, again, strict=True):
        assert b.name == a.name.replace(f"-s{a.params['seed']}", f"-s{a.params['seed'] + step}")
        assert {k: v for k, v in b.params.items() if k != "seed"} == {
            k: v for k, v in a.params.items() if k != "seed"}
