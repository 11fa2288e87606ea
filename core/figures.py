"""The pictures and 3D files of a registration result, as encoded bytes (the writers of
:data:`pwlreg.core.results.RESULTS` store them).

Pictures are drawn by :mod:`pwlreg.core.render` at a bounded size (longest side at most
:data:`~pwlreg.core.render.MAX_SIDE`); the 3D files hold the affine reconstruction of the mesh
vertices (:mod:`pwlreg.core.reconstruction`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import cv2
import numpy as np

from pwlreg.core import render
from pwlreg.core.formats.glb import encode_glb
from pwlreg.core.formats.ply import encode_ply
from pwlreg.core.io import encode_png
from pwlreg.core.reconstruction import AffineReconstruction, affine_reconstruction

if TYPE_CHECKING:
    from pwlreg.core.pipeline import RegistrationResult
    from pwlreg.core.results import Sources

TEXTURE_SIDE = 2048
"""Longest side of the glb's texture (the reference image, reduced), in pixels."""


def _png(image: np.ndarray, sources: Sources) -> bytes:
    return encode_png(image, threads=sources.threads)


def has_images(result: RegistrationResult, sources: Sources) -> bool:
    """Whether the decoded inputs are at hand (the pictures are drawn on them)."""
    return sources.reference is not None and sources.moving is not None


# --- pictures ----------------------------------------------------------------------------------


def _reference_vertices(result: RegistrationResult, sources: Sources) -> np.ndarray:
    """The reference vertices in the pixels of ``sources.reference``, which is a reduced level
    when the search ran on levels (:mod:`pwlreg.core.scaled`)."""
    return _in_picture(result.reference_vertices, result.reference_size, sources.reference)


def _moving_vertices(result: RegistrationResult, sources: Sources) -> np.ndarray:
    """The moving vertices in the pixels of ``sources.moving``."""
    return _in_picture(result.moving_vertices, result.moving_size, sources.moving)


def _in_picture(points: np.ndarray, size: tuple[int, int], picture: np.ndarray) -> np.ndarray:
    return render.scale_points(points, size, (picture.shape[1], picture.shape[0]))


def mesh_reference_png(result: RegistrationResult, sources: Sources) -> bytes:
    """Both meshes on the reference image (:func:`render.mesh_overlay`)."""
    return _png(render.mesh_overlay(
        sources.reference, _reference_vertices(result, sources), result.initial_triangles,
        result.final_triangles, extrapolated=result.extrapolated,
    ), sources)


def mesh_moving_png(result: RegistrationResult, sources: Sources) -> bytes:
    """Both meshes on the moving image (:func:`render.mesh_overlay`)."""
    return _png(render.mesh_overlay(
        sources.moving, _moving_vertices(result, sources), result.initial_triangles,
        result.final_triangles, extrapolated=result.extrapolated,
    ), sources)


def _comparison(result: RegistrationResult, sources: Sources, combine) -> bytes:
    shown = render.panel_size(result.reference_size, 2)
    reference = render.to_display(sources.reference, shown)
    panels = [
        combine(reference, render.registered_preview(
            sources.moving, result.reference_vertices, _moving_vertices(result, sources),
            triangles, result.reference_size, shown,
        ))
        for triangles in (result.initial_triangles, result.final_triangles)
    ]
    return _png(render.side_by_side(panels, ("initial mesh", "final mesh")), sources)


def checkerboard_png(result: RegistrationResult, sources: Sources) -> bytes:
    """Checkerboards of the reference and the registered image, initial mesh left, final mesh
    right (:func:`render.checkerboard`)."""
    return _comparison(result, sources, render.checkerboard)


def difference_png(result: RegistrationResult, sources: Sources) -> bytes:
    """Absolute differences of the reference and the registered image, initial mesh left,
    final mesh right (:func:`render.difference`)."""
    return _comparison(result, sources, render.difference)


def consistency_png(result: RegistrationResult, sources: Sources) -> bytes:
    """The final mesh's triangles coloured by their consistency score
    (:func:`render.consistency_map`)."""
    return _png(render.consistency_map(
        sources.reference, _reference_vertices(result, sources), result.final_triangles,
        result.quality.triangle_scores,
    ), sources)


def preview_reference_png(result: RegistrationResult, sources: Sources) -> bytes:
    """The reference image at the bounded size."""
    return _png(render.to_display(sources.reference, render.fit(result.reference_size)),
                sources)


def _preview_registered(result: RegistrationResult, sources: Sources,
                        triangles: np.ndarray) -> bytes:
    return _png(render.registered_preview(
        sources.moving, result.reference_vertices, _moving_vertices(result, sources),
        triangles, result.reference_size, render.fit(result.reference_size),
    ), sources)


def preview_registered_png(result: RegistrationResult, sources: Sources) -> bytes:
    """The registered image (final mesh) at the size of :func:`preview_reference_png`."""
    return _preview_registered(result, sources, result.final_triangles)


def preview_registered_initial_png(result: RegistrationResult, sources: Sources) -> bytes:
    """The moving image registered through the initial mesh, at the same size."""
    return _preview_registered(result, sources, result.initial_triangles)


def _curves(result: RegistrationResult) -> dict:
    s = result.search
    return {
        "mi": [s.initial_mi] + [step.mi for step in s.steps],
        "nmi": [s.initial_nmi] + [step.nmi for step in s.steps],
        "optimizer": result.options.optimizer,
        "cost": result.options.cost,
    }


def convergence_png(result: RegistrationResult, sources: Sources) -> bytes:
    """Global MI and NMI after each accepted move (:func:`render.convergence_png`)."""
    return _png(render.convergence_png(**_curves(result)), sources)


def convergence_svg(result: RegistrationResult, sources: Sources) -> bytes:
    """The same curve as SVG (:func:`render.convergence_svg`)."""
    return render.convergence_svg(**_curves(result)).encode("utf-8")


# --- 3D ----------------------------------------------------------------------------------------


def _spread(points: np.ndarray) -> bool:
    # At least 4 points, not all on one line: what the factorization needs.
    return len(points) >= 4 and np.linalg.matrix_rank(points - points.mean(axis=0)) == 2


def can_reconstruct(result: RegistrationResult, sources: Sources) -> bool:
    """Whether the mesh has the 4 vertices, not all on a line, the factorization needs."""
    return _spread(np.asarray(result.reference_vertices, dtype=np.float64))


def reconstruction(result: RegistrationResult) -> AffineReconstruction:
    """The affine reconstruction of the mesh vertices, fitted to the measured ones (to all of
    them when the measured ones are too few, or on one line)."""
    ref = np.asarray(result.reference_vertices, dtype=np.float64)
    measured = ~np.asarray(result.extrapolated, bool)
    return affine_reconstruction(
        ref, result.moving_vertices, fitted=measured if _spread(ref[measured]) else None,
    )


def _positions(rec: AffineReconstruction) -> np.ndarray:
    # x, y back in reference pixels (y down); z the reconstruction's third axis.
    return np.column_stack([rec.points[:, :2] + rec.offsets[:2], rec.points[:, 2]])


def _comments(rec: AffineReconstruction, mesh: str) -> tuple[str, ...]:
    return (
        f"pwlreg affine reconstruction, {mesh} mesh: x, y reference pixels (y down), z the "
        "third affine axis; the scene up to an affine transform",
        f"rms reprojection residual {rec.residual:.4f} px, singular values "
        + " ".join(f"{v:.6g}" for v in rec.singular_values),
    )


def _vertex_colours(result: RegistrationResult, sources: Sources) -> np.ndarray | None:
    if sources.reference is None:
        return None
    h, w = sources.reference.shape[:2]
    xy = np.round(_reference_vertices(result, sources)).astype(np.int64)
    samples = sources.reference[np.clip(xy[:, 1], 0, h - 1), np.clip(xy[:, 0], 0, w - 1)]
    bgr = render.to_display(samples.reshape(1, len(xy), -1) if samples.ndim > 1
                            else samples.reshape(1, -1))
    return bgr[0, :, ::-1]


def _ply(result: RegistrationResult, sources: Sources, triangles: np.ndarray, mesh: str
         ) -> bytes:
    rec = reconstruction(result)
    return encode_ply(_positions(rec), triangles, colors=_vertex_colours(result, sources),
                      comments=_comments(rec, mesh))


def reconstruction_ply(result: RegistrationResult, sources: Sources) -> bytes:
    """The final mesh in 3D as PLY, vertices coloured from the reference image if given."""
    return _ply(result, sources, result.final_triangles, "final")


def reconstruction_initial_ply(result: RegistrationResult, sources: Sources) -> bytes:
    """The initial mesh in 3D as PLY."""
    return _ply(result, sources, result.initial_triangles, "initial")


def reconstruction_glb(result: RegistrationResult, sources: Sources) -> bytes:
    """Both meshes in 3D as binary glTF: scene 0 (the default) the final mesh, scene 1 the
    initial one, over the same vertices, textured with the reference image (reduced to
    :data:`TEXTURE_SIDE`) when it is given.

    glTF's frame is y up: the positions of :func:`reconstruction_ply` with y and z negated
    (a half-turn about x), in pixels.
    """
    rec = reconstruction(result)
    positions = _positions(rec) * np.array([1.0, -1.0, -1.0])
    width, height = result.reference_size
    uv = (np.asarray(result.reference_vertices) + 0.5) / np.array([width, height])
    texture = None
    if sources.reference is not None:
        small = render.to_display(sources.reference, render.fit((width, height), TEXTURE_SIDE))
        ok, jpeg = cv2.imencode(".jpg", small, [cv2.IMWRITE_JPEG_QUALITY, 90])
        if not ok:
            raise ValueError("the texture could not be encoded")
        texture = jpeg.tobytes()
    return encode_glb(
        positions,
        [("final", result.final_triangles), ("initial", result.initial_triangles)],
        texcoords=uv, texture=texture,
    )
