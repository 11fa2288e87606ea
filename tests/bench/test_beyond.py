"""bench.beyond against the peers: the AROSICS figure it reads and the dense optical flow."""

import json

import cv2
import numpy as np

from bench import beyond, middlebury, quality


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


def test_the_dense_flow_is_compared_over_the_baselines_apart(capsys):
    rows = [{"group": "polyhedral, wide", "epe": {"DIS": 40.0, "default": 4.0}},
            {"group": "polyhedral, wide", "epe": {"DIS": 2.0, "default": 3.0}},
            {"group": "polyhedral", "epe": {"DIS": 1.0, "default": 2.0}}]
    beyond._dense_flow_summary(rows, "default")
    lines = {line.split()[0]: " ".join(line.split())
             for line in capsys.readouterr().out.splitlines()[1:]}
    assert lines["all"].endswith("3 cases: 2.00 / 14.33 against 3.00 / 3.00; DIS lower in 2")
    assert lines["wide"].endswith("2 cases: 21.00 / 21.00 against 3.50 / 3.50; DIS lower in 1")
    assert lines["narrow"].endswith("1 cases: 1.00 / 1.00 against 2.00 / 2.00; DIS lower in 1")


def test_a_dense_flow_follows_a_small_shift():
    rng = np.random.default_rng(0)
    texture = cv2.GaussianBlur(rng.integers(0, 256, (120, 160)).astype(np.uint8), (0, 0), 1.5)
    moving = np.roll(texture, 3, axis=1)  # moving(x + 3) = reference(x)
    fx, fy = beyond.dense_flow(texture, moving)
    inner = (slice(20, -20), slice(20, -20))
    xx = np.arange(160)[None, :].repeat(120, axis=0)
    assert np.median(np.abs(fx - xx - 3)[inner]) < 0.2
    assert np.median(np.abs(fy - np.arange(120)[:, None])[inner]) < 0.2


def test_the_share_is_reported_per_imaging_condition(capsys):
    def row(condition, default):
        camera, radiometric, noise, blur = quality.CONDITIONS[condition]
        return {"params": {"camera": camera, "radiometric": radiometric, "noise": noise,
                           "blur": blur, "seed": 1},
                "epe": {"delaunay": 2.0, "default": default, "ceiling": 1.0}}

    noisy, recoloured = 5, 3  # perspective lighting (noise 4, blur 1); affine non-monotone
    rows = [row(noisy, 1.5), row(noisy, 1.0), row(noisy, 2.5), row(recoloured, 1.2)]
    beyond._condition_summary(rows, {"default": {}})
    out = [" ".join(line.split()) for line in capsys.readouterr().out.splitlines()]
    # Shares 0.5, 1.0 and -0.5 (worse than Delaunay): median 0.5, one worse.
    assert "per lighting noise 4 blur 1 (3 cases): default 0.50 / 1" in out
    assert "aff nonmonotone noise 2 blur 0 (1 cases): default 0.80 / 0" in out
    assert len(out) == 3  # the title and the two conditions with cases


def test_inserted_pairs_off_their_truth_are_counted():
    h, w = 40, 50
    xx, yy = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    truth_x, truth_y = xx + 2.0, yy.copy()  # the moving image is the reference shifted 2 px
    truth_x[:, 40:] = np.nan  # unknown there
    reference = np.array([[10.0, 10.0], [20.5, 15.5], [30.0, 30.0], [45.0, 20.0], [5.0, 5.0]])
    moving = reference + [2.0, 0.0]
    moving[1] += [0.0, 2.9]  # within the tolerance
    moving[2] += [3.0, 1.0]  # 3.2 px off
    inserted = np.array([True, True, True, True, False])
    moving[4] += 10.0  # off, but matched, not inserted
    # The fourth has no truth: three judged, one wrong.
    assert beyond.wrong_inserted(reference, moving, inserted, truth_x, truth_y) == (1, 3)
    assert beyond.wrong_inserted(reference, moving, np.zeros(5, bool), truth_x, truth_y) == (0, 0)
