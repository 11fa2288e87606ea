"""Control points from GIS tools: QGIS Georeferencer ``.points`` files and the ground control
points (GCPs) embedded in a GeoTIFF, turned into conjugate pixel pairs.

Both give, for each point, a position in the moving image and map coordinates; the map
coordinates are placed in the reference image through its CRS and geotransform (reprojected
with pyproj when the points' CRS differs). Pixel coordinates: x right, y down, (0, 0) the centre
of the top-left pixel.
"""

from __future__ import annotations

import csv
import io
import os

import numpy as np
from pyproj import CRS as ProjCRS
from pyproj import Transformer
from pyproj.exceptions import CRSError, ProjError

from pwlreg.core.errors import InputError, UnsupportedMediaError
from pwlreg.core.formats.geotiff import (
    Georeference,
    georeference,
    ground_control,
    is_tiff,
    probe_tiff,
)

QGIS_HEADER = ("mapx", "mapy", "sourcex", "sourcey", "enable")
"""The columns of a QGIS .points file this reader uses (dX, dY and residual are QGIS's own
fit residuals, ignored)."""

ImageSource = bytes | str | os.PathLike


GCPS_KEYWORD = "gcps"
"""A points file that is just this word takes the GCPs embedded in the moving image itself."""


def is_gis_points(data: bytes | str) -> bool:
    """Whether a points file is a QGIS .points file, a TIFF (GCPs) or :data:`GCPS_KEYWORD`,
    not JSON or CSV pairs."""
    if isinstance(data, bytes) and is_tiff(data[:4]):
        return True
    text = data.decode("utf-8", "replace") if isinstance(data, bytes) else data
    first = text.lstrip("\ufeff").lstrip()[:64].lower()
    return (first.startswith("#crs") or first.replace(" ", "").startswith("mapx,mapy")
            or first.rstrip() == GCPS_KEYWORD)


def read_gis_points(
    data: bytes | str,
    field: str = "points",
    *,
    reference: ImageSource | None = None,
    moving: ImageSource | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Conjugate pairs from a QGIS .points file or from the GCPs of a GeoTIFF.

    Parameters
    ----------
    data : bytes or str
        The file (:func:`is_gis_points` is true for it); the word ``gcps`` takes the GCPs of
        the moving image.
    field : str
        Name used in error messages.
    reference : bytes or path
        The reference image: it must be georeferenced (CRS and geotransform), since the points
        give map coordinates.
    moving : bytes or path, optional
        The moving image: when it has a geotransform, a .points file's source coordinates are
        in its CRS (as QGIS writes them for a georeferenced source), else pixels; a GCP TIFF
        must have its size.

    Returns
    -------
    reference, moving : ndarray of float64, shape (N, 2)

    Raises
    ------
    InputError
        Unreadable file, no usable point, or a reference without georeferencing.
    """
    if reference is None:
        raise InputError(
            f"{field} gives map coordinates (QGIS .points or GeoTIFF GCPs): the reference image's "
            "file is needed to place them",
            field,
        )
    geo = georeference(reference)
    if geo is None:
        raise InputError(
            f"{field} gives map coordinates (QGIS .points or GeoTIFF GCPs), but the reference "
            "image is not georeferenced (no CRS and geotransform) to place them in; send pixel "
            "pairs (JSON or CSV) instead",
            field,
        )
    if isinstance(data, bytes) and is_tiff(data[:4]):
        return _from_gcps(data, field, geo, moving)
    text = data.decode("utf-8", "replace") if isinstance(data, bytes) else data
    if text.strip().lower() == GCPS_KEYWORD:
        if moving is None or not is_tiff(_head(moving)):
            raise InputError(f"{field} is {GCPS_KEYWORD!r} but the moving image is not a TIFF "
                             "(only GeoTIFFs carry GCPs)", field)
        return _from_gcps(moving, field, geo, None)
    return _from_qgis(data, field, geo, moving)


def _from_gcps(data: ImageSource, field: str, geo: Georeference,
               moving: ImageSource | None) -> tuple[np.ndarray, np.ndarray]:
    try:
        pixels, coords, crs = ground_control(data)
    except UnsupportedMediaError as exc:
        raise InputError(str(exc), field) from exc
    if len(pixels) == 0:
        raise InputError(f"{field}: the TIFF has no ground control points (GCPs)", field)
    if moving is not None and is_tiff(_head(moving)):
        own, size = probe_tiff(data, field)[:2], probe_tiff(moving, "moving")[:2]
        if own != size:
            raise InputError(
                f"{field}: the GCPs' TIFF is {own[0]}x{own[1]} pixels but the moving image is "
                f"{size[0]}x{size[1]}; GCPs must be those of the moving image",
                field,
            )
    ref = geo.to_pixels(_to_crs(coords, crs.to_wkt() if crs else None, geo, field))
    return ref, pixels


def _from_qgis(data: bytes | str, field: str, geo: Georeference,
               moving: ImageSource | None) -> tuple[np.ndarray, np.ndarray]:
    # Format of QGIS's Georeferencer (QgsGCPList::saveGcps, src/app/georeferencer/qgsgcplist.cpp
    # in qgis/QGIS): an optional first line "#CRS: <WKT of the map coordinates>", the header
    # "mapX,mapY,sourceX,sourceY,enable,dX,dY,residual", then one row per GCP. sourceX/sourceY
    # are in the source layer's coordinates: map coordinates when the raster being georeferenced
    # has a geotransform, else pixels from its top-left corner with y negative downwards (QGIS
    # lays an ungeoreferenced raster on y <= 0).
    text = data.decode("utf-8-sig", "replace") if isinstance(data, bytes) else data
    lines = text.lstrip("\ufeff").splitlines()
    crs_text = None
    if lines and lines[0].lstrip().lower().startswith("#crs:"):
        crs_text = lines.pop(0).split(":", 1)[1].strip() or None
    rows = [r for r in csv.reader(io.StringIO("\n".join(lines))) if any(c.strip() for c in r)]
    header = [c.strip().lower() for c in rows[0]] if rows else []
    if any(name not in header for name in QGIS_HEADER[:4]):
        raise InputError(
            f"{field}: a QGIS .points file needs the header mapX,mapY,sourceX,sourceY"
            f"[,enable,dX,dY,residual] (got {','.join(header)})",
            field,
        )
    cols = [header.index(name) for name in QGIS_HEADER[:4]]
    enable = header.index("enable") if "enable" in header else None
    values = []
    for number, row in enumerate(rows[1:], start=2):
        try:
            if enable is not None and int(float(row[enable])) == 0:
                continue
            values.append([float(row[c]) for c in cols])
        except (ValueError, IndexError) as exc:
            raise InputError(
                f"{field}: row {number} of the .points file is not mapX,mapY,sourceX,sourceY,"
                f"enable numbers: {exc}",
                field,
            ) from exc
    table = np.array(values, np.float64).reshape(-1, 4)
    if not np.isfinite(table).all():
        raise InputError(f"{field} contains non-finite coordinates", field)
    moving_geo = georeference(moving)
    if moving_geo is not None:
        mov = moving_geo.to_pixels(table[:, 2:])
    else:
        if (table[:, 3] > 0).any():
            raise InputError(
                f"{field}: sourceY must be zero or negative (QGIS writes the pixel rows of an "
                "image without georeferencing as negative y)",
                field,
            )
        mov = np.stack([table[:, 2] - 0.5, -table[:, 3] - 0.5], axis=1)
    ref = geo.to_pixels(_to_crs(table[:, :2], crs_text, geo, field))
    return ref, mov


def _to_crs(coords: np.ndarray, crs_text: str | None, geo: Georeference,
            field: str) -> np.ndarray:
    """Map coordinates in ``crs_text`` (None: already the reference's CRS) in the reference's
    CRS."""
    if crs_text is None or len(coords) == 0:
        return coords
    try:
        source = ProjCRS.from_user_input(crs_text)
        target = ProjCRS.from_wkt(geo.crs.to_wkt())
        if source == target:
            return coords
        x, y = Transformer.from_crs(source, target, always_xy=True).transform(
            coords[:, 0], coords[:, 1], errcheck=True
        )
    except (CRSError, ProjError) as exc:
        raise InputError(
            f"{field}: its map coordinates cannot be brought into the reference's CRS: {exc}",
            field,
        ) from exc
    return np.stack([x, y], axis=1)


def _head(source: ImageSource) -> bytes:
    if isinstance(source, bytes):
        return source[:4]
    try:
        with open(source, "rb") as handle:
            return handle.read(4)
    except OSError:
        return b""
