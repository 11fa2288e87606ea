"""PNG written strip by strip, for registered images too large to hold whole.

The rows use the "Up" filter (each byte minus the one above it), and each strip's deflate
stream is cut into pieces compressed on several threads (pigz's method: every piece ends on a
sync flush, so that their concatenation is one valid stream; the last is closed when the file
is). Memory: one strip and its compressed bytes.
"""

from __future__ import annotations

import zlib
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, BinaryIO

import numpy as np

from pwlreg.core.formats.geotiff import moving_source
from pwlreg.core.imaging import PICTURE_BAND, PictureRecipe, apply_recipe, matching_image
from pwlreg.core.tiled import warp_tiles

if TYPE_CHECKING:
    from pwlreg.core.pipeline import RegistrationResult
    from pwlreg.core.results import Sources

COLOUR_TYPES = {1: 0, 2: 4, 3: 2, 4: 6}
"""PNG colour type by channel count: grey, grey+alpha, RGB, RGBA."""
_PIECE_BYTES = 8 << 20
"""Bytes of filtered rows compressed as one piece."""
_BLOCK_BYTES = 4 << 20
"""Bytes of rows filtered by one numpy call (cache-sized)."""
_STRIP_BYTES = 16 << 20
"""Bytes of an image in memory written per strip (:func:`write_image`)."""


def _chunk(kind: bytes, data: bytes) -> bytes:
    return b"".join((len(data).to_bytes(4, "big"), kind, data,
                     zlib.crc32(data, zlib.crc32(kind)).to_bytes(4, "big")))


class PngWriter:
    """Write a PNG strip by strip.

    Parameters
    ----------
    file : binary file
        Open for writing.
    width, height : int
    channels : int
        1 (grey), 2 (grey+alpha), 3 (BGR) or 4 (BGRA): OpenCV's order, written as PNG's.
    dtype : dtype
        uint8 or uint16.
    threads : int
        Threads compressing pieces of a strip at the same time (zlib releases the GIL).
    level : int
        zlib level, 1 (fastest) to 9.

    Examples
    --------
    >>> import io
    >>> out = io.BytesIO()
    >>> with PngWriter(out, 4, 2, 1, np.uint8) as png:
    ...     png.write(np.zeros((2, 4), np.uint8))
    >>> out.getvalue()[:8]
    b'\\x89PNG\\r\\n\\x1a\\n'
    """

    def __init__(self, file: BinaryIO, width: int, height: int, channels: int,
                 dtype: np.dtype | type, *, threads: int = 1, level: int = 1) -> None:
        dtype = np.dtype(dtype)
        if channels not in COLOUR_TYPES or dtype not in (np.uint8, np.uint16):
            raise ValueError(f"cannot write {channels} channels of {dtype} as PNG")
        if width < 1 or height < 1:
            raise ValueError(f"cannot write an empty PNG ({width}x{height})")
        self.file, self.width, self.height = file, width, height
        self.channels, self.dtype, self.level = channels, dtype, level
        self.threads = max(1, int(threads))
        self._rows = 0
        self._previous: np.ndarray | None = None  # the last raw row written
        self._adler = 1
        self._started = False
        self._pool: ThreadPoolExecutor | None = None
        header = b"".join((width.to_bytes(4, "big"), height.to_bytes(4, "big"),
                           bytes((8 * dtype.itemsize, COLOUR_TYPES[channels], 0, 0, 0))))
        file.write(b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", header))

    def __enter__(self) -> PngWriter:
        return self

    def __exit__(self, kind: type[BaseException] | None, value: BaseException | None,
                 trace: TracebackType | None) -> None:
        if kind is None:
            self.close()
        elif self._pool is not None:
            self._pool.shutdown()

    def write(self, strip: np.ndarray) -> None:
        """Append the rows of ``strip`` ``(rows, width[, channels])`` (OpenCV order)."""
        if strip.ndim == 2:
            strip = strip[:, :, None]
        rows = strip.shape[0]
        if strip.shape[1:] != (self.width, self.channels) or strip.dtype != self.dtype:
            raise ValueError(f"a strip of shape {strip.shape} and {strip.dtype} does not fit a "
                             f"{self.width}-pixel {self.channels}-channel {self.dtype} PNG")
        if self._rows + rows > self.height:
            raise ValueError(f"more than the {self.height} rows of the PNG")
        filtered = np.empty((rows, 1 + self.width * self.channels * self.dtype.itemsize),
                            np.uint8)
        filtered[:, 0] = 2  # Up: each byte minus the byte above it, modulo 256
        raw = filtered[:, 1:]
        samples = raw.view(self.dtype.newbyteorder(">")).reshape(rows, self.width, self.channels)
        order = [2, 1, 0, 3][:self.channels] if self.channels >= 3 else range(self.channels)
        for i, channel in enumerate(order):  # BGR(A) -> RGB(A)
            samples[:, :, i] = strip[:, :, channel]
        last = raw[-1].copy()
        block = max(1, _BLOCK_BYTES // filtered.shape[1])
        for stop in range(rows, 1, -block):  # bottom up: each row still sees the raw row above
            start = max(1, stop - block)
            np.subtract(raw[start:stop], raw[start - 1:stop - 1], out=raw[start:stop])
        if self._previous is not None:
            np.subtract(raw[0], self._previous, out=raw[0])
        self._previous = last
        self._rows += rows
        self._deflate(memoryview(filtered).cast("B"))

    def _deflate(self, data: memoryview) -> None:
        self._adler = zlib.adler32(data, self._adler)
        # Pieces of at least 256 KB (smaller ones compress worse), on every thread.
        wanted = max(self.threads, -(-data.nbytes // _PIECE_BYTES))
        pieces = max(1, min(wanted, data.nbytes // (256 << 10)))
        bounds = np.linspace(0, data.nbytes, pieces + 1).astype(np.int64)

        def deflate(i: int) -> bytes:
            compressor = zlib.compressobj(self.level, zlib.DEFLATED, -15)
            body = compressor.compress(data[bounds[i]:bounds[i + 1]])
            return body + compressor.flush(zlib.Z_SYNC_FLUSH)

        if pieces == 1 or self.threads == 1:
            parts = [deflate(i) for i in range(pieces)]
        else:
            if self._pool is None:
                self._pool = ThreadPoolExecutor(self.threads)
            parts = list(self._pool.map(deflate, range(pieces)))
        body = b"".join(parts)
        if not self._started:
            body = b"\x78\x01" + body  # the zlib stream's header
            self._started = True
        self.file.write(_chunk(b"IDAT", body))

    def close(self) -> None:
        """End the stream (a final empty block and the checksum) and the file."""
        if self._pool is not None:
            self._pool.shutdown()
        if self._rows != self.height:
            raise ValueError(f"{self._rows} of the PNG's {self.height} rows were written")
        end = zlib.compressobj(self.level, zlib.DEFLATED, -15).flush(zlib.Z_FINISH)
        self.file.write(_chunk(b"IDAT", end + self._adler.to_bytes(4, "big"))
                        + _chunk(b"IEND", b""))


def write_image(file: BinaryIO, image: np.ndarray, *, threads: int = 1, level: int = 1) -> None:
    """Write an OpenCV-layout image (grey, grey+alpha, BGR or BGRA; uint8 or uint16) as PNG,
    a strip of about 16 MB at a time (the memory of a strip beside the image)."""
    if image.ndim == 2:
        image = image[:, :, None]
    if image.ndim != 3 or 0 in image.shape:
        raise ValueError(f"cannot write an image of shape {image.shape} as PNG")
    height, width, channels = image.shape
    with PngWriter(file, width, height, channels, image.dtype, threads=threads,
                   level=level) as png:
        rows = max(1, _STRIP_BYTES // (width * channels * image.dtype.itemsize))
        for start in range(0, height, rows):
            png.write(image[start:start + rows])


def write_registered(result: RegistrationResult, sources: Sources, path: Path) -> None:
    """Write ``registered.png``: the moving image's picture (as matching uses it: the picture
    itself, or the 8-bit band or luminance of a raster, :func:`pwlreg.core.imaging.matching_image`)
    registered onto the reference, with alpha 0 outside the mesh (grey+alpha or BGRA).

    A result at full resolution is encoded at once; a result whose search ran on levels
    (:class:`pwlreg.core.scaled.ScaledResult`) is resampled from the full-resolution moving
    image tile by tile (:func:`pwlreg.core.tiled.warp_tiles`) and written a strip of tiles at
    a time, so that the memory is a strip whatever the size.
    """
    width, height = result.reference_size
    if result.registered.shape[:2] == (height, width):
        with path.open("wb") as file:
            write_image(file, result.registered, threads=sources.threads)
        return
    with moving_source(result, sources) as source, path.open("wb") as file:
        picture = _tile_picture(source.count, getattr(result, "moving_recipe", None),
                                result.options.band)
        tiles = warp_tiles(source, result.reference_vertices, result.moving_vertices,
                           result.final_triangles, (height, width), threads=sources.threads)
        writer = None
        strip: list[np.ndarray] = []
        for tile in tiles:
            grey = picture(tile.bands)
            alpha = tile.inside.astype(grey.dtype) * np.iinfo(grey.dtype).max
            strip.append(np.dstack([grey, alpha]))
            if tile.x0 + tile.bands.shape[1] < width:
                continue
            rows = np.concatenate(strip, axis=1)
            strip = []
            if writer is None:
                writer = PngWriter(file, width, height, rows.shape[2], rows.dtype,
                                   threads=sources.threads)
            writer.write(rows)
        if writer is not None:
            writer.close()


def _tile_picture(count: int, recipe: PictureRecipe | None, band: str
                  ) -> Callable[[np.ndarray], np.ndarray]:
    """The function turning a tile's ``count`` bands (file order) into the moving image's
    matching picture: a picture's channels in OpenCV's order (colour without its alpha, or the
    chosen band), or a raster's ``recipe``."""
    if recipe is not None:
        return lambda bands: apply_recipe(recipe, bands, None)
    order = list(np.argsort(PICTURE_BAND[count])[:3])

    def picture(bands: np.ndarray) -> np.ndarray:
        image = np.ascontiguousarray(bands[:, :, order])
        return matching_image(image[:, :, 0] if count == 1 else image, band)

    return picture
