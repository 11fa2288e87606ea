"""I/O of :mod:`core`: decoding images with limits, points files, result documents (the list of
result files is :mod:`pwlreg.core.results`).

Coordinates everywhere: pixels, x right, y down, (0, 0) the centre of the top-left pixel.
"""

from __future__ import annotations

import csv
import io
import json
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np
from PIL import Image, UnidentifiedImageError

from pwlreg.core.errors import ImageTooLargeError, InputError, UnsupportedMediaError
from pwlreg.core.formats.geotiff import is_tiff, probe_tiff, read_tiff
from pwlreg.core.formats.png import write_image
from pwlreg.core.formats.points import is_gis_points, read_gis_points
from pwlreg.core.imaging import check_image
from pwlreg.core.moves import move_counts

if TYPE_CHECKING:
    from pwlreg.core.pipeline import RegistrationResult

# Pillow only parses headers here; the pixel limit is ours.
Image.MAX_IMAGE_PIXELS = None
_DECODER_MAX_PIXELS = 2**30
"""OpenCV refuses to decode more pixels than this whatever the caller allows."""
MAX_BANDS_AT_LIMIT = 16
"""A raster may hold at most this many times ``max_pixels`` samples (all bands): 16 bands at
the pixel limit, more bands on smaller rasters."""
_FORMATS = ("PNG", "JPEG", "PPM", "BMP")
"""Pillow's names of the formats it checks (its JPEG reader also opens the multi-picture JPEGs
of many cameras); TIFFs are GDAL's (:mod:`core.formats.geotiff`)."""


def probe_image(
    source: bytes | str | os.PathLike, max_pixels: int | None = None, field: str = "image"
) -> tuple[int, int]:
    """Check an image file without decoding its pixels; returns its ``(width, height)``.

    Reads the header (kind and size, checked against ``max_pixels``, so decompression bombs
    are refused cheaply) and the file's structure where the format allows it without decoding
    (PNG: every chunk's CRC and the end chunk; TIFF: that every strip or tile lies inside the
    file; both find truncated files).

    Parameters
    ----------
    source : bytes or path
        Encoded PNG, JPEG, TIFF (GeoTIFF: 1-N bands of 8/16/32-bit integers or 32/64-bit
        floats), PNM (PPM/PGM) or BMP.
    max_pixels : int, optional
        Largest accepted ``width * height``; at most 2**30, OpenCV's own limit.
    field : str
        Name used in error messages.

    Raises
    ------
    UnsupportedMediaError
        Empty, not an image of a supported kind, or structurally broken.
    InputError
        Samples of a type the registration cannot use, or less than 2 pixels wide or high.
    ImageTooLargeError
        Over ``max_pixels``.
    """
    head = _head(source)
    if not head:
        raise UnsupportedMediaError(f"{field} is empty", field)
    bands = 1
    if is_tiff(head):
        width, height, bands = probe_tiff(source, field)
    else:
        data = source if isinstance(source, bytes) else Path(source).read_bytes()
        try:
            with Image.open(io.BytesIO(data), formats=_FORMATS) as header:
                width, height = header.size
                header.verify()
        except (UnidentifiedImageError, OSError, ValueError, SyntaxError, EOFError) as exc:
            raise UnsupportedMediaError(
                f"{field} is not a supported image (PNG, JPEG, TIFF, PPM/PGM or BMP), or it is "
                "truncated or damaged",
                field,
            ) from exc
    if min(width, height) < 2:
        raise InputError(f"{field} is too small: {width}x{height} pixels", field)
    max_pixels = min(max_pixels or _DECODER_MAX_PIXELS, _DECODER_MAX_PIXELS)
    if width * height > max_pixels:
        raise ImageTooLargeError(
            f"{field} has {width}x{height} = {width * height} pixels, more than the limit of "
            f"{max_pixels}",
            field,
        )
    if width * height * bands > MAX_BANDS_AT_LIMIT * max_pixels:
        raise ImageTooLargeError(
            f"{field} has {bands} bands of {width}x{height} pixels: more samples than "
            f"{MAX_BANDS_AT_LIMIT} bands at the pixel limit of {max_pixels}",
            field,
        )
    return width, height


def _head(source: bytes | str | os.PathLike) -> bytes:
    if isinstance(source, bytes):
        return source[:8]
    with open(source, "rb") as handle:
        return handle.read(8)


def read_image(
    source: bytes | str | os.PathLike, max_pixels: int | None = None, field: str = "image"
) -> np.ndarray:
    """Decode an image file, after :func:`probe_image`'s checks.

    Parameters
    ----------
    source : bytes or path
        Encoded PNG, JPEG, TIFF, PNM (PPM/PGM) or BMP.
    max_pixels : int, optional
        Largest accepted ``width * height``.
    field : str
        Name used in error messages.

    Returns
    -------
    ndarray or numpy.ma.MaskedArray
        A picture, ``(H, W)`` grey or ``(H, W, 3|4)`` BGR(A), uint8 or uint16, or, for a TIFF
        of other sample types or bands or with invalid pixels, a raster: a masked array with
        the bands in file order (:mod:`core.imaging`, :func:`core.formats.geotiff.read_tiff`).

    Raises
    ------
    UnsupportedMediaError
        Not a decodable image of a supported kind.
    ImageTooLargeError
        Over ``max_pixels``.
    """
    if is_tiff(_head(source)):
        probe_image(source, max_pixels, field)
        return read_tiff(source, field)
    data = source if isinstance(source, bytes) else Path(source).read_bytes()
    probe_image(data, max_pixels, field)
    try:
        image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error as exc:
        raise UnsupportedMediaError(f"{field} could not be decoded: {exc.err}", field) from exc
    if image is None:
        raise UnsupportedMediaError(f"{field} could not be decoded (corrupt or truncated?)", field)
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    check_image(image, field)
    return image


def load_json(text: str | bytes, field: str) -> Any:
    """``json.loads`` of a client's document; :class:`InputError` naming ``field`` when it is
    not JSON or nests deeper than the decoder's recursion allows (about a thousand levels)."""
    try:
        return json.loads(text)
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"{field} is not valid JSON: {exc}", field) from None
    except RecursionError:
        raise InputError(f"{field} is JSON nested too deeply", field) from None


def load_points(
    data: bytes | str,
    field: str = "points",
    *,
    reference: bytes | str | os.PathLike | None = None,
    moving: bytes | str | os.PathLike | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Parse a points file: JSON ``{"reference": [[x, y], ...], "moving": [[x, y], ...]}``, CSV
    with the header ``x,y,x_moving,y_moving``, a QGIS Georeferencer ``.points`` file or a
    GeoTIFF whose GCPs are the moving image's (the format is sniffed).

    Parameters
    ----------
    data : bytes or str
    field : str
        Name used in error messages.
    reference, moving : bytes or path, optional
        The image files, needed by the GIS formats (:mod:`core.formats.points`): their map
        coordinates are placed in the reference through its georeferencing.

    Returns
    -------
    reference, moving : ndarray of float64, shape (N, 2)
        Pixels, x right, y down, (0, 0) the centre of the top-left pixel.
    """
    if data and is_gis_points(data):
        return read_gis_points(data, field, reference=reference, moving=moving)
    text = data.decode("utf-8-sig", errors="replace") if isinstance(data, bytes) else data
    text = text.lstrip("\ufeff").strip()
    if not text:
        raise InputError(f"{field} is empty", field)
    if text[0] in "{[":
        doc = load_json(text, field)
        if not isinstance(doc, dict) or "reference" not in doc or "moving" not in doc:
            raise InputError(
                f'{field} JSON must be an object with "reference" and "moving" lists of [x, y]',
                field,
            )
        ref = _as_points(doc["reference"], f"{field}.reference")
        mov = _as_points(doc["moving"], f"{field}.moving")
    else:
        try:
            rows = list(csv.reader(io.StringIO(text, newline="")))
        except csv.Error as exc:
            raise InputError(f"{field} is neither JSON nor readable CSV: {exc}", field) from exc
        header = [h.strip().lower() for h in rows[0]]
        wanted = ["x", "y", "x_moving", "y_moving"]
        if any(h not in header for h in wanted):
            raise InputError(
                f"{field} CSV must have the header x,y,x_moving,y_moving (got {','.join(header)})",
                field,
            )
        cols = [header.index(h) for h in wanted]
        try:
            values = np.array(
                [[float(r[c]) for c in cols] for r in rows[1:] if any(v.strip() for v in r)],
                dtype=np.float64,
            ).reshape(-1, 4)
        except (ValueError, IndexError) as exc:
            raise InputError(
                f"{field} CSV has a row that is not four numbers: {exc}", field
            ) from exc
        ref, mov = values[:, :2], values[:, 2:]
    if len(ref) != len(mov):
        raise InputError(
            f"{field}: {len(ref)} reference points but {len(mov)} moving points", field
        )
    if not (np.isfinite(ref).all() and np.isfinite(mov).all()):
        raise InputError(f"{field} contains non-finite coordinates", field)
    return ref, mov


def _as_points(value: object, field: str) -> np.ndarray:
    # Types are checked on an object array: numpy alone would turn "1" or true into numbers.
    if not isinstance(value, list):
        raise InputError(f"{field} must be a list of [x, y] numbers", field)
    if not value:
        return np.zeros((0, 2), np.float64)
    try:
        cells = np.array(value, dtype=object)
    except ValueError as exc:  # ragged beyond what an object array holds
        raise InputError(f"{field} must be a list of [x, y] pairs", field) from exc
    if cells.ndim != 2:
        raise InputError(f"{field} must be a list of [x, y] pairs", field)
    if not set(map(type, cells.ravel())) <= {int, float}:
        raise InputError(f"{field} must be a list of [x, y] numbers", field)
    if cells.shape[1] != 2:
        raise InputError(f"{field} must be a list of [x, y] pairs", field)
    try:
        return cells.astype(np.float64)
    except OverflowError as exc:
        raise InputError(f"{field} must be a list of [x, y] numbers", field) from exc


def _corrections(result: RegistrationResult) -> list[dict] | None:
    """The vertex moves' records of a result (None when the move did not run)."""
    return None if result.corrections is None else result.corrections.to_list()


def mesh_document(result: RegistrationResult) -> dict:
    """The ``mesh.json`` document (file contract) of a result."""
    moved = _corrections(result)
    return {
        "reference_vertices": result.reference_vertices.tolist(),
        "moving_vertices": result.moving_vertices.tolist(),
        "initial_triangles": result.initial_triangles.tolist(),
        "final_triangles": result.final_triangles.tolist(),
        "swaps": [
            {"removed": list(s.removed), "added": list(s.added), "delta": s.delta,
             "move": s.move}
            for s in result.search.steps
        ],
        "extrapolated": result.extrapolated.tolist(),
        "inserted": result.inserted.tolist(),
        "vertex_origins": result.origins,
        "insertion": result.insertion,
        "corrections": moved,
        "moves": move_counts(result.origins, result.search.steps, moved=moved),
        "quality": result.quality.to_dict(),
        "triangle_scores": [
            None if not np.isfinite(v) else round(float(v), 4)
            for v in result.quality.triangle_scores
        ],
        "parameters": result.options.model_dump(),
        "triangulation": result.triangulation.to_dict(),
        "matching": result.points.to_dict() if result.points is not None else None,
        "image_size": {
            "reference": list(result.reference_size),
            "moving": list(result.moving_size),
        },
        # Registered on reduced levels (core/scaled.py): their factors and the refinement.
        "levels": {
            "factors": [int(result.scales[0, 0]), int(result.scales[1, 0])],
            "refined": result.refined,
        } if getattr(result, "scales", None) is not None else None,
        "timings_s": result.timings,
    }


def convergence_document(result: RegistrationResult) -> dict:
    """The ``convergence.json`` document (file contract) of a result."""
    s = result.search
    moved = _corrections(result)
    return {
        "cost": result.options.cost,
        "optimizer": result.options.optimizer,
        "initial": {"mi": s.initial_mi, "nmi": s.initial_nmi},
        "iterations": [
            {
                "iteration": st.iteration,
                "removed": list(st.removed),
                "added": list(st.added),
                "delta": st.delta,
                "move": st.move,
                "mi": st.mi,
                "nmi": st.nmi,
                "elapsed_s": st.elapsed_s,
            }
            for st in s.steps
        ],
        "corrections": moved,
        "final": {"mi": s.final_mi, "nmi": s.final_nmi},
        "moves": move_counts(result.origins, s.steps, moved=moved),
        "stopped_because": s.stopped_because,
        "evaluations": s.evaluations,
    }


def encode_png(image: np.ndarray, threads: int = 1, level: int = 1) -> bytes:
    """PNG bytes of an OpenCV-layout image: grey, grey+alpha, BGR or BGRA, 8 or 16 bit.

    Written by :func:`pwlreg.core.formats.png.write_image`: every row uses the PNG "Up"
    filter and the deflate stream is compressed in pieces on ``threads`` threads (pigz's
    method). On the smooth images this service writes it takes about half the time of
    ``cv2.imencode`` for a third of the size, and OpenCV cannot write grey+alpha at all.

    Parameters
    ----------
    image : ndarray
        ``(H, W)`` or ``(H, W, 1|2|3|4)``, uint8 or uint16, channels in OpenCV order.
    threads : int
        Threads compressing pieces at the same time (zlib releases the GIL).
    level : int
        zlib level, 1 (fastest) to 9.
    """
    out = io.BytesIO()
    write_image(out, image, threads=threads, level=level)
    return out.getvalue()
