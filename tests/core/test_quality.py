"""The verdict on a registration (core.quality)."""

import cv2
import numpy as np
import pytest

from pwlreg.core.errors import UnreliableResultError
from pwlreg.core.pipeline import register
from pwlreg.core.quality import (
    EXTRAPOLATED_OFF,
    MOVING_COVERED,
    RESIDUAL_DOUBTFUL,
    RESIDUAL_FLOW_SIDE,
    flow_texture,
    peak_scores,
    reference_tones,
    residual_share,
)
from pwlreg.core.similarity import prepare_images
from pwlreg.core.triangulation import delaunay_triangles
from tests.core.synthetic import book_map, captioned, open_book, texture


def _book_case(n: int = 80, seed: int = 0):
    reference, moving = open_book(size=(240, 200), crease=120.0, seed=seed)
    rng = np.random.default_rng(seed)
    ref = rng.uniform([5, 5], [234, 194], (n, 2))
    mov = np.stack(book_map(ref[:, 0], ref[:, 1], 120.0), axis=1)
    return reference, moving, ref, mov


def test_a_correct_registration_is_good():
    reference, moving, ref, mov = _book_case()
    r = register(reference, moving, (ref, mov))
    q = r.quality.to_dict()
    assert q["verdict"] == "good", q["reasons"]
    assert q["global_peak"] > 0.25
    assert q["low_consistency_share"] < 0.3
    assert len(r.quality.triangle_scores) == len(r.final_triangles)


def test_unrelated_images_with_points_are_unreliable():
    reference, _, ref, mov = _book_case()
    other = texture(reference.shape, 99)
    r = register(reference, other, (ref, mov))
    q = r.quality.to_dict()
    assert q["verdict"] == "unreliable"
    assert any("agree" in reason or "consistent" in reason for reason in q["reasons"])
    assert q["global_peak"] < 0.1


def test_wrong_points_are_never_good():
    reference, moving, ref, mov = _book_case()
    rng = np.random.default_rng(5)
    wrong = mov + rng.normal(0, 12.0, mov.shape)  # every pair about 15 px off
    r = register(reference, moving, (ref, wrong), {"epipolar_filter": False})
    assert r.quality.verdict != "good"


def test_on_unreliable_fail_raises_with_the_reasons():
    reference, _, ref, mov = _book_case()
    other = texture(reference.shape, 99)
    with pytest.raises(UnreliableResultError) as info:
        register(reference, other, (ref, mov), {"on_unreliable": "fail"})
    assert info.value.quality["verdict"] == "unreliable"
    assert info.value.quality["reasons"][0] in str(info.value)


def test_peak_scores_are_high_at_the_truth_and_low_one_shift_away():
    reference, moving, ref, mov = _book_case()
    images = prepare_images(reference, moving, 16)
    r = np.array([[[20.0, 20.0], [100.0, 20.0], [20.0, 150.0]]])
    m = np.stack(book_map(r[..., 0], r[..., 1], 120.0), axis=-1)
    good, _, peak_good = peak_scores(images, r, m)
    off, _, peak_off = peak_scores(images, r, m + [8.0, 0.0])
    assert good[0] > 0.3 and peak_good > 0.3
    assert peak_off < 0.1


def test_coverages_are_shares_of_the_full_frame_on_a_large_image():
    """The verdict works on a reduced copy of a large image; its coverages must not."""
    reference = texture((300, 1400), 4)
    rng = np.random.default_rng(1)
    ref = rng.uniform([300, 60], [1100, 240], (60, 2))
    r = register(reference, reference, (ref, ref + 0.3), {"optimizer": "none"})
    f = r.quality.figures
    assert 0.99 < f["mesh_coverage"] <= 1.0 + 1e-9
    assert 0.2 < f["measured_coverage"] < 0.6
    assert f["measured_coverage"] + f["extrapolated_coverage"] == pytest.approx(
        f["mesh_coverage"])


def _book_mesh(xs: list[float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertices on the true map of the open book (crease at 120) at columns ``xs``."""
    ref = np.array([(x, y) for x in xs for y in (2.0, 50.0, 100.0, 150.0, 197.0)])
    mov = np.stack(book_map(ref[:, 0], ref[:, 1], 120.0), axis=1)
    return ref, mov, delaunay_triangles(ref)


def test_the_residual_flow_finds_the_part_of_a_mesh_across_a_fold_that_is_off():
    reference, moving = open_book(size=(240, 200), crease=120.0, seed=0)
    images = prepare_images(reference, moving, 16)
    ref, mov, tris = _book_mesh([2.0, 60.0, 120.0, 180.0, 237.0])  # a column on the crease
    right, _ = residual_share(images, ref, mov, tris, np.ones(len(tris), bool))
    # Only the outer columns: the triangles span the fold, 17 px off at the crease.
    ref, mov, tris = _book_mesh([2.0, 20.0, 220.0, 237.0])
    across, _ = residual_share(images, ref, mov, tris, np.ones(len(tris), bool))
    assert right < 0.05
    assert across > 0.4


def test_a_mesh_whose_triangles_span_an_unseen_fold_is_not_good():
    reference, moving = open_book(size=(240, 200), crease=120.0, seed=0)
    ref, mov, _ = _book_mesh([2.0, 8.0, 14.0, 20.0, 220.0, 226.0, 232.0, 237.0])
    r = register(reference, moving, (ref, mov),
                 {"optimizer": "none", "epipolar_filter": False, "extent": "hull"})
    assert r.quality.figures["residual_share"] > 0.25
    assert r.quality.verdict != "good"
    assert any("residual optical flow" in reason for reason in r.quality.reasons)


def test_a_mesh_off_by_pixels_over_a_fifth_of_its_area_is_not_good():
    # No vertex between x = 100 and 170: the triangles there span the fold, up to 7 px off
    # at the crease, 1 px over the whole mesh (the flow finds about 24 % of it off).
    reference, moving = open_book(size=(240, 200), crease=120.0, seed=0)
    ref, mov, _ = _book_mesh([2.0, 30.0, 60.0, 100.0, 170.0, 205.0, 237.0])
    r = register(reference, moving, (ref, mov),
                 {"optimizer": "none", "epipolar_filter": False, "extent": "hull"})
    assert r.quality.figures["residual_share"] > RESIDUAL_DOUBTFUL
    assert r.quality.verdict == "doubtful"
    assert [reason for reason in r.quality.reasons if "residual optical flow" in reason]


def test_a_mesh_off_over_a_sixth_of_its_area_is_not_good():
    # No vertex between x = 105 and 160: the flow finds about 18 % of the mesh off, under the
    # bound of 20 % that let a wide-baseline city be good at 4 px over its frame.
    reference, moving = open_book(size=(240, 200), crease=120.0, seed=0)
    ref, mov, _ = _book_mesh([2.0, 30.0, 60.0, 85.0, 105.0, 160.0, 205.0, 237.0])
    r = register(reference, moving, (ref, mov),
                 {"optimizer": "none", "epipolar_filter": False, "extent": "hull"})
    assert RESIDUAL_DOUBTFUL < r.quality.figures["residual_share"] < 0.2
    assert r.quality.verdict == "doubtful"


def test_pairs_thinned_before_the_checks_do_not_count_as_failed():
    # A copy turned half a turn: tracking fails, SIFT matches about 2000 pairs, of which only
    # those the checks can afford are checked; every checked pair passes.
    reference = texture((240, 320), 3)
    r = register(reference, reference[::-1, ::-1].copy())
    assert r.points.source == "sift"
    assert r.points.rejected["thinned"] > r.points.counts["checked"]
    assert r.quality.figures["inlier_share"] > 0.9
    h, w = reference.shape
    ref = r.reference_vertices
    truth = np.column_stack([w - 1 - ref[:, 0], h - 1 - ref[:, 1]])
    # Pairs found along the epipolar lines of a plane (a degenerate geometry, fitted on the
    # matched pairs) reach 0.63 px within 10 px of the frame's side; the others 0.1 px.
    assert np.abs(r.moving_vertices - truth).max() < 1.0
    assert np.median(np.abs(r.moving_vertices - truth)) < 0.1
    assert r.quality.verdict == "good"


def test_a_close_up_of_part_of_the_reference_is_not_doubted_for_its_small_share():
    # The moving image shows the reference's central quarter at twice the scale: only about a
    # fifth of the reference frame can be measured, and nearly all of the moving image is.
    reference = texture((480, 640), 4, sigma=1.5)
    zoom = np.array([[2.0, 0.0, -320.0], [0.0, 2.0, -240.0], [0.0, 0.0, 1.0]])
    moving = cv2.warpPerspective(reference, zoom, (640, 480), flags=cv2.INTER_CUBIC)
    r = register(reference, moving)
    f = r.quality.figures
    assert f["measured_coverage"] < 0.3
    assert f["measured_moving_coverage"] > MOVING_COVERED
    ref = r.reference_vertices[~r.extrapolated]
    truth = ref * 2.0 - [320.0, 240.0]
    assert np.abs(r.moving_vertices[~r.extrapolated] - truth).max() < 0.5
    assert r.quality.verdict == "good"


def test_a_small_crop_of_the_reference_is_not_unreliable():
    # 120x90 pixels out of 640x480: 1 % of the reference frame can be measured.
    reference = texture((480, 640), 7, sigma=1.5)
    moving = reference[200:290, 300:420].copy()
    r = register(reference, moving)
    ref = r.reference_vertices[~r.extrapolated]
    miss = np.hypot(*(r.moving_vertices[~r.extrapolated] - (ref - [300.0, 200.0])).T)
    assert np.median(miss) < 0.1 and miss.max() < 1.0
    assert r.quality.figures["measured_coverage"] < 0.05
    assert r.quality.verdict == "doubtful"


def test_points_in_one_corner_of_both_images_are_doubtful():
    reference, moving, ref, mov = _book_case(n=300)
    corner = (ref[:, 0] < 70) & (ref[:, 1] < 70)
    r = register(reference, moving, (ref[corner], mov[corner]), {"epipolar_filter": False})
    f = r.quality.figures
    assert f["measured_moving_coverage"] < 0.3
    assert r.quality.verdict != "good"
    assert any("of the moving image" in reason for reason in r.quality.reasons)


def _left_page_carried_on() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The open book's mesh with the right page's vertices extrapolated from the left page
    (the identity there): up to 41 px off at the frame's side."""
    ref, mov, tris = _book_mesh([2.0, 60.0, 120.0, 180.0, 237.0])
    right = ref[:, 0] > 120.0
    wrong = np.where(right[:, None], ref, mov)
    return ref, wrong, tris, ~right[tris].any(axis=1)


def test_the_residual_flow_judges_the_extrapolated_border_where_it_has_texture():
    reference, moving = open_book(size=(240, 200), crease=120.0, seed=0)
    ref, wrong, tris, measured = _left_page_carried_on()
    inside, border = residual_share(prepare_images(reference, moving, 16), ref, wrong, tris,
                                    measured)
    assert inside < 0.05
    assert border > 0.3  # of the frame: most of the right page
    # A blank right page: the flow follows nothing there, and says nothing of it.
    reference[:, 121:], moving[:, 120:] = 128, 128
    _, blank = residual_share(prepare_images(reference, moving, 16), ref, wrong, tris,
                              measured)
    assert blank < 0.02
    assert not flow_texture(reference, RESIDUAL_FLOW_SIDE)[:, 130:].any()
    assert flow_texture(reference, RESIDUAL_FLOW_SIDE)[10:-10, 10:110].mean() > 0.9


def test_a_border_extrapolated_wrongly_over_a_textured_surface_is_not_good():
    reference, moving = open_book(size=(240, 200), crease=120.0, seed=0)
    ref, mov, _ = _book_mesh([2.0, 30.0, 60.0, 90.0, 110.0])
    r = register(reference, moving, (ref, mov),
                 {"optimizer": "none", "epipolar_filter": False, "extent": "frame"})
    assert r.quality.figures["extrapolated_off_share"] > EXTRAPOLATED_OFF
    assert r.quality.verdict != "good"
    assert any("in the extrapolated border" in reason for reason in r.quality.reasons)


def test_a_right_registration_over_a_noisy_blank_backdrop_is_good():
    """Noise is no texture the flow can follow: the border over it is not found off."""
    reference, moving = open_book(size=(240, 200), crease=120.0, seed=0)
    rng = np.random.default_rng(3)
    book = np.zeros(reference.shape, bool)
    book[20:180, 20:220] = True
    ref_img = np.where(book, reference, 128 + rng.normal(0, 10.0, reference.shape))
    mov_img = 128 + rng.normal(0, 10.0, moving.shape)
    ys, xs = np.nonzero(book)
    mx, my = book_map(xs.astype(float), ys.astype(float), 120.0)
    inside = (mx <= 239) & (my <= 199)
    cols, rows = np.round(mx[inside]).astype(int), np.round(my[inside]).astype(int)
    mov_img[rows, cols] = moving[rows, cols]
    ref = rng.uniform([25, 25], [215, 175], (80, 2))
    mov = np.stack(book_map(ref[:, 0], ref[:, 1], 120.0), axis=1)
    r = register(np.clip(ref_img, 0, 255).astype(np.uint8),
                 np.clip(mov_img, 0, 255).astype(np.uint8), (ref, mov))
    assert r.quality.figures["extrapolated_coverage"] > 0.2
    assert r.quality.figures["extrapolated_off_share"] < 0.02
    assert r.quality.verdict == "good", r.quality.reasons


def test_the_residual_flow_reads_the_registered_image_in_the_references_tones():
    ref = texture((240, 320), 12, sigma=2.0)
    everywhere = np.ones(ref.shape, bool)
    darker = np.clip(255 * (ref / 255.0) ** 2.0, 0, 255).astype(np.uint8)
    toned = reference_tones(darker, ref, everywhere)
    assert np.abs(toned.astype(int) - ref).mean() < 1.0 < np.abs(darker.astype(int) - ref).mean()
    # A tone that changes across the image is no function of the grey level: left as it is.
    ramp = np.linspace(0.15, 1.0, 320)[None, :]
    lit = np.clip(ref * ramp, 0, 255).astype(np.uint8)
    assert reference_tones(lit, np.clip(ref * ramp[:, ::-1], 0, 255).astype(np.uint8),
                           everywhere) is lit


def test_a_gamma_between_the_images_is_no_residual_error():
    # Under a gamma of 2 the flow, which assumes constant brightness, found 12-16 % of right
    # registrations off (photographs, 0.12 px from the truth): doubtful.
    ref = cv2.addWeighted(texture((480, 640), 13, sigma=8.0), 0.6,
                          texture((480, 640), 14, sigma=32.0), 0.4, 0)
    moving = np.roll(ref, (3, -2), axis=(0, 1))
    moving = np.clip(255 * (moving / 255.0) ** 2.5, 0, 255).astype(np.uint8)
    result = register(ref, moving, options={"extent": "hull"})
    assert result.quality.figures["residual_share"] < 0.02  # 0.095 read in the moving's tones


def test_vertices_held_by_a_caption_in_both_images_make_the_verdict_doubtful():
    # Client points on a caption burned into both images stay at their pixels while the
    # scene under it moves by 8.6 px: the mesh follows the caption there.
    reference = (70 + 0.35 * texture((360, 480), 1)).astype(np.uint8)
    H = np.array([[1.0, 0.0, 7.3], [0.0, 1.0, -4.6], [0.0, 0.0, 1.0]])
    moving = cv2.warpPerspective(reference, H, (480, 360), flags=cv2.INTER_CUBIC,
                                 borderMode=cv2.BORDER_REFLECT)
    rng = np.random.default_rng(0)
    scene = rng.uniform([20, 20], [460, 280], (120, 2))
    caption = rng.uniform([15, 290], [220, 340], (12, 2))
    both = (np.concatenate([scene, caption]), np.concatenate([scene + H[:2, 2], caption]))
    r = register(captioned(reference), captioned(moving), both)
    assert r.quality.figures["fixed_in_frame_vertices"] == 12
    assert r.quality.verdict == "doubtful"
    assert any("stay at their pixel" in reason for reason in r.quality.reasons)
    scene_only = register(captioned(reference), captioned(moving), (scene, scene + H[:2, 2]))
    assert scene_only.quality.figures["fixed_in_frame_vertices"] == 0
