"""Correlation uniqueness and neighbourhood checks (core.reliability)."""

import math

import cv2
import numpy as np
import pytest

from pwlreg.core import reliability
from pwlreg.core.kernels import affine_fits, trimmed_affine_fits
from pwlreg.core.matching import find_conjugate_points
from pwlreg.core.options import RegistrationOptions
from pwlreg.core.reliability import (
    AFFINE_RIDGE,
    MIN_TEMPLATE_STD,
    neighbour_outliers,
    uniqueness,
    unjudged_pairs,
)


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


def test_neighbour_check_of_some_pairs_judges_them_as_the_whole_check_does():
    rng = np.random.default_rng(1)
    ref = rng.uniform(0, 400, (300, 2))
    mov = ref + [4.0, 1.0] + rng.normal(0, 0.3, ref.shape)
    bad = rng.choice(300, 30, replace=False)
    mov[bad] += rng.uniform(-12, 12, (30, 2))  # wrong enough that some hide each other
    whole = neighbour_outliers(ref, mov)
    wanted = np.zeros(300, bool)
    wanted[200:] = True
    some = neighbour_outliers(ref, mov, wanted=wanted)
    assert whole[200:].sum() >= 5
    assert np.array_equal(some[200:], whole[200:])
    # Outside the wanted pairs only the first pass's outliers are reported.
    assert some[:200].sum() <= whole[:200].sum()


def test_a_pair_far_from_the_others_that_none_moves_like_stands_alone():
    rng = np.random.default_rng(2)
    ref = rng.uniform(0, 200, (150, 2))  # spacing about 10 px: the fits reach 40 px or so
    mov = ref + [3.0, 0.0] + rng.normal(0, 0.3, ref.shape)
    # In a gap 300 px away: a lone pair, and three that move alike (a surface of their own).
    gap_ref = np.array([[500.0, 500.0], [540.0, 100.0], [548.0, 104.0], [544.0, 96.0]])
    gap_mov = gap_ref + [[40.0, 0.0], [25.0, 0.0], [25.5, 0.2], [24.6, -0.1]]
    ref, mov = np.concatenate([ref, gap_ref]), np.concatenate([mov, gap_mov])
    wanted = np.zeros(len(ref), bool)
    wanted[[0, 150, 151]] = True
    alone = unjudged_pairs(ref, mov, wanted=wanted)
    assert alone[150]  # nothing near, nothing moving like it
    assert not alone[151]  # two neighbours move like it
    assert not alone[0]  # among the others: the neighbour check judges it
    assert not alone[~wanted].any()  # only the wanted pairs are reported
    # Neither the neighbour check can judge: it leaves both in.
    assert not neighbour_outliers(ref, mov)[150:].any()


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


# The per-point OpenCV code that core.kernels.template_peaks replaced, kept as the reference of
# _check_scale (same signature and outputs).
_KERNEL3 = np.ones((3, 3), np.uint8)


def _reference_peaks(surface, centre):
    _, best, _, loc = cv2.minMaxLoc(surface)
    mask = cv2.compare(surface, cv2.dilate(surface, _KERNEL3), cv2.CMP_GE)
    cv2.circle(mask, loc, 2, 0, -1)
    second = cv2.minMaxLoc(surface, mask)[1] if cv2.countNonZero(mask) else -1.0
    return best, second, math.hypot(loc[0] - centre[0], loc[1] - centre[1])


def _reference_check_scale(ref, warped, ref_pts, pred_pts, template, radius, todo=None,
                           match=cv2.matchTemplate):
    n = len(ref_pts)
    best = np.full(n, np.nan)
    ratio = np.full(n, np.nan)
    dist = np.full(n, np.inf)
    flat = np.zeros(n, bool)
    half = template // 2
    h, w = ref.shape
    hw, ww = warped.shape
    if h < template or w < template:
        return best, ratio, dist, flat
    r = np.rint(ref_pts).astype(np.int64)
    r[:, 0] = np.clip(r[:, 0], half, w - 1 - half)
    r[:, 1] = np.clip(r[:, 1], half, h - 1 - half)
    expect = pred_pts + (r - ref_pts)
    p = np.rint(expect).astype(np.int64)
    inside = np.all(np.abs(r - ref_pts) <= half + 1, axis=1)
    if todo is not None:
        inside &= todo
    for i in np.flatnonzero(inside).tolist():
        rx, ry = r[i]
        px, py = p[i]
        tpl = ref[ry - half : ry + half + 1, rx - half : rx + half + 1]
        side = 2 * (radius + half) + 1
        if side > ww or side > hw:
            continue
        x0 = min(max(px - radius - half, 0), ww - side)
        y0 = min(max(py - radius - half, 0), hw - side)
        x1, y1 = x0 + side, y0 + side
        if cv2.meanStdDev(tpl)[1][0, 0] < MIN_TEMPLATE_STD:
            flat[i] = True
            continue
        surface = match(warped[y0:y1, x0:x1], tpl, cv2.TM_CCOEFF_NORMED)
        centre = (expect[i, 0] - half - x0, expect[i, 1] - half - y0)
        b, s, d = _reference_peaks(surface, centre)
        best[i] = b
        ratio[i] = s / b if b > 0 else np.inf
        dist[i] = d
    return best, ratio, dist, flat


def _exact_match(window, template, method):
    """cv2.matchTemplate's TM_CCOEFF_NORMED in float64 from exact sums, stored in float32."""
    assert method == cv2.TM_CCOEFF_NORMED
    w = np.lib.stride_tricks.sliding_window_view(window.astype(np.float64), template.shape)
    t = template.astype(np.float64)
    n = t.size
    sw, sww = w.sum(axis=(2, 3)), (w * w).sum(axis=(2, 3))
    num = n * np.einsum("ijkl,kl->ij", w, t) - sw * t.sum()
    var_w = n * sww - sw * sw
    with np.errstate(divide="ignore", invalid="ignore"):
        c = np.clip(num / np.sqrt(var_w * (n * (t * t).sum() - t.sum() ** 2)), -1.0, 1.0)
    return np.where(var_w > 0, c, 0.0).astype(np.float32)


def _exact_check_scale(*args):
    return _reference_check_scale(*args, match=_exact_match)


def _flat_patches(image, seed):
    """``image`` with flat rectangles (black, mid-grey, white) pasted in."""
    out = image.copy()
    rng = np.random.default_rng(seed)
    h, w = out.shape
    for level in (0, 128, 255, 37):
        x, y = rng.integers(0, w - 60), rng.integers(0, h - 50)
        out[y : y + int(rng.integers(20, 50)), x : x + int(rng.integers(20, 60))] = level
    return out


def _cases():
    """Image pairs, pairs of points and a prior: distinct and repeated textures, flat areas, a
    homography, points at and beyond the borders."""
    rng = np.random.default_rng(11)
    shape = (240, 320)
    border = np.array([[0.0, 0.0], [319.0, 239.0], [0.4, 120.0], [160.0, 239.4], [3.0, 5.0],
                       [316.0, 2.0], [-2.0, 100.0], [330.0, 50.0], [160.0, -9.0], [5.0, 236.0]])
    inner = rng.uniform([0, 0], [319, 239], (150, 2))
    pts = np.concatenate([border, inner])
    tex = _texture(shape, 0)
    yield "texture", tex, _shifted(tex, 7.0, -4.0, 3.0, 1), pts, pts + [7.0, -4.0], None
    wrong = pts + [7.0, -4.0] + rng.normal(0, 2.0, pts.shape)
    yield "texture, noisy pairs", tex, _shifted(tex, 7.0, -4.0, 3.0, 1), pts, wrong, None
    board = _texture(shape, 2, period=24)
    yield "checkerboard", board, _shifted(board, 5.0, 3.0, 4.0, 3), pts, pts + [29.0, 3.0], None
    shifted = _shifted(board, 5.0, 3.0, 4.0, 3)
    yield "checkerboard, right", board, shifted, pts, pts + [5.0, 3.0], None
    flat = _flat_patches(tex, 5)
    moved = _flat_patches(_shifted(tex, 2.0, 1.0, 2.0, 6), 5)
    yield "flat areas", flat, moved, pts, pts + 1.5, None
    H = np.array([[1.02, 0.03, 6.0], [-0.02, 0.99, -3.0], [1e-5, 2e-5, 1.0]])
    mov = cv2.warpPerspective(tex, H, shape[::-1], borderMode=cv2.BORDER_REFLECT)
    q = np.column_stack([pts, np.ones(len(pts))]) @ H.T
    yield "homography", tex, mov, pts, q[:, :2] / q[:, 2:], H
    yield "homography, identity prior", tex, mov, pts, q[:, :2] / q[:, 2:], None


def _clean_checkerboard():
    """Two levels and no noise: copies of a template correlate exactly alike (tied peaks)."""
    board = np.where(_texture((240, 320), 4, period=16) > 127, 200, 40).astype(np.uint8)
    pts = np.random.default_rng(12).uniform([0, 0], [319, 239], (120, 2))
    return "clean checkerboard", board, np.roll(board, 3, axis=1), pts, pts + [3.0, 0.0], None


def _both(monkeypatch, case, reference):
    """Causes from uniqueness with the kernel and with ``reference`` as _check_scale, and the
    outputs of both on every call uniqueness makes."""
    _, ref, mov, a, b, H = case
    kernel = reliability._check_scale
    calls = []

    def both(*args):
        calls.append((reference(*args), kernel(*args)))
        return calls[-1][1]

    monkeypatch.setattr(reliability, "_check_scale", both)
    got = uniqueness(ref, mov, a, b, H)
    monkeypatch.setattr(reliability, "_check_scale", reference)
    want = uniqueness(ref, mov, a, b, H)
    assert len(calls) == 2  # the fine scale and one coarse level
    assert sum(np.isfinite(c[0][0]).sum() for c in calls) > 100
    return got.cause.tolist(), want.cause.tolist(), calls


@pytest.mark.parametrize("case", list(_cases()), ids=lambda c: c[0])
def test_check_scale_decides_as_the_per_point_opencv_code(monkeypatch, case):
    """Same causes, flags and peak distances as OpenCV's per-point surfaces on every call
    uniqueness makes; the values differ only by OpenCV's rounding."""
    got, want, calls = _both(monkeypatch, case, _reference_check_scale)
    assert got == want
    for (best, ratio, dist, flat), (best_k, ratio_k, dist_k, flat_k) in calls:
        np.testing.assert_array_equal(flat_k, flat)
        np.testing.assert_array_equal(dist_k, dist)
        # OpenCV sums the cross products in float32 and rounds (the kernel's sums are exact):
        # under 2e-5 on the textures here, 3e-4 (best) and 9e-4 (ratio) on the checkerboard,
        # whose low contrast over bright squares cancels more; 1.4e-3 (ratio) with OpenCV 5.0,
        # whose float32 sums round differently.
        np.testing.assert_allclose(best_k, best, rtol=0, atol=1e-3)
        np.testing.assert_allclose(ratio_k, ratio, rtol=0, atol=2e-3)


@pytest.mark.parametrize("case", [*_cases(), _clean_checkerboard()], ids=lambda c: c[0])
def test_check_scale_is_the_per_point_code_on_exact_surfaces(monkeypatch, case):
    """Bit for bit the per-point code (cv2.minMaxLoc, dilate, circle) run on exact correlation
    surfaces, tied peaks included: the first in row-major order is the best. (OpenCV's rounding
    breaks such ties at random: on the clean checkerboard its best peak is elsewhere for 17 of
    104 pairs of the fine scale, though no decision changes here.)"""
    got, want, calls = _both(monkeypatch, case, _exact_check_scale)
    assert got == want
    for reference, kernel in calls:
        for a, b in zip(kernel, reference, strict=True):
            np.testing.assert_array_equal(a, b)


def test_the_circle_cleared_around_the_best_peak_is_the_kernels_diamond():
    """core.kernels.template_peaks skips ``|dx| + |dy| <= 2`` around the best peak: the pixels
    cv2.circle of radius 2 fills, clipped at the borders alike."""
    yy, xx = np.mgrid[0:9, 0:9]
    for loc in [(4, 4), (0, 0), (8, 3), (1, 7)]:
        mask = np.full((9, 9), 255, np.uint8)
        cv2.circle(mask, loc, 2, 0, -1)
        np.testing.assert_array_equal(mask == 0, np.abs(xx - loc[0]) + np.abs(yy - loc[1]) <= 2)


def test_low_texture_flag_follows_opencv_at_the_threshold():
    """Templates with a standard deviation on either side of MIN_TEMPLATE_STD (to the last
    bit of cv2.meanStdDev) are flagged as OpenCV flags them."""
    rng = np.random.default_rng(3)
    ref = np.zeros((40, 40 * 60), np.uint8)
    for k in range(60):
        amp = 1 + k % 5
        ref[:, 40 * k : 40 * k + 40] = np.clip(120 + rng.integers(-amp, amp + 1, (40, 40)), 0, 255)
    pts = np.array([[40.0 * k + 20, 20.0] for k in range(60)])
    for template, radius in [(11, 10), (15, 3)]:
        _, _, _, flat_k = reliability._check_scale(ref, ref, pts, pts, template, radius)
        _, _, _, flat = _reference_check_scale(ref, ref, pts, pts, template, radius)
        np.testing.assert_array_equal(flat_k, flat)
        assert 0 < flat.sum() < len(pts)


def _numpy_affine(X, Y, weight, ridge):
    Xw = X * weight[:, :, None]
    XtX = np.matmul(Xw.transpose(0, 2, 1), X) + ridge * np.eye(3)
    return np.linalg.solve(XtX, np.matmul(Xw.transpose(0, 2, 1), Y))


def _numpy_local_fits(offsets, moving, near, min_px):
    """The numpy form the compiled fits replaced: batched normal equations, LAPACK's solve."""
    n, k = near.shape
    X = np.concatenate([offsets, np.ones((n, k, 1))], axis=2)

    def median(values):
        ordered = np.sort(np.where(near, values, np.inf), axis=1)
        count = near.sum(axis=1)
        rows = np.arange(n)
        lo = ordered[rows, np.maximum(count - 1, 0) // 2]
        hi = ordered[rows, np.minimum(count // 2, k - 1)]
        return np.where(count > 0, 0.5 * (lo + hi), 0.0)

    weight = near.astype(np.float64)
    for _ in range(2):
        A = _numpy_affine(X, moving, weight, AFFINE_RIDGE)
        res = np.linalg.norm(np.matmul(X, A) - moving, axis=2)
        weight = (near & (res <= np.maximum(min_px, 2.5 * median(res)[:, None]))).astype(float)
    A = _numpy_affine(X, moving, weight, AFFINE_RIDGE)
    return A, median(np.linalg.norm(np.matmul(X, A) - moving, axis=2))


def test_compiled_affine_fits_match_the_numpy_form():
    # Neighbourhoods on a plane with noise, some neighbours wrong by 5-40 px, some far (not
    # near), a few with fewer than three near neighbours (the ridge keeps them solvable).
    rng = np.random.default_rng(3)
    n, k = 400, 10
    offsets = rng.uniform(-30, 30, (n, k, 2))
    affine = rng.normal(0, 0.1, (n, 3, 2)) + np.array([[1, 0], [0, 1], [0, 0]])
    affine[:, 2] = rng.uniform(-50, 50, (n, 2))
    moving = np.einsum("nkj,njc->nkc", offsets, affine[:, :2]) + affine[:, 2][:, None, :]
    moving += rng.normal(0, 0.4, moving.shape)
    wrong = rng.random((n, k)) < 0.15
    moving[wrong] += rng.uniform(5, 40, (wrong.sum(), 2)) * rng.choice([-1, 1], (wrong.sum(), 2))
    near = rng.random((n, k)) < 0.85
    near[:20, 2:] = False
    A, spread = trimmed_affine_fits(offsets, moving, near, 3.0, AFFINE_RIDGE)
    A_np, spread_np = _numpy_local_fits(offsets, moving, near, 3.0)
    # Where a pair is judged (five near neighbours or more) the two agree to rounding; the
    # ridge's fits of two neighbours are ill-conditioned (about 1e9) and only finite.
    judged = near.sum(axis=1) >= 5
    assert judged.sum() > 300 and np.isfinite(A).all()
    assert np.allclose(A[judged], A_np[judged], rtol=1e-9, atol=1e-9)
    assert np.allclose(spread[judged], spread_np[judged], rtol=1e-9, atol=1e-9)
    # The untrimmed fits with weights of any size (the frame's extrapolation).
    weight = np.where(near, rng.uniform(0.1, 1.0, near.shape), 0.0)
    X = np.concatenate([offsets, np.ones((n, k, 1))], axis=2)
    assert np.allclose(affine_fits(offsets[judged], moving[judged], weight[judged], 1e-9),
                       _numpy_affine(X, moving, weight, 1e-9)[judged], rtol=1e-9, atol=1e-9)
    # The trimming drops a wrong neighbour: with one among seven or more right ones the map is
    # mostly within a pixel of the true one (a far outlier can bend the first fit past
    # recovery).
    good = ((near & ~wrong).sum(axis=1) >= 7) & ((near & wrong).sum(axis=1) == 1)
    close = np.abs(A[good] - affine[good]).max(axis=(1, 2)) < 1.0
    assert good.sum() > 50 and close.mean() > 0.9


def test_pairs_still_where_the_scene_moves_are_fixed_in_the_frame():
    ref = np.array([[10.0, 10.0], [50.0, 50.0], [90.0, 20.0], [30.0, 70.0], [60.0, 60.0]])
    mov = ref + [[0.3, -0.2], [0.0, 0.0], [2.0, 0.0], [0.1, 0.1], [0.0, 0.4]]
    predicted = ref + [[7.0, -4.0], [1.5, 0.0], [7.0, -4.0], [np.nan, np.nan], [-3.0, 0.0]]
    # Still under a moving prediction: fixed. Still where the scene barely moves, moving
    # itself, or without a prediction: not.
    assert reliability.fixed_in_frame(ref, mov, predicted).tolist() == [
        True, False, False, False, True]
