"""Resampling the moving image through a piecewise-affine map.

Coordinates are pixels, x right, y down, (0, 0) the centre of the top-left pixel. Resampling is
bilinear (OpenCV's ``remap``, whose interpolation weights are quantized to 1/32 pixel).
"""

from __future__ import annotations

import cv2
import numpy as np

from core.raster import Spans, affine_maps, expand, rasterize

_ROW = 8192
MAX_SIDE = 32766
"""Largest image side (pixels) that OpenCV's remap accepts."""


def remap_buffers(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Two float32 coordinate buffers of at least ``n`` entries shaped for :func:`cv2.remap`.

    ``remap`` refuses images with a side of 32767 or more, so long lists of sample positions
    are laid out as rows of a fixed width; the padding is filled with zeros.
    """
    rows = max(1, -(-n // _ROW))
    mx = np.empty(rows * _ROW, dtype=np.float32)
    my = np.empty(rows * _ROW, dtype=np.float32)
    mx[n:] = 0
    my[n:] = 0
    return mx, my


def sample_bilinear(
    image: np.ndarray, x: np.ndarray, y: np.ndarray, border: int = cv2.BORDER_REPLICATE
) -> np.ndarray:
    """Bilinear samples of ``image`` at the points ``(x, y)``.

    Parameters
    ----------
    image : ndarray, shape (H, W) or (H, W, C)
        Any dtype ``remap`` accepts (uint8, uint16, float32), at most 4 channels.
    x, y : ndarray of float32, shape (P,)
        Sample positions in pixels. If they are views of buffers from :func:`remap_buffers`
        no copy is made.
    border : int
        OpenCV border mode for samples outside the image (replicate by default).

    Returns
    -------
    ndarray, shape (P,) or (P, C)
        Samples, same dtype as ``image``.
    """
    n = len(x)
    rows = max(1, -(-n // _ROW))
    if x.base is not None and x.base.size == rows * _ROW and y.base is not None:
        mx, my = x.base, y.base
    else:
        mx, my = remap_buffers(n)
        mx[:n] = x
        my[:n] = y
    out = cv2.remap(
        image, mx.reshape(rows, _ROW), my.reshape(rows, _ROW), cv2.INTER_LINEAR, borderMode=border
    )
    if image.ndim == 3:
        return out.reshape(rows * _ROW, -1)[:n]
    return out.reshape(-1)[:n]


def map_spans(
    spans: Spans, maps: np.ndarray, width: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixels of ``spans`` and where each lands through its triangle's affine map.

    This is the hot path of scoring: affine maps are linear along a run, so each pixel's
    position is its run's start value plus a constant step times its offset in the run.

    Parameters
    ----------
    spans : Spans
        Runs from :func:`core.raster.rasterize`.
    maps : ndarray, shape (T, 2, 3)
        Affine map of each rasterized triangle (reference -> moving pixels).
    width : int
        Width of the reference grid.

    Returns
    -------
    flat : ndarray of intp, shape (P,)
        Row-major index ``y * width + x`` of each pixel, in run order.
    mx, my : ndarray of float32, shape (P,)
        Mapped coordinates in the moving image (pixels).
    """
    n = spans.length
    total = int(n.sum())
    m = maps[spans.triangle]  # (S, 2, 3)
    start_x = (m[:, 0, 0] * spans.x0 + m[:, 0, 1] * spans.y + m[:, 0, 2]).astype(np.float32)
    start_y = (m[:, 1, 0] * spans.x0 + m[:, 1, 1] * spans.y + m[:, 1, 2]).astype(np.float32)
    offsets = np.cumsum(n) - n
    ramp = np.arange(total, dtype=np.intp)
    ramp -= np.repeat(offsets, n)
    ramp_f = ramp.astype(np.float32)
    buf_x, buf_y = remap_buffers(total)
    mx, my = buf_x[:total], buf_y[:total]
    np.multiply(np.repeat(m[:, 0, 0].astype(np.float32), n), ramp_f, out=mx)
    mx += np.repeat(start_x, n)
    np.multiply(np.repeat(m[:, 1, 0].astype(np.float32), n), ramp_f, out=my)
    my += np.repeat(start_y, n)
    ramp += np.repeat(spans.y * width + spans.x0, n)
    return ramp, mx, my


def piecewise_map(
    reference_vertices: np.ndarray,
    moving_vertices: np.ndarray,
    triangles: np.ndarray,
    shape: tuple[int, int],
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Dense piecewise-affine map from the reference grid to the moving image.

    Parameters
    ----------
    reference_vertices, moving_vertices : ndarray, shape (N, 2)
        Vertex coordinates in pixels (quantized, as in :class:`core.mesh.Mesh`).
    triangles : ndarray, shape (T, 3)
        Vertex indices.
    shape : (int, int)
        ``(height, width)`` of the reference grid.

    Returns
    -------
    map_x, map_y : ndarray of float64, shape (H, W)
        Position in the moving image of each reference pixel; NaN outside the mesh.
    label : ndarray of int32, shape (H, W)
        Index of the triangle owning each pixel, -1 outside the mesh.
    """
    ref = np.asarray(reference_vertices, dtype=np.float64)
    mov = np.asarray(moving_vertices, dtype=np.float64)
    tris = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    maps = affine_maps(ref[tris], mov[tris])
    spans = rasterize(ref[tris], shape)
    span_index, x, y = expand(spans)
    tri = spans.triangle[span_index]
    map_x = np.full(shape, np.nan)
    map_y = np.full(shape, np.nan)
    label = np.full(shape, -1, dtype=np.int32)
    xf = x.astype(np.float64)
    yf = y.astype(np.float64)
    m = maps[tri]
    map_x[y, x] = m[:, 0, 0] * xf + m[:, 0, 1] * yf + m[:, 0, 2]
    map_y[y, x] = m[:, 1, 0] * xf + m[:, 1, 1] * yf + m[:, 1, 2]
    label[y, x] = tri
    return map_x, map_y, label


def warp_image(
    moving: np.ndarray,
    reference_vertices: np.ndarray,
    moving_vertices: np.ndarray,
    triangles: np.ndarray,
    shape: tuple[int, int],
) -> np.ndarray:
    """The moving image resampled into the reference frame through the mesh, with alpha.

    Every band is kept and the dtype is preserved; an alpha band is appended (full scale where
    the reference pixel lies inside the mesh and maps inside the moving image, 0 elsewhere).

    Parameters
    ----------
    moving : ndarray, shape (H', W') or (H', W', C)
        Moving image, uint8 or uint16; grey, BGR or BGRA (an existing alpha band is treated as
        data and multiplied into the output alpha).
    reference_vertices, moving_vertices, triangles
        The mesh (see :func:`piecewise_map`).
    shape : (int, int)
        ``(height, width)`` of the reference image.

    Returns
    -------
    ndarray, shape (H, W, 2) for grey input or (H, W, 4) for colour
        Grey+alpha or BGRA, dtype of ``moving``.
    """
    height, width = int(shape[0]), int(shape[1])
    src = moving if moving.ndim == 3 else moving[:, :, None]
    bands = src.shape[2]
    colour = src[:, :, :3] if bands >= 3 else src[:, :, :1]
    full = np.iinfo(moving.dtype).max
    ref = np.asarray(reference_vertices, dtype=np.float64)
    mov = np.asarray(moving_vertices, dtype=np.float64)
    tris = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    spans = rasterize(ref[tris], (height, width))
    flat, mx, my = map_spans(spans, affine_maps(ref[tris], mov[tris]), width)
    out = np.zeros((height * width, colour.shape[2] + 1), dtype=moving.dtype)
    values = sample_bilinear(np.ascontiguousarray(colour), mx, my, cv2.BORDER_CONSTANT)
    out[flat, : colour.shape[2]] = values.reshape(len(flat), -1)
    h2, w2 = moving.shape[:2]
    inside = (mx >= 0) & (mx <= w2 - 1) & (my >= 0) & (my <= h2 - 1)
    alpha = np.where(inside, full, 0).astype(moving.dtype)
    if bands == 4:
        src_alpha = sample_bilinear(
            np.ascontiguousarray(src[:, :, -1]), mx, my, cv2.BORDER_CONSTANT
        )
        alpha = np.minimum(alpha, src_alpha)
    out[flat, -1] = alpha
    return out.reshape(height, width, -1)
