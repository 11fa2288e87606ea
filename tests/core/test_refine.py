"""Tests of core.refine: vertex insertion guided by the current piecewise map."""

import cv2
import numpy as np
import pytest
from scipy.spatial import cKDTree

from pwlreg.core import refine
from pwlreg.core.epipolar import EpipolarModel
from pwlreg.core.extent import border_positions, local_affine_extrapolation
from pwlreg.core.flow import flow_scale
from pwlreg.core.io import convergence_document, mesh_document
from pwlreg.core.kernels import spaced, window_fits
from pwlreg.core.mesh import Mesh
from pwlreg.core.moves import MOVES, insertions
from pwlreg.core.pipeline import register
from pwlreg.core.refine import (
    CORNER_QUALITY,
    EPI_AMBIGUITY,
    MIN_SPACING,
    STEP_NEAR,
    STEP_OFFSET,
    STEP_WINDOW,
    Insertion,
    epipolar_pairs,
    guide,
    guided_pairs,
    levels,
    sharpen_vertices,
    sharpened,
    step_points,
    vertex_maps,
)
from pwlreg.core.similarity import prepare_images
from pwlreg.core.triangulation import initial_mesh
from pwlreg.core.warp import piecewise_map
from tests.core.synthetic import book_map, book_points, box_front, open_book

SIZE, CREASE = (320, 240), 150.0


def _far_points(zoom: int = 1) -> tuple[np.ndarray, np.ndarray]:
    # A grid that leaves a 90 px band around the crease without vertices: the mesh's triangles
    # span the fold, so their affine maps are off there.
    xs = np.array([5.0, 60.0, 105.0, 195.0, 250.0, 314.0]) * zoom
    ys = np.array([5.0, 80.0, 160.0, 234.0]) * zoom
    ref = np.array([(x, y) for x in xs for y in ys])
    return ref, np.column_stack(book_map(ref[:, 0], ref[:, 1], CREASE * zoom))


def _mean_epe(result) -> float:
    h, w = SIZE[1], SIZE[0]
    mx, my, label = piecewise_map(result.reference_vertices, result.moving_vertices,
                                  result.final_triangles, (h, w))
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    tx, ty = book_map(xx, yy, CREASE)
    return float(np.nanmean(np.hypot(mx - tx, my - ty)[label >= 0]))


def _misses(mesh, found, zoom: int = 1) -> tuple[np.ndarray, np.ndarray]:  # type: ignore[no-untyped-def]
    """Distance (px) of each new pair's moving point to the truth, and of the old mesh's map
    there."""
    truth = np.column_stack(book_map(found.reference[:, 0], found.reference[:, 1],
                                     CREASE * zoom))
    mx, my, _ = piecewise_map(mesh.reference, mesh.moving, mesh.triangles,
                              (SIZE[1] * zoom, SIZE[0] * zoom))
    cells = np.rint(found.reference).astype(int)
    old_miss = np.hypot(mx[cells[:, 1], cells[:, 0]] - truth[:, 0],
                        my[cells[:, 1], cells[:, 0]] - truth[:, 1])
    return np.hypot(*(found.moving - truth).T), old_miss


@pytest.mark.parametrize(("zoom", "scale"), [(1, 1), (3, 2)])
def test_guided_pairs_lie_on_the_true_map(zoom: int, scale: int) -> None:
    # At 960x720 the residual flow stops at a quarter of the side (FLOW_SIDE), not at half.
    ref_img, mov_img = open_book((SIZE[0] * zoom, SIZE[1] * zoom), CREASE * zoom, seed=3)
    assert flow_scale(ref_img.shape) == scale
    ref, mov = _far_points(zoom)
    mesh, _ = initial_mesh(ref, mov, 25.0)
    grey = levels(ref_img, mov_img)
    found = guided_pairs(guide(grey, mesh.reference, mesh.moving, mesh.triangles),
                         prepare_images(ref_img, mov_img, 16), measured=len(ref), budget=len(ref),
                         epsilon=0.01, epsilon_pixels=250.0)
    assert found.counts["inserted"] == len(found.reference) >= 10, found.counts
    assert found.counts["inserted"] <= len(ref)  # the budget
    miss, old_miss = _misses(mesh, found, zoom)
    assert np.median(miss) < 0.5 and miss.max() < 2.0, np.sort(miss)[-5:]
    # Near the fold the old map was wrong by pixels: the new pairs correct it there.
    assert old_miss.max() > 2.0 and miss.mean() < old_miss.mean() / 3


def test_a_small_budget_checks_fewer_candidates_for_the_same_pairs() -> None:
    # The flow's candidates are checked largest correction first, only as far as the budget
    # reaches: the pairs are the budget's largest of those that checking them all gives.
    ref_img, mov_img = open_book(SIZE, CREASE, seed=3)
    ref, mov = _far_points()
    mesh, _ = initial_mesh(ref, mov, 25.0)
    current = guide(levels(ref_img, mov_img), mesh.reference, mesh.moving, mesh.triangles)
    images = prepare_images(ref_img, mov_img, 16)

    def found(budget: int) -> Insertion:
        return guided_pairs(current, images, measured=len(ref), budget=budget, epsilon=0.01,
                            epsilon_pixels=250.0)

    every = found(10_000)
    assert every.counts["checked"] == every.counts["consistent"] > 20
    for budget in (3, 8):
        few = found(budget)
        assert few.counts["checked"] < every.counts["checked"]
        assert few.counts["inserted"] == budget
        np.testing.assert_array_equal(few.reference, every.reference[:budget])
        np.testing.assert_array_equal(few.moving, every.moving[:budget])


#: The open book's epipolar geometry: every displacement is parallel to (-1, 1), so
#: ``x' + y' - x - y = 0`` (an affine fundamental matrix, ``x_mov^T F x_ref = 0``).
BOOK_MODEL = EpipolarModel(
    "affine", np.array([[0.0, 0.0, 0.5], [0.0, 0.0, 0.5], [-0.5, -0.5, 0.0]]), threshold=1.5,
    num_pairs=0, num_inliers=0, iterations=0, rms=0.0)


def _epipolar_pairs(ref_img: np.ndarray, mov_img: np.ndarray):  # type: ignore[no-untyped-def]
    ref, mov = _far_points()
    mesh, _ = initial_mesh(ref, mov, 25.0)
    none = np.zeros((0, 2))
    grey = levels(ref_img, mov_img)
    found = epipolar_pairs(guide(grey, mesh.reference, mesh.moving, mesh.triangles),
                           prepare_images(ref_img, mov_img, 16), BOOK_MODEL,
                           added=(none, none), measured=len(ref), budget=len(ref), epsilon=0.01,
                           epsilon_pixels=250.0)
    return mesh, found


def test_epipolar_pairs_lie_on_the_true_map() -> None:
    ref_img, mov_img = open_book(SIZE, CREASE, seed=3)
    mesh, found = _epipolar_pairs(ref_img, mov_img)
    assert 10 <= found.counts["inserted"] == len(found.reference) <= len(mesh.reference)
    miss, old_miss = _misses(mesh, found)
    assert np.median(miss) < 0.5 and miss.max() < 1.5, np.sort(miss)[-5:]
    assert old_miss.max() > 2.0 and miss.mean() < old_miss.mean() / 3


def test_extrapolated_border_vertices_leave_room_for_measured_pairs() -> None:
    # Measured vertices in the middle only, and the frame's border extrapolated from them
    # (extent="frame"): the border vertices are no measurement, so corners near the frame's
    # side may become pairs; counted as vertices, they kept every candidate within 15 px of
    # the side away.
    ref_img, mov_img = open_book(SIZE, CREASE, seed=3)
    xs, ys = np.linspace(70.0, 250.0, 4), np.linspace(60.0, 180.0, 3)
    ref = np.array([(x, y) for x in xs for y in ys])
    mov = np.column_stack(book_map(ref[:, 0], ref[:, 1], CREASE))
    border = border_positions((SIZE[1], SIZE[0]), 40.0)
    mesh, report = initial_mesh(
        np.concatenate([ref, border]),
        np.concatenate([mov, local_affine_extrapolation(ref, mov, border)]),
        25.0, np.arange(len(ref) + len(border)) >= len(ref))
    grey, images = levels(ref_img, mov_img), prepare_images(ref_img, mov_img, 16)
    none = np.zeros((0, 2))

    def near_side(extrapolated: np.ndarray | None) -> np.ndarray:
        found = epipolar_pairs(
            guide(grey, mesh.reference, mesh.moving, mesh.triangles, extrapolated=extrapolated),
            images, BOOK_MODEL, added=(none, none), measured=len(ref), budget=2 * len(ref),
            epsilon=0.01, epsilon_pixels=250.0)
        x, y = found.reference.T
        near = np.minimum(np.minimum(x, SIZE[0] - 1 - x), np.minimum(y, SIZE[1] - 1 - y)) < 15
        truth = np.column_stack(book_map(x[near], y[near], CREASE))
        return np.hypot(*(found.moving[near] - truth).T)

    assert len(near_side(None)) == 0
    miss = near_side(report.extrapolated)
    assert len(miss) >= 3 and miss.max() < 1.5, miss


def test_epipolar_pairs_refuse_repeated_texture() -> None:
    # A 4 px motif repeated over the image: along any epipolar line the patch comes back
    # every 5.7 px, so no match is unambiguous (a wrong one is as likely as the right one).
    rng = np.random.default_rng(5)
    motif = rng.integers(0, 256, (4, 4)).astype(np.uint8)
    moving = np.tile(motif, (SIZE[1] // 4 + 8, SIZE[0] // 4 + 4))[:SIZE[1], :SIZE[0]].copy()
    moving = cv2.GaussianBlur(moving, (0, 0), 1.0)
    ys, xs = np.mgrid[0:SIZE[1], 0:SIZE[0]].astype(np.float32)
    mx, my = book_map(xs, ys, CREASE)
    reference = cv2.remap(moving, mx.astype(np.float32), my.astype(np.float32),
                          cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    _, found = _epipolar_pairs(reference, moving)
    assert found.counts["candidates"] > 20, found.counts
    assert found.counts["unique"] <= found.counts["candidates"] // 4, found.counts
    assert found.counts["inserted"] == 0, found.counts


def test_epipolar_pairs_keep_to_the_line_where_an_edge_crosses_it() -> None:
    # Horizontal stripes: every patch is an edge, which the epipolar lines (along (-1, 1))
    # cross at 45 degrees. Searched a band across the line, the correlation is as high anywhere
    # along the edge: the match must stay where the line crosses it (without EPI_TIE, 1.45 px
    # off along the edge; before the band-edge and sharpness rules, 3.7 px).
    rng = np.random.default_rng(1)
    w, h = SIZE
    profile = cv2.GaussianBlur(rng.uniform(0, 255, (1, 4 * h)).astype(np.float32), (0, 0), 1.5)
    moving = np.repeat(profile.ravel()[2 * h:3 * h, None], w, axis=1)
    moving = np.clip(moving + rng.normal(0, 2, moving.shape), 0, 255).astype(np.uint8)
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    mx, my = book_map(xs, ys, CREASE)
    reference = cv2.remap(moving, mx.astype(np.float32), my.astype(np.float32),
                          cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    mesh, found = _epipolar_pairs(reference, moving)
    assert found.counts["inserted"] >= 10, found.counts
    miss, _ = _misses(mesh, found)
    # A patch on the fold itself sees both pages: about a pixel off there.
    off_fold = np.abs(found.reference[:, 0] - CREASE) > 10
    assert off_fold.sum() >= 10
    assert miss[off_fold].max() < 1.0 and miss.max() < 1.5, np.sort(miss)[-5:]


def test_insertion_lowers_the_error_and_is_recorded() -> None:
    ref_img, mov_img = open_book(SIZE, CREASE, seed=3)
    points = _far_points()
    options = {"epipolar_filter": False, "extent": "hull"}
    plain = register(ref_img, mov_img, points, {**options, "insert_vertices": "automatic"})
    refined = register(ref_img, mov_img, points, {**options, "insert_vertices": "always"})
    assert plain.insertion is None and not plain.inserted.any()  # client points are kept as sent
    # Nor are they sharpened with the pairs the insertion adds.
    client = np.array(refined.origins) == "client"
    truth = np.column_stack(book_map(*refined.reference_vertices[client].T, CREASE))
    assert np.abs(refined.moving_vertices[client] - truth).max() <= 1 / 256
    assert refined.insertion["sharpened"] > 0
    assert refined.inserted.sum() == refined.insertion["inserted"] > 0
    assert len(refined.reference_vertices) == len(refined.points.reference) + refined.inserted.sum()
    assert _mean_epe(refined) < 0.5 * _mean_epe(plain)
    # Each vertex names what put it there; mesh.json and convergence.json count every move.
    assert set(plain.origins) == {"client"}
    for name, _ in insertions():
        assert refined.origins.count(name) == refined.insertion.get(f"{name} inserted", 0)
    moves = {m["move"]: m for m in mesh_document(refined)["moves"]}
    assert moves == {m["move"]: m for m in convergence_document(refined)["moves"]}
    assert sum(m["count"] for m in moves.values() if m["kind"] == "insertion") == (
        refined.inserted.sum())
    assert sum(m["count"] for m in moves.values() if m["kind"] == "swap") == (
        len(refined.search.steps))
    assert all(m["reason"] == MOVES[name].reason for name, m in moves.items())
    assert mesh_document(refined)["vertex_origins"] == refined.origins


def test_the_flow_reads_the_mesh_the_epipolar_search_corrected(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # With an epipolar geometry the first round searches along the lines only and the flow
    # reads the mesh it corrected, once; without one the flow reads every round's mesh.
    import pwlreg.core.moves as moves
    import pwlreg.core.pipeline as pipeline

    meshes: list[int] = []  # vertices of each mesh the insertion looked at
    read: list[int] = []  # of those the flow read

    def seen_guide(grey, reference, *args, **kwargs):  # noqa: ANN001, ANN202 - spies
        meshes.append(len(reference))
        return guide(grey, reference, *args, **kwargs)

    def seen_flow(mesh, *args, **kwargs):  # noqa: ANN001, ANN202
        read.append(len(mesh.reference_vertices))
        return guided_pairs(mesh, *args, **kwargs)

    monkeypatch.setattr(pipeline, "guide", seen_guide)
    monkeypatch.setattr(moves, "guided_pairs", seen_flow)
    ref_img, mov_img = open_book((320, 240), 160.0, seed=1)
    with_model = register(ref_img, mov_img)
    assert with_model.points.epipolar is not None
    assert len(meshes) == 2 and meshes[1] > meshes[0] and read == meshes[1:]
    assert with_model.insertion["flow inserted"] > 0
    meshes.clear()
    read.clear()
    without = register(ref_img, mov_img, options={"epipolar_filter": False})
    assert without.points.epipolar is None and read == meshes and len(read) == 2


def test_spaced_is_the_greedy_choice_in_order() -> None:
    rng = np.random.default_rng(5)
    points = rng.uniform(0, 200, (3000, 2))
    points[:50] = points[0] + rng.normal(0, 1.0, (50, 2))  # a dense cluster first
    pixels = rng.integers(0, 60, (3000, 2)).astype(np.float64)  # whole pixels, as corners are
    cases = [(points, d, c) for d, c in ((7.5, 10_000), (12.0, 100), (2.0, 3000))]
    cases += [(pixels, d, 10_000) for d in (1.0, 2.0, 2 * np.sqrt(2), 3.0, 5.0, np.sqrt(50))]
    for points, distance, count in cases:
        kept: list[int] = []
        for i, p in enumerate(points):
            if len(kept) == count:
                break
            # OpenCV's rule, on squared distances (ties at whole pixels fall the same way).
            if all(((points[kept] - p) ** 2).sum(axis=1) >= distance**2) if kept else True:
                kept.append(i)
        assert spaced(points, distance, count).tolist() == kept
    assert spaced(points[:0], 5.0, 10).tolist() == []


def test_shared_corners_are_what_opencv_chooses() -> None:
    # Thinning the one detection to a source's spacing gives OpenCV's own choice at that
    # spacing, so both sources and both rounds share one detection.
    ref_img, mov_img = open_book(SIZE, CREASE, seed=3)
    grey = levels(ref_img, mov_img)
    for vertices in (24, 60, 200, 5000):
        distance = max(np.sqrt(SIZE[0] * SIZE[1] / vertices) * MIN_SPACING, 2.0)
        direct = cv2.goodFeaturesToTrack(ref_img, 4 * vertices, CORNER_QUALITY, distance)
        chosen = grey.corners[spaced(grey.corners, distance, 4 * vertices)]
        np.testing.assert_array_equal(chosen, direct.reshape(-1, 2))


def test_epipolar_pairs_reach_a_surface_with_no_vertex(monkeypatch: pytest.MonkeyPatch) -> None:
    # A block standing 20 px along the epipolar direction (-1, 1) off a flat background, with
    # every vertex on the background: its neighbours' displacements (all zero) say nothing of
    # it, so the search must reach beyond them and their 8 px margin (EPI_REACH). (Few of its
    # pairs pass the mutual-information test: one vertex moves little of a triangle that
    # large.)
    w, h = SIZE
    shift = 14.0  # 20 px along (-1, 1)
    moving = open_book(SIZE, CREASE, seed=4)[1]
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    block = (xs >= 120) & (xs < 200) & (ys >= 80) & (ys < 160)
    mx, my = np.where(block, xs - shift, xs), np.where(block, ys + shift, ys)
    reference = cv2.remap(moving, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    grid = np.array([(x, y) for x in np.linspace(4, w - 5, 7) for y in np.linspace(4, h - 5, 5)])
    outside = ~((grid[:, 0] > 105) & (grid[:, 0] < 215) & (grid[:, 1] > 65) & (grid[:, 1] < 175))
    # A ring just outside the block: the triangles over it hold little but the block.
    ring = [(x, y) for x in np.linspace(115, 205, 5) for y in (75.0, 165.0)]
    ring += [(x, y) for x in (115.0, 205.0) for y in np.linspace(97.5, 142.5, 3)]
    ref = np.concatenate([grid[outside], ring])
    mesh, _ = initial_mesh(ref, ref.copy(), 25.0)
    none = np.zeros((0, 2))

    def found_on_block():  # type: ignore[no-untyped-def]
        found = epipolar_pairs(guide(levels(reference, moving), mesh.reference, mesh.moving,
                                     mesh.triangles),
                               prepare_images(reference, moving, 16), BOOK_MODEL,
                               added=(none, none), measured=len(ref), budget=len(ref),
                               epsilon=0.01, epsilon_pixels=250.0)
        cells = np.rint(found.reference).astype(int)
        inside = block[cells[:, 1], cells[:, 0]]
        truth = found.reference[inside] + [-shift, shift]
        return np.hypot(*(found.moving[inside] - truth).T)

    miss = found_on_block()
    assert len(miss) >= 3 and miss.max() < 0.5, np.sort(miss)
    monkeypatch.setattr("pwlreg.core.refine.EPI_REACH", 0)
    assert len(found_on_block()) == 0


def test_a_pair_standing_alone_needs_a_clearer_peak(monkeypatch: pytest.MonkeyPatch) -> None:
    # The block of the test above with no vertex near it: its pairs are many and move alike,
    # so none stands alone; made to, they must clear EPI_ALONE_AMBIGUITY instead of
    # EPI_AMBIGUITY.
    w, h = SIZE
    moving = open_book(SIZE, CREASE, seed=4)[1]
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    block = (xs >= 120) & (xs < 200) & (ys >= 80) & (ys < 160)
    reference = cv2.remap(moving, np.where(block, xs - 14.0, xs), np.where(block, ys + 14.0, ys),
                          cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    grid = np.array([(x, y) for x in np.linspace(4, w - 5, 7) for y in np.linspace(4, h - 5, 5)])
    ref = grid[~((grid[:, 0] > 105) & (grid[:, 0] < 215) & (grid[:, 1] > 65)
                 & (grid[:, 1] < 175))]
    mesh, _ = initial_mesh(ref, ref.copy(), 25.0)
    none = np.zeros((0, 2))

    def passed() -> int:  # the pairs through the neighbours' checks
        return epipolar_pairs(guide(levels(reference, moving), mesh.reference, mesh.moving,
                                    mesh.triangles),
                              prepare_images(reference, moving, 16), BOOK_MODEL,
                              added=(none, none), measured=len(ref), budget=len(ref),
                              epsilon=0.01, epsilon_pixels=250.0).counts["neighbours"]

    judged = passed()
    assert judged >= 10
    monkeypatch.setattr("pwlreg.core.refine.unjudged_pairs",
                        lambda reference, moving, *, wanted: np.asarray(wanted, bool))
    assert 0 < passed() < judged  # some rival peaks reach 0.8 (none 0.9: EPI_AMBIGUITY)
    monkeypatch.setattr("pwlreg.core.refine.EPI_ALONE_AMBIGUITY", EPI_AMBIGUITY)
    assert passed() == judged
    monkeypatch.setattr("pwlreg.core.refine.EPI_ALONE_AMBIGUITY", 0.0)
    assert passed() == 0


RECTIFIED = EpipolarModel(
    "affine", np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]), threshold=1.5,
    num_pairs=0, num_inliers=0, iterations=0, rms=0.0)
BOX = (110, 70, 210, 170)


def test_step_pairs_lie_on_both_sides_of_a_depth_step() -> None:
    # A box in front of a wall, a mesh with no vertex within 15 px of the box's outline: its
    # triangles there span the depth step and map like neither surface.
    ref_img, mov_img, disparity = box_front(box=BOX, seed=2)
    ref = np.array([(x, y) for x in np.linspace(5.0, 314.0, 8) for y in np.linspace(5.0, 234.0, 6)])
    mov = ref - np.column_stack([disparity[ref[:, 1].astype(int), ref[:, 0].astype(int)],
                                 np.zeros(len(ref))])
    mesh, _ = initial_mesh(ref, mov, 25.0)
    current = guide(levels(ref_img, mov_img), mesh.reference, mesh.moving, mesh.triangles)
    points, shifts = step_points(current)
    # Beside the outline, on both sides of it, never closer together than STEP_NEAR.
    x0, y0, x1, y1 = BOX
    inside = (points[:, 0] >= x0) & (points[:, 0] < x1) & (points[:, 1] >= y0) & (points[:, 1] < y1)
    to_outline = np.minimum.reduce([np.abs(points[:, 0] - x0), np.abs(points[:, 0] - x1),
                                    np.abs(points[:, 1] - y0), np.abs(points[:, 1] - y1)])
    assert inside.sum() >= 8 and (~inside).sum() >= 8, points
    # Most beside the outline; the others where the flow inside the box, wrong by up to 12 px,
    # is not smooth.
    assert np.mean(to_outline < STEP_OFFSET + 3) > 0.5, np.sort(to_outline)
    gaps, _ = cKDTree(points).query(points, k=2)
    assert gaps[:, 1].min() >= STEP_NEAR

    # Each patch is centred STEP_WINDOW beyond its point, away from the jump.
    assert np.allclose(np.hypot(*shifts.T), STEP_WINDOW)
    sides = np.einsum("ij,ij->i", shifts, points - np.array([(x0 + x1) / 2, (y0 + y1) / 2]))
    assert np.mean((sides > 0) != inside) > 0.8

    none = np.zeros((0, 2))

    def search(offsets: np.ndarray) -> tuple[Insertion, np.ndarray, np.ndarray, np.ndarray]:
        found = epipolar_pairs(current, prepare_images(ref_img, mov_img, 16), RECTIFIED,
                               added=(none, none), measured=len(ref), budget=len(points),
                               epsilon=0.01, epsilon_pixels=250.0, candidates=(points, offsets))
        cells = np.rint(found.reference).astype(int)
        truth = found.reference - np.column_stack([disparity[cells[:, 1], cells[:, 0]],
                                                   np.zeros(len(cells))])
        return found, cells, truth, np.hypot(*(found.moving - truth).T)

    # Patches centred on the points reach over the step more often and correlate less.
    centred, _, _, miss = search(np.zeros_like(shifts))
    assert np.median(miss) < 0.3 and miss.max() < 1.5, np.sort(miss)[-5:]
    found, cells, truth, miss = search(shifts)
    assert found.counts["correlated"] > centred.counts["correlated"], (found.counts,
                                                                       centred.counts)
    assert found.counts["inserted"] == len(found.reference) >= 16, found.counts
    # The match of a shifted patch is moved back to its point by the map that shaped the
    # patch; the mesh's triangles over this step map some 25 % off both surfaces, 4 px of
    # which is 1 px.
    assert np.median(miss) < 0.6 and miss.max() < 2.0, np.sort(miss)[-5:]
    on_box = (cells[:, 0] >= x0) & (cells[:, 0] < x1) & (cells[:, 1] >= y0) & (cells[:, 1] < y1)
    assert on_box.sum() >= 4 and (~on_box).sum() >= 4
    # The mesh was wrong there by pixels (the box moves 12 px more than the wall).
    mx, my, _ = piecewise_map(mesh.reference, mesh.moving, mesh.triangles, disparity.shape)
    old_miss = np.hypot(mx[cells[:, 1], cells[:, 0]] - truth[:, 0],
                        my[cells[:, 1], cells[:, 0]] - truth[:, 1])
    assert np.mean(old_miss) > 2.0 and np.mean(miss) < np.mean(old_miss) / 4


def test_step_pairs_lower_the_error_of_a_mesh_across_depth_steps() -> None:
    # The whole pipeline with the client's sparse points refined (insert_vertices="always"):
    # the step source puts vertices along the box's outline, and the mean error over the
    # pixels the wall and the box both show falls.
    # Two rows of the points cross the box: with the two pairs on it in one row, the wall's
    # pairs and theirs leave a one-parameter family of rank-2 epipolar geometries open (the
    # eight-point rows have a second null direction), and the steps were found only because
    # the robust fit happened to pick the right member.
    ref_img, mov_img, disparity = box_front(box=BOX, seed=2)
    xs, ys = np.linspace(5.0, 314.0, 6), np.linspace(5.0, 234.0, 6)
    ref = np.array([(x, y) for x in xs for y in ys])
    mov = ref - np.column_stack([disparity[ref[:, 1].astype(int), ref[:, 0].astype(int)],
                                 np.zeros(len(ref))])
    r = register(ref_img, mov_img, (ref, mov), {"extent": "hull", "insert_vertices": "always"})
    assert r.origins.count("step") == r.insertion["step inserted"] >= 10, r.insertion
    h, w = disparity.shape
    mx, my, label = piecewise_map(r.reference_vertices, r.moving_vertices, r.final_triangles,
                                  (h, w))
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    err = np.hypot(mx - (xx - disparity), my - yy)[label >= 0]
    assert np.mean(err) < 0.5, np.mean(err)


def _containing_numpy(vertices, tris, points):
    """The numpy form the compiled point location replaced: every point against every
    triangle, the first that holds it."""
    a, b, c = (vertices[tris[:, k]] for k in range(3))
    v0, v1 = c - a, b - a
    d00, d01, d11 = (v0 * v0).sum(1), (v0 * v1).sum(1), (v1 * v1).sum(1)
    den = d00 * d11 - d01 * d01
    v2 = points[:, None, :] - a[None]
    d20, d21 = (v2 * v0).sum(2), (v2 * v1).sum(2)
    with np.errstate(divide="ignore", invalid="ignore"):
        u = (d11 * d20 - d01 * d21) / den
        v = (d00 * d21 - d01 * d20) / den
    hit = (u >= 0) & (v >= 0) & (u + v <= 1)
    return np.where(hit.any(axis=1), hit.argmax(axis=1), -1)


@pytest.mark.parametrize("seed", range(6))
def test_point_location_is_the_numpy_one(seed: int) -> None:
    from scipy.spatial import Delaunay

    from pwlreg.core.raster import quantize
    from pwlreg.core.refine import _containing

    rng = np.random.default_rng(seed)
    n = int(rng.integers(3, 300))
    v = quantize(rng.uniform(0, 200, (n, 2)))
    if seed % 2:  # collinear vertices and shared coordinates
        v = np.unique(np.round(v / 10) * 10, axis=0)
        n = len(v)
    tris = Delaunay(v).simplices
    # Degenerate and overlapping triangles too, and points on vertices and on edges.
    tris = np.concatenate([tris, rng.integers(0, n, (4, 3))])
    pts = np.concatenate([quantize(rng.uniform(-10, 210, (150, 2))), v[rng.integers(0, n, 10)],
                          (v[tris[:8, 0]] + v[tris[:8, 1]]) / 2])
    got = _containing(v, tris, pts)
    assert (got >= 0).sum() > 100
    np.testing.assert_array_equal(got, _containing_numpy(v, tris, pts))


def _book_pairs(n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Reference points of the open book away from its crease and the frame, their true
    moving points, and the book's linear map at each."""
    rng = np.random.default_rng(seed)
    ref = np.column_stack([rng.uniform(30, SIZE[0] - 30, 4 * n),
                           rng.uniform(30, SIZE[1] - 60, 4 * n)])
    ref = ref[np.abs(ref[:, 0] - CREASE) > 25][:n]
    truth = np.column_stack(book_map(ref[:, 0], ref[:, 1], CREASE))
    right = ref[:, 0] > CREASE
    linear = np.where(right[:, None, None], [[0.65, 0.0], [0.35, 1.0]], np.eye(2))
    return ref, truth, linear


def test_sharpened_pairs_come_nearer_their_truth() -> None:
    ref_img, mov_img = open_book(SIZE, CREASE, seed=3)
    ref, truth, linear = _book_pairs(40, seed=1)
    rng = np.random.default_rng(2)
    off = rng.uniform(-0.6, 0.6, truth.shape)
    off[0] = [3.0, 0.0]  # farther than a sharpened pair may move
    found = sharpened(levels(ref_img, mov_img), ref, truth + off, linear, model=None)
    before, after = np.hypot(*off.T), np.hypot(*(found - truth).T)
    assert np.array_equal(found[0], truth[0] + off[0])
    assert np.median(after[1:]) < 0.1 < np.median(before[1:]), np.median(after)
    assert (after[1:] < before[1:]).mean() > 0.9
    # Where the new positions are off their epipolar lines (here a pixel beside the true
    # ones, with a tolerance of 0.01 px), the pairs stay where they were.
    shifted = BOOK_MODEL.matrix + [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    strict = EpipolarModel(BOOK_MODEL.kind, shifted, threshold=0.01, num_pairs=0,
                           num_inliers=0, iterations=0, rms=0.0)
    kept = sharpened(levels(ref_img, mov_img), ref, truth + off, linear, model=strict)
    assert np.array_equal(kept, truth + off)


def test_vertex_maps_are_the_mean_of_the_triangles_around() -> None:
    ref, mov = book_points(100.0)
    mesh, _ = initial_mesh(ref, mov, 25.0)
    maps, spread = vertex_maps(mesh.reference, mesh.moving, mesh.triangles)
    left = mesh.reference[:, 0] < 70  # every triangle around them lies left of the crease
    assert np.allclose(maps[left], np.eye(2), atol=1e-3) and np.all(spread[left] < 1e-3)
    # Crease vertices have triangles on both pages (and across the fold): their maps differ.
    crease = np.isclose(mesh.reference[:, 0], 100.0, atol=0.01)
    assert crease.any() and np.all(spread[crease] > 0.15)


def _textured(shape: tuple[int, int], seed: int) -> np.ndarray:
    """Smoothed noise: texture at every scale the fits look at."""
    noise = np.random.default_rng(seed).uniform(0, 255, shape).astype(np.float32)
    return cv2.GaussianBlur(noise, (0, 0), 1.5) * 3.0 - 250.0


def test_window_fits_recover_an_affine_map_as_opencv_does() -> None:
    ref = _textured((160, 160), seed=4)
    # The moving image is the reference under a known affine map, with another gain and offset.
    true = np.array([[1.06, 0.08, 7.3], [-0.05, 0.97, -4.6]])
    mov = cv2.warpAffine(ref, true, (160, 160), flags=cv2.INTER_CUBIC) * 0.6 + 30.0
    rng = np.random.default_rng(5)
    points = rng.uniform(40, 120, (20, 2))
    # First guesses 0.8 px off, with the identity as the local map.
    start = points @ true[:, :2].T + true[:, 2] + rng.uniform(-0.8, 0.8, points.shape)
    maps = np.concatenate([np.tile(np.eye(2), (20, 1, 1)), start[:, :, None]], axis=2)
    centres, scores = np.empty((20, 2)), np.empty(20)
    window_fits(ref, mov.astype(np.float32), points, maps, 15, 10, 1e-4, centres, scores)
    truth = points @ true[:, :2].T + true[:, 2]
    error = np.hypot(*(centres - truth).T)
    assert np.all(scores > 0.99) and error.max() < 0.05, error
    # OpenCV's forward fit of the same windows lands at the same places.
    for k in range(0, 20, 4):
        window = cv2.getRectSubPix(ref, (31, 31), tuple(points[k]))
        warp = maps[k].astype(np.float32).copy()
        warp[:, 2] -= warp[:, :2] @ [15, 15]
        _, warp = cv2.findTransformECC(window, mov.astype(np.float32), warp,
                                       cv2.MOTION_AFFINE,
                                       (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-6),
                                       None, 1)
        opencv = warp[:, :2] @ [15, 15] + warp[:, 2]
        assert np.hypot(*(centres[k] - opencv)) < 0.05


def test_window_fits_refuse_flat_windows_and_the_border() -> None:
    ref = _textured((100, 100), seed=6)
    ref[:, 60:] = 80.0
    points = np.array([[30.0, 50.0], [80.0, 50.0], [8.0, 50.0]])
    maps = np.concatenate([np.tile(np.eye(2), (3, 1, 1)), points[:, :, None]], axis=2)
    centres, scores = np.empty((3, 2)), np.empty(3)
    window_fits(ref, ref, points, maps, 15, 5, 1e-3, centres, scores)
    assert scores[0] > 0.999 and np.allclose(centres[0], points[0], atol=1e-3)
    assert scores[1] == -1.0 and scores[2] == -2.0  # flat; the window leaves the image
    assert np.array_equal(centres[1:], points[1:])


def test_sharpened_vertices_fold_no_triangle(monkeypatch: pytest.MonkeyPatch) -> None:
    ref = np.array([[0.0, 0.0], [40.0, 0.0], [0.0, 40.0], [40.0, 40.0], [20.0, 20.0]])
    mesh, _ = initial_mesh(ref, ref + 3.0, 1.0)
    moves = {4: [1.0, 0.5], 2: [0.5, -0.5], 3: [0.0, 1.0]}

    def fitted(image_levels, reference, moving, linear, *, model):  # type: ignore[no-untyped-def]
        index = cKDTree(mesh.reference).query(reference)[1]
        return moving + np.array([moves.get(int(i), [0.0, 0.0]) for i in index])

    monkeypatch.setattr(refine, "sharpened", fitted)
    movable = np.array([True, True, True, False, True])
    out = sharpen_vertices(None, mesh.reference, mesh.moving, mesh.triangles, movable,
                           model=None)
    assert np.allclose(out[[2, 4]], mesh.moving[[2, 4]] + [[0.5, -0.5], [1.0, 0.5]])
    assert np.array_equal(out[3], mesh.moving[3])  # not movable
    # Vertex 1 across the centre would fold its triangles: they keep their corners, the
    # centre among them; vertex 2, on none of them, still moves.
    moves[1] = [-45.0, 22.0]
    out = sharpen_vertices(None, mesh.reference, mesh.moving, mesh.triangles, movable,
                           model=None)
    assert not Mesh(mesh.reference, out, mesh.triangles).reversed_slots()
    around = np.unique(mesh.triangles[(mesh.triangles == 1).any(axis=1)])
    assert 4 in around and 2 not in around
    assert np.array_equal(out[around], mesh.moving[around])
    assert np.allclose(out[2], mesh.moving[2] + [0.5, -0.5])
