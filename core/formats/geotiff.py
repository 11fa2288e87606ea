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

import numpy as np
import rasterio
from rasterio.crs import CRS
from rasterio.enums import ColorInterp, Resampling
from rasterio.errors import NotGeoreferencedWarning, RasterioError
from rasterio.io import MemoryFile
from rasterio.transform import Affine
from rasterio.windows import Window

from pwlreg.core.errors import InputError, UnsupportedMediaError
from pwlreg.core.imaging import RASTER_DTYPES, is_picture
from pwlreg.core.tiled import LEVEL_PIXELS, ArrayBands, BandSource, reduce_area, warp_tiles

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
_COLOUR = (ColorInterp.red, ColorInterp.green, ColorInterp.blue)
CACHE_BYTES = 64 * 1024 * 1024
_LEVEL_WINDOW = 2048
"""Side (pixels) of the windows :meth:`RasterFile.level` reads."""
"""GDAL's block cache while a :class:`RasterFile` is open (its default grows with the RAM)."""


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
            layout = _Layout.of(ds)
            data = np.moveaxis(ds.read(layout.indexes), 0, -1)
            invalid = ds.dataset_mask() == 0 if layout.masked else None
        except RasterioError as exc:
            raise UnsupportedMediaError(
                f"{field} could not be decoded (damaged pixel data?): {exc}", field
            ) from exc
    return layout.image(data, invalid)


@dataclass(frozen=True)
class _Layout:
    """Which bands of a TIFF are data (an alpha band is not: its meaning is in the mask), and
    how they become a picture or a raster (:func:`read_tiff`)."""

    indexes: list[int]
    colour: bool
    masked: bool

    @classmethod
    def of(cls, ds: rasterio.DatasetReader) -> _Layout:
        interp = list(ds.colorinterp)
        alpha = [i for i, c in enumerate(interp) if c == ColorInterp.alpha]
        if len(alpha) == len(interp):
            alpha = []
        kept = [c for i, c in enumerate(interp) if i not in alpha]
        return cls(
            indexes=[i + 1 for i in range(ds.count) if i not in alpha],
            colour=tuple(kept) == _COLOUR,
            masked=any({f.name for f in flags} != {"all_valid"} for flags in ds.mask_flag_enums),
        )

    def image(self, data: np.ndarray, invalid: np.ndarray | None) -> np.ndarray:
        """The picture or raster of ``data`` ``(H, W, C)`` (these bands, file order)."""
        if data.dtype.kind == "f":
            nan = ~np.isfinite(data).all(axis=2)
            invalid = nan if invalid is None else invalid | nan
        if invalid is not None and not invalid.any():
            invalid = None
        bands = data.shape[2]
        if data.dtype in (np.uint8, np.uint16) and invalid is None and (bands == 1 or self.colour):
            return data[:, :, 0] if bands == 1 else np.ascontiguousarray(data[:, :, ::-1])
        if invalid is None:
            return np.ma.MaskedArray(data[:, :, 0] if bands == 1 else data, mask=np.ma.nomask)
        if bands == 1:
            return np.ma.MaskedArray(data[:, :, 0], mask=invalid)
        return np.ma.MaskedArray(data, mask=np.repeat(invalid[:, :, None], bands, axis=2))


class RasterFile:
    """A TIFF file read window by window (a :class:`pwlreg.core.tiled.BandSource`), for rasters
    too large to decode at once.

    Its bands and validity are those :func:`read_tiff` gives (alpha band dropped, GDAL's mask,
    NaN); :meth:`level` reads it reduced, averaging, in :func:`read_tiff`'s layout. GDAL's block
    cache is bounded (:data:`CACHE_BYTES`), so the memory does not grow with the file. A
    palette TIFF has no window reader: :func:`pwlreg.core.io.open_image` decodes those whole.

    Parameters
    ----------
    path : path
        A TIFF already checked by :func:`probe_tiff`.
    field : str
        Name used in error messages.
    threads : int
        Threads GDAL may use to decode the blocks of one read.
    """

    def __init__(self, path: str | os.PathLike, field: str = "image", *, threads: int = 1
                 ) -> None:
        self.path, self.field = Path(path), field
        self._stack = contextlib.ExitStack()
        self._stack.enter_context(rasterio.Env(GDAL_CACHEMAX=CACHE_BYTES,
                                               GDAL_NUM_THREADS=str(max(1, threads))))
        self._ds = self._stack.enter_context(open_tiff(self.path, field))
        self._layout = _Layout.of(self._ds)
        self.height, self.width = self._ds.height, self._ds.width
        self.count = len(self._layout.indexes)
        self.dtype = np.dtype(self._ds.dtypes[0])

    def __enter__(self) -> RasterFile:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Close the file."""
        self._stack.close()

    def read(self, x0: int, y0: int, x1: int, y1: int) -> tuple[np.ndarray, np.ndarray | None]:
        """Columns ``x0:x1`` and rows ``y0:y1``: bands ``(h, w, count)`` in file order and
        validity (None when all valid)."""
        window = Window(x0, y0, x1 - x0, y1 - y0)
        try:
            data = np.moveaxis(self._ds.read(self._layout.indexes, window=window), 0, -1)
            valid = self._ds.dataset_mask(window=window) != 0 if self._layout.masked else None
        except RasterioError as exc:
            raise UnsupportedMediaError(
                f"{self.field} could not be decoded (damaged pixel data?): {exc}", self.field
            ) from exc
        if data.dtype.kind == "f":
            finite = np.isfinite(data).all(axis=2)
            valid = finite if valid is None else valid & finite
        return data, (None if valid is None or valid.all() else valid)

    def level(self, factor: int) -> np.ndarray:
        """The file reduced ``factor`` times (:meth:`pwlreg.core.tiled.BandSource.level`: a
        pixel is invalid when less than half of its block is valid), as :func:`read_tiff` would
        give it. Read in windows of about 2048 pixels, each decoded once."""
        h, w = self.height // factor, self.width // factor
        out = np.empty((h, w, self.count), self.dtype)
        invalid = np.zeros((h, w), bool)
        step = factor * max(1, round(_LEVEL_WINDOW / factor))
        for y0 in range(0, h * factor, step):
            y1 = min(y0 + step, h * factor)
            for x0 in range(0, w * factor, step):
                x1 = min(x0 + step, w * factor)
                data, valid = self.read(x0, y0, x1, y1)
                rows = slice(y0 // factor, y1 // factor)
                cols = slice(x0 // factor, x1 // factor)
                out[rows, cols] = reduce_area(data, factor)
                if valid is not None:
                    invalid[rows, cols] = reduce_area(valid.astype(np.float32), factor) < 0.5
        return self._layout.image(out, invalid)

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
        """(N, 2) map coordinates -> (N, 2) pixel positions (centre convention);
        :class:`InputError` when the geotransform has no inverse (a pixel of zero size)."""
        if self.transform.is_degenerate:
            raise InputError("the reference GeoTIFF's geotransform is degenerate (a pixel of "
                             f"zero size: {tuple(self.transform)[:6]}): map coordinates cannot "
                             "be placed on it", "reference")
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
    pixel are nodata: the moving file's nodata value, else NaN for float samples, else 0.
    Resampling is :func:`pwlreg.core.tiled.warp_tiles` (bilinear, the pixels of registered.png)
    from the full-resolution moving image (:func:`moving_source`: a large TIFF is read window
    by window), one 512-pixel tile at a time, each written and compressed once: the work
    memory is a few tiles whatever the size. Files whose longer side exceeds 1024 pixels get
    overviews (averages, factors 2, 4, ...) down to that size.
    """
    geo = georeference(sources.reference_path)
    if geo is None:
        raise ValueError("registered.tif needs a georeferenced reference file")
    with moving_source(result, sources) as source:
        _write_tiles(result, source, geo, _nodata(sources.moving_path), path,
                     threads=sources.threads, colour=_picture_bands(result, sources))


def _picture_bands(result: RegistrationResult, sources: Sources) -> int:
    """The bands of a colour picture (3 or 4, written as RGB(A)), else 0."""
    if hasattr(result, "moving_recipe"):  # registered on levels: is its level a picture?
        moving = result.moving_level if result.moving_recipe is None else None
    else:
        moving = sources.moving_raster if sources.moving_raster is not None else sources.moving
    if moving is None or not is_picture(moving) or moving.ndim != 3:
        return 0
    return moving.shape[2]


def _write_tiles(result: RegistrationResult, source: BandSource, geo: Georeference,
                 nodata: float | None, path: Path, *, threads: int, colour: int) -> None:
    dtype = np.dtype(source.dtype)
    if nodata is None:
        nodata = float("nan") if dtype.kind == "f" else 0
    height, width = geo.height, geo.width
    profile = {
        "driver": "GTiff", "width": width, "height": height, "count": source.count,
        "dtype": dtype.name, "crs": geo.crs, "transform": geo.transform, "nodata": nodata,
        "tiled": True, "blockxsize": _BLOCK, "blockysize": _BLOCK, "compress": "deflate",
        "predictor": 3 if dtype.kind == "f" else 2, "interleave": "pixel",
        "zlevel": 1, "bigtiff": "if_safer", "num_threads": max(1, threads),
    }
    tiles = warp_tiles(source, result.reference_vertices, result.moving_vertices,
                       result.final_triangles, (height, width), nodata=nodata,
                       threads=threads)
    with rasterio.Env(ZLEVEL_OVERVIEW=1, GDAL_CACHEMAX=CACHE_BYTES), \
            rasterio.open(path, "w", **profile) as dst:
        if colour:
            dst.colorinterp = [*_COLOUR, ColorInterp.alpha][:colour]
        for tile in tiles:
            rows, cols = tile.bands.shape[:2]
            dst.write(np.moveaxis(tile.bands, -1, 0), window=Window(tile.x0, tile.y0, cols, rows))
        factors, factor = [], 1
        while max(width, height) // factor > _OVERVIEW_SIDE:
            factor *= 2
            factors.append(factor)
        if factors:
            dst.build_overviews(factors, Resampling.average)


def moving_source(result: RegistrationResult, sources: Sources
                  ) -> contextlib.AbstractContextManager[BandSource]:
    """The moving image at full resolution, as a :class:`~pwlreg.core.tiled.BandSource`: the
    decoded raster or picture in ``sources`` when it is at full size, or the one a result
    registered on levels kept (``moving_image``), else its file (a TIFF read by windows,
    another format decoded)."""
    width, height = result.moving_size
    for image in (sources.moving_raster, sources.moving, getattr(result, "moving_image", None)):
        if image is not None and image.shape[:2] == (height, width):
            return contextlib.nullcontext(ArrayBands(image))
    path = sources.moving_path
    if path is None:
        raise ValueError("the moving image is not at hand")
    if _starts_as_tiff(path):
        with open_tiff(path, "moving") as ds:
            palette = ds.count == 1 and ds.colorinterp[0] == ColorInterp.palette
        if not palette:
            return RasterFile(path, "moving", threads=sources.threads)
    from pwlreg.core.io import read_image

    return contextlib.nullcontext(ArrayBands(read_image(path, field="moving")))


def _nodata(source: str | os.PathLike | None) -> float | None:
    if source is None or not _starts_as_tiff(source):
        return None
    with open_tiff(source, "moving") as ds:
        return ds.nodata




def read_by_windows(path: str | os.PathLike, level_pixels: int = LEVEL_PIXELS) -> bool:
    """Whether :func:`open_image` reads this file window by window: a TIFF of more than
    ``level_pixels`` pixels (but a palette TIFF, expanded whole)."""
    if not _starts_as_tiff(path):
        return False
    try:
        with open_tiff(path, "image") as ds:
            palette = ds.count == 1 and ds.colorinterp[0] == ColorInterp.palette
            return ds.width * ds.height > level_pixels and not palette
    except UnsupportedMediaError:
        return False  # the probe says why


def open_image(path: str | os.PathLike, *, max_pixels: int | None = None,
               max_raster_pixels: int | None = None, level_pixels: int = LEVEL_PIXELS,
               field: str = "image", threads: int = 1) -> np.ndarray | RasterFile:
    """An image file, decoded, or, for a TIFF of more than ``level_pixels`` pixels, opened
    for reading window by window (:class:`RasterFile`; close it after use).

    Parameters
    ----------
    path : path
    max_pixels : int, optional
        Largest image decoded whole (:func:`pwlreg.core.io.read_image`).
    max_raster_pixels : int, optional
        Largest TIFF read window by window (the work memory does not grow with it; the
        limit keeps a job's time bounded). None: the decoder's limit, 2**30.
    level_pixels : int
        TIFFs up to this size are decoded whole.
    field : str
        Name used in error messages.
    threads : int
        Threads GDAL may use to decode a :class:`RasterFile`'s blocks.

    Raises
    ------
    UnsupportedMediaError, InputError, ImageTooLargeError
        As :func:`pwlreg.core.io.probe_image`.
    """
    from pwlreg.core.io import probe_image, read_image

    if read_by_windows(path, level_pixels):
        probe_image(path, max_raster_pixels, field)
        return RasterFile(path, field, threads=threads)
    return read_image(path, max_pixels, field)
