"""Whole-frame meshes: border vertices and their extrapolated positions (core.extent)."""

import numpy as np

from pwlreg.core.extent import border_positions, frame_vertices, local_affine_extrapolation
from pwlreg.core.pipeline import register
from pwlreg.core.similarity import prepare_images
from tests.core.synthetic import book_map, open_book, texture


def test_border_positions_run_around_the_frame_with_its_corners():
    pts = border_positions((100, 200), 30.0)
    corners = {(-0.5, -0.5), (199.5, -0.5), (199.5, 99.5), (-0.5, 99.5)}
    assert corners <= {tuple(p) for p in pts.tolist()}
    on_side = (np.isclose(pts[:, 0], -0.5) | np.isclose(pts[:, 0], 199.5)
               | np.isclose(pts[:, 1], -0.5) | np.isclose(pts[:, 1], 99.5))
    assert on_side.all()
    # Consecutive points along the top side are at most the spacing apart.
    top = np.sort(pts[np.isclose(pts[:, 1], -0.5), 0])
    assert np.diff(top).max() <= 30.0 + 1e-9


def test_local_affine_extrapolation_is_exact_for_an_affine_map_and_ignores_a_wrong_pair():
    rng = np.random.default_rng(0)
    ref = rng.uniform(50, 150, (40, 2))
    A = np.array([[1.1, 0.2], [-0.1, 0.9]])
    mov = ref @ A.T + [5.0, -3.0]
    targets = np.array([[-0.5, -0.5], [199.5, 60.0], [100.0, 199.5]])
    expected = targets @ A.T + [5.0, -3.0]
    assert np.allclose(local_affine_extrapolation(ref, mov, targets), expected, atol=1e-6)
    # One wrong pair among the nearest is trimmed away.
    near = np.argmin(np.linalg.norm(ref - targets[0], axis=1))
    mov[near] += [30.0, 0.0]
    got = local_affine_extrapolation(ref, mov, targets[:1])
    assert np.linalg.norm(got - expected[:1]) < 0.5


def test_frame_vertices_follow_the_plane_the_border_shows():
    reference, moving = open_book(size=(200, 160), crease=100.0)
    # Points only in the middle of the image.
    rng = np.random.default_rng(1)
    ref = rng.uniform([40, 40], [160, 120], (60, 2))
    mov = np.stack(book_map(ref[:, 0], ref[:, 1], 100.0), axis=1)
    images = prepare_images(reference, moving, 16)
    border, border_mov = frame_vertices(ref, mov, reference.shape, images=images)
    truth = np.stack(book_map(border[:, 0], border[:, 1], 100.0), axis=1)
    err = np.linalg.norm(border_mov - truth, axis=1)
    assert np.median(err) < 1.0, err


def test_extent_frame_covers_the_whole_reference_frame_and_marks_extrapolated_vertices():
    reference, moving = open_book(size=(200, 160), crease=100.0)
    rng = np.random.default_rng(2)
    ref = rng.uniform([50, 40], [150, 120], (40, 2))
    mov = np.stack(book_map(ref[:, 0], ref[:, 1], 100.0), axis=1)
    hull = register(reference, moving, (ref, mov), {"extent": "hull", "optimizer": "none"})
    frame = register(reference, moving, (ref, mov), {"extent": "frame", "optimizer": "none"})
    assert not hull.extrapolated.any()
    assert frame.extrapolated.sum() >= 4
    # Measured vertices are the client's points, unchanged in number.
    assert (~frame.extrapolated).sum() == len(ref)
    inside_hull = hull.registered[:, :, -1] > 0
    inside_frame = frame.registered[:, :, -1] > 0
    assert inside_hull.mean() < 0.6
    # Everything but where the map leaves the moving image (bottom rows of the sheared half).
    assert inside_frame.mean() > 0.9
    # Only the client's own slivers (under min_triangle_area) are holes.
    assert frame.quality.figures["mesh_coverage"] > 0.97
    assert frame.quality.figures["measured_coverage"] < 0.6


def test_frame_is_the_default_extent():
    reference = texture((120, 160), 3)
    ref = np.array([[40.0, 30], [120, 30], [80, 90], [50, 80], [110, 85]])
    r = register(reference, reference, (ref, ref), {"optimizer": "none"})
    assert r.options.extent == "frame"
    assert r.extrapolated.any()
