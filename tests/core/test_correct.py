"""The vertex moves of core.correct: a contradicted vertex moves with its neighbours, a right
one stays; an extrapolated border vertex is searched for along its epipolar line, within the
segment its extrapolations span."""

import cv2
import numpy as np
import pytest
from scipy.spatial import Delaunay

from bench import middlebury
from bench.metrics import endpoint_error
from pwlreg.core.align import REACH as ALIGN_REACH
from pwlreg.core.correct import (
    ALIGN_MOVE,
    BORDER_MOVE,
    MOVE,
    REMOVE_MOVE,
    Corrections,
    border_search,
    contradicted_vertices,
    removed_vertices,
)
from pwlreg.core.io import convergence_document, mesh_document
from pwlreg.core.moves import MOVES
from pwlreg.core.options import RegistrationOptions
from pwlreg.core.pipeline import register
from pwlreg.core.raster import orientation, triangle_areas
from pwlreg.core.similarity import prepare_images, reduced
from tests.core.synthetic import book_map, open_book, texture

CREASE = 100.0
DEFAULTS = RegistrationOptions()


def _book_mesh() -> tuple:
    """The open book and a right mesh over it: vertices on both planes, their moving
    positions true (the right plane shears: neighbours there move up to 9 px apart)."""
    reference, moving = open_book((200, 160), CREASE, seed=5)
    xs, ys = np.meshgrid([10, 35, 60, 85, 115, 140, 165, 190], [10, 45, 80, 115, 150])
    ref_v = np.column_stack([xs.ravel(), ys.ravel()]).astype(np.float64)
    mov_v = np.column_stack(book_map(ref_v[:, 0], ref_v[:, 1], CREASE))
    tris = Delaunay(ref_v).simplices
    return prepare_images(reference, moving, DEFAULTS.bins), ref_v, mov_v, tris


def _check(images, ref_v, mov_v, tris, movable=None, cost="mi"):  # type: ignore[no-untyped-def]
    movable = np.ones(len(ref_v), bool) if movable is None else movable
    return contradicted_vertices(images, ref_v, mov_v, tris, movable, cost=cost,
                                 epsilon=DEFAULTS.epsilon, epsilon_pixels=DEFAULTS.epsilon_pixels)


def test_a_right_mesh_keeps_its_vertices_where_neighbours_move_apart() -> None:
    images, ref_v, mov_v, tris = _book_mesh()
    found = _check(images, ref_v, mov_v, tris)
    assert found.tested > 0  # scored: the sheared plane's neighbours differ by over SUSPECT_PX
    assert len(found.vertices) == 0


@pytest.mark.parametrize("cost", ["mi", "ncc"])
def test_a_vertex_off_its_plane_moves_back_with_its_neighbours(cost: str) -> None:
    images, ref_v, mov_v, tris = _book_mesh()
    wrong = int(np.flatnonzero((ref_v[:, 0] == 35) & (ref_v[:, 1] == 80))[0])
    off = mov_v.copy()
    off[wrong] += [5.0, -2.0]
    found = _check(images, ref_v, off, tris, cost=cost)
    # Only that vertex: each of its neighbours has one neighbour (it) moving apart, and one
    # neighbour moves nothing.
    assert found.vertices.tolist() == [wrong]
    np.testing.assert_allclose(found.moving[0], mov_v[wrong], atol=1e-9)
    np.testing.assert_allclose(found.before[0], off[wrong])
    assert found.gains[0] > 0
    record = found.to_list()[0]
    assert record["vertex"] == wrong and record["move"] == MOVE == "correct"
    # A vertex that may not move (the client's) stays where it is.
    fixed = np.ones(len(ref_v), bool)
    fixed[wrong] = False
    assert len(_check(images, ref_v, off, tris, fixed, cost).vertices) == 0


def test_only_witnesses_propose_a_motion() -> None:
    images, ref_v, mov_v, tris = _book_mesh()
    wrong = int(np.flatnonzero((ref_v[:, 0] == 35) & (ref_v[:, 1] == 80))[0])
    off = mov_v.copy()
    off[wrong] += [5.0, -2.0]
    # Its neighbours' motions (true here) are guesses, as a border's extrapolated ones are.
    guessed = np.ones(len(ref_v), bool)
    guessed[np.unique(tris[(tris == wrong).any(axis=1)])] = False
    guessed[wrong] = True
    found = contradicted_vertices(images, ref_v, off, tris, np.ones(len(ref_v), bool),
                                  witnesses=guessed, epsilon=DEFAULTS.epsilon,
                                  epsilon_pixels=DEFAULTS.epsilon_pixels)
    assert wrong not in found.vertices.tolist()
    assert wrong in _check(images, ref_v, off, tris).vertices.tolist()


def test_of_two_neighbours_off_their_plane_one_moves_in_a_pass() -> None:
    images, ref_v, mov_v, tris = _book_mesh()
    pair = [int(np.flatnonzero((ref_v[:, 0] == 35) & (ref_v[:, 1] == y))[0]) for y in (45, 80)]
    assert any(set(pair) <= set(t) for t in tris.tolist())  # neighbours
    off = mov_v.copy()
    off[pair] += [5.0, -2.0]
    found = _check(images, ref_v, off, tris)
    # Each was scored with the other in place: only the larger gain moves, to its truth.
    assert len(found.vertices) == 1 and found.vertices[0] in pair
    np.testing.assert_allclose(found.moving[0], mov_v[found.vertices[0]], atol=1e-9)
    # The next pass moves the other one.
    again = off.copy()
    again[found.vertices] = found.moving
    second = _check(images, ref_v, again, tris)
    assert second.vertices.tolist() == [v for v in pair if v != found.vertices[0]]


def test_a_client_point_the_images_contradict_is_kept_as_sent() -> None:
    reference, moving = open_book((200, 160), CREASE, seed=5)
    xs, ys = np.meshgrid([10, 35, 60, 85, 115, 140, 165, 190], [10, 45, 80, 115, 150])
    ref_pts = np.column_stack([xs.ravel(), ys.ravel()]).astype(np.float64)
    mov_pts = np.column_stack(book_map(ref_pts[:, 0], ref_pts[:, 1], CREASE))
    wrong = int(np.flatnonzero((ref_pts[:, 0] == 35) & (ref_pts[:, 1] == 80))[0])
    mov_pts[wrong] += [5.0, -2.0]
    options = {"epipolar_filter": False, "extent": "hull", "insert_vertices": "always"}
    result = register(reference, moving, (ref_pts, mov_pts), options)
    assert result.corrections is not None  # the move ran (with the insertion)
    at = int(np.argmin(np.linalg.norm(result.reference_vertices - ref_pts[wrong], axis=1)))
    assert result.origins[at] == "client"
    np.testing.assert_allclose(result.moving_vertices[at], mov_pts[wrong], atol=0.01)
    assert all(result.origins[v] != "client" for v in result.corrections.vertices)


def test_a_move_that_would_fold_a_triangle_is_not_made() -> None:
    # The moving image is the reference 12 px to the right; a vertex and one neighbour stay
    # put, its three other neighbours move 12 px right (true).
    reference = texture((160, 200), seed=7)
    moving = np.roll(reference, 12, axis=1)
    images = prepare_images(reference, moving, DEFAULTS.bins)

    def star(near_x: float):  # type: ignore[no-untyped-def]
        ref_v = np.array([[100, 80], [60, 80], [100, 120], [near_x, 80], [100, 40]], float)
        mov_v = ref_v + [[0, 0], [12, 0], [12, 0], [0, 0], [12, 0]]
        tris = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 4], [0, 4, 1]])
        movable = np.array([True, False, False, False, False])
        return contradicted_vertices(images, ref_v, mov_v, tris, movable,
                                     epsilon=DEFAULTS.epsilon,
                                     epsilon_pixels=DEFAULTS.epsilon_pixels)

    # With the still neighbour 40 px away the vertex moves to its true place...
    far = star(140.0)
    assert far.vertices.tolist() == [0]
    np.testing.assert_allclose(far.moving[0], [112, 80])
    # ... with it 8 px away that place lies beyond it: two triangles would fold.
    near = star(108.0)
    assert near.tested == 1 and len(near.vertices) == 0


def _remove(images, ref_v, mov_v, tris, removable=None, cost="mi"):  # type: ignore[no-untyped-def]
    removable = np.ones(len(ref_v), bool) if removable is None else removable
    return removed_vertices(images, ref_v, mov_v, tris, removable, epsilon=DEFAULTS.epsilon,
                            epsilon_pixels=DEFAULTS.epsilon_pixels, cost=cost)


def _positive(ref_v: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """The triangles, each positively oriented in the reference (as a Mesh holds them)."""
    tris = tris.copy()
    back = orientation(*ref_v[tris].transpose(1, 0, 2)) < 0
    tris[back] = tris[back][:, [0, 2, 1]]
    return tris


def test_a_right_mesh_loses_no_vertex() -> None:
    images, ref_v, mov_v, tris = _book_mesh()
    tris = _positive(ref_v, tris)
    found, out = _remove(images, ref_v, mov_v, tris)
    # Scored: the inner vertices (18 of 40).
    assert found.tested == 18 and len(found.vertices) == 0
    np.testing.assert_array_equal(out, tris)


@pytest.mark.parametrize("cost", ["mi", "ncc"])
def test_a_vertex_off_its_surface_leaves_the_mesh_its_star_refilled(cost: str) -> None:
    images, ref_v, mov_v, tris = _book_mesh()
    tris = _positive(ref_v, tris)
    wrong = int(np.flatnonzero((ref_v[:, 0] == 35) & (ref_v[:, 1] == 80))[0])
    off = mov_v.copy()
    off[wrong] += [5.0, -2.0]
    found, out = _remove(images, ref_v, off, tris, cost=cost)
    assert found.vertices.tolist() == [wrong] and found.moves == (REMOVE_MOVE,)
    assert found.gains[0] > 0
    record = found.to_list()[0]
    assert record["move"] == REMOVE_MOVE and record["to"] == record["from"] == off[wrong].tolist()
    # The star's polygon filled again without it: the same reference area, the triangles
    # away from it untouched, no fold in either image.
    assert not (out == wrong).any()
    star = (tris == wrong).any(axis=1)
    assert len(out) == len(tris) - 2
    assert {tuple(t) for t in tris[~star].tolist()} <= {tuple(t) for t in out.tolist()}
    np.testing.assert_allclose(triangle_areas(ref_v[out]).sum(),
                               triangle_areas(ref_v[tris]).sum())
    assert (orientation(*ref_v[out].transpose(1, 0, 2)) > 0).all()
    assert (orientation(*off[out].transpose(1, 0, 2)) > 0).all()
    # A vertex that may not leave (the client's) stays.
    fixed = np.ones(len(ref_v), bool)
    fixed[wrong] = False
    assert wrong not in _remove(images, ref_v, off, tris, fixed, cost)[0].vertices.tolist()


def test_a_vertex_on_the_mesh_boundary_never_leaves() -> None:
    images, ref_v, mov_v, tris = _book_mesh()
    tris = _positive(ref_v, tris)
    side = int(np.flatnonzero((ref_v[:, 0] == 10) & (ref_v[:, 1] == 80))[0])
    off = mov_v.copy()
    off[side] += [5.0, -2.0]
    found, out = _remove(images, ref_v, off, tris)
    assert side not in found.vertices.tolist()
    assert (out == side).any()


def _border_star(shift: float, extrapolations: list[float]):  # type: ignore[no-untyped-def]
    """The moving image is the reference 12 px to the right (epipolar lines are rows); a
    vertex on the frame's bottom side sits ``shift`` px right of its reference position, its
    neighbours at the truth; ``extrapolations`` are its extrapolated shifts."""
    reference = texture((160, 200), seed=3)
    moving = np.roll(reference, 12, axis=1)
    images = prepare_images(reference, moving, DEFAULTS.bins)
    ref_v = np.array([[100, 159.5], [40, 130], [100, 90], [160, 130]], float)
    mov_v = ref_v + [[shift, 0], [12, 0], [12, 0], [12, 0]]
    tris = np.array([[0, 1, 2], [0, 2, 3]])
    border = np.array([True, False, False, False])
    candidates = np.array([[[100 + e, 159.5]] for e in extrapolations])
    rows = np.array([[0, 0, 0], [0, 0, -1], [0, 1, 0]], float)  # y_mov = y_ref
    return border_search(images, ref_v, mov_v, tris, border, candidates, rows,
                         epsilon=DEFAULTS.epsilon, epsilon_pixels=DEFAULTS.epsilon_pixels)


def test_a_border_vertex_found_along_its_epipolar_line() -> None:
    # Extrapolated 4 and 8 px right where the truth is 12: the segment [4, 8] is searched
    # over [-2, 14] (its length and 2 px more at both ends).
    found = _border_star(4.0, [4.0, 8.0])
    assert found.vertices.tolist() == [0] and found.moves == (BORDER_MOVE,)
    np.testing.assert_allclose(found.moving[0], [112, 159.5], atol=1.0)
    np.testing.assert_allclose(found.before[0], [104, 159.5])
    assert found.gains[0] > 0


def test_a_right_border_vertex_stays() -> None:
    found = _border_star(12.0, [12.0, 13.0])
    assert found.tested == 1
    assert len(found.vertices) == 0 or abs(found.moving[0, 0] - 112) <= 1.0


def test_a_border_vertex_moves_no_farther_than_its_extrapolations_allow() -> None:
    # Extrapolated 4 and 5 px right: searched over [1, 8], the truth (12) is out of reach;
    # the vertex goes as near as it may.
    found = _border_star(4.0, [4.0, 5.0])
    assert found.vertices.tolist() == [0]
    np.testing.assert_allclose(found.moving[0], [108, 159.5], atol=1e-6)


def test_a_border_vertex_found_on_reduced_images_along_a_slanted_line() -> None:
    # The moving image is the reference moved by (24, -12): epipolar lines are slanted. The
    # images are scored halved (scale 0.5); the vertex starts a third of the way and its
    # extrapolations reach two thirds.
    shift = np.array([24, -12])
    reference = texture((320, 400), seed=3)
    moving = np.roll(np.roll(reference, shift[0], axis=1), shift[1], axis=0)
    images, scale = reduced(prepare_images(reference, moving, DEFAULTS.bins), 200)
    assert scale == 0.5
    ref_v = np.array([[200, 319.5], [80, 200], [200, 120], [320, 200]], float)
    mov_v = ref_v + shift
    mov_v[0] = ref_v[0] + shift / 3
    candidates = np.array([[ref_v[0] + shift / 3], [ref_v[0] + 2 * shift / 3]])
    epipole = np.array([shift[0], shift[1], 0.0])  # F = [t]x for a translation t
    F = 7.3 * np.array([[0, -epipole[2], epipole[1]], [epipole[2], 0, -epipole[0]],
                        [-epipole[1], epipole[0], 0]])
    found = border_search(images, ref_v, mov_v, np.array([[0, 1, 2], [0, 2, 3]]),
                          np.array([True, False, False, False]), candidates, F,
                          epsilon=DEFAULTS.epsilon, epsilon_pixels=DEFAULTS.epsilon_pixels,
                          scale=scale)
    assert found.vertices.tolist() == [0] and found.tested == 1
    np.testing.assert_allclose(found.before[0], mov_v[0])  # full-image pixels
    np.testing.assert_allclose(found.moving[0], ref_v[0] + shift, atol=1.5)
    x_ref, x_mov = np.r_[ref_v[0], 1], np.r_[found.moving[0], 1]
    line = F @ x_ref
    assert abs(x_mov @ line) / np.hypot(*line[:2]) < 1e-6  # on the line


def test_both_moves_records_join_in_vertex_order() -> None:
    correct = Corrections(np.array([2, 7]), np.array([[1.0, 1], [2, 2]]),
                          np.array([[0.0, 0], [0, 0]]), np.array([0.1, 0.2]), 5, (MOVE, MOVE))
    border = Corrections(np.array([4]), np.array([[3.0, 3]]), np.array([[9.0, 9]]),
                         np.array([0.3]), 4, (BORDER_MOVE,))
    both = correct + border
    assert both.vertices.tolist() == [2, 4, 7] and both.tested == 9
    assert both.moves == (MOVE, BORDER_MOVE, MOVE)
    assert [r["move"] for r in both.to_list()] == [MOVE, BORDER_MOVE, MOVE]
    assert both.to_list()[1] == {"vertex": 4, "from": [9.0, 9.0], "to": [3.0, 3.0],
                                 "gain": 0.3, "move": BORDER_MOVE}
    assert (correct + Corrections.none()).to_list() == correct.to_list()


def test_border_moves_are_recorded_like_the_mesh_they_leave() -> None:
    # A stereo-like pair: rows shift 6 px, a band above the bottom 14 px, the last 14 rows 6
    # px again (unmatched: the border's extrapolations disagree there).
    h, w, strip = 240, 320, 14
    moving = texture((h, w + 60), seed=3)[:, 20:20 + w].copy()
    rows = np.arange(h)
    shift = np.where((rows >= int(0.7 * h)) & (rows < h - strip), 14.0, 6.0).astype(np.float32)
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    reference = cv2.remap(moving, xs + shift[:, None], ys, cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_REFLECT)
    result = register(reference, moving, options={"extent": "frame"})
    moved = result.corrections
    assert moved is not None
    border = np.array(moved.moves) == BORDER_MOVE
    assert border.any()
    assert result.extrapolated[moved.vertices[border]].all()
    mesh, convergence = mesh_document(result), convergence_document(result)
    assert mesh["corrections"] == convergence["corrections"] == moved.to_list()
    # A vertex's records follow one another; the last one ends where the vertex is.
    last = np.r_[moved.vertices[1:] != moved.vertices[:-1], True]
    for record, final in zip(mesh["corrections"], last, strict=True):
        if final:
            np.testing.assert_allclose(record["to"], mesh["moving_vertices"][record["vertex"]],
                                       atol=0.01)
    for a, b in zip(moved.to_list()[:-1], moved.to_list()[1:], strict=True):
        if a["vertex"] == b["vertex"]:
            np.testing.assert_allclose(b["from"], a["to"])
    counts = {m["move"]: m["count"] for m in mesh["moves"]}
    assert counts[BORDER_MOVE] == int(border.sum())
    # Each border move ends on the epipolar line of the vertex's reference position.
    F = result.points.epipolar.matrix
    for v, to in zip(moved.vertices[border], moved.moving[border], strict=True):
        line = F @ np.r_[result.reference_vertices[v], 1.0]
        distance = abs(np.r_[to, 1.0] @ line) / np.hypot(*line[:2])
        assert distance < 0.01


@pytest.mark.skipif("middlebury2003_teddy" not in middlebury.available_middlebury(),
                    reason=f"Middlebury teddy not found under {middlebury.real_data_root()} "
                    f"(set ${middlebury.ENV_VAR})")
def test_teddys_moved_vertices_lower_its_error_and_are_recorded() -> None:
    pair = middlebury.load_middlebury("middlebury2003_teddy")
    result = register(pair.reference, pair.moving, options={"extent": "frame"})
    moved = result.corrections
    assert moved is not None
    moves = np.array(moved.moves)
    correct, border, align = moves == MOVE, moves == BORDER_MOVE, moves == ALIGN_MOVE
    remove = moves == REMOVE_MOVE
    assert correct.any() and border.any() and align.any()
    assert (correct | border | align | remove).all()
    # A removed vertex is in the initial mesh, in no final triangle, where it was.
    assert np.isin(moved.vertices[remove], result.initial_triangles).all()
    assert not np.isin(moved.vertices[remove], result.final_triangles).any()
    np.testing.assert_array_equal(moved.moving[remove], moved.before[remove])
    assert not result.extrapolated[moved.vertices[correct]].any()
    assert result.extrapolated[moved.vertices[border]].all()
    # The alignment comes last: a vertex's last record ends where the vertex is.
    last = np.r_[moved.vertices[1:] != moved.vertices[:-1], True]
    np.testing.assert_allclose(result.moving_vertices[moved.vertices[last]], moved.moving[last],
                               atol=0.01)
    assert (np.linalg.norm(moved.moving - moved.before, axis=1)[correct] > 2.0).all()
    assert (np.linalg.norm(moved.moving - moved.before, axis=1)[align] <= ALIGN_REACH).all()

    def epe(mov: np.ndarray) -> float:
        return endpoint_error(result.reference_vertices, mov, result.final_triangles,
                              pair.truth_x, pair.truth_y, pair.valid)["mean"]

    # Each move lowers the error on its own, undone last first (measured: the alignment
    # 0.02 px, the correct move 0.03 px, the border search 0.12 px, its floor along the bottom
    # side).
    before = result.moving_vertices.copy()
    for which, drop in ((align, 0.01), (correct, 0.01), (border, 0.05)):
        undone = before.copy()
        undone[moved.vertices[which]] = moved.before[which]
        assert epe(before) < epe(undone) - drop
        before = undone
    mesh, convergence = mesh_document(result), convergence_document(result)
    assert mesh["corrections"] == convergence["corrections"]
    for record, final in zip(mesh["corrections"], last, strict=True):
        v = record["vertex"]
        if final:
            np.testing.assert_allclose(record["to"], mesh["moving_vertices"][v], atol=0.01)
        assert record["move"] in (MOVE, BORDER_MOVE, ALIGN_MOVE, REMOVE_MOVE)
        assert record["gain"] > 0 if record["move"] != ALIGN_MOVE else record["gain"] >= 0
    counts = {m["move"]: m for m in mesh["moves"]}
    for name, which in ((MOVE, correct), (BORDER_MOVE, border), (ALIGN_MOVE, align),
                        (REMOVE_MOVE, remove)):
        if name not in counts:
            assert not which.any()
            continue
        assert counts[name]["count"] == int(which.sum())
        assert counts[name]["kind"] == "vertex"
        assert counts[name]["reason"] == MOVES[name].reason
    assert f"{len(np.unique(moved.vertices[~remove]))} vertices moved" in result.summary()
