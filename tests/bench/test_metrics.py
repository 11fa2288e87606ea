"""Metrics on hand-made meshes with known answers, and the Middlebury ground truth."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.spatial import Delaunay

from bench import middlebury
from bench.metrics import (
    TRIANGLE_CLASSES,
    disparity_steps,
    edge_compatibility,
    endpoint_error,
    endpoint_error_map,
    epipolar_line_error,
    epipolar_map_error,
    error_by_triangle,
    error_summary,
    global_mi,
    mesh_correctness,
    mesh_edges,
    truth_at,
)
from bench.scenes import make_scene
from pwlreg.core.warp import piecewise_map


def reference_piecewise_map(ref, mov, tris, shape):
    """A slow, independent piecewise-affine map by barycentric coordinates (no fill rule)."""
    h, w = shape
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    map_x = np.full(shape, np.nan)
    map_y = np.full(shape, np.nan)
    for t in np.asarray(tris):
        a, b, c = ref[t]
        T = np.array([[b[0] - a[0], c[0] - a[0]], [b[1] - a[1], c[1] - a[1]]])
        if abs(np.linalg.det(T)) < 1e-12:
            continue
        l1, l2 = np.linalg.solve(T, np.stack([xs.ravel() - a[0], ys.ravel() - a[1]]))
        l0 = 1 - l1 - l2
        inside = (l0 >= -1e-9) & (l1 >= -1e-9) & (l2 >= -1e-9)
        pos = np.outer(l0, mov[t[0]]) + np.outer(l1, mov[t[1]]) + np.outer(l2, mov[t[2]])
        map_x.ravel()[inside] = pos[inside, 0]
        map_y.ravel()[inside] = pos[inside, 1]
    return map_x, map_y


# --- an analytic open book --------------------------------------------------------------------
# Two planes meeting at the vertical crease x = C. Left of it the moving image is the reference;
# right of it points move by (K, G) * (x - C). The quad is the rhombus |x - C| + |y - YM| < A.
SHAPE = (80, 100)
C, YM, A = 50.3, 40.6, 30.0  # no pixel centre lies on an edge of the rhombus or on the crease
K, G = 0.5, -0.25


def _book_truth():
    ys, xs = np.mgrid[0 : SHAPE[0], 0 : SHAPE[1]].astype(np.float64)
    bend = np.maximum(xs - C, 0.0)
    plane = (xs >= C).astype(np.int32)
    return xs + K * bend, ys + G * bend, plane, xs, ys


def _book_mesh():
    ref = np.array([[C - A, YM], [C + A, YM], [C, YM - A], [C, YM + A]])  # L, R, T, B
    bend = np.maximum(ref[:, 0] - C, 0.0)
    mov = ref + np.column_stack([K * bend, G * bend])
    good = np.array([[0, 2, 3], [1, 2, 3]])  # diagonal T-B along the crease
    bad = np.array([[0, 1, 2], [0, 1, 3]])  # diagonal L-R across the crease
    return ref, mov, good, bad


def test_core_piecewise_map_agrees_with_a_reference_implementation():
    rng = np.random.default_rng(0)
    ref = rng.uniform(0, [99, 79], (25, 2))
    mov = ref + rng.normal(0, 3, ref.shape)
    tris = Delaunay(ref).simplices
    mx, my, label = piecewise_map(ref, mov, tris, SHAPE)
    rx, ry = reference_piecewise_map(ref, mov, tris, SHAPE)
    both = (label >= 0) & np.isfinite(rx)
    assert both.sum() > 0.95 * np.isfinite(rx).sum()
    # core decides pixel ownership on vertices quantized to 1/256 px, so a pixel centre within
    # that distance of an edge may take the neighbour's map, extrapolated by as little; the map
    # is continuous, so values differ by ~1e-3 px there (1/256 px times the jump in slope).
    np.testing.assert_allclose(mx[both], rx[both], atol=1e-2)
    np.testing.assert_allclose(my[both], ry[both], atol=1e-2)
    assert np.mean(np.abs(mx[both] - rx[both]) < 1e-9) > 0.99


def test_open_book_mesh_following_the_crease_is_exact_and_correct():
    tx, ty, plane, _, _ = _book_truth()
    ref, mov, good, _ = _book_mesh()
    e = endpoint_error(ref, mov, good, tx, ty)
    assert e["n"] > 1500 and e["max"] < 1e-9
    c = mesh_correctness(ref, good, plane)
    assert c == {
        "correctness": 1.0, "internal_edges": 1, "compatible_internal": 1,
        "incompatible_internal": 0, "boundary_edges": 4, "compatible_boundary": 4,
        "boundary_correctness": 1.0,
    }


def test_open_book_mesh_crossing_the_crease_has_the_expected_error():
    tx, ty, plane, xs, ys = _book_truth()
    ref, mov, good, bad = _book_mesh()
    err = endpoint_error_map(ref, mov, bad, tx, ty)
    inside = np.isfinite(err)
    # Closed form: the interpolant of the bend over a triangle with its apex on the crease is
    # off by (A - |x - C| - |y - YM|) / 2 times |(K, G)|.
    expected = np.hypot(K, G) * (A - np.abs(xs - C) - np.abs(ys - YM)) / 2
    rhombus = np.abs(xs - C) + np.abs(ys - YM) < A
    np.testing.assert_array_equal(inside, rhombus)
    np.testing.assert_allclose(err[inside], expected[inside], atol=1e-9)
    e = endpoint_error(ref, mov, bad, tx, ty)
    # The continuum mean over the rhombus is |(K, G)| * A / 6.
    assert e["mean"] == pytest.approx(np.hypot(K, G) * A / 6, rel=0.02)
    assert e["mean"] > endpoint_error(ref, mov, good, tx, ty)["mean"] + 2.0
    c = mesh_correctness(ref, bad, plane)
    assert c["correctness"] == 0.0 and c["incompatible_internal"] == 1
    assert c["compatible_boundary"] == 4
    # Restricting to a valid mask restricts the statistics.
    left = xs < C
    e_left = endpoint_error(ref, mov, bad, tx, ty, valid=left)
    assert e_left["n"] == int((rhombus & left).sum())
    assert e_left["coverage"] == pytest.approx((rhombus & left).sum() / left.sum())


def test_mesh_edges_counts_internal_and_boundary_edges():
    edges, count = mesh_edges(np.array([[0, 1, 2], [2, 1, 3]]))
    assert edges.tolist() == [[0, 1], [0, 2], [1, 2], [1, 3], [2, 3]]
    assert count.tolist() == [1, 1, 2, 1, 1]


def test_edge_compatibility_tolerances():
    plane = np.zeros((40, 60), dtype=np.int32)
    plane[:, 30:] = 1
    plane[30:, :] = -1  # background at the bottom
    verts = np.array([
        [5.0, 5.0], [25.0, 20.0],  # inside plane 0
        [29.6, 2.0], [29.6, 25.0],  # along the crease (between columns 29 and 30)
        [10.0, 10.0], [50.0, 12.0],  # across the crease
        [10.0, 20.0], [10.0, 38.0],  # into the background
        [30.0, 10.0], [31.0, 10.0],  # a 1 px edge: the margin shrinks, samples remain
    ])
    edges = np.array([[0, 1], [2, 3], [4, 5], [6, 7], [8, 9]])
    r = edge_compatibility(verts, edges, plane)
    assert r.compatible.tolist() == [True, True, False, False, True]
    assert r.plane[0] == 0 and r.plane[2] in (0, 1)
    assert 0.4 < r.agreement[2] < 0.6
    assert 1 <= r.samples[4] <= 2
    # An edge that overshoots the crease by a few pixels: the agreement threshold decides.
    over = (np.array([[5.0, 10.0], [34.0, 10.0]]), np.array([[0, 1]]))
    r = edge_compatibility(*over, plane)
    assert r.agreement[0] == pytest.approx(0.94, abs=0.03) and not r.compatible[0]
    assert edge_compatibility(*over, plane, agreement=0.9).compatible[0]


def test_vertex_planes_catch_edges_leaving_an_occluding_contour():
    plane = np.zeros((60, 80), dtype=np.int32)  # ground
    plane[10:30, 10:30] = 1  # a box top, seen against the ground
    verts = np.array([[29.5, 29.5], [60.0, 50.0], [12.0, 12.0]])  # top corner, ground, top
    edges = np.array([[0, 1], [0, 2]])
    on = np.array([[False, True], [True, False], [False, True]])  # the corner is not on the ground
    assert edge_compatibility(verts, edges, plane).compatible.tolist() == [True, True]
    r = edge_compatibility(verts, edges, plane, vertex_planes=on)
    assert r.compatible.tolist() == [False, True]
    assert r.plane.tolist() == [-1, 1]
    with pytest.raises(ValueError, match="vertex_planes"):
        edge_compatibility(verts, edges, plane, vertex_planes=on[:, :1])


def test_scene_vertex_planes():
    s = make_scene("box", 5, size=(120, 90))
    table = s.point_planes
    assert table.shape == (len(s.points_world), len(s.planes))
    inner = ~s.is_corner
    assert np.array_equal(table[inner], np.eye(len(s.planes), dtype=bool)[s.points_plane[inner]])
    assert np.all(table[s.is_corner].sum(axis=1) >= 2)  # box corners: two or three planes
    # Vertices found by position, whatever their order, quantization or extra vertices.
    order = np.random.default_rng(0).permutation(len(s.points_reference))
    verts = np.vstack([np.rint(s.points_reference[order] * 256) / 256, [[-50.0, -50.0]]])
    vp = s.vertex_planes(verts)
    assert np.array_equal(vp[:-1], table[order])
    assert vp[-1].all()


def test_mesh_correctness_on_scenes_is_one_for_a_plane():
    s = make_scene("plane", 3, size=(120, 90))
    tri = Delaunay(s.points_reference).simplices
    c = mesh_correctness(s.points_reference, tri, s.face, s.vertex_planes(s.points_reference))
    assert c["correctness"] == 1.0 and c["internal_edges"] > 10


def test_triangles_on_one_plane_register_exactly():
    """Under affine cameras the error of a triangle whose vertices lie on one plane is zero."""
    s = make_scene("box", 4, size=(160, 120), n_interior=60)
    ref, mov = s.points_reference_exact, s.points_moving_exact
    tri = Delaunay(ref).simplices
    err = endpoint_error_map(ref, mov, tri, s.truth_x, s.truth_y, s.covisible)
    _, _, label = piecewise_map(ref, mov, tri, s.shape)
    planes = s.points_plane[tri]
    flat = np.flatnonzero((planes[:, 0] >= 0) & (planes == planes[:, :1]).all(axis=1))
    assert len(flat) >= 3
    on_flat = np.isin(label, flat) & np.isfinite(err)
    assert on_flat.sum() > 100
    assert np.nanmax(err[on_flat]) < 1e-6
    assert np.nanmax(err) > 1.0  # and other triangles do not


def test_error_summary():
    e = error_summary(np.array([np.nan, 1.0, 2.0, 3.0, 4.0]))
    assert e["mean"] == 2.5 and e["median"] == 2.5 and e["max"] == 4.0 and e["n"] == 4
    assert e["p90"] == pytest.approx(3.7)
    assert e["rms"] == pytest.approx(np.sqrt(7.5))
    assert np.isnan(error_summary(np.array([np.nan]))["mean"])


def _entropy_bits(values: np.ndarray) -> float:
    p = np.bincount(values) / values.size
    p = p[p > 0]
    return float(-(p * np.log2(p)).sum())


def test_global_mi():
    rng = np.random.default_rng(1)
    a = rng.integers(0, 256, (64, 64)).astype(np.uint8)
    h_a = _entropy_bits((a.astype(int) * 16 // 256).ravel())
    assert global_mi(a, a) == pytest.approx(h_a, abs=1e-12)
    # Any one-to-one relabelling of the bins keeps MI = H(A), even a non-monotone one.
    assert global_mi(a, 255 - a) == pytest.approx(h_a, abs=1e-12)
    b = rng.integers(0, 256, (64, 64)).astype(np.uint8)
    assert global_mi(a, b) < 0.1
    # Masks and NaN (pixels outside the mesh in a float registered image).
    reg = a.astype(np.float64)
    reg[:, :32] = np.nan
    half = _entropy_bits((a[:, 32:].astype(int) * 16 // 256).ravel())
    assert global_mi(a, reg) == pytest.approx(half, abs=1e-12)
    mask = np.zeros(a.shape, dtype=bool)
    mask[:, 32:] = True
    assert global_mi(a, a, mask) == pytest.approx(half, abs=1e-12)
    assert global_mi(a, a, np.zeros(a.shape, dtype=bool)) == 0.0
    assert global_mi(a, a, bins=4) < global_mi(a, a, bins=16)


# --- Middlebury ---------------------------------------------------------------------------------

_AVAILABLE = middlebury.available_middlebury()
needs_data = pytest.mark.skipif(
    "middlebury2001_sawtooth" not in _AVAILABLE,
    reason=f"Middlebury data not found under {middlebury.real_data_root()} "
    f"(set ${middlebury.ENV_VAR})",
)


def test_real_data_root_can_be_overridden(monkeypatch, tmp_path):
    monkeypatch.setenv(middlebury.ENV_VAR, str(tmp_path))
    assert middlebury.real_data_root() == tmp_path
    assert middlebury.available_middlebury() == []
    with pytest.raises(FileNotFoundError):
        middlebury.load_middlebury("middlebury2001_sawtooth")


@pytest.fixture(scope="module")
def sawtooth():
    return middlebury.load_middlebury("middlebury2001_sawtooth")


@needs_data
def test_middlebury_truth_matches_its_documented_check(sawtooth):
    p = sawtooth
    assert p.reference.shape == (380, 434) and p.reference.dtype == np.uint8
    assert p.known.all()
    # SOURCE.md: 94.9 % of pixels pass the left-right check; the image warped by the truth
    # differs from the reference by 3.26 grey levels there (4.75 over all valid pixels).
    assert p.valid.mean() == pytest.approx(0.949, abs=0.003)
    ref = cv2.imread(str(middlebury.real_data_root() / p.name / "im2.ppm"))
    mov = cv2.imread(str(middlebury.real_data_root() / p.name / "im6.ppm"))
    grey = lambda im: im[..., ::-1].astype(np.float64) @ [0.299, 0.587, 0.114]  # noqa: E731
    warped = cv2.remap(grey(mov).astype(np.float32), p.truth_x.astype(np.float32),
                       p.truth_y.astype(np.float32), cv2.INTER_LINEAR)
    assert np.abs(warped - grey(ref))[p.valid].mean() == pytest.approx(3.26, abs=0.05)
    assert np.array_equal(p.truth_y[p.known], np.nonzero(p.known)[0].astype(float))


@needs_data
@pytest.mark.parametrize("method", ["corners", "grid"])
def test_middlebury_sampled_points_follow_the_truth(sawtooth, method):
    ref, mov = middlebury.sample_points(sawtooth, n=80, seed=3, method=method)
    again = middlebury.sample_points(sawtooth, n=80, seed=3, method=method)
    other = middlebury.sample_points(sawtooth, n=80, seed=4, method=method)
    np.testing.assert_array_equal(ref, again[0])
    assert not np.array_equal(ref, other[0])
    assert 60 <= len(ref) <= 80
    col, row = ref.astype(int).T
    assert sawtooth.valid[row, col].all()
    np.testing.assert_array_equal(mov[:, 1], ref[:, 1])
    np.testing.assert_allclose(ref[:, 0] - mov[:, 0], sawtooth.disparity[row, col])
    noisy, _ = middlebury.sample_points(sawtooth, n=80, seed=3, method=method, noise=0.5)
    assert 0.3 < np.std(noisy - ref) < 0.7


@needs_data
def test_middlebury_delaunay_baseline(sawtooth):
    """SOURCE.md: Delaunay over 80 grid samples scores a dense EPE of about 0.77 / 0.048 px."""
    stats = []
    for seed in range(3):
        ref, mov = middlebury.sample_points(sawtooth, n=80, seed=seed, method="grid")
        tri = Delaunay(ref).simplices
        stats.append(endpoint_error(ref, mov, tri, sawtooth.truth_x, sawtooth.truth_y,
                                    sawtooth.valid))
    assert 0.3 < np.mean([s["mean"] for s in stats]) < 1.2
    assert np.mean([s["median"] for s in stats]) < 0.1
    assert all(0.8 < s["coverage"] < 1.0 for s in stats)


def test_error_by_triangle_finds_the_step_the_bad_vertex_and_the_border():
    # Two fronto-parallel planes (disparity 5 left of x = 50, 15 right), two squares of exact
    # vertices joined across the step; vertex 0 flagged extrapolated, vertex 7 moved 2 px.
    disparity = np.where(np.arange(100)[None, :] < 50, 5.0, 15.0).repeat(60, axis=0)
    yy, xx = np.mgrid[0:60, 0:100].astype(np.float64)
    truth_x, truth_y = xx - disparity, yy
    ref = np.array([[10.0, 10], [40, 10], [10, 50], [40, 50],
                    [60, 10], [90, 10], [60, 50], [90, 50]])
    mov = ref - np.where(ref[:, :1] < 50, 5.0, 15.0) * np.array([[1.0, 0.0]])
    mov[7] += [2.0, 0.0]
    tris = np.array([[0, 1, 2], [1, 3, 2], [1, 4, 3], [4, 6, 3], [4, 5, 6], [5, 7, 6]])
    extrapolated = np.zeros(8, bool)
    extrapolated[0] = True
    valid = np.ones(disparity.shape, bool)
    steps = disparity_steps(disparity)
    assert steps.sum() == 60 and steps[:, 49].all()
    classes = error_by_triangle(ref, mov, tris, truth_x, truth_y, valid, steps=steps,
                                extrapolated=extrapolated, others={"flow": np.zeros((60, 100))})
    assert tuple(classes) == TRIANGLE_CLASSES
    assert classes["clean"]["mean"] < 1e-6 and classes["extrapolated"]["mean"] < 1e-6
    assert classes["step"]["mean"] > 2.0
    assert 0.1 < classes["vertex off"]["mean"] < 2.0
    assert sum(c["share"] for c in classes.values()) == pytest.approx(1.0)
    overall = endpoint_error(ref, mov, tris, truth_x, truth_y, valid)["mean"]
    assert sum(c["contribution"] for c in classes.values()) == pytest.approx(overall)
    assert all(c["flow mean"] == 0.0 for c in classes.values())


def test_epipolar_line_error_is_the_distance_of_the_true_match_to_its_line():
    # A rectified pair: F maps a reference pixel to the row it sits on in the moving image.
    F = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    h, w = 20, 30
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    truth_x, truth_y = xs + 7.0, ys.copy()
    truth_y[10:] += 2.5  # the lower half lands 2.5 px below its line
    truth_x[0, :] = np.nan  # unknown truth is not scored
    valid = np.ones((h, w), bool)
    valid[:, 25:] = False
    err = epipolar_line_error(F, truth_x, truth_y, valid, step=1)
    assert len(err) == (h - 1) * 25
    np.testing.assert_allclose(np.sort(err), np.r_[np.zeros(9 * 25), np.full(10 * 25, 2.5)],
                               atol=1e-12)
    assert len(epipolar_line_error(F, truth_x, truth_y, valid, step=4)) == 4 * 7


def test_truth_of_a_silhouette_point_comes_from_the_nearest_pixel_that_sees_the_scene():
    s = make_scene("plane", 0, size=(160, 120), supersample=1, n_interior=5)
    seen = np.isfinite(s.truth_x)
    edge = np.argwhere(seen[:, :-1] & ~seen[:, 1:])  # seen pixel, background to its right
    y, x = edge[len(edge) // 2]
    pts = np.array([[x + 0.4, y]], dtype=float)  # between the two: bilinear truth is NaN
    truth = truth_at(s.truth_x, s.truth_y, pts)
    assert np.allclose(truth[0], [s.truth_x[y, x], s.truth_y[y, x]])
    far = np.argwhere(~seen)[0]  # a background pixel: no truth if none is within reach
    if not seen[max(far[0] - 3, 0):far[0] + 4, max(far[1] - 3, 0):far[1] + 4].any():
        assert not np.isfinite(truth_at(s.truth_x, s.truth_y, far[None, ::-1].astype(float))).any()


@pytest.mark.parametrize("scale", [1.0, 0.5])
def test_epipolar_map_error_measures_across_the_lines_in_full_resolution_pixels(scale):
    # A rectified pair: the epipolar lines are the rows, x'^T F x = y - y'. A map shifted by
    # (5, 1) pixels of the registered images is 1 / scale pixels off its line at full
    # resolution, whose Sampson distance is that over sqrt(2); the shift along the line is not
    # seen.
    F = np.array([[0.0, 0, 0], [0, 0, -1], [0, 1, 0]])
    h, w = 80, 100
    ref = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [-0.5, h - 0.5], [w - 0.5, h - 0.5]])
    both = np.array([[0, 1, 2], [1, 3, 2]])
    d, coverage = epipolar_map_error(F, ref, ref + [5.0, 1.0], both, (h, w), scale=scale)
    assert coverage == pytest.approx(1.0)
    assert np.allclose(d, 1.0 / scale / np.sqrt(2))
    d, coverage = epipolar_map_error(F, ref, ref + [5.0, 0.0], both[:1], (h, w))
    assert 0.4 < coverage < 0.6 and np.allclose(d, 0.0)
