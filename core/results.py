"""The results of a registration, declared once.

Each :class:`ResultFormat` names a file, its media type and its writer. The worker and the CLI
write the results from :data:`RESULTS`; the service's job links and result routes (and so the
OpenAPI document) are generated from it. Adding a result is one entry here.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from pwlreg.core import figures, render
from pwlreg.core.formats import geojson, geotiff, png
from pwlreg.core.imaging import is_picture, matching_image
from pwlreg.core.io import convergence_document, mesh_document
from pwlreg.core.scaled import ScaledResult

if TYPE_CHECKING:
    from pwlreg.core.pipeline import RegistrationResult


@dataclass(frozen=True)
class Sources:
    """What writers may need beyond the result: the decoded inputs, their files (for metadata
    such as georeferencing) and the threads to use.

    ``reference`` and ``moving`` are pictures (OpenCV layout, what the figures draw on): an
    input given as a raster (:mod:`core.imaging`: multi-band, float, masked) is kept as
    ``reference_raster`` / ``moving_raster`` and replaced by its luminance picture
    (:func:`core.imaging.matching_image`).
    """

    reference: np.ndarray | None = None
    moving: np.ndarray | None = None
    reference_path: Path | None = None
    moving_path: Path | None = None
    threads: int = 1
    reference_raster: np.ndarray | None = None
    moving_raster: np.ndarray | None = None

    def __post_init__(self) -> None:
        for name in ("reference", "moving"):
            image = getattr(self, name)
            if image is not None and not is_picture(image):
                object.__setattr__(self, f"{name}_raster", image)
                object.__setattr__(self, name, matching_image(image, field=name))


Writer = Callable[["RegistrationResult", Sources, Path], None]


def _always(result: RegistrationResult, sources: Sources) -> bool:
    return True


@dataclass(frozen=True)
class ResultFormat:
    """One result file of a registration.

    Attributes
    ----------
    name : str
        Key of the result (in :func:`write_outputs`'s answer and the storage).
    filename : str
        File name in the results directory (and the download's name).
    route : str
        Last segment of the result's URL under ``/v1/jobs/{id}/``.
    media_type : str
        Its ``Content-Type``.
    title : str
        One line, used as the job link's title and the route's summary.
    description : str
        What the file holds (the route's description).
    write : callable
        ``write(result, sources, path)`` writes the file.
    applies : callable
        ``applies(result, sources)``: whether the result exists for this registration (a
        GeoTIFF only for a georeferenced reference, say). Absent results have no link.
    """

    name: str
    filename: str
    route: str
    media_type: str
    title: str
    description: str
    write: Writer
    applies: Callable[[RegistrationResult, Sources], bool] = _always


def _write_json(document: Callable[..., dict], indent: int | None = None,
                sources: bool = False) -> Writer:
    """A writer of ``document(result)``, or ``document(result, sources)`` with ``sources``."""
    def write(result: RegistrationResult, given: Sources, path: Path) -> None:
        doc = document(result, given) if sources else document(result)
        path.write_text(json.dumps(doc, indent=indent))
    return write


def _write_bytes(encode: Callable[[RegistrationResult, Sources], bytes]) -> Writer:
    def write(result: RegistrationResult, sources: Sources, path: Path) -> None:
        path.write_bytes(encode(result, sources))
    return write


_COLOURS = (
    "Edges both meshes share are amber, edges of the initial mesh the optimizer swapped away "
    "red, edges its swaps created green; measured vertices are white dots, extrapolated ones "
    "white rings; a magenta ring marks a vertex only the initial mesh uses, a cyan ring one only "
    "the final mesh uses."
)
_BOUNDED = f"Drawn with its longest side at most {render.MAX_SIDE} pixels."


RESULTS: dict[str, ResultFormat] = {
    r.name: r
    for r in (
        ResultFormat(
            "mesh", "mesh.json", "mesh", "application/json",
            "Meshes, swaps and matching results",
            "mesh.json: reference and moving vertices, initial and final triangles, the swaps, "
            "the parameters, the quality verdict and the matching results (pixel coordinates, x "
            "right, y down, (0, 0) the centre of the top-left pixel).",
            _write_json(mesh_document),
        ),
        ResultFormat(
            "registered", "registered.png", "registered.png", "image/png",
            "Moving image registered onto the reference (alpha = inside the mesh)",
            "The moving image warped onto the reference, PNG with alpha (opaque inside the "
            "mesh).",
            png.write_registered,
        ),
        ResultFormat(
            "registered_geotiff", "registered.tif", "registered.tif", geotiff.MEDIA_TYPE,
            "Moving image registered onto the reference, GeoTIFF in the reference's grid",
            "Every band of the moving image at its own data type, resampled through the final "
            "mesh into the reference's grid (its CRS and geotransform); nodata outside the "
            "mesh (the moving file's nodata value, else NaN for floats, else 0); tiled 512 x "
            "512, DEFLATE, overviews when over 1024 pixels. Only for a georeferenced reference.",
            geotiff.write_registered, geotiff.applies,
        ),
        ResultFormat(
            "mesh_geojson", "mesh.geojson", "mesh.geojson", geojson.MEDIA_TYPE,
            "Final mesh as GeoJSON polygons",
            "mesh.geojson: one Polygon per final triangle (id = its index) with its vertices, "
            "reference and moving pixel corners, swapped (made by the search), consistency "
            "(triangle_scores) and extrapolated; WGS 84 longitude/latitude (RFC 7946) for a "
            "georeferenced reference, else reference pixels (member crs says which).",
            _write_json(geojson.mesh_collection, sources=True),
        ),
        ResultFormat(
            "tiepoints_geojson", "tiepoints.geojson", "tiepoints.geojson", geojson.MEDIA_TYPE,
            "Tie points as GeoJSON points",
            "tiepoints.geojson: one Point per conjugate pair at its reference position: the "
            "pairs the mesh stands on first (id = index in mesh.json's matching.reference), "
            "then every pair dropped on the way; reference_px, moving_px, moving_position "
            "(georeferenced moving image), residual_px (epipolar; null where none judged the "
            "pair), kept, reason (null, or thinned, fixed in the frame, ambiguous, "
            "disagreement, low texture, unverifiable, epipolar, neighbours, spread; for client "
            "points not finite, outside "
            "image, duplicate, epipolar) and status (kept/dropped); the member dropped counts "
            "them per cause. Same coordinates as mesh.geojson.",
            _write_json(geojson.tiepoints_collection, sources=True),
        ),
        ResultFormat(
            "convergence", "convergence.json", "convergence", "application/json",
            "Consistency (MI, NMI) per iteration of the optimizer",
            "convergence.json: initial and final MI/NMI (bits, dimensionless), every iteration "
            "with its swap, delta, MI, NMI and elapsed seconds, and why it stopped.",
            _write_json(convergence_document, indent=1),
        ),
        ResultFormat(
            "mesh_reference", "mesh_reference.png", "mesh_reference.png", "image/png",
            "Initial and final mesh on the reference image",
            f"The reference image with the initial and the final mesh drawn on it. {_COLOURS} "
            f"{_BOUNDED}",
            _write_bytes(figures.mesh_reference_png), figures.has_images,
        ),
        ResultFormat(
            "mesh_moving", "mesh_moving.png", "mesh_moving.png", "image/png",
            "Initial and final mesh on the moving image",
            f"The moving image with the initial and the final mesh drawn on it. {_COLOURS} "
            f"{_BOUNDED}",
            _write_bytes(figures.mesh_moving_png), figures.has_images,
        ),
        ResultFormat(
            "checkerboard", "checkerboard.png", "checkerboard.png", "image/png",
            "Checkerboard of reference and registered image, initial and final mesh",
            "Alternating tiles of the reference (top-left tile) and the registered image (black "
            "outside the mesh), with the initial mesh on the left and the final mesh on the "
            f"right: edges break where the registration is wrong. {_BOUNDED}",
            _write_bytes(figures.checkerboard_png), figures.has_images,
        ),
        ResultFormat(
            "difference", "difference.png", "difference.png", "image/png",
            "Absolute difference of reference and registered image, initial and final mesh",
            "|reference - registered| of the grey levels, times "
            f"{render.DIFFERENCE_GAIN} (saturating at "
            f"{256 // render.DIFFERENCE_GAIN} levels), in the inferno colour map "
            "(black = equal), grey outside the mesh; the initial mesh on the left, the final "
            f"mesh on the right. {_BOUNDED}",
            _write_bytes(figures.difference_png), figures.has_images,
        ),
        ResultFormat(
            "consistency", "consistency.png", "consistency.png", "image/png",
            "Consistency of each triangle of the final mesh",
            "The final mesh over the grey reference, each triangle coloured by its consistency "
            "score (the share of its MI lost one step away, mesh.json's triangle_scores): red "
            f"at 0 or below (no peak), yellow at 0.5, green at 1; grey without texture. {_BOUNDED}",
            _write_bytes(figures.consistency_png), figures.has_images,
        ),
        ResultFormat(
            "convergence_png", "convergence.png", "convergence.png", "image/png",
            "Convergence curve (PNG)",
            "Global MI (bits, above) and NMI (below) before the first move and after each "
            "accepted move of the optimizer, 800x520 pixels.",
            _write_bytes(figures.convergence_png),
        ),
        ResultFormat(
            "convergence_svg", "convergence.svg", "convergence.svg", "image/svg+xml",
            "Convergence curve (SVG)",
            "The convergence curve of convergence.png as SVG.",
            _write_bytes(figures.convergence_svg),
        ),
        ResultFormat(
            "preview_reference", "preview_reference.png", "preview_reference.png", "image/png",
            "Reference image, reduced",
            f"The reference image (8-bit, no alpha). {_BOUNDED}",
            _write_bytes(figures.preview_reference_png), figures.has_images,
        ),
        ResultFormat(
            "preview_registered", "preview_registered.png", "preview_registered.png",
            "image/png", "Registered image (final mesh), reduced",
            "The moving image registered through the final mesh, 8-bit with alpha (opaque "
            "inside the mesh), at the size of preview_reference.png.",
            _write_bytes(figures.preview_registered_png), figures.has_images,
        ),
        ResultFormat(
            "preview_registered_initial", "preview_registered_initial.png",
            "preview_registered_initial.png", "image/png",
            "Registered image through the initial mesh, reduced",
            "The moving image registered through the initial mesh (before the optimizer), "
            "8-bit with alpha, at the size of preview_reference.png.",
            _write_bytes(figures.preview_registered_initial_png), figures.has_images,
        ),
        ResultFormat(
            "reconstruction_ply", "reconstruction.ply", "reconstruction.ply",
            "model/x-ply", "Affine 3D reconstruction of the final mesh (PLY)",
            "The mesh vertices reconstructed in 3D by affine factorization (Tomasi-Kanade) with "
            "the final mesh's triangles, binary PLY, vertices coloured from the reference: x, y "
            "reference pixels (y down), z the third affine axis. Affine: the scene up to an "
            "affine transform, meaningful when the cameras are far from the scene.",
            _write_bytes(figures.reconstruction_ply), figures.can_reconstruct,
        ),
        ResultFormat(
            "reconstruction_initial_ply", "reconstruction_initial.ply",
            "reconstruction_initial.ply", "model/x-ply",
            "Affine 3D reconstruction of the initial mesh (PLY)",
            "As reconstruction.ply, with the initial mesh's triangles.",
            _write_bytes(figures.reconstruction_initial_ply), figures.can_reconstruct,
        ),
        ResultFormat(
            "reconstruction_glb", "reconstruction.glb", "reconstruction.glb",
            "model/gltf-binary", "Affine 3D reconstruction, textured (glTF)",
            "The affine reconstruction as binary glTF 2.0 textured with the reference image "
            f"(at most {figures.TEXTURE_SIDE} pixels on its longest side): scene 0 (the "
            "default) the final mesh, scene 1 the initial mesh, over the same vertices; y up "
            "(the PLY's y and z negated), pixel units, unlit material.",
            _write_bytes(figures.reconstruction_glb), figures.can_reconstruct,
        ),
    )
}
"""Every result a registration can have, by name, in the order of the job links."""


def write_outputs(
    result: RegistrationResult,
    out_dir: str | os.PathLike,
    *,
    sources: Sources | None = None,
    threads: int = 1,
) -> dict[str, Path]:
    """Write every result that applies into ``out_dir``.

    Parameters
    ----------
    result : RegistrationResult
    out_dir : path
        Created if needed.
    sources : Sources, optional
        The decoded inputs, for results drawn on them; ``threads`` is used when omitted.
    threads : int
        Threads a writer may use (PNG compression).

    Returns
    -------
    dict
        The written files' paths by result name.
    """
    sources = _completed(sources or Sources(threads=threads), result)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written = {}
    for fmt in RESULTS.values():
        if fmt.applies(result, sources):
            path = out / fmt.filename
            fmt.write(result, sources, path)
            written[fmt.name] = path
    return written


def _completed(sources: Sources, result: RegistrationResult) -> Sources:
    """``sources`` with what a result registered on levels brings: its levels as the pictures
    (the figures are drawn on them) and the files it read window by window."""
    if not isinstance(result, ScaledResult):
        return sources
    return replace(
        sources,
        reference=sources.reference if sources.reference is not None
        else result.reference_level,
        moving=sources.moving if sources.moving is not None else result.moving_level,
        reference_path=sources.reference_path or result.paths[0],
        moving_path=sources.moving_path or result.paths[1],
    )
