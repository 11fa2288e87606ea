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

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Protocol

import cv2
import numpy as np
from numba import njit

from pwlreg.core.imaging import file_bands
from pwlreg.core.kernels import _load_triangle, _row_range, row_span
from pwlreg.core.raster import affine_maps
from pwlreg.core.warp import outer_edge_flags

LEVEL_PIXELS = 1 << 24
"""Largest image registered at full resolution (16.8 MP: about 250 MB of work memory); larger
ones are registered on a reduced level (:mod:`pwlreg.core.scaled`) and their files, when TIFFs,
read window by window."""
TILE = 1024
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
        return self._bands[y0:y1, x0:x1], valid

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


@njit(cache=True)
def _tile_maps(ref_tris, maps, closed, x0, y0, mw, mh, map_x, map_y):  # type: ignore[no-untyped-def]
    """Fill ``map_x``/``map_y`` (float32, the tile's shape) with each owned pixel's position in
    the moving image relative to the window it needs; -1 where the pixel is outside the mesh
    or maps outside the moving image. ``ref_tris`` are shifted by ``(-x0, -y0)``.

    Returns the window ``(sx0, sy0, sx1, sy1)`` (end exclusive; empty when nothing maps).
    Along a row of a triangle the map is affine, so the window comes from the runs' ends.
    """
    height, width = map_x.shape
    q = np.empty((3, 2), dtype=np.int64)
    lo_x, lo_y, hi_x, hi_y = np.inf, np.inf, -np.inf, -np.inf
    n_tri = ref_tris.shape[0]
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
            for y in range(r0, r1 + 1):
                lo, hi = row_span(q, y, width, mask)
                if lo > hi:
                    continue
                gy = y + y0
                for gx in (lo + x0, hi + x0):
                    mx = min(max(maps[t, 0, 0] * gx + maps[t, 0, 1] * gy + maps[t, 0, 2], 0.0),
                             mw - 1.0)
                    my = min(max(maps[t, 1, 0] * gx + maps[t, 1, 1] * gy + maps[t, 1, 2], 0.0),
                             mh - 1.0)
                    lo_x = min(lo_x, mx)
                    hi_x = max(hi_x, mx)
                    lo_y = min(lo_y, my)
                    hi_y = max(hi_y, my)
    if lo_x > hi_x:
        return 0, 0, 0, 0
    sx0 = int(lo_x)
    sy0 = int(lo_y)
    sx1 = min(int(hi_x) + 2, mw)
    sy1 = min(int(hi_y) + 2, mh)
    owned = np.zeros((height, width), dtype=np.uint8)
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
            ax, bx = maps[t, 0, 0], maps[t, 0, 1]
            ay, by = maps[t, 1, 0], maps[t, 1, 1]
            for y in range(r0, r1 + 1):
                lo, hi = row_span(q, y, width, mask)
                gy = y + y0
                cx = bx * gy + maps[t, 0, 2]
                cy = by * gy + maps[t, 1, 2]
                for x in range(lo, hi + 1):
                    if owned[y, x]:
                        continue
                    owned[y, x] = 1
                    gx = x + x0
                    mx = ax * gx + cx
                    my = ay * gx + cy
                    if mx >= 0.0 and my >= 0.0 and mx <= mw - 1 and my <= mh - 1:
                        map_x[y, x] = mx - sx0
                        map_y[y, x] = my - sy0
    return sx0, sy0, sx1, sy1


def warp_tiles(
    source: BandSource,
    reference_vertices: np.ndarray,
    moving_vertices: np.ndarray,
    triangles: np.ndarray,
    shape: tuple[int, int],
    *,
    tile: int = TILE,
    nodata: float = 0,
) -> Iterator[Tile]:
    """The registered image as tiles, row of tiles by row of tiles, left to right.

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
    lo, hi = ref_tris.min(axis=1), ref_tris.max(axis=1)  # (T, 2) bounding boxes
    for y0 in range(0, height, tile):
        rows = min(tile, height - y0)
        in_rows = (hi[:, 1] >= y0 - 1) & (lo[:, 1] <= y0 + rows)
        for x0 in range(0, width, tile):
            cols = min(tile, width - x0)
            near = in_rows & (hi[:, 0] >= x0 - 1) & (lo[:, 0] <= x0 + cols)
            yield _one_tile(source, ref_tris[near], maps[near], closed[near], x0, y0,
                            rows, cols, nodata)


def _one_tile(source: BandSource, ref_tris: np.ndarray, maps: np.ndarray, closed: np.ndarray,
              x0: int, y0: int, rows: int, cols: int, nodata: float) -> Tile:
    out = np.full((rows, cols, source.count), nodata, dtype=source.dtype)
    inside = np.zeros((rows, cols), bool)
    if not len(ref_tris):
        return Tile(x0, y0, out, inside)
    map_x = np.full((rows, cols), -1.0, np.float32)
    map_y = np.zeros((rows, cols), np.float32)
    shifted = np.ascontiguousarray(ref_tris - np.array([x0, y0], np.float64))
    sx0, sy0, sx1, sy1 = _tile_maps(shifted, maps, closed, x0, y0, source.width,
                                    source.height, map_x, map_y)
    if sx1 <= sx0 or sy1 <= sy0:
        return Tile(x0, y0, out, inside)
    inside = map_x >= 0
    part, valid = source.read(sx0, sy0, sx1, sy1)
    if valid is not None:
        if part.dtype.kind == "f":  # a NaN weighted 0 still makes NaN: only finite samples
            part = np.where(valid[:, :, None], part, 0)
        ok = cv2.remap(valid.astype(np.uint8) * np.uint8(255), map_x, map_y, cv2.INTER_LINEAR,
                       borderMode=cv2.BORDER_REPLICATE)
        inside &= ok == 255
    exact = part.dtype in _REMAP_DTYPES
    for c0 in range(0, source.count, 4):  # remap takes up to 4 channels at once
        chunk = np.ascontiguousarray(part[:, :, c0:c0 + 4])
        warped = cv2.remap(chunk if exact else chunk.astype(np.float64), map_x, map_y,
                           cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        warped = warped.reshape(rows, cols, -1)
        if not exact:
            info = np.iinfo(source.dtype)
            warped = np.clip(np.round(warped), info.min, info.max)
        np.copyto(out[:, :, c0:c0 + 4], warped, where=inside[:, :, None], casting="unsafe")
    return Tile(x0, y0, out, inside)
