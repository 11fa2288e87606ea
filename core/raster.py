"""Exact triangle rasterization with one fill rule, and per-triangle affine maps.

Conventions
-----------
Pixel ``(x, y)`` is the point at the centre of column ``x`` and row ``y`` (x right, y down,
(0, 0) the centre of the top-left pixel). Vertex coordinates are quantized to
``1 / SUBPIXEL`` pixel (:func:`quantize`), so every geometric predicate below is evaluated in
exact int64 arithmetic.

Fill rule: a pixel centre belongs to a triangle when it lies strictly inside, or on an edge
or vertex and the point displaced by an infinitesimal ``(d, d**2)`` lies inside (a symbolic
perturbation; for pixel centres on a horizontal edge the pixel goes to the triangle below,
otherwise to the triangle on the right). Triangles that tile a region therefore own every
pixel centre of that region exactly once, and a union of triangles owns exactly the union of
their pixels: the joint histogram of a quad is the sum of its two triangles' histograms.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

SUBPIXEL = 256
"""Vertex coordinates are multiples of ``1 / SUBPIXEL`` pixel."""

_BIG = np.int64(2**62)


def quantize(points: np.ndarray) -> np.ndarray:
    """Round coordinates (pixels) to the ``1 / SUBPIXEL`` grid used by every predicate."""
    return np.rint(np.asarray(points, dtype=np.float64) * SUBPIXEL) / SUBPIXEL


def _fixed(points: np.ndarray) -> np.ndarray:
    return np.rint(np.asarray(points, dtype=np.float64) * SUBPIXEL).astype(np.int64)


def orientation(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Exact sign (-1, 0, +1) of the signed area of triangles ``(a, b, c)``.

    ``a``, ``b``, ``c`` are ``(..., 2)`` arrays of quantized pixel coordinates. In image axes
    (y down) a positive sign means the vertices turn clockwise on screen.
    """
    a, b, c = _fixed(a), _fixed(b), _fixed(c)
    cross = (b[..., 0] - a[..., 0]) * (c[..., 1] - a[..., 1]) - (b[..., 1] - a[..., 1]) * (
        c[..., 0] - a[..., 0]
    )
    return np.sign(cross).astype(np.int8)


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
    height, width = int(shape[0]), int(shape[1])
    q = _fixed(tri_xy).reshape(-1, 3, 2)
    cross = (q[:, 1, 0] - q[:, 0, 0]) * (q[:, 2, 1] - q[:, 0, 1]) - (q[:, 1, 1] - q[:, 0, 1]) * (
        q[:, 2, 0] - q[:, 0, 0]
    )
    # Make every triangle positively oriented so that its interior is where all edge
    # functions are positive.
    flip = cross < 0
    q[flip] = q[flip][:, [0, 2, 1]]
    alive = cross != 0

    ys = q[:, :, 1]
    ymin = -((-ys.min(axis=1)) // SUBPIXEL)  # ceil
    ymax = ys.max(axis=1) // SUBPIXEL  # floor
    ymin = np.maximum(ymin, 0)
    ymax = np.minimum(ymax, height - 1)
    nrows = np.where(alive, np.maximum(ymax - ymin + 1, 0), 0)
    total = int(nrows.sum())
    empty = np.zeros(0, dtype=np.intp)
    if total == 0:
        return Spans(empty, empty, empty, empty)

    tri = np.repeat(np.arange(len(q), dtype=np.intp), nrows)
    starts = np.cumsum(nrows) - nrows
    y = ymin[tri] + (np.arange(total, dtype=np.int64) - np.repeat(starts, nrows))
    py = y * SUBPIXEL

    lo = np.zeros(total, dtype=np.int64)
    hi = np.full(total, width - 1, dtype=np.int64)
    keep = np.ones(total, dtype=bool)
    for e in range(3):
        a = q[tri, e]
        b = q[tri, (e + 1) % 3]
        dx = b[:, 0] - a[:, 0]
        dy = b[:, 1] - a[:, 1]
        # Edge function E(px) = -dy * PX + k with PX = px * SUBPIXEL; inside is E > 0, and
        # E == 0 counts as inside when the perturbation (d, d^2) enters: -dy > 0, or dy == 0
        # and dx > 0.
        k = dx * (py - a[:, 1]) + dy * a[:, 0]
        den = np.abs(dy) * SUBPIXEL
        safe = np.where(den == 0, 1, den)
        # dy < 0: px >= ceil(-k / den) = -(k // den)
        lower = np.where(dy < 0, -(k // safe), -_BIG)
        # dy > 0: px < k / den  <=>  px <= ceil(k / den) - 1
        upper = np.where(dy > 0, -((-k) // safe) - 1, _BIG)
        lo = np.maximum(lo, lower)
        hi = np.minimum(hi, upper)
        flat = dy == 0
        keep &= ~flat | (k > 0) | ((k == 0) & (dx > 0))
    keep &= lo <= hi
    return Spans(
        triangle=tri[keep],
        y=y[keep].astype(np.intp),
        x0=lo[keep].astype(np.intp),
        length=(hi[keep] - lo[keep] + 1).astype(np.intp),
    )


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
    span_index, x, y = expand(spans)
    labels[y, x] = spans.triangle[span_index]
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
    src = np.asarray(src_tri, dtype=np.float64)
    dst = np.asarray(dst_tri, dtype=np.float64)
    # Solve in coordinates relative to the first vertex: better conditioned for large images.
    d1 = src[:, 1] - src[:, 0]
    d2 = src[:, 2] - src[:, 0]
    det = d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = (
            np.stack([np.stack([d2[:, 1], -d2[:, 0]], -1), np.stack([-d1[:, 1], d1[:, 0]], -1)], 1)
            / det[:, None, None]
        )
    e1 = dst[:, 1] - dst[:, 0]
    e2 = dst[:, 2] - dst[:, 0]
    lin = np.stack([e1, e2], axis=-1) @ inv  # (T, 2, 2)
    trans = dst[:, 0] - np.einsum("tij,tj->ti", lin, src[:, 0])
    return np.concatenate([lin, trans[:, :, None]], axis=2)
