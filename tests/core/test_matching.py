"""Tests of core.matching: matchers, client points, epipolar filter, spread, real pairs."""

from __future__ import annotations

import json
import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from bench import realdata
from bench.scenes import make_scene
from pwlreg.core.epipolar import (
    MIN_PAIRS,
    PARALLAX_SUPPORT,
    PLANE_PX,
    epipolar_lines,
    line_direction,
    plane_homography,
    transfer_distance,
)
from pwlreg.core.errors import InputError, NotEnoughPointsError
from pwlreg.core.imaging import matching_image
from pwlreg.core.matching import (
    _LK_CRITERIA,
    LISTED_AUTOMATIC,
    LISTED_CLIENT,
    ConjugatePoints,
    _lk_pair,
    detect_corners,
    estimate_global_prior,
    find_conjugate_points,
    fixed_in_frame_pairs,
    match_lk,
    match_sift,
    spread_points,
)
from pwlreg.core.options import RegistrationOptions
from pwlreg.core.pipeline import register
from pwlreg.core.scaled import register as register_on_levels
from tests.core.synthetic import captioned

MAX_INLIER_LOSS = 0.01  # stated rate for client points with 0.3 px noise at a 1.5 px threshold


# --- synthetic pairs with known correspondences -------------------------------------------------


def texture(shape=(360, 480), seed=0) -> np.ndarray:
    """Grey uint8 texture with corners at several scales (blurred noise plus blocks)."""
    rng = np.random.default_rng(seed)
    h, w = shape
    img = np.zeros(shape, np.float64)
    for sigma, weight in ((1.2, 1.0), (3.0, 1.0), (8.0, 0.7)):
        layer = cv2.GaussianBlur(rng.normal(0, 1, shape), (0, 0), sigma)
        img += weight * layer / layer.std()
    for _ in range(80):
        x, y = rng.integers(0, w - 20), rng.integers(0, h - 20)
        img[y : y + rng.integers(5, 20), x : x + rng.integers(5, 20)] += rng.normal(0, 1.5)
    img = np.clip(img, -4, 4)
    img = (img - img.min()) / (img.max() - img.min())
    return np.round(255 * img).astype(np.uint8)


def homography(angle_deg=6.0, scale=0.95, tx=12.0, ty=-8.0, px=2e-5, centre=(240, 180)):
    """Homography about ``centre`` (reference -> moving pixels)."""
    a = np.deg2rad(angle_deg)
    c = np.array([[1, 0, centre[0]], [0, 1, centre[1]], [0, 0, 1.0]])
    S = np.array(
        [
            [scale * np.cos(a), -scale * np.sin(a), tx],
            [scale * np.sin(a), scale * np.cos(a), ty],
            [px, 0, 1],
        ]
    )
    return c @ S @ np.linalg.inv(c)


def warp(image: np.ndarray, H: np.ndarray, size=None) -> np.ndarray:
    """Moving image such that moving(H x) = reference(x)."""
    h, w = image.shape[:2]
    return cv2.warpPerspective(
        image, H, size or (w, h), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT
    )


def transfer(H: np.ndarray, points: np.ndarray) -> np.ndarray:
    q = np.c_[points, np.ones(len(points))] @ H.T
    return q[:, :2] / q[:, 2:]


def transfer_error(H, ref, mov) -> np.ndarray:
    return np.linalg.norm(transfer(H, ref) - mov, axis=1)


@pytest.fixture(scope="module")
def planar_pair():
    ref = texture()
    H = homography()
    return ref, warp(ref, H), H


def opts(**kw) -> RegistrationOptions:
    return RegistrationOptions(**kw)


# --- automatic matching ---------------------------------------------------------------------------


@pytest.mark.parametrize("matcher", ["lk", "sift", "auto"])
def test_matchers_find_accurate_spread_pairs(planar_pair, matcher):
    ref, mov, H = planar_pair
    cp = find_conjugate_points(ref, mov, opts(matcher=matcher, max_points=300, min_distance=8))
    assert cp.source == ("sift" if matcher == "sift" else "lk")
    assert 100 <= len(cp) <= 300
    err = transfer_error(H, cp.reference, cp.moving)
    assert np.median(err) < (0.3 if cp.source == "lk" else 0.6)
    assert np.percentile(err, 95) < 1.5
    # Counts tell every stage, and they only decrease.
    stages = ["detected", "consistent", "epipolar", "kept"]
    values = [cp.counts[s] for s in stages]
    assert values == sorted(values, reverse=True) and values[-1] == len(cp)
    assert cp.rejected["spread"] == cp.counts["epipolar"] - cp.counts["kept"]
    # Minimum distance, residuals and model.
    d = np.linalg.norm(cp.reference[:, None] - cp.reference[None], axis=2)
    assert np.min(d + 1e9 * np.eye(len(cp))) >= 8.0
    assert cp.epipolar is not None and cp.epipolar.kind == "projective"
    assert cp.residuals.shape == (len(cp),) and np.all(cp.residuals <= 1.5)
    assert cp.reference.dtype == cp.moving.dtype == np.float64


def test_points_spread_over_the_image(planar_pair):
    ref, mov, _ = planar_pair
    cp = find_conjugate_points(ref, mov, opts(matcher="lk", max_points=200))
    counts, _, _ = np.histogram2d(
        cp.reference[:, 1], cp.reference[:, 0], bins=(3, 4), range=((0, 360), (0, 480))
    )
    # Every cell of a 3x4 grid gets points (the moving image covers all but some border).
    assert np.all(counts >= 5), counts


def test_colour_16_bit_and_different_sizes_give_the_same_geometry(planar_pair):
    ref, _, H = planar_pair
    ref_bgr = cv2.cvtColor(ref, cv2.COLOR_GRAY2BGR)
    ref16 = ref_bgr.astype(np.uint16) * 257
    mov = warp(ref, H, size=(420, 330))  # smaller moving image
    mov_bgra = cv2.cvtColor(mov, cv2.COLOR_GRAY2BGRA)
    cp = find_conjugate_points(ref16, mov_bgra, opts(matcher="lk", max_points=300))
    assert len(cp) >= 100
    assert np.all(cp.moving[:, 0] <= 419.5) and np.all(cp.moving[:, 1] <= 329.5)
    assert np.median(transfer_error(H, cp.reference, cp.moving)) < 0.3


def test_auto_falls_back_to_sift_on_wide_baseline():
    ref = texture(seed=3)
    H = homography(angle_deg=60.0, scale=0.6, tx=20, ty=10, px=0.0)
    mov = warp(ref, H)
    lk = match_lk(ref, mov, 900, 10.0)
    assert lk.counts["consistent"] < 50  # plain tracking does not survive this rotation
    cp = find_conjugate_points(ref, mov, opts(max_points=300))
    assert len(cp) >= 50
    # auto says what happened: SIFT matches, or tracking restarted from their homography.
    assert cp.source in ("sift", "lk")
    assert "lk_consistent" in cp.counts
    if cp.source == "lk":
        assert cp.counts["prior_sift_pairs"] > 0
    assert np.median(transfer_error(H, cp.reference, cp.moving)) < 0.6


def test_lighting_change_is_tolerated(planar_pair):
    ref, mov, H = planar_pair
    dark = np.round(255 * (mov / 255.0) ** 2.2 * 0.4).astype(np.uint8)  # darker, non-linear
    cp = find_conjugate_points(ref, dark, opts(max_points=300))
    assert len(cp) >= 100
    assert np.median(transfer_error(H, cp.reference, cp.moving)) < 0.4


def test_matching_is_deterministic(planar_pair):
    ref, mov, _ = planar_pair
    a = find_conjugate_points(ref, mov, opts(max_points=200, seed=5))
    b = find_conjugate_points(ref, mov, opts(max_points=200, seed=5))
    np.testing.assert_array_equal(a.reference, b.reference)
    np.testing.assert_array_equal(a.moving, b.moving)
    np.testing.assert_array_equal(a.epipolar.matrix, b.epipolar.matrix)


def test_featureless_images_raise_not_enough_points():
    flat = np.full((100, 120), 128, np.uint8)
    with pytest.raises(NotEnoughPointsError) as info:
        find_conjugate_points(flat, flat, opts())
    assert info.value.found == 0 and info.value.needed >= 3
    assert "at least" in str(info.value)


@pytest.mark.parametrize("shape", [(2, 2), (9, 7), (30, 30), (5, 400)])
@pytest.mark.parametrize("matcher", ["lk", "sift", "auto"])
def test_tiny_images_raise_not_enough_points(shape, matcher):
    img = (np.random.default_rng(0).random(shape) * 255).astype(np.uint8)
    with pytest.raises(NotEnoughPointsError):
        find_conjugate_points(img, np.roll(img, 1, axis=1), opts(matcher=matcher))


def test_filter_off_keeps_nan_residuals(planar_pair):
    ref, mov, _ = planar_pair
    cp = find_conjugate_points(ref, mov, opts(matcher="lk", epipolar_filter=False, max_points=100))
    assert cp.epipolar is None and np.all(np.isnan(cp.residuals))
    assert "epipolar" not in cp.rejected
    json.dumps(cp.to_dict())


def test_affine_model_option(planar_pair):
    ref, mov, _ = planar_pair
    cp = find_conjugate_points(ref, mov, opts(matcher="lk", epipolar_model="affine"))
    assert cp.epipolar.kind == "affine"


def test_to_dict_is_json(planar_pair):
    ref, mov, _ = planar_pair
    cp = find_conjugate_points(ref, mov, opts(max_points=50))
    d = json.loads(json.dumps(cp.to_dict()))
    assert d["source"] == cp.source and d["num_pairs"] == len(cp) == len(d["reference"])
    assert d["epipolar"]["kind"] == "projective" and len(d["residuals_px"]) == len(cp)


def test_detect_corners_sub_pixel_at_full_resolution():
    """A corner detected on a pyramid level is refined at full resolution."""
    img = np.zeros((2400, 2400), np.uint8)
    img[1000:, 1000:] = 200  # one corner at (999.5, 999.5) between the pixels
    img = cv2.GaussianBlur(img, (0, 0), 1.0)
    pts = detect_corners(img, 10, 10.0)
    assert len(pts) >= 1
    assert np.min(np.linalg.norm(pts - 999.5, axis=1)) < 0.3


def test_tracking_back_only_the_forward_tracks_changes_no_result():
    """The forward-backward check tracks back only what LK kept forward: the same tracks and
    errors as tracking every point back, the points lost forward failed with no error."""
    ref = texture()
    mov = np.roll(ref, (2, 3), axis=(0, 1))
    # The last points leave the image on the way forward.
    points = np.array([[100.0, 100.0], [240.5, 180.25], [400.0, 300.0], [479.0, 359.0],
                       [478.5, 10.0]])
    tracked, ok, fb = _lk_pair(ref, mov, points, 21, 3)
    p0 = points.astype(np.float32).reshape(-1, 1, 2)
    p1, st1, _ = cv2.calcOpticalFlowPyrLK(ref, mov, p0, None, winSize=(21, 21), maxLevel=3,
                                          criteria=_LK_CRITERIA)
    p2, st2, _ = cv2.calcOpticalFlowPyrLK(mov, ref, p1, None, winSize=(21, 21), maxLevel=3,
                                          criteria=_LK_CRITERIA)
    forward = st1.ravel() == 1
    assert forward[:3].all() and not forward.all()
    np.testing.assert_array_equal(tracked, p1.reshape(-1, 2))
    np.testing.assert_array_equal(ok, forward & (st2.ravel() == 1))
    np.testing.assert_array_equal(fb[forward], np.linalg.norm((p2 - p0).reshape(-1, 2),
                                                              axis=1)[forward])
    assert np.isinf(fb[~forward]).all()
    np.testing.assert_allclose(tracked[:3], points[:3] + [3.0, 2.0], atol=0.05)


def test_sift_reports_ratio_and_mutual_rejections(planar_pair):
    ref, mov, _ = planar_pair
    m = match_sift(ref, mov, 2000)
    assert m.counts["matched"] + m.rejected["ratio test"] <= m.counts["detected"]
    assert m.counts["consistent"] == m.counts["matched"] - m.rejected["mutual check"]


# --- dropped pairs, one by one -------------------------------------------------------------------


def listed_counts(cp: ConjugatePoints) -> dict[str, int]:
    """What ``rejected`` counts of the causes whose pairs are listed."""
    causes = LISTED_CLIENT if cp.source == "client" else LISTED_AUTOMATIC
    return {k: v for k, v in cp.rejected.items() if k in causes and v}


def dropped_counts(cp: ConjugatePoints) -> dict[str, int]:
    reasons, n = np.unique(cp.dropped.reason, return_counts=True)
    return dict(zip(reasons.tolist(), n.tolist(), strict=True))


@pytest.mark.parametrize("matcher", ["lk", "sift"])
def test_every_candidate_pair_is_kept_or_listed_with_its_cause(planar_pair, matcher):
    ref, mov, H = planar_pair
    cp = find_conjugate_points(ref, mov, opts(matcher=matcher, max_points=100, min_distance=8))
    dropped = cp.dropped
    assert dropped_counts(cp) == listed_counts(cp)
    # Every pair that passed the matcher's own consistency check is accounted for once.
    assert len(cp) + len(dropped) == cp.counts["consistent"]
    assert dropped_counts(cp)["spread"] == cp.counts["neighbours"] - cp.counts["kept"]
    # Residuals where an epipolar geometry judged the pair: beyond its threshold for the
    # epipolar drops, within it for the later ones, unknown for those dropped before it.
    threshold = cp.epipolar.threshold
    reason, res = dropped.reason, dropped.residuals
    later = np.isin(reason, ["neighbours", "spread"])
    assert np.all(res[reason == "epipolar"] > threshold)
    assert np.all(res[later] <= threshold) and later.any()
    assert np.isnan(res[~later & (reason != "epipolar")]).all()
    np.testing.assert_allclose(
        cp.epipolar.residuals(dropped.reference[later], dropped.moving[later]), res[later])
    # The moving positions are the matcher's: the drops of the spread rule are good pairs.
    assert np.median(transfer_error(H, dropped.reference[later], dropped.moving[later])) < 0.6


def test_ambiguous_pairs_on_a_repeated_patch_are_listed_where_the_pattern_is():
    ref = texture()
    yy, xx = np.mgrid[0:140, 0:160]
    ref[110:250, 160:320] = np.where(((xx // 10) + (yy // 10)) % 2 == 0, 40, 215)
    H = homography()
    cp = find_conjugate_points(ref, warp(ref, H), opts(matcher="lk", max_points=300,
                                                        min_distance=8))
    assert dropped_counts(cp) == listed_counts(cp)
    ambiguous = cp.dropped.reference[cp.dropped.reason == "ambiguous"]
    assert len(ambiguous) >= 10
    assert np.all((ambiguous >= [150, 100]) & (ambiguous <= [330, 260]))  # the board, +10 px
    assert len(cp) + len(cp.dropped) == cp.counts["consistent"]


def test_dropped_pairs_of_a_registration_on_levels_come_back_at_full_resolution():
    ref = cv2.resize(texture(seed=2), (960, 720), interpolation=cv2.INTER_CUBIC)
    H = homography(centre=(480, 360), tx=20.0, ty=-12.0)
    result = register_on_levels(ref, warp(ref, H), None, {"max_points": 150},
                                level_pixels=200_000)
    assert result.scales.tolist() == [[2.0, 2.0], [2.0, 2.0]]  # matched on half-size levels
    dropped = result.points.dropped
    assert dropped_counts(result.points) == listed_counts(result.points)
    good = np.isin(dropped.reason, ["thinned", "spread"])
    assert good.sum() > 50
    # Full-resolution pixels: the true map holds them (on the level they would be ~2x off).
    assert np.median(transfer_error(H, dropped.reference[good], dropped.moving[good])) < 0.5
    assert dropped.reference[:, 0].max() > 500
    # The pairs lie on one plane, which the model carries in full-resolution pixels too.
    plane = result.points.epipolar.plane
    assert plane is not None
    kept = result.points.reference
    assert np.abs(transfer(plane, kept) - transfer(H, kept)).max() < 1.0


# --- client points --------------------------------------------------------------------------------


def client_pairs(n=200, outliers=0.3, seed=0):
    """Noisy true pairs of a perspective 3-D scene plus outliers far from the epipolar lines."""
    rng = np.random.default_rng(seed)
    K = np.array([[500.0, 0, 240], [0, 500, 180], [0, 0, 1]])
    X = rng.uniform(-1, 1, (n, 3)) * [2.0, 1.5, 1.0] + [0, 0, 6]
    a = 0.15
    R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    t = np.array([-0.8, 0.05, 0.1])
    r = X @ K.T
    m = (X @ R.T + t) @ K.T
    ref, mov = r[:, :2] / r[:, 2:], m[:, :2] / m[:, 2:]
    ref += rng.normal(0, 0.3, ref.shape)
    mov += rng.normal(0, 0.3, mov.shape)
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    F = np.linalg.inv(K).T @ tx @ R @ np.linalg.inv(K)
    out = np.zeros(n, bool)
    out[rng.choice(n, int(outliers * n), replace=False)] = True
    from pwlreg.core.epipolar import sampson_distance

    for i in np.flatnonzero(out):
        while True:
            cand = mov[i] + rng.uniform(-40, 40, 2)
            if sampson_distance(F, ref[i : i + 1], cand[None])[0] > 4.5:
                mov[i] = cand
                break
    return ref, mov, out


@pytest.mark.parametrize("model", ["affine", "projective"])
def test_client_outliers_are_all_rejected(model):
    ref, mov, out = client_pairs()
    img = np.zeros((360, 480), np.uint8)
    # The affine model cannot describe this close-range scene: only test it on the pairs near
    # the image centre, where the perspective effect stays under the noise.
    if model == "affine":
        near = np.linalg.norm(ref - [240, 180], axis=1) < 90
        ref, mov, out = ref[near], mov[near], out[near]
    cp = find_conjugate_points(img, img, opts(epipolar_model=model), points=(ref, mov))
    assert cp.source == "client"
    kept = {tuple(p) for p in cp.reference}
    kept_mask = np.array([tuple(p) in kept for p in ref])
    assert not np.any(kept_mask & out), "an outlier survived"
    assert np.mean(~kept_mask[~out]) <= MAX_INLIER_LOSS
    assert cp.rejected["epipolar"] == np.count_nonzero(out)
    assert cp.counts["given"] == len(ref) and cp.counts["kept"] == len(cp)
    assert "spread" not in cp.rejected
    # The dropped pairs are the client's own, each with its residual over the threshold.
    dropped = {tuple(p) for p in cp.dropped.reference}
    assert dropped == {tuple(p) for p in ref[~kept_mask]}
    assert set(cp.dropped.reason) == {"epipolar"}
    assert np.all(cp.dropped.residuals > cp.epipolar.threshold)
    index = [np.flatnonzero((ref == p).all(axis=1))[0] for p in cp.dropped.reference]
    np.testing.assert_array_equal(cp.dropped.moving, mov[index])


@pytest.mark.parametrize("seed", range(12))
def test_client_outliers_on_one_plane_are_dropped_or_flagged(seed):
    # Pairs on one plane fit a whole family of fundamental matrices: the robust fit picked one
    # whose lines two random outliers also lay on (7 seeds of 12), or found none and refused
    # the 28 true pairs (2 seeds). Now the plane is the model when no fundamental matrix is
    # found, and a kept pair off the plane is counted as unverified.
    rng = np.random.default_rng(seed)
    H = np.array([[0.8, 0.25, 60], [-0.1, 0.9, 40], [2e-4, 4e-4, 1.0]])
    ref = rng.uniform([10, 10], [630, 470], (30, 2))
    mov = transfer(H, ref) + rng.normal(0, 0.3, ref.shape)
    mov[:2] = rng.uniform([5, 5], [634, 474], (2, 2))
    img = np.zeros((480, 640), np.uint8)
    cp = find_conjugate_points(img, img, opts(), points=(ref, mov))
    kept = np.array([(cp.reference == p).all(axis=1).any() for p in ref])
    assert kept[2:].all()  # every true pair
    assert cp.counts["unverified"] == np.count_nonzero(kept[:2])
    assert cp.epipolar.plane is not None
    assert transfer_error(cp.epipolar.plane, ref[2:], mov[2:]).max() < 1.5
    assert cp.to_dict()["epipolar"]["plane"] is not None


def test_a_planes_lines_hold_on_the_plane_only():
    # Every line through the plane's map of a point fits the pairs: a match found along the
    # chosen one is a lookalike unless it lies on the plane.
    rng = np.random.default_rng(0)
    H = np.array([[0.8, 0.25, 60], [-0.1, 0.9, 40], [2e-4, 4e-4, 1.0]])
    ref = rng.uniform([10, 10], [630, 470], (40, 2))
    img = np.zeros((480, 640), np.uint8)
    model = find_conjugate_points(img, img, opts(), points=(ref, transfer(H, ref))).epipolar
    assert model.plane is not None
    points = rng.uniform([50, 50], [590, 430], (20, 2))
    on_plane = transfer(H, points)
    along = on_plane + line_direction(epipolar_lines(model.matrix, points)) * 30.0
    assert model.inliers(points, on_plane).all()
    assert model.residuals(points, along).max() < 0.01  # on the chosen lines
    assert not model.inliers(points, along).any()


def true_line_miss(scene, model):
    """The 90th percentile over the covisible pixels of their true match's distance to its
    epipolar line under ``model``."""
    ys, xs = np.nonzero(scene.covisible)
    truth = np.column_stack([scene.truth_x[ys, xs], scene.truth_y[ys, xs]])
    lines = epipolar_lines(model.matrix, np.column_stack([xs, ys]).astype(float))
    return np.percentile(np.abs(np.sum(lines[:, :2] * truth, axis=1) + lines[:, 2]), 90)


def box_on_the_ground(seed, family="box"):
    scene = make_scene(family, seed, size=(640, 480), n_interior=0, supersample=2,
                       camera="perspective", radiometric="lighting", noise=3.0, blur=0.5,
                       baseline=12.0)
    cp = find_conjugate_points(matching_image(scene.reference), matching_image(scene.moving),
                               opts())
    off = transfer_distance(plane_homography(cp.reference, cp.moving), cp.reference,
                            cp.moving) > PLANE_PX
    return scene, cp, np.count_nonzero(off)


def test_sift_pairs_fix_the_epipole_one_tracked_pair_off_the_plane_leaves_open():
    # A box on a ground plane: the tracker's pairs stand on the ground but one. The robust fit
    # drew its lines through that one in a direction of its own: the true matches of the box
    # lay 20 px (90th percentile) from them, and the line search found the planks' lookalikes.
    scene, cp, off = box_on_the_ground(91)
    assert 0 < off < 3
    model = cp.epipolar
    assert model.plane is None and model.parallax >= PARALLAX_SUPPORT
    assert cp.to_dict()["epipolar"]["parallax_pairs"] == model.parallax
    assert true_line_miss(scene, model) < 3.0
    # The tracker's own pairs stay on the lines.
    assert np.all(model.residuals(cp.reference, cp.moving) <= model.threshold)


def test_sift_pairs_fix_the_epipole_no_tracked_pair_off_the_plane_leaves_open():
    # Every tracked pair on the ground: the plane's model, whose lines hold on the ground only
    # (19 px from the box's true matches at the 90th percentile), kept the insertion there.
    scene, cp, off = box_on_the_ground(101)
    assert off == 0
    model = cp.epipolar
    assert model.plane is None and model.parallax >= PARALLAX_SUPPORT
    assert true_line_miss(scene, model) < 3.0
    assert np.all(model.residuals(cp.reference, cp.moving) <= model.threshold)


def test_sift_pairs_overrule_wrong_tracked_pairs_off_the_plane():
    # A prism on the ground: the tracker's two pairs off the ground are wrong (corners of the
    # prism's edge over the ground, 12 and 27 px from their truth), and the robust fit drew
    # its lines through them: the true matches lay 20.9 px from them at the 90th percentile.
    # SIFT's pairs off the ground fix the epipole without them.
    scene, cp, off = box_on_the_ground(113, family="prism")
    assert 0 < off < 3
    model = cp.epipolar
    assert model.plane is None and model.parallax >= PARALLAX_SUPPORT
    assert true_line_miss(scene, model) < 3.0


def test_client_outliers_on_their_epipolar_lines_are_flagged_by_their_neighbours():
    # An outlier that lies on its epipolar line passes the epipolar filter (a rectified pair's
    # horizontal lines let one 275 px off pass): the matcher's neighbourhood check, at a gross
    # miss, finds it.
    ref, mov, _ = client_pairs(outliers=0.0)
    img = np.zeros((360, 480), np.uint8)
    clean = find_conjugate_points(img, img, opts(), points=(ref, mov))
    line = epipolar_lines(clean.epipolar.matrix, ref[:6])
    moved = mov.copy()
    moved[:6] += line_direction(line) * np.array([120, -150, 200, 90, 160, -180])[:, None]
    assert (moved[:6] > 0).all() and (moved[:6] < [480, 360]).all()
    assert clean.epipolar.inliers(ref[:6], moved[:6]).all()
    cp = find_conjugate_points(img, img, opts(), points=(ref, moved))
    assert cp.rejected["epipolar"] == clean.rejected["epipolar"]
    assert len(cp) == len(clean)  # kept: nothing tells them from true pairs on a roof
    assert clean.counts["unverified"] == 0
    assert cp.counts["unverified"] == 6


def test_client_pairs_off_a_plane_with_a_common_epipole_are_kept():
    # Parallax on three or more pairs determines the epipole: they are kept and the model has
    # no plane (a scene of two planes).
    ref, mov, out = client_pairs(outliers=0.0)
    img = np.zeros((360, 480), np.uint8)
    cp = find_conjugate_points(img, img, opts(), points=(ref, mov))
    assert cp.epipolar.plane is None
    assert len(cp) >= (1 - MAX_INLIER_LOSS) * len(ref)


def test_client_points_are_validated():
    ref, mov, out = client_pairs(outliers=0.0)
    img = np.zeros((360, 480, 3), np.uint8)
    ref = np.vstack([ref, [[np.nan, 5.0], [-10.0, 5.0], [5.0, 5.0]], ref[:2]])
    mov = np.vstack([mov, [[5.0, 5.0], [5.0, 5.0], [5.0, 500.0]], mov[:2]])
    cp = find_conjugate_points(img, img, opts(), points=(ref, mov))
    assert cp.rejected["not finite"] == 1
    assert cp.rejected["outside image"] == 2
    assert cp.rejected["duplicate"] == 2
    assert cp.counts["valid"] == 200
    # Listed in the order given, as given; the duplicates are the second copies.
    assert cp.dropped.reason.tolist() == ["not finite", "outside image", "outside image",
                                          "duplicate", "duplicate"]
    np.testing.assert_array_equal(cp.dropped.reference, ref[200:])
    np.testing.assert_array_equal(cp.dropped.moving, mov[200:])
    assert np.isnan(cp.dropped.residuals).all()


def test_client_points_on_the_border_are_kept():
    img = np.zeros((100, 100), np.uint8)
    ref = np.array([[-0.5, -0.5], [99.5, 0.0], [0.0, 99.5], [50.0, 50.0]])
    cp = find_conjugate_points(img, img, opts(epipolar_filter=False), points=(ref, ref + 0.2))
    assert len(cp) == 4 and cp.epipolar is None


def test_too_few_client_points_for_the_filter_skip_it_and_say_so():
    img = np.zeros((100, 100), np.uint8)
    ref = np.array([[10.0, 10.0], [80.0, 15.0], [40.0, 70.0], [60.0, 60.0]])
    cp = find_conjugate_points(img, img, opts(), points=(ref, ref + 1))
    assert len(cp) == 4 and cp.epipolar is None
    assert f"at least {MIN_PAIRS['projective']}" in cp.notes[0]
    assert cp.to_dict()["notes"] == list(cp.notes)
    cp = find_conjugate_points(img, img, opts(epipolar_filter=False), points=(ref, ref + 1))
    assert len(cp) == 4
    with pytest.raises(NotEnoughPointsError) as info:
        find_conjugate_points(img, img, opts(epipolar_filter=False), points=(ref[:2], ref[:2]))
    assert info.value.needed == 3


def test_malformed_client_points_are_input_errors():
    img = np.zeros((100, 100), np.uint8)
    with pytest.raises(InputError):
        find_conjugate_points(img, img, opts(), points=(np.zeros((5, 3)), np.zeros((5, 3))))
    with pytest.raises(InputError):
        find_conjugate_points(img, img, opts(), points=(np.zeros((5, 2)), np.zeros((4, 2))))
    with pytest.raises(InputError):
        find_conjugate_points(img.astype(np.float32), img, opts())


# --- spread ---------------------------------------------------------------------------------------


def test_spread_keeps_min_distance_and_strongest():
    rng = np.random.default_rng(0)
    pts = rng.uniform(0, 100, (2000, 2))
    score = rng.uniform(0, 1, 2000)
    keep = spread_points(pts, score, 10_000, 5.0)
    sub = pts[keep]
    d = np.linalg.norm(sub[:, None] - sub[None], axis=2) + 1e9 * np.eye(len(sub))
    assert d.min() >= 5.0
    assert keep.tolist() == sorted(keep.tolist())
    assert int(np.argmax(score)) in keep.tolist()


def test_spread_thins_clusters_before_sparse_areas():
    rng = np.random.default_rng(1)
    cluster = rng.uniform(0, 50, (1500, 2))  # one dense, strong, textured patch
    sparse = rng.uniform(0, 500, (100, 2))
    pts = np.vstack([cluster, sparse])
    score = np.r_[np.full(1500, 10.0) + rng.uniform(0, 1, 1500), rng.uniform(0, 1, 100)]
    keep = spread_points(pts, score, 150, 0.0)
    assert len(keep) == 150
    from_sparse = np.count_nonzero(keep >= 1500)
    assert from_sparse >= 90  # almost every sparse point survives although weaker


def test_spread_drops_exact_duplicates():
    pts = np.array([[1.0, 1.0], [1.0, 1.0], [2.0, 2.0]])
    assert spread_points(pts, np.array([0.5, 0.9, 0.1]), 10, 0.0).tolist() == [1, 2]


# --- real pairs -----------------------------------------------------------------------------------

REAL = Path(
    os.environ.get(realdata.ENV_VAR)
    or Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "real"
)


def real_pair(name: str) -> realdata.RealPair:
    if not (REAL / name).is_dir():
        pytest.skip(
            f"real data folder {REAL / name} is absent (set {realdata.ENV_VAR} to its "
            "location to run this test)"
        )
    return realdata.load_pair(name, REAL)


def downscale(pair: realdata.RealPair, factor: int) -> realdata.RealPair:
    """Pair at 1/factor size (pyrDown) with its F scaled to match."""
    ref, mov = pair.reference, pair.moving
    for _ in range(int(np.log2(factor))):
        ref, mov = cv2.pyrDown(ref), cv2.pyrDown(mov)
    s = 1.0 / factor
    # x_level = s (x + 0.5) - 0.5
    T = np.array([[s, 0, 0.5 * s - 0.5], [0, s, 0.5 * s - 0.5], [0, 0, 1]])
    Ti = np.linalg.inv(T)
    F = Ti.T @ pair.F @ Ti
    return realdata.RealPair(pair.name, pair.family, ref, mov, F=F / np.linalg.norm(F))


@pytest.mark.parametrize("name", ["strecha_castle_p19", "strecha_herzjesu_p8", "strecha_entry_p10"])
def test_strecha_pairs_agree_with_the_true_fundamental_matrix(name):
    pair = downscale(real_pair(name), 2)  # 1536x1024 keeps the test fast
    cp = find_conjugate_points(pair.reference, pair.moving, opts(max_points=600))
    err = realdata.sampson_distance(pair.F, cp.reference, cp.moving)
    assert cp.source == "lk"
    # The uniqueness check drops the repeated arches and windows (herzjesu keeps about 260).
    assert len(cp) >= 200
    assert np.percentile(err, 99) < 1.5
    assert np.median(err) < 0.35  # 0.5 px at full size is 0.25 px at half size (+ margin)


@pytest.mark.parametrize("name", ["oxford_leuven", "oxford_graf"])
def test_oxford_pairs_agree_with_the_true_homography(name):
    pair = real_pair(name)
    cp = find_conjugate_points(pair.reference, pair.moving, opts(max_points=500))
    err = realdata.transfer_error(pair.H, cp.reference, cp.moving)
    assert len(cp) >= 200
    assert np.median(err) < 1.0


def test_real_data_helpers_match_the_shipped_fundamental_matrix():
    pair = real_pair("strecha_castle_p19")
    shipped = np.loadtxt(REAL / pair.name / "F_0002_to_0003_derived.txt", comments="#")
    shipped /= np.linalg.norm(shipped)
    assert min(np.abs(shipped - pair.F).max(), np.abs(shipped + pair.F).max()) < 1e-9


def test_conjugate_points_type_is_exported():
    assert ConjugatePoints.__dataclass_params__.frozen


def test_a_wide_pair_is_tracked_although_its_coarse_level_is_a_few_rows_high() -> None:
    # 5000x200: the coarse prior's level (at most COARSE_SIDE wide) has 13 rows, fewer than
    # cv2.cornerSubPix's 5x5 window needs (it asserted, and the job failed as an internal error).
    rng = np.random.default_rng(3)
    big = cv2.GaussianBlur((rng.random((208, 5008)) * 255).astype(np.uint8), (0, 0), 1.5)
    big = cv2.normalize(big, None, 0, 255, cv2.NORM_MINMAX)
    ref, mov = np.ascontiguousarray(big[4:204, 4:5004]), np.ascontiguousarray(big[5:205, 6:5006])
    assert len(detect_corners(cv2.resize(ref, (320, 13)), 100, 3.0)) > 0
    estimate_global_prior(ref, mov)  # None or a homography, never an OpenCV assertion
    matches = match_lk(ref, mov, 500, 5.0)
    assert len(matches.reference) > 100
    shift = np.median(matches.moving - matches.reference, axis=0)
    np.testing.assert_allclose(shift, [-2.0, -1.0], atol=0.1)


def test_pairs_that_stay_where_a_homography_of_the_others_moves_are_fixed_in_the_frame():
    rng = np.random.default_rng(3)
    H = homography(angle_deg=2.0, scale=1.0, tx=7.3, ty=-4.6, px=0)
    scene = rng.uniform([0, 0], [480, 360], (200, 2))
    caption = rng.uniform([10, 290], [200, 340], (40, 2))  # a caption: no motion
    ref = np.concatenate([scene, caption])
    mov = np.concatenate([transfer(H, scene), caption + rng.normal(0, 0.2, caption.shape)])
    fixed = fixed_in_frame_pairs(ref, mov)
    assert fixed.tolist() == [False] * 200 + [True] * 40
    # A camera that stayed (most pairs still) or a scene that barely moves: nothing fixed.
    assert not fixed_in_frame_pairs(ref[170:], mov[170:]).any()
    small = homography(angle_deg=0.0, scale=1.0, tx=1.0, ty=-1.0, px=0)
    still_scene = np.concatenate([transfer(small, scene), caption])
    assert not fixed_in_frame_pairs(ref, still_scene).any()


def test_a_caption_burned_into_both_images_does_not_hold_the_mesh():
    # A low-contrast scene moved by 8.6 px under a caption at the same pixels of both images:
    # its corners matched themselves, still, and 14 vertices of the mesh sat on them 8.6 px
    # off the scene (verdict good).
    ref = (70 + 0.35 * texture(seed=1)).astype(np.uint8)
    H = homography(angle_deg=2.0, scale=1.0, tx=7.3, ty=-4.6, px=0)
    r = register(captioned(ref), captioned(warp(ref, H)))
    assert r.points.rejected["fixed in the frame"] > 10
    measured = ~r.extrapolated
    off = transfer_error(H, r.reference_vertices[measured], r.moving_vertices[measured])
    assert np.count_nonzero(off > 3.0) == 0
