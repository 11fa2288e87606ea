import cv2
import numpy as np
import pytest
from scipy.ndimage import map_coordinates
from scipy.spatial import Delaunay

from pwlreg.core.mesh import Mesh
from pwlreg.core.optimize import TriangleCache, quad_keys, quad_triples
from pwlreg.core.raster import quantize
from pwlreg.core.similarity import (
    from_level,
    group_statistics,
    level_range,
    mutual_information,
    ncc,
    prepare_images,
    reduced,
    ssd,
    summed_information,
    to_level,
    triangle_statistics,
)
from pwlreg.core.warp import piecewise_map
from tests.core.synthetic import texture


def _pair(seed=0, shape=(120, 160)):
    ref = texture(shape, seed)
    A = np.array([[0.97, 0.04, 2.5], [-0.03, 1.01, 1.5]])
    mov = cv2.warpAffine(ref, A, (shape[1], shape[0]), flags=cv2.WARP_INVERSE_MAP)
    rng = np.random.default_rng(seed)
    pts = quantize(rng.uniform(0, [shape[1] - 1, shape[0] - 1], size=(30, 2)))
    mpts = quantize(pts @ A[:, :2].T + A[:, 2])
    return ref, mov, pts, mpts


def test_mi_known_values():
    m = 4
    identical = np.diag([10, 20, 30, 40]).ravel()
    mi, nmi = mutual_information(identical, m)
    p = np.array([1, 2, 3, 4]) / 10
    h = -(p * np.log2(p)).sum()
    assert mi == pytest.approx(h)
    assert nmi == pytest.approx(1.0)
    independent = np.outer([1, 2, 3, 4], [4, 1, 1, 2]).ravel()
    mi, nmi = mutual_information(independent, m)
    assert mi == pytest.approx(0.0, abs=1e-12) and nmi == pytest.approx(0.0, abs=1e-12)
    mi, nmi = mutual_information(np.zeros(16), m)
    assert mi == 0 and nmi == 0
    # One occupied cell carries no information (not a perfect match), whatever its count.
    for count in range(1, 200):
        one = np.zeros(16)
        one[5] = count
        assert mutual_information(one, m) == (0.0, 0.0)


def test_level_range_bins_twelve_bit_data_in_sixteen_bits():
    rng = np.random.default_rng(0)
    twelve = rng.integers(0, 4096, size=(50, 60)).astype(np.uint16)
    assert level_range(twelve)[2] < 4096
    images = prepare_images(twelve, twelve, 16)
    assert len(np.unique(images.reference_bins)) == 16
    pts = np.array([[0.0, 0.0], [59.0, 0.0], [0.0, 49.0], [59.0, 49.0]])
    h, _ = triangle_statistics(images, pts[[[0, 1, 2], [1, 3, 2]]], pts[[[0, 1, 2], [1, 3, 2]]])
    mi, nmi = mutual_information(h.sum(0), 16)
    assert mi > 3.5 and nmi > 0.95  # identical images: MI close to H = 4 bits


def test_ncc_and_ssd_from_moments():
    rng = np.random.default_rng(0)
    a = rng.random(500)
    b = 0.5 * a + 0.1 + 0.01 * rng.random(500)
    mom = np.array([len(a), a.sum(), b.sum(), (a * a).sum(), (b * b).sum(), (a * b).sum()])
    assert ncc(mom) == pytest.approx(np.corrcoef(a, b)[0, 1])
    assert ssd(mom) == pytest.approx(((a - b) ** 2).sum())


def test_global_histogram_equals_sum_of_triangles_and_dense_path():
    ref, mov, pts, mpts = _pair()
    tris = Delaunay(pts).simplices
    images = prepare_images(ref, mov, 16)
    hist, mom = triangle_statistics(images, pts[tris], mpts[tris], with_moments=True)
    # Independent dense path: full-image map, scipy's bilinear interpolation, one histogram.
    map_x, map_y, label = piecewise_map(pts, mpts, tris, ref.shape)
    inside = label >= 0
    warped = np.zeros(ref.shape)
    warped[inside] = map_coordinates(
        mov.astype(np.float64), [map_y[inside], map_x[inside]], order=1, mode="nearest"
    )
    r_lo, r_hi = level_range(ref)[1:]
    m_lo, m_hi = level_range(mov)[1:]

    def ref_bin(sel):
        return np.clip((ref.astype(int)[sel] - r_lo) * 16 // (r_hi - r_lo + 1), 0, 15)

    def mov_bin(sel):
        return np.clip(np.floor((warped[sel] - m_lo) * 16 / (m_hi - m_lo + 1)), 0, 15).astype(int)

    a = ref_bin(inside)
    b = mov_bin(inside)
    dense = np.bincount(a * 16 + b, minlength=256)
    np.testing.assert_array_equal(hist.sum(axis=0), dense)
    assert mom[:, 0].sum() == inside.sum()
    # Per triangle too.
    for t in (0, 5, len(tris) - 1):
        sel = label == t
        a = ref_bin(sel)
        b = mov_bin(sel)
        np.testing.assert_array_equal(hist[t], np.bincount(a * 16 + b, minlength=256))


def test_group_statistics_sum_their_triangles_in_order():
    ref, mov, pts, mpts = _pair(2)
    tris = Delaunay(pts).simplices
    images = prepare_images(ref, mov, 16)
    # Triangles in several groups, out of group order, one group empty; some triangles twice.
    pick = np.concatenate([np.arange(len(tris)), [0, 3, 3]])
    owner = np.random.default_rng(0).integers(0, 5, len(pick))
    owner[owner == 2] = 4
    hist, mom = triangle_statistics(images, pts[tris[pick]], mpts[tris[pick]],
                                    with_moments=True)
    group_hist, group_mom = group_statistics(images, pts[tris[pick]], mpts[tris[pick]], owner, 5,
                                             with_moments=True)
    for g in range(5):
        np.testing.assert_array_equal(group_hist[g], hist[owner == g].sum(axis=0))
        expected = np.zeros(6)
        for row in mom[owner == g]:
            expected = expected + row
        np.testing.assert_array_equal(group_mom[g], expected)
    assert not group_hist[2].any() and group_hist.sum() == hist.sum()
    assert group_statistics(images, pts[tris], mpts[tris], owner[:len(tris)], 5)[1] is None


def test_quad_histogram_is_exactly_sum_of_its_triangles():
    ref, mov, pts, mpts = _pair(1)
    mesh = Mesh(pts, mpts, Delaunay(pts).simplices)
    images = prepare_images(ref, mov, 16)
    cache = TriangleCache(images, mesh)
    checked = 0
    for e in mesh.internal_edges():
        if not mesh.can_swap(e):
            continue
        q = mesh.quad(e)
        old0, old1, new0, new1 = quad_triples(q, mesh)
        cache.ensure([old0, old1, new0, new1])
        # Both diagonals cover the same pixels: same reference marginal, same pixel count.
        h_old = cache.hist([old0, old1]).reshape(16, 16)
        h_new = cache.hist([new0, new1]).reshape(16, 16)
        np.testing.assert_array_equal(h_old.sum(axis=1), h_new.sum(axis=1))
        # The quad rasterized as one polygon (two triangles, same fill rule) is the sum.
        quad_ref = mesh.reference[[q.i, q.k, q.j, q.l]]
        quad_mov = mesh.moving[[q.i, q.k, q.j, q.l]]
        tri_ref = quad_ref[[[0, 1, 2], [0, 2, 3]]]
        tri_mov = quad_mov[[[0, 1, 2], [0, 2, 3]]]
        h, _ = triangle_statistics(images, tri_ref, tri_mov)
        np.testing.assert_array_equal(
            h.sum(axis=0).reshape(16, 16), h_new if {q.i, q.j} & set() else h_old
        )
        checked += 1
    assert checked > 10


def test_statistics_counted_into_given_rows_and_quad_keys():
    ref, mov, pts, mpts = _pair(3)
    tris = Delaunay(pts).simplices
    images = prepare_images(ref, mov, 16)
    h, mom = triangle_statistics(images, pts[tris], mpts[tris], with_moments=True)
    # Into a cache's int32 rows: the same counts and moments, no copy made.
    rows = np.zeros((len(tris) + 2, 256), dtype=np.int32)
    moments = np.zeros((len(tris) + 2, 6))
    h32, m32 = triangle_statistics(images, pts[tris], mpts[tris], with_moments=True,
                                   hist_out=rows[1:-1], moments_out=moments[1:-1])
    assert np.shares_memory(h32, rows)
    np.testing.assert_array_equal(rows[1:-1], h)
    np.testing.assert_array_equal(moments[1:-1], mom)
    assert not rows[[0, -1]].any() and not moments[[0, -1]].any()
    # The triples of many quads, sorted by numpy or one by one, are quad_triples's.
    mesh = Mesh(pts, mpts, tris)
    quads = [mesh.quad(e) for e in mesh.internal_edges()]
    assert len(quads) > 40
    expected = [t for q in quads for t in quad_triples(q, mesh)]
    assert quad_keys(quads) == expected
    assert [t for q in quads for t in quad_keys([q])] == expected


def test_summed_information_is_mutual_information_of_the_sums():
    rng = np.random.default_rng(4)
    table = rng.integers(0, 40, size=(50, 256)).astype(np.int32)
    table[3] = 0  # an empty row, and a row with one occupied cell
    table[4] = 0
    table[4, 17] = 9
    rows = rng.integers(0, 50, size=(7, 2, 3))
    rows[0, 0] = 3
    rows[0, 1] = [4, 3, 3]
    mi, nmi, pixels = summed_information(table, rows, 16)
    assert mi.shape == nmi.shape == pixels.shape == (7, 2)
    sums = table[rows].sum(axis=-2)
    ref_mi, ref_nmi = mutual_information(sums, 16)
    # Bit for bit: the search must rank the same way whichever path scores it.
    np.testing.assert_array_equal(mi, ref_mi)
    np.testing.assert_array_equal(nmi, ref_nmi)
    np.testing.assert_array_equal(pixels, sums.sum(axis=-1))
    assert mi[0, 0] == nmi[0, 0] == mi[0, 1] == 0.0


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_prepared_bins_and_level_range_are_the_plain_numpy_ones(dtype):
    # The fast paths (level counts in a kernel, cv2.LUT) change nothing.
    rng = np.random.default_rng(5)
    top = np.iinfo(dtype).max
    ref = np.clip(rng.normal(0.4, 0.15, (97, 131)) * top, 0, top).astype(dtype)
    mov = np.clip(rng.normal(0.6, 0.1, (90, 120)) * top, 0, top).astype(dtype)
    for gray in (ref, mov, ref[::2, 1::3]):
        counts = np.bincount(gray.ravel(), minlength=int(top) + 1)
        cdf = np.cumsum(counts)
        lo = int(np.searchsorted(cdf, 5e-4 * cdf[-1], side="right"))
        hi = int(np.searchsorted(cdf, (1.0 - 5e-4) * cdf[-1], side="left"))
        assert level_range(gray)[1:] == (lo, max(hi, lo))
    for bins in (16, 64):
        images = prepare_images(ref, mov, bins)
        r_lo, r_hi = level_range(ref)[1:]
        levels = np.arange(int(top) + 1, dtype=np.int64)
        lut = np.clip((levels - r_lo) * bins // (r_hi - r_lo + 1), 0, bins - 1).astype(np.uint8)
        np.testing.assert_array_equal(images.reference_bins, lut[ref].ravel())
        assert images.reference_bins.dtype == np.uint8


def test_sixteen_bit_and_colour_inputs_bin_consistently():
    ref, mov, pts, mpts = _pair(2)
    tris = Delaunay(pts).simplices
    h8, _ = triangle_statistics(prepare_images(ref, mov, 16), pts[tris], mpts[tris])
    ref16 = ref.astype(np.uint16) * 257
    mov_bgr = np.dstack([mov, mov, mov])
    h16, _ = triangle_statistics(prepare_images(ref16, mov_bgr, 16), pts[tris], mpts[tris])
    mi8 = mutual_information(h8.sum(0), 16)[0]
    mi16 = mutual_information(h16.sum(0), 16)[0]
    assert mi16 == pytest.approx(mi8, abs=0.02)


def test_threaded_kernel_gives_the_serial_histograms_and_moments(monkeypatch):
    from pwlreg.core import similarity

    rng = np.random.default_rng(5)
    shape = (120, 160)
    images = prepare_images(texture(shape, 2), texture(shape, 3), 16)
    pts = quantize(np.vstack([rng.uniform(0, [159, 119], (90, 2)),
                              [[0, 0], [159, 0], [0, 119], [159, 119]]]))
    tris = Delaunay(pts).simplices
    assert len(tris) >= similarity.PARALLEL_TRIANGLES
    mov = quantize(pts + rng.normal(0, 2, pts.shape))
    threaded = triangle_statistics(images, pts[tris], mov[tris], with_moments=True)
    monkeypatch.setattr(similarity, "PARALLEL_TRIANGLES", len(tris) + 1)
    serial = triangle_statistics(images, pts[tris], mov[tris], with_moments=True)
    np.testing.assert_array_equal(threaded[0], serial[0])
    np.testing.assert_array_equal(threaded[1], serial[1])


def test_level_positions_follow_the_gaussian_pyramid() -> None:
    # A blob's centre on the images the verdict and the insertion read is to_level of its
    # centre at full resolution: pyrDown centres its pixel i on pixel 2 i (an area average
    # would put it half a pixel of the level further), on one halving and on two.
    y, x = np.mgrid[0:700, 0:1700].astype(np.float64)
    centre = np.array([[800.3, 333.7]])
    blob = 200 * np.exp(-((x - centre[0, 0]) ** 2 + (y - centre[0, 1]) ** 2) / (2 * 12.0**2))
    image = blob.astype(np.uint8)
    for side in (1000, 500):
        level, scale = reduced(prepare_images(image, image, 256), side)
        values = level.reference_values.reshape(level.shape).astype(np.float64)
        rows, cols = np.mgrid[0:level.shape[0], 0:level.shape[1]]
        seen = np.array([(values * cols).sum(), (values * rows).sum()]) / values.sum()
        np.testing.assert_allclose(seen, to_level(centre, scale)[0], atol=0.02)
        np.testing.assert_allclose(from_level(to_level(centre, scale), scale), centre)


def test_isolated_hot_pixels_do_not_stretch_the_bins():
    # 16-bit data in 1000-1400 with 0.3 % of its pixels stuck at 65535: counted, they spread
    # the bins over 1008-65535 and the whole scene fell into one of them.
    rng = np.random.default_rng(0)
    scene = (1000 + texture((200, 300), 6).astype(np.uint16) * 400 // 255).astype(np.uint16)
    gray = scene.copy()
    hot = rng.random(gray.shape) < 0.003
    gray[hot] = 65535
    clipped, lo, hi = level_range(gray)
    assert (lo, hi) == level_range(scene)[1:]
    assert hi <= 1400 and clipped.max() == gray[~hot].max()
    images = prepare_images(gray, gray, 32)
    assert len(np.unique(images.reference_bins)) >= 24


def test_levels_apart_that_form_lines_or_fill_a_photo_are_kept():
    # A drawing: 3 % black lines on white paper, as far apart as hot pixels from a scene.
    drawing = np.full((200, 300), 255, np.uint8)
    drawing[::20, :] = 0
    clipped, lo, hi = level_range(drawing)
    assert clipped is drawing and (lo, hi) == (0, 255)
    # A photograph's levels: nothing apart, nothing clipped.
    photo = texture((200, 300), 5)
    clipped, lo, hi = level_range(photo)
    assert clipped is photo
