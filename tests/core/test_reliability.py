"""Correlation uniqueness and neighbourhood checks (core.reliability)."""

import cv2
import numpy as np
import pytest

from pwlreg.core.matching import find_conjugate_points
from pwlreg.core.options import RegistrationOptions
from pwlreg.core.reliability import neighbour_outliers, uniqueness


def _texture(shape, seed, period=None):
    rng = np.random.default_rng(seed)
    h, w = shape
    if period is None:
        small = rng.random((h // 4, w // 4)).astype(np.float32)
        tex = cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)
    else:
        yy, xx = np.mgrid[0:h, 0:w]
        tex = (((xx // period) + (yy // period)) % 2).astype(np.float32)
        tex += 0.02 * rng.standard_normal((h, w)).astype(np.float32)
    tex = (tex - tex.min()) / (tex.max() - tex.min())
    return np.round(tex * 255).astype(np.uint8)


def _shifted(image, dx, dy, noise, seed):
    M = np.float32([[1, 0, dx], [0, 1, dy]])
    out = cv2.warpAffine(image, M, image.shape[::-1], borderMode=cv2.BORDER_REFLECT)
    rng = np.random.default_rng(seed)
    return np.clip(out + rng.normal(0, noise, out.shape), 0, 255).astype(np.uint8)


def test_true_pairs_on_a_distinct_texture_pass():
    ref = _texture((240, 320), 0)
    mov = _shifted(ref, 7.0, -4.0, 3.0, 1)
    pts = np.random.default_rng(2).uniform([20, 20], [300, 220], (60, 2))
    check = uniqueness(ref, mov, pts, pts + [7.0, -4.0], None)
    assert check.ok.mean() > 0.9


def test_pairs_off_by_one_period_of_a_checkerboard_are_ambiguous():
    period = 24
    ref = _texture((240, 320), 0, period=period)
    mov = _shifted(ref, 5.0, 3.0, 4.0, 1)
    pts = np.random.default_rng(2).uniform([20, 20], [300, 220], (60, 2))
    wrong = pts + [5.0 + period, 3.0]  # locked on the next copy of the pattern
    check = uniqueness(ref, mov, pts, wrong, None)
    assert not check.ok.any()
    # Inside a flat square the fine scale already disagrees; elsewhere the copies tie.
    assert check.counts().get("ambiguous", 0) >= 10
    assert set(check.counts()) <= {"ambiguous", "disagreement"}
    right = uniqueness(ref, mov, pts, pts + [5.0, 3.0], None)
    assert not right.ok.any()  # even the true pairs cannot be told from their copies


def test_a_pair_the_matcher_misplaced_disagrees_with_the_correlation_peak():
    ref = _texture((240, 320), 3)
    mov = _shifted(ref, 0.0, 0.0, 2.0, 4)
    pts = np.array([[100.0, 100.0], [200.0, 150.0]])
    check = uniqueness(ref, mov, pts, pts + [[4.0, 0.0], [0.0, 0.0]], None)
    assert check.cause.tolist() == ["disagreement", ""]


def test_neighbour_check_drops_a_planted_outlier_and_keeps_a_depth_step():
    rng = np.random.default_rng(0)
    ref = rng.uniform(0, 400, (200, 2))
    # Two planes: a disparity step of 15 px at x = 200.
    mov = ref + np.where(ref[:, :1] < 200, [[5.0, 0.0]], [[20.0, 0.0]])
    mov += rng.normal(0, 0.3, mov.shape)
    mov[17] += [9.0, -6.0]
    out = neighbour_outliers(ref, mov)
    assert out[17]
    assert out.sum() <= 3  # a few points right at the step at most


def test_automatic_matching_refuses_a_checkerboard_seen_off_by_a_period():
    """The failure of issue 9: a plane of consistently shifted matches passed every filter."""
    ref = _texture((480, 640), 5, period=40)
    mov = _shifted(ref, 40.0 + 6.0, 2.0, 5.0, 6)  # the truth is 46 px: the prior can lock on 6
    try:
        cp = find_conjugate_points(ref, mov, RegistrationOptions())
    except ValueError as exc:
        assert "pairs" in str(exc)
        return
    err = np.linalg.norm(cp.moving - cp.reference - [46.0, 2.0], axis=1)
    assert np.mean(err > 3) < 0.01, cp.rejected


@pytest.mark.parametrize("k", [3, 4])
def test_neighbour_check_needs_enough_points(k):
    ref = np.random.default_rng(0).uniform(0, 100, (k, 2))
    assert not neighbour_outliers(ref, ref + 1).any()


def test_ambiguous_pairs_confirmed_by_their_anchors_are_resolved_but_a_period_off_are_not():
    from pwlreg.core.reliability import resolved_by_anchors

    rng = np.random.default_rng(3)
    A = np.array([[1.02, 0.03], [-0.02, 0.98]])

    def truth(p):
        return p @ A.T + [12.0, -4.0]

    anchors = rng.uniform(0, 300, (80, 2))
    ambiguous = rng.uniform(20, 280, (30, 2))
    right = truth(ambiguous) + rng.normal(0, 0.2, (30, 2))
    off = right + [24.0, 0.0]  # the next copy of the pattern
    anchor_mov = truth(anchors) + rng.normal(0, 0.2, (80, 2))
    assert resolved_by_anchors(anchors, anchor_mov, ambiguous, right).mean() > 0.9
    assert not resolved_by_anchors(anchors, anchor_mov, ambiguous, off).any()
    # Without anchors nothing is resolved.
    assert not resolved_by_anchors(anchors[:3], anchor_mov[:3], ambiguous, right).any()
