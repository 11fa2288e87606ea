import numpy as np
import pytest
from scipy.spatial import Delaunay

from pwlreg.core.raster import affine_maps, expand, label_image, quantize, rasterize
from pwlreg.core.warp import piecewise_map, warp_image
from tests.core.synthetic import texture

skimage_transform = pytest.importorskip("skimage.transform")


def _mesh(shape, seed=1, n=40, jitter=2.0):
    h, w = shape
    rng = np.random.default_rng(seed)
    corners = [[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1]]
    ref = quantize(np.vstack([rng.uniform(5, [w - 5, h - 5], (n, 2)), corners]))
    mov = quantize(ref + rng.normal(0, jitter, ref.shape))
    return ref, mov, Delaunay(ref).simplices


def test_matches_scikit_image_piecewise_affine_within_one_grey_level():
    shape = (180, 240)
    moving = texture(shape, 3, sigma=3.0)
    ref, mov, tris = _mesh(shape)
    tform = skimage_transform.PiecewiseAffineTransform.from_estimate(ref, mov)
    expected = skimage_transform.warp(
        moving, tform, output_shape=shape, order=1, preserve_range=True, cval=-1
    )
    ours = warp_image(moving, ref, mov, tris, shape)
    both = (ours[..., 1] > 0) & (expected >= 0)
    assert both.sum() > 0.95 * shape[0] * shape[1]
    diff = np.abs(ours[..., 0].astype(float) - expected)[both]
    assert diff.max() <= 1.0


def test_colour_sixteen_bit_and_alpha():
    shape = (60, 80)
    base = texture(shape, 5).astype(np.uint16) * 257
    moving = np.dstack([base, base // 2, 65535 - base])
    ref, mov, tris = _mesh(shape, n=10, jitter=0.0)
    out = warp_image(moving, ref, mov, tris, shape)
    assert out.dtype == np.uint16 and out.shape == (60, 80, 4)
    inside = out[..., 3] == 65535
    # Identity mesh: every band is reproduced where alpha is set.
    np.testing.assert_array_equal(out[..., :3][inside], moving[inside])
    # Outside the mesh (a corner cut off) alpha is 0.
    cut = tris[1:]
    out2 = warp_image(moving, ref, mov, cut, shape)
    assert (out2[..., 3] == 0).sum() > 0
    assert np.all(out2[..., :3][out2[..., 3] == 0] == 0)


def test_piecewise_map_reproduces_affine_inside_triangle():
    ref = np.array([[0, 0], [50, 0], [0, 40]], float)
    A = np.array([[1.1, 0.2, 3.0], [0.1, 0.9, -1.0]])
    mov = ref @ A[:, :2].T + A[:, 2]
    mx, my, label = piecewise_map(ref, mov, np.array([[0, 1, 2]]), (41, 51))
    ys, xs = np.nonzero(label == 0)
    np.testing.assert_allclose(mx[ys, xs], A[0, 0] * xs + A[0, 1] * ys + A[0, 2], atol=1e-9)
    np.testing.assert_allclose(my[ys, xs], A[1, 0] * xs + A[1, 1] * ys + A[1, 2], atol=1e-9)
    assert np.isnan(mx[label < 0]).all()


def test_outer_edges_are_closed_so_corner_points_cover_the_whole_image():
    shape = (40, 60)
    img = texture(shape, 1)
    pts = np.array([[0, 0], [59, 0], [0, 39], [59, 39], [30, 20], [10, 39], [59, 12]], float)
    out = warp_image(img, pts, pts, Delaunay(pts).simplices, shape)
    assert (out[..., 1] == 255).all()
    np.testing.assert_array_equal(out[..., 0], img)


def test_rendered_region_is_the_closed_mesh_outline():
    from scipy.spatial import ConvexHull

    rng = np.random.default_rng(5)
    shape = (50, 70)
    pts = np.unique(np.round(rng.uniform(-5, [75, 55], size=(25, 2))), axis=0)
    img = texture(shape, 2)
    out = warp_image(img, pts, pts, Delaunay(pts).simplices, shape)
    ys, xs = np.mgrid[0 : shape[0], 0 : shape[1]]
    grid = np.c_[xs.ravel(), ys.ravel(), np.ones(xs.size)]
    inside_or_on = (grid @ ConvexHull(pts).equations.T <= 1e-9).all(axis=1).reshape(shape)
    np.testing.assert_array_equal(out[..., 1] > 0, inside_or_on)


def test_piecewise_map_kernel_equals_the_per_pixel_expression():
    # The span-filling kernel must give the numpy expression's values bit for bit (no fused
    # multiply-add), and every pixel of the label image the owner the spans give it.
    shape = (150, 210)
    ref, mov, tris = _mesh(shape, seed=4, n=60, jitter=5.0)
    map_x, map_y, label = piecewise_map(ref, mov, tris, shape)
    spans = rasterize(ref[tris], shape)
    run, x, y = expand(spans)
    m = affine_maps(ref[tris], mov[tris])[spans.triangle[run]]
    xf, yf = x.astype(np.float64), y.astype(np.float64)
    np.testing.assert_array_equal(map_x[y, x], m[:, 0, 0] * xf + m[:, 0, 1] * yf + m[:, 0, 2])
    np.testing.assert_array_equal(map_y[y, x], m[:, 1, 0] * xf + m[:, 1, 1] * yf + m[:, 1, 2])
    np.testing.assert_array_equal(label[y, x], spans.triangle[run])
    np.testing.assert_array_equal(label, label_image(ref[tris], shape))
    outside = np.ones(shape, bool)
    outside[y, x] = False
    assert (label[outside] == -1).all() and np.isnan(map_x[outside]).all()
