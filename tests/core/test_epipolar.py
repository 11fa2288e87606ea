"""Tests of core.epipolar: affine MSAC and projective USAC fundamental matrices."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pwlreg.core.epipolar import (
    MIN_PAIRS,
    estimate_affine_fundamental,
    estimate_fundamental,
    estimate_projective_fundamental,
    fit_affine_fundamental,
    parallax_fundamental,
    plane_fundamental,
    sampson_distance,
)
from pwlreg.core.errors import InputError

THRESHOLD = 1.5
NOISE = 0.3  # px, per coordinate
MAX_INLIER_LOSS = 0.01  # stated rate: at most 1 % of true pairs rejected at 5 sigma


def rotation(rx: float, ry: float, rz: float) -> np.ndarray:
    cx, sx, cy, sy, cz, sz = np.cos(rx), np.sin(rx), np.cos(ry), np.sin(ry), np.cos(rz), np.sin(rz)
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def affine_scene(rng: np.random.Generator, n: int, angles=(0.05, 0.15, 0.03)):
    """Two affine cameras viewing random 3-D points; returns ref, mov and the true hyperplane."""
    X = rng.uniform(-1, 1, (n, 3)) * [400, 300, 150]
    M1 = np.eye(3)[:2]
    M2 = 0.9 * rotation(*angles)[:2]
    t1, t2 = np.array([500.0, 400.0]), np.array([520.0, 380.0])
    return X @ M1.T + t1, X @ M2.T + t2


K_CAMERA = np.array([[800.0, 0, 400], [0, 800, 300], [0, 0, 1]])
R_MOVING, T_MOVING = rotation(0.02, 0.17, 0.01), np.array([-1.2, 0.1, 0.2])


def two_views(X: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """3-D points seen by two pinhole cameras 10 deg apart: ref, mov and the true F."""
    a = X @ K_CAMERA.T
    b = (X @ R_MOVING.T + T_MOVING) @ K_CAMERA.T
    t = T_MOVING
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    K_inv = np.linalg.inv(K_CAMERA)
    F = K_inv.T @ tx @ R_MOVING @ K_inv
    return a[:, :2] / a[:, 2:3], b[:, :2] / b[:, 2:3], F / np.linalg.norm(F)


def perspective_scene(rng: np.random.Generator, n: int):
    """Two pinhole cameras 10 deg apart around a 3-D point cloud; returns ref, mov, true F."""
    return two_views(rng.uniform(-1, 1, (n, 3)) * [3, 2, 1.5] + [0, 0, 8])


def inject_outliers(rng, ref, mov, F, share, min_residual):
    """Move a share of the moving points off their epipolar line by at least min_residual."""
    mov = mov.copy()
    n = len(ref)
    out = np.zeros(n, bool)
    out[rng.choice(n, int(share * n), replace=False)] = True
    for i in np.flatnonzero(out):
        while True:
            cand = mov[i] + rng.uniform(-60, 60, 2)
            if sampson_distance(F, ref[i : i + 1], cand[None])[0] >= min_residual:
                mov[i] = cand
                break
    return mov, out


def test_sampson_distance_of_affine_f_is_the_hyperplane_distance():
    rng = np.random.default_rng(0)
    ref, mov = rng.uniform(0, 500, (50, 2)), rng.uniform(0, 500, (50, 2))
    a, b, c, d, e = 0.3, -0.5, 0.2, 0.4, 12.0
    F = np.array([[0, 0, a], [0, 0, b], [c, d, e]])
    expected = np.abs(a * mov[:, 0] + b * mov[:, 1] + c * ref[:, 0] + d * ref[:, 1] + e)
    expected /= np.sqrt(a * a + b * b + c * c + d * d)
    np.testing.assert_allclose(sampson_distance(F, ref, mov), expected, rtol=1e-12)


def test_fit_affine_fundamental_is_exact_on_affine_cameras():
    ref, mov = affine_scene(np.random.default_rng(1), 30)
    F = fit_affine_fundamental(ref, mov)
    assert F[0, 0] == F[0, 1] == F[1, 0] == F[1, 1] == 0.0
    assert np.linalg.norm([F[0, 2], F[1, 2], F[2, 0], F[2, 1]]) == pytest.approx(1.0)
    # Convention x_mov^T F x_ref = 0.
    r = np.einsum("ni,ij,nj->n", np.c_[mov, np.ones(30)], F, np.c_[ref, np.ones(30)])
    assert np.max(np.abs(r)) < 1e-8


@pytest.mark.parametrize("share", [0.0, 0.3, 0.6])
def test_affine_msac_rejects_every_outlier_and_keeps_the_inliers(share):
    rng = np.random.default_rng(2)
    ref, mov = affine_scene(rng, 800)
    F_true = fit_affine_fundamental(ref, mov)
    ref_n = ref + rng.normal(0, NOISE, ref.shape)
    mov_n = mov + rng.normal(0, NOISE, mov.shape)
    mov_n, out = inject_outliers(rng, ref_n, mov_n, F_true, share, 3 * THRESHOLD)
    model = estimate_affine_fundamental(ref_n, mov_n, threshold=THRESHOLD, seed=0)
    inl = model.inliers(ref_n, mov_n)
    assert model.kind == "affine"
    assert not np.any(inl & out), "an injected outlier survived"
    assert np.mean(~inl[~out]) <= MAX_INLIER_LOSS
    assert model.num_inliers == np.count_nonzero(inl)
    assert model.rms < 2 * NOISE
    # The refit is close to the truth: true pairs (noise-free) have tiny residuals.
    assert np.median(model.residuals(ref, mov)) < 0.1


def test_affine_msac_adapts_its_iterations():
    rng = np.random.default_rng(3)
    ref, mov = affine_scene(rng, 500)
    mov = mov + rng.normal(0, NOISE, mov.shape)
    clean = estimate_affine_fundamental(ref, mov, THRESHOLD, seed=0)
    F_true = fit_affine_fundamental(ref, mov)
    mov_o, _ = inject_outliers(rng, ref, mov, F_true, 0.6, 3 * THRESHOLD)
    dirty = estimate_affine_fundamental(ref, mov_o, THRESHOLD, seed=0)
    assert clean.iterations <= 128  # one batch suffices at 0 % outliers
    assert dirty.iterations > clean.iterations
    assert dirty.iterations <= 10_000


def test_affine_msac_is_deterministic_per_seed():
    rng = np.random.default_rng(4)
    ref, mov = affine_scene(rng, 300)
    mov = mov + rng.normal(0, 2.0, mov.shape)
    a = estimate_affine_fundamental(ref, mov, THRESHOLD, seed=7)
    b = estimate_affine_fundamental(ref, mov, THRESHOLD, seed=7)
    np.testing.assert_array_equal(a.matrix, b.matrix)


@pytest.mark.parametrize("share", [0.0, 0.4])
def test_projective_usac_rejects_every_outlier_and_keeps_the_inliers(share):
    rng = np.random.default_rng(5)
    ref, mov, F_true = perspective_scene(rng, 600)
    ref_n = ref + rng.normal(0, NOISE, ref.shape)
    mov_n = mov + rng.normal(0, NOISE, mov.shape)
    mov_n, out = inject_outliers(rng, ref_n, mov_n, F_true, share, 3 * THRESHOLD)
    model = estimate_projective_fundamental(ref_n, mov_n, threshold=THRESHOLD, seed=0)
    inl = model.inliers(ref_n, mov_n)
    assert model.kind == "projective"
    assert np.linalg.norm(model.matrix) == pytest.approx(1.0)
    assert not np.any(inl & out)
    assert np.mean(~inl[~out]) <= MAX_INLIER_LOSS
    assert np.median(model.residuals(ref, mov)) < 0.2
    again = estimate_projective_fundamental(ref_n, mov_n, threshold=THRESHOLD, seed=0)
    np.testing.assert_array_equal(model.matrix, again.matrix)


def test_affine_model_misses_strong_perspective_and_projective_does_not():
    """Why the projective model is the default for close-range photos."""
    rng = np.random.default_rng(6)
    ref, mov, _ = perspective_scene(rng, 400)
    affine = estimate_affine_fundamental(ref, mov, THRESHOLD, seed=0)
    projective = estimate_projective_fundamental(ref, mov, THRESHOLD, seed=0)
    assert projective.num_inliers == 400
    assert affine.num_inliers < projective.num_inliers


@pytest.mark.parametrize("kind", ["affine", "projective"])
def test_too_few_or_degenerate_pairs_are_an_input_error(kind):
    n = MIN_PAIRS[kind] - 1
    rng = np.random.default_rng(0)
    with pytest.raises(InputError, match=f"at least {MIN_PAIRS[kind]}"):
        estimate_fundamental(rng.uniform(0, 100, (n, 2)), rng.uniform(0, 100, (n, 2)), kind)
    with pytest.raises(InputError, match="finite"):
        bad = rng.uniform(0, 100, (20, 2))
        bad[3, 0] = np.nan
        estimate_fundamental(bad, bad, kind)


#: 16 pairs SIFT returned on a synthetic box (1024 x 768), two of them twice, all on one
#: homography: OpenCV's USAC asserted on them with seeds 0 and 1.
DEGENERATE = np.array([
    [44.368, 299.647, 142.967, 293.12], [57.797, 11.407, 243.511, 43.887],
    [65.808, 11.77, 251.926, 44.827], [74.388, 10.353, 259.549, 44.555],
    [126.431, 738.116, 76.799, 696.125], [141.005, 749.849, 87.669, 710.083],
    [584.353, 664.083, 546.318, 700.459], [596.123, 647.283, 563.976, 686.073],
    [615.44, 647.088, 584.931, 689.951], [738.023, 564.782, 699.34, 702.584],
    [738.023, 564.782, 699.34, 702.584], [819.538, 345.679, 898.639, 424.255],
    [819.538, 345.679, 898.639, 424.255], [822.914, 343.884, 901.282, 423.838],
    [853.19, 214.629, 975.481, 300.6], [873.876, 231.62, 993.678, 319.62]])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_projective_fit_of_a_degenerate_set_is_a_model_or_an_input_error(seed):
    try:
        model = estimate_projective_fundamental(DEGENERATE[:, :2], DEGENERATE[:, 2:], THRESHOLD,
                                                seed=seed)
    except InputError as exc:
        assert "no projective fundamental matrix" in str(exc)
    else:
        assert model.matrix.shape == (3, 3)


def test_affine_pairs_without_parallax_are_all_kept():
    """Pairs related by one 2-D affine map leave the hyperplane undetermined: keep them all."""
    rng = np.random.default_rng(9)
    ref = rng.uniform(0, 500, (40, 2))
    mov = ref @ np.array([[0.9, 0.1], [-0.1, 0.9]]).T + [5.0, -3.0]
    model = estimate_affine_fundamental(ref, mov, THRESHOLD)
    assert model.num_inliers == 40
    assert np.max(model.residuals(ref, mov)) < 1e-6


def test_unknown_kind_is_an_input_error():
    x = np.zeros((20, 2))
    with pytest.raises(InputError):
        estimate_fundamental(x, x, "bogus")  # type: ignore[arg-type]


def test_to_dict_is_json():
    ref, mov = affine_scene(np.random.default_rng(8), 50)
    d = estimate_affine_fundamental(ref, mov).to_dict()
    assert json.loads(json.dumps(d))["kind"] == "affine"
    assert len(d["matrix"]) == 3 and d["num_inliers"] == 50


@settings(max_examples=25, deadline=None)
@given(
    rx=st.floats(-0.3, 0.3),
    ry=st.floats(-0.3, 0.3),
    rz=st.floats(-3.0, 3.0),
    seed=st.integers(0, 1000),
)
def test_affine_msac_recovers_any_affine_pair(rx, ry, rz, seed):
    ref, mov = affine_scene(np.random.default_rng(seed), 60, (rx, ry, rz))
    model = estimate_affine_fundamental(ref, mov, THRESHOLD, seed=seed)
    assert model.num_inliers == 60
    assert np.max(model.residuals(ref, mov)) < 1e-6


def plane_and_parallax(rng: np.random.Generator, off: int, noise: float = 0.3):
    """The cameras of :func:`two_views` over a tilted ground plane and ``off`` points above
    it: the plane's homography, the pairs on it and the pairs off it (noisy), and the true F."""

    def ground(n):
        xy = rng.uniform(-1, 1, (n, 2)) * [3, 2]
        return np.column_stack([xy, 8.0 + 0.4 * xy[:, 1]])

    plane_ref, plane_mov, _ = two_views(ground(40))
    H = cv2.findHomography(plane_ref, plane_mov)[0]
    X = ground(off)
    X[:, 2] -= rng.uniform(1.5, 3.0, off)  # nearer the cameras than the ground
    ref, mov, F = two_views(X)
    noisy = mov + rng.normal(0, noise, mov.shape)
    return H, (plane_ref, plane_mov), (ref, noisy), F


def a_wrong_epipole(H, ref, mov, along):
    """``[e']_x H`` with ``e'`` on the parallax line of the pair ``ref[0], mov[0]`` but ``along``
    pixels from where the true lines meet: one pair off the plane leaves that open."""
    line = np.cross(np.append(cv2.perspectiveTransform(ref[None, :1], H)[0, 0], 1.0),
                    np.append(mov[0], 1.0))
    foot = mov[0] + along * np.array([line[1], -line[0]]) / np.hypot(line[0], line[1])
    return cross_matrix(np.append(foot, 1.0)) @ H


def test_pairs_off_the_plane_fix_the_epipole_one_pair_leaves_open():
    rng = np.random.default_rng(3)
    H, (p_ref, p_mov), (ref, mov), F_true = plane_and_parallax(rng, 13)
    wrong = a_wrong_epipole(H, ref, mov, 40.0)
    # The lines through the one pair off the plane miss the others' true matches.
    assert np.median(sampson_distance(wrong, ref[1:], mov[1:])) > 5.0
    lookalikes = rng.uniform([0, 0], [800, 600], (2, 40, 2))
    pairs = (np.concatenate([ref[1:], p_ref, lookalikes[0]]),
             np.concatenate([mov[1:], p_mov, lookalikes[1]]))
    found = parallax_fundamental(H, (ref[:1], mov[:1]), pairs, wrong, threshold=THRESHOLD)
    assert found is not None
    F, support = found
    assert support >= 11
    assert sampson_distance(F, ref, mov).max() < 1.0
    assert np.isclose(np.linalg.norm(F), 1.0) and np.sum(F * wrong) > 0


def test_lookalikes_alone_do_not_move_the_epipole():
    rng = np.random.default_rng(4)
    H, (p_ref, p_mov), (ref, mov), _ = plane_and_parallax(rng, 1)
    wrong = a_wrong_epipole(H, ref, mov, 40.0)
    for seed in range(50):
        lookalikes = np.random.default_rng(seed).uniform([0, 0], [800, 600], (2, 60, 2))
        pairs = (np.concatenate([p_ref, lookalikes[0]]), np.concatenate([p_mov, lookalikes[1]]))
        assert parallax_fundamental(H, (ref, mov), pairs, wrong, threshold=THRESHOLD) is None


def vertical_lines(H):
    """``[e']_x H`` with ``e'`` at infinity along y: lines a plane allows, across the true ones
    of :func:`two_views` (the cameras move sideways)."""
    return np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 0.0], [-1.0, 0.0, 0.0]]) @ H


def no_pair():
    return np.zeros((0, 2)), np.zeros((0, 2))


def test_pairs_off_the_plane_fix_the_epipole_no_pair_fixes():
    # All the matcher's pairs on the ground: the plane's model has lines of its own choosing.
    rng = np.random.default_rng(5)
    H, (p_ref, p_mov), (ref, mov), F_true = plane_and_parallax(rng, 14)
    wrong = vertical_lines(H)
    assert np.median(sampson_distance(wrong, ref, mov)) > 5.0
    lookalikes = rng.uniform([0, 0], [800, 600], (2, 40, 2))
    pairs = (np.concatenate([ref, p_ref, lookalikes[0]]),
             np.concatenate([mov, p_mov, lookalikes[1]]))
    found = parallax_fundamental(H, no_pair(), pairs, wrong, threshold=THRESHOLD)
    assert found is not None
    F, support = found
    assert support >= 12
    # The lines pass near the exact matches of other points above the plane.
    exact_ref, exact_mov, _ = perspective_scene(rng, 200)
    assert np.percentile(sampson_distance(wrong, exact_ref, exact_mov), 90) > 10.0
    assert np.percentile(sampson_distance(F, exact_ref, exact_mov), 90) < 1.5


def test_lookalikes_alone_do_not_move_the_plane_s_epipole():
    rng = np.random.default_rng(6)
    H, (p_ref, p_mov), _, _ = plane_and_parallax(rng, 1)
    wrong = plane_fundamental(H)
    for seed in range(50):
        lookalikes = np.random.default_rng(seed).uniform([0, 0], [800, 600], (2, 60, 2))
        pairs = (np.concatenate([p_ref, lookalikes[0]]), np.concatenate([p_mov, lookalikes[1]]))
        assert parallax_fundamental(H, no_pair(), pairs, wrong, threshold=THRESHOLD) is None


def test_a_pattern_one_period_off_does_not_move_the_plane_s_epipole():
    # Windows of a facade matched one window off: every pair moved alike, their lines parallel.
    rng = np.random.default_rng(7)
    H, (p_ref, p_mov), _, _ = plane_and_parallax(rng, 1)
    wrong = plane_fundamental(H)
    period = p_mov + [24.0, 1.0] + rng.normal(0, 0.3, p_mov.shape)
    lookalikes = rng.uniform([0, 0], [800, 600], (2, 20, 2))
    pairs = (np.concatenate([p_ref, p_ref, lookalikes[0]]),
             np.concatenate([p_mov, period, lookalikes[1]]))
    assert parallax_fundamental(H, no_pair(), pairs, wrong, threshold=THRESHOLD) is None


def epipole_of(lines):
    """The point (homogeneous) where two lines ``(2, 3)`` meet."""
    return np.cross(lines[0], lines[1])


def parallax_lines(H, ref, mov):
    """The lines through each pair's plane image ``H ref`` and its moving point."""
    ones = np.ones((len(ref), 1))
    return np.cross(np.hstack([cv2.perspectiveTransform(ref[None], H)[0], ones]),
                    np.hstack([mov, ones]))


def cross_matrix(e):
    return np.array([[0, -e[2], e[1]], [e[2], 0, -e[0]], [-e[1], e[0], 0]])


def test_wrong_pairs_off_the_plane_give_way_to_the_other_pairs_epipole():
    # The matcher's only pairs off the ground are two corners of an occluding edge, matched
    # where the edge makes the same corner over other ground: off the plane with no depth of
    # their own. Their lines met at an epipole of their own, 20-60 px from the true matches
    # of a prism above the ground (trust suite, seeds 1, 61, 113).
    rng = np.random.default_rng(8)
    H, (p_ref, p_mov), (ref, mov), _ = plane_and_parallax(rng, 16)
    wrong_ref = rng.uniform([100, 100], [700, 500], (2, 2))
    angle = rng.uniform(0, 2 * np.pi, 2)
    wrong_mov = (cv2.perspectiveTransform(wrong_ref[None], H)[0]
                 + rng.uniform(12, 27, (2, 1)) * np.column_stack([np.cos(angle), np.sin(angle)]))
    current = cross_matrix(epipole_of(parallax_lines(H, wrong_ref, wrong_mov))) @ H
    assert np.median(sampson_distance(current, ref, mov)) > 5.0
    lookalikes = rng.uniform([0, 0], [800, 600], (2, 40, 2))
    pairs = (np.concatenate([ref, p_ref, lookalikes[0]]),
             np.concatenate([mov, p_mov, lookalikes[1]]))
    found = parallax_fundamental(H, (wrong_ref, wrong_mov), pairs, current, threshold=THRESHOLD)
    assert found is not None
    F, support = found
    assert support >= 14
    exact_ref, exact_mov, _ = perspective_scene(rng, 200)
    assert np.percentile(sampson_distance(F, exact_ref, exact_mov), 90) < 1.5
    assert (sampson_distance(F, wrong_ref, wrong_mov) > THRESHOLD).all()


def test_pairs_off_the_plane_overrule_a_fixed_pair_only_twice_as_many():
    # A right pair off the plane and five pairs that agree with it, against ten that agree
    # on another epipole (occluders of the trust suite, seeds 82-83: their pairs' lines then
    # missed the true matches by 4-20 px, against 2-3 px through the fixed pairs).
    rng = np.random.default_rng(9)
    H, (p_ref, p_mov), (ref, mov), F_true = plane_and_parallax(rng, 6)
    other_ref = rng.uniform([50, 50], [750, 550], (10, 2))
    on_plane = cv2.perspectiveTransform(other_ref[None], H)[0]
    towards = np.array([-900.0, 2400.0]) - on_plane
    other_mov = on_plane + (rng.uniform(10, 40, (10, 1)) * towards
                            / np.linalg.norm(towards, axis=1, keepdims=True))
    other_mov += rng.normal(0, 0.3, other_mov.shape)
    current = a_wrong_epipole(H, ref, mov, 40.0)
    pairs = (np.concatenate([ref[1:], other_ref, p_ref]),
             np.concatenate([mov[1:], other_mov, p_mov]))
    assert parallax_fundamental(H, (ref[:1], mov[:1]), pairs, current,
                                threshold=THRESHOLD) is None
    # Alone, the same pairs would have moved the epipole to theirs.
    free = parallax_fundamental(H, no_pair(), pairs, current, threshold=THRESHOLD)
    assert free is not None
    assert (sampson_distance(free[0], other_ref, other_mov) <= THRESHOLD).sum() >= 10


def test_the_right_one_of_two_pairs_off_the_plane_fixes_the_epipole():
    # One of the matcher's two pairs off the plane is right, the other 17 px off; SIFT's pairs
    # off the plane are too few to fix an epipole alone (a prism of the trust suite, seed
    # 132: lines through both pairs 37 px from the true matches at p90, 20 through the right
    # one, and the registration 4.10 -> 1.53 px, Delaunay 2.61).
    rng = np.random.default_rng(10)
    H, (p_ref, p_mov), (ref, mov), _ = plane_and_parallax(rng, 8)
    wrong_ref = np.array([[420.0, 260.0]])
    wrong_mov = cv2.perspectiveTransform(wrong_ref[None], H)[0] + [12.0, -12.0]
    fixed = (np.concatenate([ref[:1], wrong_ref]), np.concatenate([mov[:1], wrong_mov]))
    current = cross_matrix(epipole_of(parallax_lines(H, *fixed))) @ H
    lookalikes = rng.uniform([0, 0], [800, 600], (2, 30, 2))
    pairs = (np.concatenate([ref[1:], p_ref, lookalikes[0]]),
             np.concatenate([mov[1:], p_mov, lookalikes[1]]))
    # Neither both pairs' lines nor the seven other pairs alone fix it.
    assert parallax_fundamental(H, no_pair(), pairs, current, threshold=THRESHOLD) is None
    found = parallax_fundamental(H, fixed, pairs, current, threshold=THRESHOLD)
    assert found is not None
    F, support = found
    assert support >= 6
    assert sampson_distance(F, ref, mov).max() < 1.0
    assert sampson_distance(F, wrong_ref, wrong_mov)[0] > THRESHOLD


def test_lookalikes_alone_do_not_move_the_epipole_of_two_pairs():
    rng = np.random.default_rng(11)
    H, (p_ref, p_mov), (ref, mov), _ = plane_and_parallax(rng, 2)
    current = cross_matrix(epipole_of(parallax_lines(H, ref, mov))) @ H
    for seed in range(50):
        lookalikes = np.random.default_rng(seed).uniform([0, 0], [800, 600], (2, 60, 2))
        pairs = (np.concatenate([p_ref, lookalikes[0]]), np.concatenate([p_mov, lookalikes[1]]))
        assert parallax_fundamental(H, (ref, mov), pairs, current, threshold=THRESHOLD) is None
