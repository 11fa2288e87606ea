"""Exact triangle rasterization with one fill rule, and per-triangle affine maps.

Conventions
-----------
Pixel ``(x, y)`` is the point at the centre of column ``x`` and row ``y`` (x right, y down,
(0, 0) the centre of the top-left pixel). Vertex coordinates are quantized to
``1 / SUBPIXEL`` pixel (:func:`quantize`), so every geometric predicate below is evaluated in
exact int64 arithmetic.

Fill rule (implemented once, in :func:`core.kernels.row_span`): a pixel centre belongs to a
triangle when it lies strictly inside, or on an edge
or vertex and the point displaced by an infinitesimal ``(d, d**2)`` lies inside (a symbolic
perturbation; for pixel centres on a horizontal edge the pixel goes to the triangle below,
otherwise to the triangle on the right). Triangles that tile a region therefore own every
pixel centre of that region exactly once, and a union of triangles owns exactly the union of
their pixels: the joint histogram of a quad is the sum of its two triangles' histograms.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pwlreg.core import kernels

SUBPIXEL = kernels.SUBPIXEL
"""Vertex coordinates are multiples of ``1 / SUBPIXEL`` pixel."""


def quantize(points: np.ndarray) -> np.ndarray:
    """Round coordinates (pixels) to the ``1 / SUBPIXEL`` grid used by every predicate."""
    return fixed_point(points) / SUBPIXEL


def first_occurrences(points: np.ndarray) -> np.ndarray:
    """Index of the first of each distinct point of ``points`` ``(N, 2)``, in the order of the
    points sorted by x then y: ``np.unique(points, axis=0, return_index=True)[1]``, a tenth
    of its time (each row one complex number, whose sort is the same lexicographic one)."""
    rows = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 2)
    return np.unique(rows.view(np.complex128).ravel(), return_index=True)[1]


def fixed_point(points: np.ndarray) -> np.ndarray:
    """Coordinates as int64 multiples of ``1 / SUBPIXEL`` pixel (the kernels' input)."""
    # floor(v + 0.5), as kernels.to_fixed: the kernels quantize their input the same way.
    return np.floor(np.asarray(points, dtype=np.float64) * SUBPIXEL + 0.5).astype(np.int64)


def cross_fixed(p: np.ndarray, q: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Twice the signed areas of fixed-point triangles ``(p, q, r)`` (:func:`fixed_point`),
    ``(..., 2)`` int64 each.

    Exact for coordinates within ``core.mesh.MAX_COORDINATE``: twice the area of a triangle in
    a square of side ``2 * MAX_COORDINATE * SUBPIXEL = 2**31`` is at most ``2**62``.
    """
    return (q[..., 0] - p[..., 0]) * (r[..., 1] - p[..., 1]) - (q[..., 1] - p[..., 1]) * (
        r[..., 0] - p[..., 0]
    )


def orientation(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Exact sign (-1, 0, +1) of the signed area of triangles ``(a, b, c)``.

    ``a``, ``b``, ``c`` are ``(..., 2)`` arrays of quantized pixel coordinates. In image axes
    (y down) a positive sign means the vertices turn clockwise on screen.
    """
    return np.sign(cross_fixed(fixed_point(a), fixed_point(b), fixed_point(c))).astype(np.int8)


def triangle_areas(tri_xy: np.ndarray) -> np.ndarray:
    """Unsigned areas in square pixels of triangles given as a ``(T, 3, 2)`` array."""
    t = np.asarray(tri_xy, dtype=np.float64)
    d1 = t[:, 1] - t[:, 0]
    d2 = t[:, 2] - t[:, 0]
    return 0.5 * np.abs(d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0])


@dataclass(frozen=True)
class Spans:
    """Horizontal runs of pixels owned by triangles.

    Attributes
    ----------
    triangle : ndarray of intp, shape (S,)
        Index (into the rasterized batch) of the triangle owning each run.
    y : ndarray of intp, shape (S,)
        Row of each run.
    x0 : ndarray of intp, shape (S,)
        First column of each run.
    length : ndarray of intp, shape (S,)
        Number of pixels of each run (at least 1).
    """

    triangle: np.ndarray
    y: np.ndarray
    x0: np.ndarray
    length: np.ndarray

    @property
    def n_pixels(self) -> int:
        """Total number of pixels in all runs."""
        return int(self.length.sum())


def rasterize(tri_xy: np.ndarray, shape: tuple[int, int]) -> Spans:
    """Pixels of the image grid owned by each triangle, as horizontal runs.

    Parameters
    ----------
    tri_xy : ndarray, shape (T, 3, 2)
        Vertex coordinates (pixels, quantized by :func:`quantize`), any orientation.
        Degenerate (zero-area) triangles own no pixel.
    shape : (int, int)
        ``(height, width)`` of the image grid; pixels outside it are clipped.

    Returns
    -------
    Spans
        Runs ordered by triangle, then row.
    """
    tris = np.ascontiguousarray(tri_xy, dtype=np.float64).reshape(-1, 3, 2)
    tri, y, x0, length = kernels.spans(tris, int(shape[0]), int(shape[1]))
    return Spans(triangle=tri, y=y, x0=x0, length=length)


def expand(spans: Spans) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Expand runs into one entry per pixel.

    Returns
    -------
    span_index : ndarray of intp, shape (P,)
        Run of each pixel.
    x, y : ndarray of intp, shape (P,)
        Pixel coordinates.
    """
    n = spans.length
    total = int(n.sum())
    span_index = np.repeat(np.arange(len(n), dtype=np.intp), n)
    offsets = np.cumsum(n) - n
    ramp = np.arange(total, dtype=np.intp) - np.repeat(offsets, n)
    return span_index, spans.x0[span_index] + ramp, spans.y[span_index]


def label_image(tri_xy: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """``(H, W)`` int32 image of the index of the triangle owning each pixel, -1 for none."""
    spans = rasterize(tri_xy, shape)
    labels = np.full(shape, -1, dtype=np.int32)
    none = np.empty((0, 0))
    kernels.fill_spans(spans.triangle, spans.y, spans.x0, spans.length, np.empty((0, 2, 3)),
                       none, none, labels)
    return labels


def affine_maps(src_tri: np.ndarray, dst_tri: np.ndarray) -> np.ndarray:
    """Affine maps taking each source triangle onto its destination triangle.

    Parameters
    ----------
    src_tri, dst_tri : ndarray, shape (T, 3, 2)
        Corresponding vertices (pixels).

    Returns
    -------
    ndarray, shape (T, 2, 3)
        ``A`` with ``dst = A @ [x, y, 1]``. Degenerate source triangles get NaN.
    """
    src = np.ascontiguousarray(src_tri, dtype=np.float64).reshape(-1, 3, 2)
    dst = np.ascontiguousarray(dst_tri, dtype=np.float64).reshape(-1, 3, 2)
    out = np.empty((len(src), 2, 3))
    kernels.affine_maps(src, dst, out)
    return out
