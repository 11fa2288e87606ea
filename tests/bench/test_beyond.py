"""The Middlebury whole-frame comparison of bench.beyond."""

import json

from bench import beyond, middlebury


def _run(all_mean: float, nonocc_mean: float | None) -> dict:
    return {"dense_tps": {"all": {"mean_epe": all_mean}, "nonocc": {"mean_epe": nonocc_mean}}}


def test_the_peer_figure_is_the_best_run_over_the_mask_asked_for(tmp_path, monkeypatch):
    real = tmp_path / "data" / "real"
    real.mkdir(parents=True)
    peer = tmp_path / "peers" / "arosics"
    peer.mkdir(parents=True)
    runs = [_run(0.9, 0.8), _run(0.7, 0.85), {"dense_tps": None}, _run(0.95, None)]
    (peer / "results.json").write_text(json.dumps({"pairs": {"venus": {"runs": runs}}}))
    monkeypatch.setenv(middlebury.ENV_VAR, str(real))
    # Each mask's own best: another run is best over the other mask.
    assert beyond._arosics_best("venus", "all") == 0.7
    assert beyond._arosics_best("venus", "nonocc") == 0.8
    assert beyond._arosics_best("teddy", "all") is None
