"""The registered image tile by tile, so that memory does not grow with the raster.

:func:`warp_tiles` resamples any :class:`BandSource` (bands in memory, or a file read window by
window) through the mesh's piecewise-affine map one output tile at a time: a compiled kernel
writes the tile's sampling maps with the fill rule of :mod:`pwlreg.core.kernels` (each pixel
to one triangle, the mesh's outer edges closed as in :func:`pwlreg.core.warp.warp_image`) and
finds the part of the moving image the tile maps onto, only that part is read, and OpenCV's
``remap`` samples it (bilinear, 1/32-pixel weights, integers rounded). The work memory is a few
tiles and their source windows, whatever the size of the images.

Coordinates: pixels, x right, y down, (0, 0) the centre of the top-left pixel.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Protocol

import cv2
import numpy as np
from numba import njit

from pwlreg.core.imaging import file_bands
from pwlreg.core.kernels import _load_triangle, _row_range, row_span, to_fixed
from pwlreg.core.raster import affine_maps
from pwlreg.core.warp import outer_edge_flags

LEVEL_PIXELS = 1 << 24
"""Largest image registered at full resolution (16.8 MP: about 250 MB of work memory); larger
ones are registered on a reduced level (:mod:`pwlreg.core.scaled`) and their files, when TIFFs,
read window by window."""
TILE = 512
"""Side of the output tiles, in pixels (a multiple of registered.tif's 512-pixel blocks)."""
_REMAP_DTYPES = (np.uint8, np.uint16, np.int16, np.float32, np.float64)
"""Sample types OpenCV's remap takes as they are (32-bit integers go through float64)."""


class BandSource(Protocol):
    """An image read window by window: its bands in file order and its valid pixels."""

    height: int
    width: int
    count: int
    dtype: np.dtype

    def read(self, x0: int, y0: int, x1: int, y1: int) -> tuple[np.ndarray, np.ndarray | None]:
        """Columns ``x0:x1`` and rows ``y0:y1``: bands ``(h, w, count)`` and validity
        ``(h, w)`` bool (None when every pixel there is valid)."""
        ...

    def level(self, factor: int) -> np.ndarray:
        """The image reduced ``factor`` times on both axes (each level pixel the mean of a
        ``factor x factor`` block; the last ``width % factor`` columns and ``height % factor``
        rows are left out), a picture or a raster as :mod:`pwlreg.core.imaging` defines them."""
        ...


def reduce_area(data: np.ndarray, factor: int) -> np.ndarray:
    """``data`` ``(h, w[, C])``, both sides multiples of ``factor``, averaged over
    ``factor x factor`` blocks (OpenCV's area resampling, exact for an integer factor; integer
    samples rounded)."""
    h, w = data.shape[0] // factor, data.shape[1] // factor
    if factor == 1:
        return data
    exact = data.dtype in _REMAP_DTYPES
    small = cv2.resize(data if exact else data.astype(np.float64), (w, h),
                       interpolation=cv2.INTER_AREA)
    if data.ndim == 3 and small.ndim == 2:
        small = small[:, :, None]
    if not exact:
        info = np.iinfo(data.dtype)
        small = np.clip(np.round(small), info.min, info.max).astype(data.dtype)
    return small


class ArrayBands:
    """A :class:`BandSource` over a decoded picture or raster (:mod:`pwlreg.core.imaging`)."""

    def __init__(self, image: np.ndarray) -> None:
        self._image = image
        self._bands, self._valid = file_bands(image)
        self.height, self.width, self.count = self._bands.shape
        self.dtype = self._bands.dtype

    def read(self, x0: int, y0: int, x1: int, y1: int) -> tuple[np.ndarray, np.ndarray | None]:
        valid = None if self._valid is None else self._valid[y0:y1, x0:x1]
        # None for a window of valid pixels only, as RasterFile.read says it: a mask there
        # kept every pair of the window from its refinement at full resolution.
        return self._bands[y0:y1, x0:x1], None if valid is None or valid.all() else valid

    def level(self, factor: int) -> np.ndarray:
        h, w = self.height // factor * factor, self.width // factor * factor
        small = reduce_area(np.ma.getdata(self._image)[:h, :w], factor)
        if not np.ma.isMaskedArray(self._image):
            return small
        mask = np.ma.getmaskarray(self._image)[:h, :w]
        return np.ma.MaskedArray(small, mask=reduce_area(mask.astype(np.float32), factor) > 0.5)


@dataclass(frozen=True)
class Tile:
    """One tile of the registered image.

    Attributes
    ----------
    x0, y0 : int
        Its top-left pixel in the reference grid.
    bands : ndarray, shape (h, w, count)
        The moving image's bands resampled, the source's dtype; ``nodata`` where not ``inside``.
    inside : ndarray of bool, shape (h, w)
        Pixels inside the mesh that map inside the moving image onto valid pixels only.
    """

    x0: int
    y0: int
    bands: np.ndarray
    inside: np.ndarray


_OUTSIDE = -2.0
"""``map_x`` of a pixel owned by a triangle but mapped outside the moving image; -1: owned by
none yet. Both are outside any window, so ``remap`` gives them the border value."""


@njit(cache=True, inline="always")
def _sampled(ax, cx, ay, cy, x0, x, mw, mh):  # type: ignore[no-untyped-def]
    mx = ax * (x + x0) + cx
    my = ay * (x + x0) + cy
    return mx >= 0.0 and my >= 0.0 and mx <= mw - 1 and my <= mh - 1


@njit(cache=True, inline="always")
def _run_inside(lo, hi, ax, cx, ay, cy, x0, mw, mh):  # type: ignore[no-untyped-def]
    """The columns of ``lo..hi`` whose map falls inside the moving image (an interval: the map
    is affine along the row), found from the analytic bounds, then checked at its ends with the
    per-pixel test so that rounding cannot move them."""
    first, last = float(lo), float(hi)
    for a, c, top in ((ax, cx, mw - 1.0), (ay, cy, mh - 1.0)):
        if a > 0.0:
            first = max(first, (0.0 - c) / a - x0)
            last = min(last, (top - c) / a - x0)
        elif a < 0.0:
            first = max(first, (top - c) / a - x0)
            last = min(last, (0.0 - c) / a - x0)
        elif not (0.0 <= c <= top):
            return 0, -1
    if first > last + 1.0:
        return 0, -1
    vlo = max(lo, min(hi, int(np.ceil(first))))
    while vlo > lo and _sampled(ax, cx, ay, cy, x0, vlo - 1, mw, mh):
        vlo -= 1
    while vlo <= hi and not _sampled(ax, cx, ay, cy, x0, vlo, mw, mh):
        vlo += 1
    if vlo > hi:
        return 0, -1
    vhi = max(vlo, min(hi, int(np.floor(last))))
    while vhi < hi and _sampled(ax, cx, ay, cy, x0, vhi + 1, mw, mh):
        vhi += 1
    while vhi > vlo and not _sampled(ax, cx, ay, cy, x0, vhi, mw, mh):
        vhi -= 1
    return vlo, vhi


@njit(cache=True, nogil=True)
def _tile_maps(ref_tris, maps, closed, whole, x0, y0, mw, mh, map_x, map_y):  # type: ignore[no-untyped-def]
    """Fill ``map_x`` and ``map_y`` (float32, the tile's shape; ``map_x`` -1 on entry) with each
    owned pixel's position in the moving image relative to the window it needs;
    :data:`_OUTSIDE` in ``map_x`` where the pixel maps outside the moving image. ``ref_tris``
    are shifted by ``(-x0, -y0)``; ``whole[t]`` says that triangle ``t`` maps wholly inside the
    moving image.

    Returns the window ``(sx0, sy0, sx1, sy1)`` (end exclusive; empty when nothing maps).
    The runs of the fill rule (every pixel to one triangle of the reference triangulation) and
    of the second pass that closes the mesh's outer edges are found once; along a run the map
    is affine, so the window comes from the runs' ends, and the runs of the first pass are
    written without a test per pixel (the second's only on pixels still unowned).
    """
    height, width = map_x.shape
    q = np.empty((3, 2), dtype=np.int64)
    n_tri = ref_tris.shape[0]
    total = 0
    for t in range(n_tri):
        r0, r1 = _row_range(_load_rows(ref_tris[t], q), height)
        if r1 >= r0:
            total += (r1 - r0 + 1) * (2 if closed[t] else 1)
    runs = np.empty((total, 6), np.int64)  # triangle, y, lo, hi, inside lo, inside hi
    n = 0
    lo_x, lo_y, hi_x, hi_y = np.inf, np.inf, -np.inf, -np.inf
    first_pass = 0
    for second in range(2):
        for t in range(n_tri):
            mask = 0
            if second:
                if closed[t] == 0:
                    continue
                mask = closed[t]
            flip = _load_triangle(ref_tris[t], q)
            if flip == 0:
                continue
            if flip < 0:
                mask = (mask & 2) | ((mask & 1) << 2) | ((mask >> 2) & 1)
            r0, r1 = _row_range(q, height)
            ax, ay = maps[t, 0, 0], maps[t, 1, 0]
            for y in range(r0, r1 + 1):
                lo, hi = row_span(q, y, width, mask)
                if lo > hi:
                    continue
                gy = y + y0
                cx = maps[t, 0, 1] * gy + maps[t, 0, 2]
                cy = maps[t, 1, 1] * gy + maps[t, 1, 2]
                if whole[t]:
                    vlo, vhi = lo, hi
                else:
                    vlo, vhi = _run_inside(lo, hi, ax, cx, ay, cy, x0, mw, mh)
                runs[n, 0], runs[n, 1], runs[n, 2], runs[n, 3] = t, y, lo, hi
                runs[n, 4], runs[n, 5] = vlo, vhi
                n += 1
                if vlo > vhi:
                    continue
                for x in (vlo, vhi):
                    mx = ax * (x + x0) + cx
                    my = ay * (x + x0) + cy
                    lo_x = min(lo_x, mx)
                    hi_x = max(hi_x, mx)
                    lo_y = min(lo_y, my)
                    hi_y = max(hi_y, my)
        if not second:
            first_pass = n
    if lo_x > hi_x:
        return 0, 0, 0, 0
    sx0 = int(lo_x)
    sy0 = int(lo_y)
    sx1 = min(int(hi_x) + 2, mw)
    sy1 = min(int(hi_y) + 2, mh)
    for r in range(n):
        t, y, lo, hi, vlo, vhi = runs[r, 0], runs[r, 1], runs[r, 2], runs[r, 3], runs[r, 4], \
            runs[r, 5]
        if vlo > vhi:
            vlo, vhi = hi + 1, hi
        gy = y + y0
        ax, ay = maps[t, 0, 0], maps[t, 1, 0]
        cx = maps[t, 0, 1] * gy + maps[t, 0, 2] - sx0  # relative to the window
        cy = maps[t, 1, 1] * gy + maps[t, 1, 2] - sy0
        row_x = map_x[y]
        row_y = map_y[y]
        if r < first_pass:
            # Indices counted from 0 over slices: numba then emits no negative-index check and
            # the loop vectorizes (3x faster); x + x0 is the same integer, so the same value.
            row_x[lo:vlo] = _OUTSIDE
            row_x[vhi + 1:hi + 1] = _OUTSIDE
            run_x = row_x[vlo:vhi + 1]
            run_y = row_y[vlo:vhi + 1]
            start = vlo + x0
            for k in range(vhi + 1 - vlo):
                run_x[k] = ax * (k + start) + cx
                run_y[k] = ay * (k + start) + cy
        else:
            for x in range(lo, hi + 1):
                if row_x[x] != -1.0:
                    continue
                if x < vlo or x > vhi:
                    row_x[x] = _OUTSIDE
                else:
                    row_x[x] = ax * (x + x0) + cx
                    row_y[x] = ay * (x + x0) + cy
    return sx0, sy0, sx1, sy1


@njit(cache=True, inline="always")
def _load_rows(tri, q):  # type: ignore[no-untyped-def]
    """``q`` with the fixed-point rows of ``tri`` (for :func:`_row_range`)."""
    for v in range(3):
        q[v, 1] = to_fixed(tri[v, 1])
    return q


def warp_tiles(
    source: BandSource,
    reference_vertices: np.ndarray,
    moving_vertices: np.ndarray,
    triangles: np.ndarray,
    shape: tuple[int, int],
    *,
    tile: int = TILE,
    nodata: float = 0,
    threads: int = 1,
) -> Iterator[Tile]:
    """The registered image as tiles, row of tiles by row of tiles, left to right.

    ``threads`` tiles are computed at once (the map kernel and OpenCV release the GIL; the
    source is read by one thread at a time, as a GDAL dataset must be), so the memory is that
    many tiles and their windows.

    Parameters
    ----------
    source : BandSource
        The moving image.
    reference_vertices, moving_vertices : ndarray, shape (N, 2)
        The mesh's vertices in the full-resolution reference and moving images.
    triangles : ndarray, shape (T, 3)
        The mesh's triangles.
    shape : (int, int)
        ``(height, width)`` of the reference grid.
    tile : int
        Tile side in pixels.
    nodata : float
        Value of the pixels that are not ``inside`` (cast to the source's dtype).
    threads : int
        Tiles computed at the same time.

    Yields
    ------
    Tile
        Every tile of the grid, with the pixels nothing maps onto at ``nodata``.
    """
    height, width = int(shape[0]), int(shape[1])
    ref = np.asarray(reference_vertices, np.float64)
    tris = np.asarray(triangles, np.int64).reshape(-1, 3)
    ref_tris = np.ascontiguousarray(ref[tris])
    mov_tris = np.ascontiguousarray(np.asarray(moving_vertices, np.float64)[tris])
    maps = affine_maps(ref_tris, mov_tris)
    closed = outer_edge_flags(tris)
    # Triangles mapped wholly inside the moving image need no test per run: a convex
    # combination of their corners is inside too. The margin covers the pixels the fill rule
    # gives a triangle from its 1/256-pixel corners, up to 1/256 px outside the exact ones.
    margin = 0.5
    whole = ((mov_tris >= margin).all(axis=(1, 2))
             & (mov_tris[:, :, 0] <= source.width - 1 - margin).all(axis=1)
             & (mov_tris[:, :, 1] <= source.height - 1 - margin).all(axis=1))
    lo, hi = ref_tris.min(axis=1), ref_tris.max(axis=1)  # (T, 2) bounding boxes
    reads = threading.Lock()

    def one(corner: tuple[int, int]) -> Tile:
        x0, y0 = corner
        rows, cols = min(tile, height - y0), min(tile, width - x0)
        near = ((hi[:, 1] >= y0 - 1) & (lo[:, 1] <= y0 + rows)
                & (hi[:, 0] >= x0 - 1) & (lo[:, 0] <= x0 + cols))
        return _one_tile(source, ref_tris[near], maps[near], closed[near], whole[near], x0, y0,
                         rows, cols, nodata, reads)

    corners = [(x0, y0) for y0 in range(0, height, tile) for x0 in range(0, width, tile)]
    if threads <= 1:
        yield from map(one, corners)
        return
    with ThreadPoolExecutor(threads) as pool:
        pending: deque[Future[Tile]] = deque()
        for corner in corners:
            pending.append(pool.submit(one, corner))
            if len(pending) > threads:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()


def _one_tile(source: BandSource, ref_tris: np.ndarray, maps: np.ndarray, closed: np.ndarray,
              whole: np.ndarray, x0: int, y0: int, rows: int, cols: int, nodata: float,
              reads: threading.Lock) -> Tile:
    map_x = np.full((rows, cols), -1.0, np.float32)
    # Where map_x < 0, map_y is never read: x alone puts the pixel outside any window.
    map_y = np.empty((rows, cols), np.float32)
    window = (0, 0, 0, 0)
    if len(ref_tris):
        shifted = np.ascontiguousarray(ref_tris - np.array([x0, y0], np.float64))
        window = _tile_maps(shifted, maps, closed, whole, x0, y0, source.width, source.height,
                            map_x, map_y)
    sx0, sy0, sx1, sy1 = window
    if sx1 <= sx0 or sy1 <= sy0:
        out = np.full((rows, cols, source.count), nodata, dtype=source.dtype)
        return Tile(x0, y0, out, np.zeros((rows, cols), bool))
    inside = map_x >= 0
    with reads:
        part, valid = source.read(sx0, sy0, sx1, sy1)
    if valid is not None:
        if part.dtype.kind == "f":  # a NaN weighted 0 still makes NaN: only finite samples
            part = np.where(valid[:, :, None], part, 0)
        ok = cv2.remap(valid.astype(np.uint8) * np.uint8(255), map_x, map_y, cv2.INTER_LINEAR,
                       borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        inside &= ok == 255
    exact = part.dtype in _REMAP_DTYPES
    chunks = []
    for c0 in range(0, source.count, 4):  # remap takes up to 4 channels at once
        chunk = np.ascontiguousarray(part[:, :, c0:c0 + 4])
        # Unmapped pixels point outside the window: the border value is their nodata.
        warped = cv2.remap(chunk if exact else chunk.astype(np.float64), map_x, map_y,
                           cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                           borderValue=(nodata,) * 4)
        chunks.append(warped.reshape(rows, cols, -1))
    out = chunks[0] if len(chunks) == 1 else np.concatenate(chunks, axis=2)
    if not exact:
        info = np.iinfo(source.dtype)
        out = np.clip(np.round(out), info.min, info.max).astype(source.dtype)
    if valid is not None:
        out[~inside] = np.array(nodata).astype(source.dtype)
    return Tile(x0, y0, out, inside)
