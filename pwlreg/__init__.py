"""pwlreg: piecewise-linear image registration with a mesh optimized by mutual information.

The in-process API (the HTTP service in :mod:`pwlreg.service` runs the same function)::

    import pwlreg

    result = pwlreg.register("reference.png", "moving.png", extent="frame")
    print(result.summary(), result.quality.verdict)
    pwlreg.write_outputs(result, "out/")          # mesh.json, registered.png, convergence.json, ...

Pass ``sources=pwlreg.Sources(reference_array, moving_array, reference_path, moving_path)`` to
:func:`write_outputs` for the results drawn on the inputs (the pictures) or read from their files
(``registered.tif`` of a georeferenced reference).

Images are paths, encoded bytes or OpenCV-layout arrays (grey, BGR or BGRA; uint8 or uint16;
or rasters as :mod:`pwlreg.core.imaging` defines them). Images over 16.8 MP are registered on a
reduced level and the geometry refined at full resolution (:mod:`pwlreg.core.scaled`); a TIFF
path that large is read window by window, so the memory does not grow with it;
points are ``(reference (N, 2), moving (N, 2))`` arrays in pixels or a points file (JSON or
CSV, as the service takes). Options are keyword arguments named as in
:class:`RegistrationOptions` (the same names as the service's ``options``).
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from pwlreg.core.errors import (
    InputError,
    NotEnoughPointsError,
    RegistrationError,
    UnreliableResultError,
)
from pwlreg.core.formats.geotiff import open_image
from pwlreg.core.formats.points import GCPS_KEYWORD
from pwlreg.core.io import load_points, read_image
from pwlreg.core.options import RegistrationOptions
from pwlreg.core.pipeline import STAGES, RegistrationResult, parse_options
from pwlreg.core.results import Sources, write_outputs
from pwlreg.core.scaled import register as _register

try:
    from importlib.metadata import PackageNotFoundError, version

    __version__ = version("pwlreg")
except PackageNotFoundError:  # a source tree that is not installed
    __version__ = "0.1.0"

__all__ = [
    "STAGES",
    "Sources",
    "InputError",
    "NotEnoughPointsError",
    "RegistrationError",
    "RegistrationOptions",
    "RegistrationResult",
    "UnreliableResultError",
    "load_points",
    "read_image",
    "register",
    "write_outputs",
]

ImageLike = np.ndarray | bytes | str | os.PathLike
PointsLike = tuple[np.ndarray, np.ndarray] | bytes | str | os.PathLike


def _image(value: ImageLike, field: str, files: contextlib.ExitStack) -> Any:
    if isinstance(value, np.ndarray):
        return value
    if isinstance(value, bytes):
        return read_image(value, field=field)
    if not isinstance(value, str | os.PathLike):
        raise InputError(f"{field} must be an image array, encoded image bytes or a path; got "
                         f"{type(value).__name__}", field)
    image = open_image(value, field=field)
    return files.enter_context(image) if hasattr(image, "close") else image


def _points(value: PointsLike | None, reference: ImageLike, moving: ImageLike
            ) -> tuple[np.ndarray, np.ndarray] | None:
    if value is None or isinstance(value, tuple):
        return value
    # The GIS formats (QGIS .points, GCPs) place map coordinates through the images' files.
    files = {name: image for name, image in (("reference", reference), ("moving", moving))
             if not isinstance(image, np.ndarray)}
    if isinstance(value, bytes) or value == GCPS_KEYWORD:  # the keyword: the moving file's GCPs
        return load_points(value, **files)
    with open(value, "rb") as handle:
        return load_points(handle.read(), **files)


def register(
    reference: ImageLike,
    moving: ImageLike,
    points: PointsLike | None = None,
    *,
    options: RegistrationOptions | Mapping[str, Any] | None = None,
    progress: Callable[[str, float], None] | None = None,
    **option_values: Any,
) -> RegistrationResult:
    """Register ``moving`` onto ``reference``.

    Parameters
    ----------
    reference, moving : ndarray, bytes or path
        The images: arrays in OpenCV layout, encoded files, or paths to them.
    points : (ndarray, ndarray), bytes or path, optional
        Conjugate points ``(reference (N, 2), moving (N, 2))`` in pixels, or a points file
        (JSON, CSV, QGIS ``.points``, or a GeoTIFF with GCPs; ``"gcps"`` takes the moving
        GeoTIFF's own). Without them the automatic matcher finds them.
    options : RegistrationOptions or mapping, optional
        All options at once; ``option_values`` override single ones (``optimizer="greedy"``).
    progress : callable, optional
        ``progress(stage, fraction)``; raising from it stops the registration.

    Returns
    -------
    RegistrationResult
        Vertices, initial and final triangles, the search history, the registered image, the
        quality verdict and timings; :func:`write_outputs` writes the service's result files.

    Raises
    ------
    InputError
        Unreadable images or points, invalid options, or too few consistent conjugate points.
    UnreliableResultError
        The verdict is ``unreliable`` and ``on_unreliable="fail"``.
    """
    merged = parse_options(options).model_dump(exclude_unset=True)
    merged.update(option_values)
    with contextlib.ExitStack() as files:
        return _register(_image(reference, "reference", files), _image(moving, "moving", files),
                         points=_points(points, reference, moving), options=merged,
                         progress=progress)
