import numpy as np
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from scipy.spatial import ConvexHull, Delaunay

from pwlreg.core.raster import (
    affine_maps,
    expand,
    first_occurrences,
    label_image,
    orientation,
    quantize,
    rasterize,
)


def _counts(tri_xy, shape):
    spans = rasterize(tri_xy, shape)
    _, x, y = expand(spans)
    counts = np.zeros(shape, dtype=int)
    np.add.at(counts, (y, x), 1)
    return counts


def _brute_inside(tri, shape):
    """Pixel centres strictly inside a triangle (float test, ties excluded)."""
    h, w = shape
    ys, xs = np.mgrid[0:h, 0:w]
    a, b, c = tri

    def side(p, q):
        return (q[0] - p[0]) * (ys - p[1]) - (q[1] - p[1]) * (xs - p[0])

    s1, s2, s3 = side(a, b), side(b, c), side(c, a)
    return ((s1 > 0) & (s2 > 0) & (s3 > 0)) | ((s1 < 0) & (s2 < 0) & (s3 < 0))


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**31), st.booleans())
def test_tiling_owns_every_pixel_exactly_once(seed, integer_vertices):
    rng = np.random.default_rng(seed)
    shape = (60, 80)
    pts = rng.uniform(-10, 90, size=(25, 2))
    if integer_vertices:  # many pixel centres fall exactly on edges and vertices
        pts = np.unique(np.round(pts / 5) * 5, axis=0)
        assume(len(pts) >= 4)
    pts = quantize(pts)
    d = Delaunay(pts)
    counts = _counts(pts[d.simplices], shape)
    assert counts.max() <= 1
    ys, xs = np.mgrid[0 : shape[0], 0 : shape[1]]
    grid = np.c_[xs.ravel(), ys.ravel(), np.ones(xs.size)]
    # Every pixel strictly inside the hull is owned; pixels on the hull boundary may or may not.
    strict = (grid @ ConvexHull(pts).equations.T < -1e-9).all(axis=1).reshape(shape)
    assert np.all(counts[strict] == 1)


def test_single_triangle_matches_brute_force_interior():
    tri = quantize(np.array([[3.3, 2.1], [40.7, 10.2], [12.5, 33.9]]))
    counts = _counts(tri[None], (40, 50))
    assert np.array_equal(counts.astype(bool), _brute_inside(tri, (40, 50)))


def test_fill_rule_on_shared_edges_and_vertices():
    # Four triangles around the pixel centre (10, 10), which lies on all their shared edges.
    c = [10.0, 10.0]
    ring = [[0, 0], [20, 0], [20, 20], [0, 20]]
    tris = np.array([[c, ring[i], ring[(i + 1) % 4]] for i in range(4)])
    counts = _counts(tris, (21, 21))
    assert counts[10, 10] == 1
    # Horizontal shared edge: the pixel goes to the triangle below (larger y).
    labels = label_image(tris, (21, 21))
    assert labels[10, 15] == 1  # triangle (c, (20,0), (20,20)) is on the right
    assert counts[1:20, 1:20].min() == 1 and counts.max() == 1


def test_clipping_and_degenerate():
    tris = np.array([[[-50, -50], [200, -50], [-50, 200]], [[0, 0], [5, 5], [10, 10]]], float)
    spans = rasterize(tris, (10, 12))
    assert set(spans.triangle.tolist()) == {0}
    assert spans.n_pixels == 120


def test_orientation_exact_and_affine_maps():
    a, b, c = np.array([0.0, 0.0]), np.array([1.0, 0.0]), np.array([0.0, 1.0])
    assert orientation(a, b, c) == 1 and orientation(a, c, b) == -1
    assert orientation(a, b, np.array([2.0, 0.0])) == 0
    src = np.array([[[0, 0], [10, 0], [0, 10]]], float)
    A = np.array([[1.5, 0.2, 3.0], [-0.1, 0.9, -2.0]])
    dst = src @ A[:, :2].T + A[:, 2]
    np.testing.assert_allclose(affine_maps(src, dst)[0], A, atol=1e-12)


def test_first_occurrences_is_numpys_unique_rows_first_index():
    rng = np.random.default_rng(0)
    points = np.round(rng.uniform(-50, 50, (300, 2)) * 4) / 4
    points[10] = points[200]
    points[20] = points[21] = points[250]
    points[30] = (0.0, 3.0)
    points[31] = (-0.0, 3.0)  # the same point
    expected = np.unique(points, axis=0, return_index=True)[1]
    np.testing.assert_array_equal(first_occurrences(points), expected)
    assert 31 not in first_occurrences(points) and 200 not in first_occurrences(points)
