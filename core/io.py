"""The only I/O of :mod:`core`: decoding images with limits, points files, result documents.

Coordinates everywhere: pixels, x right, y down, (0, 0) the centre of the top-left pixel.
"""

from __future__ import annotations

import csv
import io
import json
import os
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np
from PIL import Image, UnidentifiedImageError

from core.errors import ImageTooLargeError, InputError, UnsupportedMediaError
from core.imaging import check_image

if TYPE_CHECKING:
    from core.pipeline import RegistrationResult

# Header parsing only; the pixel limit is ours.
Image.MAX_IMAGE_PIXELS = None
_DECODER_MAX_PIXELS = 2**30


def read_image(
    source: bytes | str | os.PathLike, max_pixels: int | None = None, field: str = "image"
) -> np.ndarray:
    """Decode an image file into an OpenCV-layout array.

    The size is read from the file header and checked against ``max_pixels`` before any pixel
    is decoded, so decompression bombs are refused cheaply.

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
    ndarray
        ``(H, W)`` grey or ``(H, W, 3|4)`` BGR(A), uint8 or uint16.

    Raises
    ------
    UnsupportedMediaError
        Not a decodable image of a supported kind.
    ImageTooLargeError
        Over ``max_pixels``.
    """
    data = source if isinstance(source, bytes) else Path(source).read_bytes()
    if not data:
        raise UnsupportedMediaError(f"{field} is empty", field)
    try:
        with Image.open(io.BytesIO(data)) as header:
            width, height = header.size
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError) as exc:
        raise UnsupportedMediaError(
            f"{field} is not a supported image (PNG, JPEG, TIFF, PPM/PGM or BMP)", field
        ) from exc
    # OpenCV refuses to decode more than 2**30 pixels whatever the caller allows.
    max_pixels = min(max_pixels or _DECODER_MAX_PIXELS, _DECODER_MAX_PIXELS)
    if width * height > max_pixels:
        raise ImageTooLargeError(
            f"{field} has {width}x{height} = {width * height} pixels, more than the limit of "
            f"{max_pixels}",
            field,
        )
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


def load_points(data: bytes | str, field: str = "points") -> tuple[np.ndarray, np.ndarray]:
    """Parse a points file: JSON ``{"reference": [[x, y], ...], "moving": [[x, y], ...]}`` or
    CSV with the header ``x,y,x_moving,y_moving``.

    Returns
    -------
    reference, moving : ndarray of float64, shape (N, 2)
    """
    text = data.decode("utf-8-sig", errors="replace") if isinstance(data, bytes) else data
    text = text.lstrip("\ufeff").strip()
    if not text:
        raise InputError(f"{field} is empty", field)
    if text[0] in "{[":
        try:
            doc = json.loads(text)
        except json.JSONDecodeError as exc:
            raise InputError(f"{field} is not valid JSON: {exc}", field) from exc
        except RecursionError as exc:
            raise InputError(f"{field} JSON is nested too deeply", field) from exc
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
    if not isinstance(value, list) or not all(
        isinstance(p, list)
        and all(isinstance(v, int | float) and not isinstance(v, bool) for v in p)
        for p in value
    ):
        raise InputError(f"{field} must be a list of [x, y] numbers", field)
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError) as exc:
        raise InputError(f"{field} must be a list of [x, y] numbers", field) from exc
    if arr.size == 0:
        return arr.reshape(0, 2)
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise InputError(f"{field} must be a list of [x, y] pairs", field)
    return arr


def mesh_document(result: RegistrationResult) -> dict:
    """The ``mesh.json`` document (file contract) of a result."""
    return {
        "reference_vertices": result.reference_vertices.tolist(),
        "moving_vertices": result.moving_vertices.tolist(),
        "initial_triangles": result.initial_triangles.tolist(),
        "final_triangles": result.final_triangles.tolist(),
        "swaps": [
            {"removed": list(s.removed), "added": list(s.added), "delta": s.delta}
            for s in result.search.steps
        ],
        "parameters": result.options.model_dump(),
        "triangulation": result.triangulation.to_dict(),
        "matching": result.points.to_dict() if result.points is not None else None,
        "image_size": {
            "reference": list(result.reference_size),
            "moving": list(result.moving_size),
        },
        "timings_s": result.timings,
    }


def convergence_document(result: RegistrationResult) -> dict:
    """The ``convergence.json`` document (file contract) of a result."""
    s = result.search
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
                "mi": st.mi,
                "nmi": st.nmi,
                "elapsed_s": st.elapsed_s,
            }
            for st in s.steps
        ],
        "final": {"mi": s.final_mi, "nmi": s.final_nmi},
        "stopped_because": s.stopped_because,
        "evaluations": s.evaluations,
    }


def encode_png(image: np.ndarray) -> bytes:
    """PNG bytes of an OpenCV-layout image (8 or 16 bit, grey, grey+alpha, BGR or BGRA)."""
    if image.ndim == 3 and image.shape[2] == 2:
        # OpenCV writes no grey+alpha PNG; expand to BGRA.
        image = np.dstack([image[:, :, 0]] * 3 + [image[:, :, 1]])
    ok, buf = cv2.imencode(".png", image)
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return buf.tobytes()


def write_outputs(result: RegistrationResult, out_dir: str | os.PathLike) -> dict[str, Path]:
    """Write ``mesh.json``, ``registered.png`` and ``convergence.json`` into ``out_dir``.

    Returns the paths under the keys ``mesh``, ``registered`` and ``convergence``.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {
        "mesh": out / "mesh.json",
        "registered": out / "registered.png",
        "convergence": out / "convergence.json",
    }
    paths["mesh"].write_text(json.dumps(mesh_document(result)))
    paths["convergence"].write_text(json.dumps(convergence_document(result), indent=1))
    paths["registered"].write_bytes(encode_png(result.registered))
    return paths
