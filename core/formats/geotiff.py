"""TIFF and GeoTIFF through rasterio (GDAL): header checks, decoding, georeferencing, ground
control points, and ``registered.tif``.

Every TIFF is read here (the size limits are applied by :mod:`pwlreg.core.io`, the one place of
decoding limits). Only GDAL's GTiff driver is ever used, so a file cannot make GDAL open another
format (a VRT naming other files, say). Pixel coordinates: x right, y down, (0, 0) the centre of
the top-left pixel; a GDAL geotransform maps the top-left *corner* of pixel (col, row), so a
pixel position ``(x, y)`` here is ``(x + 0.5, y + 0.5)`` for the transform.
"""

from __future__ import annotations

import contextlib
import os
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np
import rasterio
from rasterio.crs import CRS
from rasterio.enums import ColorInterp, Resampling
from rasterio.errors import NotGeoreferencedWarning, RasterioError
from rasterio.io import MemoryFile
from rasterio.transform import Affine
from rasterio.windows import Window

from pwlreg.core.errors import InputError, UnsupportedMediaError
from pwlreg.core.imaging import RASTER_DTYPES, file_bands, is_picture
from pwlreg.core.raster import affine_maps, expand, rasterize

if TYPE_CHECKING:
    from pwlreg.core.pipeline import RegistrationResult
    from pwlreg.core.results import Sources

TIFF_MAGIC = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")
"""Classic and BigTIFF signatures, little and big endian."""
MEDIA_TYPE = "image/tiff; application=geotiff"
"""Media type of ``registered.tif`` (OGC's GeoTIFF media type)."""
_BLOCK = 512
"""Tile side of registered.tif."""
_OVERVIEW_SIDE = 1024
"""registered.tif gets overviews (2, 4, ...) until its longer side is at most this."""
_REMAP_DTYPES = (np.uint8, np.uint16, np.int16, np.float32, np.float64)
"""Sample types OpenCV's remap takes as they are (32-bit integers go through float64)."""
_COLOUR = (ColorInterp.red, ColorInterp.green, ColorInterp.blue)


def is_tiff(head: bytes) -> bool:
    """Whether ``head`` (a file's first bytes) starts like a TIFF or BigTIFF."""
    return head[:4] in TIFF_MAGIC


@contextlib.contextmanager
def open_tiff(source: bytes | str | os.PathLike, field: str) -> Iterator[rasterio.DatasetReader]:
    """Open a TIFF (bytes or path) with the GTiff driver; :class:`UnsupportedMediaError` if
    GDAL cannot read its header."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        try:
            with contextlib.ExitStack() as stack:
                if isinstance(source, bytes):
                    memory = stack.enter_context(MemoryFile(source))
                    dataset = stack.enter_context(memory.open(driver="GTiff"))
                else:
                    dataset = stack.enter_context(rasterio.open(source, driver="GTiff"))
                yield dataset
        except RasterioError as exc:
            raise UnsupportedMediaError(
                f"{field} is not a readable TIFF, or it is truncated or damaged: {exc}", field
            ) from exc


def probe_tiff(source: bytes | str | os.PathLike, field: str) -> tuple[int, int, int]:
    """Check a TIFF without decoding its pixels; returns ``(width, height, bands)``.

    GDAL reads the header; the sample type must be one of
    :data:`core.imaging.RASTER_DTYPES`; every block (strip or tile) of pixel data must lie
    inside the file, which finds truncated files.

    Raises
    ------
    UnsupportedMediaError
        Not a TIFF GDAL reads, or a block beyond the end of the file.
    InputError
        Samples of another type (complex, 64-bit integers, signed bytes...).
    """
    size = len(source) if isinstance(source, bytes) else Path(source).stat().st_size
    with open_tiff(source, field) as ds:
        dtypes = set(ds.dtypes)
        if len(dtypes) != 1 or np.dtype(dtypes.pop()) not in RASTER_DTYPES:
            names = ", ".join(np.dtype(d).name for d in RASTER_DTYPES)
            raise InputError(
                f"{field} has samples of type {', '.join(sorted(set(ds.dtypes)))}; accepted: "
                f"{names} (the same for every band)",
                field,
            )
        _check_blocks(ds, size, field)
        return ds.width, ds.height, ds.count


def _check_blocks(ds: rasterio.DatasetReader, size: int, field: str) -> None:
    interleaved = ds.interleaving is None or ds.interleaving.name != "BAND"
    block_h, block_w = ds.block_shapes[0]
    rows, cols = -(-ds.height // block_h), -(-ds.width // block_w)
    for bidx in (1,) if interleaved else range(1, ds.count + 1):
        for row in range(rows):
            for col in range(cols):
                offset = ds.get_tag_item(f"BLOCK_OFFSET_{col}_{row}", "TIFF", bidx=bidx)
                length = ds.get_tag_item(f"BLOCK_SIZE_{col}_{row}", "TIFF", bidx=bidx)
                if offset is None or length is None:
                    continue  # a sparse block (absent: nodata), or GDAL cannot tell
                if int(offset) + int(length) > size:
                    raise UnsupportedMediaError(
                        f"{field} is truncated or damaged: a block of band {bidx} ends at byte "
                        f"{int(offset) + int(length)} of a {size}-byte file",
                        field,
                    )


def read_tiff(source: bytes | str | os.PathLike, field: str) -> np.ndarray:
    """Decode a TIFF (already probed) into a picture or a raster (:mod:`core.imaging`).

    An 8- or 16-bit unsigned TIFF of one band, or of three whose colour interpretation is RGB,
    with no invalid pixel, is a picture (BGR, as OpenCV's decoder gives it); a palette TIFF is
    expanded to a BGR picture. Anything else is a raster: a masked array with the bands in file
    order, masked where GDAL's mask says invalid (nodata value, mask band, alpha band; an alpha
    band is dropped from the data, its meaning being in the mask) or a sample is NaN.
    """
    with open_tiff(source, field) as ds:
        try:
            if ds.count == 1 and ds.colorinterp[0] == ColorInterp.palette:
                return _palette(ds)
            data = np.moveaxis(ds.read(), 0, -1)
            masked = any(
                {f.name for f in flags} != {"all_valid"} for flags in ds.mask_flag_enums
            )
            invalid = ds.dataset_mask() == 0 if masked else None
        except RasterioError as exc:
            raise UnsupportedMediaError(
                f"{field} could not be decoded (damaged pixel data?): {exc}", field
            ) from exc
        interp = list(ds.colorinterp)
    alpha = [i for i, c in enumerate(interp) if c == ColorInterp.alpha]
    if alpha and len(alpha) < data.shape[2]:
        data = np.delete(data, alpha, axis=2)
        interp = [c for c in interp if c != ColorInterp.alpha]
    if data.dtype.kind == "f":
        nan = ~np.isfinite(data).all(axis=2)
        invalid = nan if invalid is None else invalid | nan
    if invalid is not None and not invalid.any():
        invalid = None
    bands = data.shape[2]
    colour = bands == 3 and tuple(interp) == _COLOUR
    if data.dtype in (np.uint8, np.uint16) and invalid is None and (bands == 1 or colour):
        return data[:, :, 0] if bands == 1 else np.ascontiguousarray(data[:, :, ::-1])
    if invalid is None:
        return np.ma.MaskedArray(data[:, :, 0] if bands == 1 else data, mask=np.ma.nomask)
    if bands == 1:
        return np.ma.MaskedArray(data[:, :, 0], mask=invalid)
    return np.ma.MaskedArray(data, mask=np.repeat(invalid[:, :, None], bands, axis=2))


def _palette(ds: rasterio.DatasetReader) -> np.ndarray:
    colours = ds.colormap(1)
    lut = np.zeros((256, 3), np.uint8)
    for index, rgba in colours.items():
        if 0 <= index < 256:
            lut[index] = rgba[2], rgba[1], rgba[0]
    return lut[ds.read(1)]


# --- georeferencing and ground control points --------------------------------------------------


@dataclass(frozen=True)
class Georeference:
    """Where a raster's pixels are on the ground.

    Attributes
    ----------
    crs : rasterio.crs.CRS
    transform : affine.Affine
        GDAL geotransform: map position of the top-left corner of pixel (col, row).
    width, height : int
    nodata : float or None
        The file's nodata value (first band).
    """

    crs: CRS
    transform: Affine
    width: int
    height: int
    nodata: float | None

    def to_map(self, pixels: np.ndarray) -> np.ndarray:
        """(N, 2) pixel positions (centre convention) -> (N, 2) map coordinates."""
        p = np.asarray(pixels, np.float64).reshape(-1, 2) + 0.5
        t = self.transform
        return np.stack([t.a * p[:, 0] + t.b * p[:, 1] + t.c,
                         t.d * p[:, 0] + t.e * p[:, 1] + t.f], axis=1)

    def to_pixels(self, coords: np.ndarray) -> np.ndarray:
        """(N, 2) map coordinates -> (N, 2) pixel positions (centre convention)."""
        q = np.asarray(coords, np.float64).reshape(-1, 2)
        t = ~self.transform
        return np.stack([t.a * q[:, 0] + t.b * q[:, 1] + t.c - 0.5,
                         t.d * q[:, 0] + t.e * q[:, 1] + t.f - 0.5], axis=1)


def georeference(source: bytes | str | os.PathLike | None) -> Georeference | None:
    """The georeferencing of a GeoTIFF (CRS and geotransform), or None: not a TIFF, no CRS, or
    no geotransform (a TIFF referenced by GCPs alone has none: see :func:`ground_control`)."""
    if source is None or not _starts_as_tiff(source):
        return None
    try:
        with open_tiff(source, "image") as ds:
            if ds.crs is None or ds.transform.is_identity:
                return None
            return Georeference(ds.crs, ds.transform, ds.width, ds.height, ds.nodata)
    except UnsupportedMediaError:
        return None


def ground_control(source: bytes | str | os.PathLike) -> tuple[np.ndarray, np.ndarray, CRS | None]:
    """Ground control points embedded in a TIFF.

    Returns
    -------
    pixels : ndarray, shape (N, 2)
        Positions in the TIFF (x right, y down, (0, 0) the centre of the top-left pixel; GDAL's
        GCP (col, row) counts from the top-left corner).
    coords : ndarray, shape (N, 2)
        Their map coordinates ``(x, y)`` in ``crs``.
    crs : rasterio.crs.CRS or None
    """
    with open_tiff(source, "points") as ds:
        gcps, crs = ds.gcps
    pixels = np.array([[g.col - 0.5, g.row - 0.5] for g in gcps], np.float64).reshape(-1, 2)
    coords = np.array([[g.x, g.y] for g in gcps], np.float64).reshape(-1, 2)
    return pixels, coords, crs


def _starts_as_tiff(source: bytes | str | os.PathLike) -> bool:
    if isinstance(source, bytes):
        return is_tiff(source[:4])
    try:
        with open(source, "rb") as handle:
            return is_tiff(handle.read(4))
    except OSError:
        return False


# --- registered.tif ----------------------------------------------------------------------------


def applies(result: RegistrationResult, sources: Sources) -> bool:
    """registered.tif exists when the reference file is georeferenced (and the moving image is
    at hand)."""
    has_moving = any(s is not None for s in (sources.moving, sources.moving_path))
    return has_moving and georeference(sources.reference_path) is not None


def write_registered(result: RegistrationResult, sources: Sources, path: Path) -> None:
    """Write every band of the moving image, at its data type, resampled into the reference's
    grid through the final mesh, as a tiled (512 x 512), DEFLATE-compressed GeoTIFF with the
    reference's CRS and geotransform; DEFLATE level 1 (the fastest, as for registered.png)
    with a predictor.

    Pixels outside the mesh, mapped outside the moving image, or next to an invalid moving
    pixel are nodata: the moving file's nodata value, else NaN for float samples, else 0 (so
    are pixel centres lying exactly on the mesh's outline, which registered.png gives to their
    triangle in a second pass; with ``extent="frame"`` the outline is the frame's border).
    Resampling is bilinear (OpenCV's ``remap``, rounded for integer samples) through the mesh's
    piecewise-affine maps with the fill rule of :mod:`core.raster`, one tile at a time (each
    tile written and compressed once; the work memory is a few tiles). Files whose longer side
    exceeds 1024 pixels get overviews (averages, factors 2, 4, ...) down to that size.
    """
    geo = georeference(sources.reference_path)
    if geo is None:
        raise ValueError("registered.tif needs a georeferenced reference file")
    moving = sources.moving_raster if sources.moving_raster is not None else sources.moving
    if moving is None:
        from pwlreg.core.io import read_image

        moving = read_image(sources.moving_path, field="moving")
    bands, valid = file_bands(moving)
    dtype = bands.dtype
    nodata = _nodata(sources.moving_path)
    if nodata is None:
        nodata = float("nan") if dtype.kind == "f" else 0
    height, width = geo.height, geo.width
    profile = {
        "driver": "GTiff", "width": width, "height": height, "count": bands.shape[2],
        "dtype": dtype.name, "crs": geo.crs, "transform": geo.transform, "nodata": nodata,
        "tiled": True, "blockxsize": _BLOCK, "blockysize": _BLOCK, "compress": "deflate",
        "predictor": 3 if dtype.kind == "f" else 2, "interleave": "pixel",
        "zlevel": 1, "bigtiff": "if_safer", "num_threads": max(1, sources.threads),
    }
    ref = np.asarray(result.reference_vertices, np.float64)
    tris = np.asarray(result.final_triangles, np.int64).reshape(-1, 3)
    maps = affine_maps(ref[tris], np.asarray(result.moving_vertices, np.float64)[tris])
    valid8 = None if valid is None else valid.astype(np.uint8) * np.uint8(255)
    with rasterio.Env(ZLEVEL_OVERVIEW=1), rasterio.open(path, "w", **profile) as dst:
        if is_picture(moving) and bands.shape[2] in (3, 4):
            dst.colorinterp = [*_COLOUR, ColorInterp.alpha][: bands.shape[2]]
        for y0 in range(0, height, _BLOCK):
            for x0 in range(0, width, _BLOCK):
                window = Window(x0, y0, min(_BLOCK, width - x0), min(_BLOCK, height - y0))
                tile = _warp_tile(bands, valid8, ref[tris], maps, window, nodata)
                dst.write(np.moveaxis(tile, -1, 0), window=window)
        factors, factor = [], 1
        while max(width, height) // factor > _OVERVIEW_SIDE:
            factor *= 2
            factors.append(factor)
        if factors:
            dst.build_overviews(factors, Resampling.average)


def _nodata(source: str | os.PathLike | None) -> float | None:
    if source is None or not _starts_as_tiff(source):
        return None
    with open_tiff(source, "moving") as ds:
        return ds.nodata


def _warp_tile(src: np.ndarray, valid8: np.ndarray | None, ref_tris: np.ndarray,
               maps: np.ndarray, window: Window, nodata: float) -> np.ndarray:
    """One tile of the registered raster, ``(rows, cols, C)``.

    The fill rule of :mod:`core.raster` gives each tile pixel to one triangle (the grid shifted
    by whole pixels owns the same pixels), whose affine map places it in the moving image;
    OpenCV's bilinear ``remap`` (1/32-pixel weights) samples the part of the moving image the
    tile maps onto. A pixel is nodata outside the mesh, where it maps outside the moving image,
    or where one of its four source pixels is invalid.
    """
    rows, cols = int(window.height), int(window.width)
    x0, y0 = int(window.col_off), int(window.row_off)
    out = np.full((rows, cols, src.shape[2]), nodata, dtype=src.dtype)
    spans = rasterize(ref_tris - np.array([x0, y0], np.float64), (rows, cols))
    if not spans.length.sum():
        return out
    _, x, y = expand(spans)
    # Along a run the map is x -> a x + b: coefficients per run, repeated over its pixels.
    m = maps[spans.triangle]
    yy = (spans.y + y0).astype(np.float64)
    n = spans.length
    xf = (x + x0).astype(np.float64)
    mx = np.repeat(m[:, 0, 0], n) * xf + np.repeat(m[:, 0, 1] * yy + m[:, 0, 2], n)
    my = np.repeat(m[:, 1, 0], n) * xf + np.repeat(m[:, 1, 1] * yy + m[:, 1, 2], n)
    mh, mw = src.shape[:2]
    keep = (mx >= 0) & (my >= 0) & (mx <= mw - 1) & (my <= mh - 1)
    if not keep.any():
        return out
    flat, mx, my = (y * cols + x)[keep], mx[keep], my[keep]
    sx0, sy0 = int(mx.min()), int(my.min())
    sx1, sy1 = min(int(mx.max()) + 2, mw), min(int(my.max()) + 2, mh)
    map_x = np.full(rows * cols, -1.0, np.float32)  # -1: not mapped
    map_y = np.zeros(rows * cols, np.float32)
    map_x[flat] = mx - sx0
    map_y[flat] = my - sy0
    map_x, map_y = map_x.reshape(rows, cols), map_y.reshape(rows, cols)
    inside = map_x >= 0
    if valid8 is not None:
        ok = cv2.remap(valid8[sy0:sy1, sx0:sx1], map_x, map_y, cv2.INTER_LINEAR,
                       borderMode=cv2.BORDER_REPLICATE)
        inside &= ok == 255
    part = src[sy0:sy1, sx0:sx1]
    exact = part.dtype in _REMAP_DTYPES
    for c0 in range(0, src.shape[2], 4):  # remap takes up to 4 channels at once
        chunk = np.ascontiguousarray(part[:, :, c0:c0 + 4])
        warped = cv2.remap(chunk if exact else chunk.astype(np.float64), map_x, map_y,
                           cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        warped = warped.reshape(rows, cols, -1)
        if not exact:
            info = np.iinfo(src.dtype)
            warped = np.clip(np.round(warped), info.min, info.max)
        np.copyto(out[:, :, c0:c0 + 4], warped, where=inside[:, :, None], casting="unsafe")
    return out
