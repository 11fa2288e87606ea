"""Affine 3D reconstruction of the mesh vertices from the two views (the paper's figure 13).

Tomasi and Kanade's factorization: the centred 4xN measurement matrix of the conjugate points
(reference x and y, moving x and y) has rank 3 when both cameras are affine (orthographic,
weak-perspective or para-perspective: the scene's depth range small against its distance to the
cameras). One SVD splits it into the two cameras (4x3) and the points (3xN). The result is the
*unscaled affine* reconstruction: the true scene is any affine transform of it (the ambiguity
two uncalibrated affine views cannot resolve), and it is only meaningful when the cameras are far
from the scene; a planar scene comes out flat.

Coordinates: image points in pixels, x right, y down, (0, 0) the centre of the top-left pixel.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class AffineReconstruction:
    """Points in 3D and the affine cameras that project them onto both images.

    Attributes
    ----------
    points : ndarray, shape (N, 3)
        Reconstructed vertices. The frame is fixed (one choice within the affine ambiguity) so
        that x and y are the reference image's axes in pixels, from the fitted points' centroid
        (``points[:, :2] + offsets[:2]`` is the reference position, up to the residual), and
        z the remaining direction (its scale and its shear with x, y are arbitrary; it is
        scaled so that its spread is to the x, y spread as the third singular value's square
        root is to the first's).
    cameras : ndarray, shape (4, 3)
        Rows 0-1 project onto the reference (``[[1, 0, 0], [0, 1, 0]]`` in this frame), rows
        2-3 onto the moving image: ``image = cameras @ point + offsets``.
    offsets : ndarray, shape (4,)
        Image position of the frame's origin (the centroid of the fitted points).
    singular_values : ndarray, shape (4,)
        Of the centred measurement matrix of the fitted points. The fourth measures how far the
        pairs are from any pair of affine cameras (0 for exact affine views).
    residual : float
        Root mean square distance (pixels) between the fitted points' measured positions and
        their reprojections, over the four image coordinates.
    """

    points: np.ndarray
    cameras: np.ndarray
    offsets: np.ndarray
    singular_values: np.ndarray
    residual: float

    def project(self, points: np.ndarray | None = None) -> np.ndarray:
        """``(N, 4)`` image coordinates (reference x, y, moving x, y) of ``points`` (default:
        the reconstructed ones)."""
        pts = self.points if points is None else np.asarray(points, dtype=np.float64)
        return pts @ self.cameras.T + self.offsets


def affine_reconstruction(
    reference_points: np.ndarray,
    moving_points: np.ndarray,
    *,
    fitted: np.ndarray | None = None,
) -> AffineReconstruction:
    """Unscaled affine reconstruction of conjugate points by factorization (rank 3 SVD).

    Parameters
    ----------
    reference_points, moving_points : ndarray, shape (N, 2)
        Conjugate points in pixels.
    fitted : ndarray of bool, shape (N,), optional
        Points the cameras are fitted to (default: all). The others (e.g. border vertices
        extrapolated rather than measured) are placed by least squares through those cameras.

    Returns
    -------
    AffineReconstruction

    Raises
    ------
    ValueError
        Fewer than 4 fitted points, or shapes that do not match.
    """
    ref = np.asarray(reference_points, dtype=np.float64)
    mov = np.asarray(moving_points, dtype=np.float64)
    if ref.ndim != 2 or ref.shape[1:] != (2,) or mov.shape != ref.shape:
        raise ValueError(f"expected two (N, 2) arrays, got {ref.shape} and {mov.shape}")
    measured = np.concatenate([ref, mov], axis=1)  # (N, 4)
    mask = np.ones(len(ref), bool) if fitted is None else np.asarray(fitted, bool)
    if mask.shape != (len(ref),) or mask.sum() < 4:
        raise ValueError("the factorization needs at least 4 fitted points")
    offsets = measured[mask].mean(axis=0)
    w = (measured[mask] - offsets).T  # the centred 4xN measurement matrix
    u, s, vt = np.linalg.svd(w, full_matrices=False)
    motion = u[:, :3] * np.sqrt(s[:3])  # (4, 3); the shape, sqrt(s) vt, is solved for below

    # Fix the ambiguity so that the reference camera is the identity on x, y: B maps the SVD
    # frame to one whose first two axes are the reference's rows, the third orthogonal to them.
    ref_rows = motion[:2]
    normal = np.cross(ref_rows[0], ref_rows[1])
    if np.linalg.norm(normal) < 1e-12 * max(np.linalg.norm(ref_rows), 1e-300):
        raise ValueError("the reference points are degenerate (collinear)")
    normal /= np.linalg.norm(normal)
    cameras = motion @ np.linalg.inv(np.vstack([ref_rows, normal]))
    cameras[:2] = np.eye(2, 3)  # exact, instead of within rounding
    # Every point, fitted or not, by least squares through the cameras.
    points = np.linalg.lstsq(cameras, (measured - offsets).T, rcond=None)[0].T
    # Scale z so that its spread is to the x, y spread as the third singular value's share of
    # the shape is to the first's: a relief drawn at a readable size, flat for a planar scene.
    spread = np.std(points[mask, 2])
    if spread > 0:
        k = np.sqrt(s[2] / s[0]) * np.std(points[mask, :2], axis=0).mean() / spread
        points[:, 2] *= k
        cameras[:, 2] /= k
    reprojected = points[mask] @ cameras.T + offsets
    residual = float(np.sqrt(np.mean((reprojected - measured[mask]) ** 2)))
    return AffineReconstruction(points, cameras, offsets, s, residual)
