"""GeoJSON of a registration: the final mesh (``mesh.geojson``) and the tie points
(``tiepoints.geojson``).

With a georeferenced reference the coordinates are WGS 84 longitude, latitude (RFC 7946),
reprojected with pyproj from the reference's CRS through its geotransform; when the CRS has no
transformation to WGS 84 they stay in the reference's CRS, named by a ``crs`` member (the 2008
GeoJSON convention GDAL still reads). Without georeferencing they are pixels of the reference
image (x right, y down, (0, 0) the centre of the top-left pixel), said by the same member.
Each document also has a ``coordinate_system`` member saying which in words.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np
from pyproj import CRS as ProjCRS
from pyproj import Transformer
from pyproj.exceptions import ProjError

from pwlreg.core.formats.geotiff import Georeference, georeference

if TYPE_CHECKING:
    from pwlreg.core.pipeline import RegistrationResult
    from pwlreg.core.results import Sources

MEDIA_TYPE = "application/geo+json"
PIXEL_CRS = "urn:pwlreg:crs:pixel"
"""``crs`` name of documents in reference pixels."""
_DIGITS = {"lonlat": 9, "map": 4, "pixel": 4}
"""Decimals kept: 1e-9 degree is 0.1 mm on the ground."""

Mapper = Callable[[np.ndarray], np.ndarray]


def _frame(geo: Georeference | None) -> tuple[Mapper, dict, str]:
    """How reference pixels become output coordinates: the mapper, the members naming the
    coordinate system, and the rounding key."""
    if geo is None:
        return (lambda p: np.asarray(p, np.float64).reshape(-1, 2),
                {"crs": {"type": "name", "properties": {"name": PIXEL_CRS}},
                 "coordinate_system": "pixels of the reference image: x right, y down, (0, 0) "
                 "the centre of the top-left pixel"}, "pixel")
    try:
        transformer = Transformer.from_crs(ProjCRS.from_wkt(geo.crs.to_wkt()), "EPSG:4326",
                                           always_xy=True)
        corners = geo.to_map(np.array([[0.0, 0.0], [geo.width - 1.0, geo.height - 1.0]]))
        ok = np.isfinite(np.array(transformer.transform(corners[:, 0], corners[:, 1]))).all()
    except ProjError:
        ok = False
    if ok:
        def to_lonlat(pixels: np.ndarray) -> np.ndarray:
            xy = geo.to_map(pixels)
            return np.stack(transformer.transform(xy[:, 0], xy[:, 1]), axis=1)

        return to_lonlat, {"coordinate_system": "WGS 84 longitude, latitude (RFC 7946), "
                           f"reprojected from the reference's {_crs_name(geo)}"}, "lonlat"
    code = geo.crs.to_epsg()
    name = f"urn:ogc:def:crs:EPSG::{code}" if code else geo.crs.to_wkt()
    return geo.to_map, {"crs": {"type": "name", "properties": {"name": name}},
                        "coordinate_system": f"the reference's {_crs_name(geo)} (no "
                        "transformation to WGS 84 is known for it)"}, "map"


def _crs_name(geo: Georeference) -> str:
    code = geo.crs.to_epsg()
    return f"EPSG:{code}" if code else "coordinate reference system"


def _rounded(coords: np.ndarray, key: str) -> list[list[float]]:
    return np.round(coords, _DIGITS[key]).tolist()


def mesh_collection(result: RegistrationResult, sources: Sources) -> dict:
    """The final mesh as a FeatureCollection of triangles.

    Each Feature is a Polygon (the triangle in the reference, counter-clockwise, closed), with
    ``id`` its index in ``final_triangles`` and the properties ``vertices`` (indices into
    mesh.json's vertex lists), ``reference_px`` and ``moving_px`` (the corners in each image's
    pixels), ``swapped`` (true when the edge-swap search made it: it is not a triangle of the
    initial mesh), ``consistency`` (mesh.json's ``triangle_scores``: the share of mutual
    information lost when the moving side moves 8 pixels of the scoring level; 1 a sharp peak,
    0 or less no evidence; null without texture) and ``extrapolated`` (a corner is a border
    vertex whose moving position was extrapolated, not measured).
    """
    reference_geo = georeference(sources.reference_path)
    to_out, members, key = _frame(reference_geo)
    ref = np.asarray(result.reference_vertices, np.float64).reshape(-1, 2)
    mov = np.asarray(result.moving_vertices, np.float64).reshape(-1, 2)
    tris = np.asarray(result.final_triangles, np.int64).reshape(-1, 3)
    initial = {tuple(sorted(t)) for t in np.asarray(result.initial_triangles).tolist()}
    scores = np.asarray(result.quality.triangle_scores, np.float64)
    extrapolated = np.asarray(result.extrapolated, bool)[tris].any(axis=1).tolist()
    corners = to_out(ref)[tris] if len(tris) else np.zeros((0, 3, 2))
    ab, ac = corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
    clockwise = ab[:, 0] * ac[:, 1] < ab[:, 1] * ac[:, 0]
    corners[clockwise] = corners[clockwise][:, [0, 2, 1]]  # RFC 7946: counter-clockwise rings
    rings = _rounded(np.concatenate([corners, corners[:, :1]], axis=1), key)
    ref_px, mov_px = _rounded(ref[tris], "pixel"), _rounded(mov[tris], "pixel")
    features = []
    for t, vertices in enumerate(tris.tolist()):
        score = scores[t] if t < len(scores) else np.nan
        features.append({
            "type": "Feature",
            "id": t,
            "geometry": {"type": "Polygon", "coordinates": [rings[t]]},
            "properties": {
                "vertices": vertices,
                "reference_px": ref_px[t],
                "moving_px": mov_px[t],
                "swapped": tuple(sorted(vertices)) not in initial,
                "consistency": round(float(score), 4) if np.isfinite(score) else None,
                "extrapolated": extrapolated[t],
            },
        })
    return {"type": "FeatureCollection", **members, "features": features}


def tiepoints_collection(result: RegistrationResult, sources: Sources) -> dict:
    """The conjugate points, kept and dropped, as a FeatureCollection of Points.

    Each Feature is a pair at its reference position. The pairs the mesh stands on come first,
    ``id`` their index in mesh.json's ``matching.reference``; the pairs dropped on the way
    follow (``id`` from the number of kept pairs on). Properties: ``reference_px`` and
    ``moving_px`` (pixels of each image), ``moving_position`` (where the moving point is on
    the ground, in the same coordinates as the geometry, when the moving image is
    georeferenced by a geotransform, in a system that reprojects to WGS 84 or in the
    reference's own: the line from the geometry to it is the shift the registration
    corrects), ``residual_px`` (distance to the robust epipolar geometry, pixels; null when
    none judged the pair: the filter off or skipped, or the pair dropped before it), ``kept``
    (true or false), ``reason`` (null for a kept pair, else the cause: one of
    :data:`core.matching.LISTED_AUTOMATIC` for automatic pairs; ``not finite``, ``outside image``,
    ``duplicate``, ``epipolar`` for the client's), ``status`` (``kept`` or ``dropped``) and,
    on a client's kept pair the filter judged, ``unverified`` (true when it could not check
    it: :func:`core.matching.unverified_pairs`). A coordinate the client gave as no finite
    number is null (and the geometry with it). The member ``dropped`` counts the drops by
    cause (as mesh.json's ``matching.rejected``, which also counts the matcher's own losses,
    listed nowhere: a failed track is not a pair), with ``source`` (``client``, ``lk``,
    ``sift``) and ``notes``.
    """
    reference_geo = georeference(sources.reference_path)
    to_out, members, key = _frame(reference_geo)
    points = result.points
    kept = len(points.reference)
    dropped = points.dropped
    ref = np.concatenate([np.asarray(points.reference, np.float64).reshape(-1, 2),
                          dropped.reference])
    mov = np.concatenate([np.asarray(points.moving, np.float64).reshape(-1, 2),
                          dropped.moving])
    residuals = np.concatenate([np.asarray(points.residuals, np.float64), dropped.residuals])
    reasons = [None] * kept + dropped.reason.tolist()
    coords = _mapped(to_out, ref)
    moving_geo = georeference(sources.moving_path)
    moving_coords = None
    if moving_geo is not None and len(mov):
        mov_frame = _frame(moving_geo)
        if key == "lonlat" and mov_frame[2] == key:
            moving_coords = _mapped(mov_frame[0], mov)
        elif key == "map" and moving_geo.crs == reference_geo.crs:
            # A system with no known way to WGS 84 (a site's local grid): both in it.
            moving_coords = _mapped(moving_geo.to_map, mov)
    features = []
    for i in range(len(ref)):
        properties = {
            "reference_px": _point(ref[i], "pixel"),
            "moving_px": _point(mov[i], "pixel"),
            "residual_px": round(float(residuals[i]), 4) if np.isfinite(residuals[i]) else None,
            "kept": i < kept,
            "reason": reasons[i],
            "status": "kept" if i < kept else "dropped",
        }
        if points.unverified is not None and i < kept:
            properties["unverified"] = bool(points.unverified[i])
        if moving_coords is not None:
            properties["moving_position"] = _point(moving_coords[i], key)
        position = _point(coords[i], key)
        features.append({
            "type": "Feature",
            "id": i,
            "geometry": None if position is None else {"type": "Point", "coordinates": position},
            "properties": properties,
        })
    return {
        "type": "FeatureCollection",
        **members,
        "source": points.source,
        "dropped": {k: int(v) for k, v in points.rejected.items()},
        "notes": list(points.notes),
        "features": features,
    }


def _mapped(to_out: Mapper, pixels: np.ndarray) -> np.ndarray:
    """``to_out`` of the finite rows of ``pixels`` (N, 2); NaN rows stay NaN."""
    out = np.full(pixels.shape, np.nan)
    finite = np.isfinite(pixels).all(axis=1)
    if finite.any():
        out[finite] = to_out(pixels[finite])
    return out


def _point(xy: np.ndarray, key: str) -> list[float] | None:
    """A position rounded for its frame, or None when it is not finite (JSON has no NaN)."""
    return _rounded(xy, key) if np.isfinite(xy).all() else None
