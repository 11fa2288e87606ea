"""Vertices on the border of the reference frame, so that the mesh covers all of it.

The matched points cover only their convex hull: 61-77 % of the frame on the real pairs. With
``extent="frame"`` the pipeline adds vertices along the four sides of the reference frame whose
moving positions are extrapolated from the nearby pairs, and marks them so: nothing was measured
there, and the quality verdict counts that area apart.

Conventions: point arrays ``(N, 2)`` float64 pixels, x right, y down, (0, 0) the centre of the
top-left pixel; the frame of a ``(H, W)`` image is ``[-0.5, W - 0.5] x [-0.5, H - 0.5]``.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from scipy.spatial import Delaunay, cKDTree

from pwlreg.core.kernels import affine_fits
from pwlreg.core.similarity import (
    ScoringImages,
    from_level,
    group_statistics,
    mutual_information,
    to_level,
)

#: Pairs the local model of a border vertex is fitted to.
NEIGHBOURS = 12


def border_positions(shape: tuple[int, int], spacing: float) -> np.ndarray:
    """Points along the four sides of the frame, corners included, about ``spacing`` apart.

    Parameters
    ----------
    shape : (int, int)
        ``(height, width)`` of the reference image.
    spacing : float
        Target distance between consecutive points, pixels.

    Returns
    -------
    ndarray, shape (M, 2)
        Corners first, then the inner points of each side.
    """
    h, w = int(shape[0]), int(shape[1])
    x0, y0, x1, y1 = -0.5, -0.5, w - 0.5, h - 0.5
    pts = [[x0, y0], [x1, y0], [x1, y1], [x0, y1]]
    for (ax, ay), (bx, by) in (((x0, y0), (x1, y0)), ((x1, y0), (x1, y1)),
                               ((x1, y1), (x0, y1)), ((x0, y1), (x0, y0))):
        n = max(1, math.ceil(math.hypot(bx - ax, by - ay) / spacing))
        t = np.arange(1, n) / n
        pts.extend(np.column_stack([ax + t * (bx - ax), ay + t * (by - ay)]).tolist())
    return np.asarray(pts, dtype=np.float64)


def local_affine_extrapolation(
    reference: np.ndarray, moving: np.ndarray, targets: np.ndarray, *, k: int = NEIGHBOURS
) -> np.ndarray:
    """Moving positions of ``targets`` from affine maps fitted to their nearest pairs.

    Each target gets its own affine map reference -> moving, a least-squares fit to its ``k``
    nearest pairs weighted by ``1 / (d^2 + r^2)`` (``d`` the distance to the target, ``r`` the
    median of those distances), trimmed once of the pairs it misses by more than three times
    the median miss: the nearest part of the scene decides, one wrong pair does not.

    Parameters
    ----------
    reference, moving : ndarray, shape (N, 2)
        Measured pairs (at least 3, not all collinear).
    targets : ndarray, shape (M, 2)
        Reference positions to extrapolate to.
    k : int
        Pairs per fit.

    Returns
    -------
    ndarray, shape (M, 2)
    """
    ref = np.asarray(reference, dtype=np.float64).reshape(-1, 2)
    mov = np.asarray(moving, dtype=np.float64).reshape(-1, 2)
    tgt = np.asarray(targets, dtype=np.float64).reshape(-1, 2)
    kk = min(k, len(ref))
    dist, nb = cKDTree(ref).query(tgt, kk)
    dist, nb = dist.reshape(len(tgt), kk), nb.reshape(len(tgt), kk)
    scale = np.median(dist, axis=1, keepdims=True) + 1e-9
    weight = scale**2 / (dist**2 + scale**2)
    offsets = (ref[nb] - tgt[:, None, :]) / scale[:, :, None]
    Y = mov[nb]
    A = affine_fits(offsets, Y, weight, 1e-9)
    miss = np.linalg.norm(np.matmul(offsets, A[:, :2]) + A[:, 2:] - Y, axis=2)
    limit = 3.0 * np.median(miss, axis=1, keepdims=True) + 0.5
    A = affine_fits(offsets, Y, np.where(miss <= limit, weight, 0.0), 1e-9)
    # The target sits at the origin of its own fit: its position is the constant term.
    return A[:, 2, :]


def frame_vertices(
    reference: np.ndarray,
    moving: np.ndarray,
    shape: tuple[int, int],
    *,
    spacing: float | None = None,
    images: ScoringImages | None = None,
    scale: float = 1.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Border vertices of the reference frame and their extrapolated moving positions.

    Parameters
    ----------
    reference, moving : ndarray, shape (N, 2)
        The measured pairs (at least 3).
    shape : (int, int)
        ``(height, width)`` of the reference image.
    spacing : float, optional
        Distance between border vertices, pixels. By default twice the median distance between
        neighbouring measured points, within 1/16 and 1/4 of the shorter side: as dense as the
        mesh near the border, without slivers.
    images : ScoringImages, optional
        With the images, each border vertex takes the candidate of
        :func:`choose_by_agreement` (the local affine extrapolation or the pairs' global
        homography); without them, the local affine extrapolation. They may be reduced by
        ``scale`` (:func:`core.similarity.reduced`).
    scale : float
        Scale of ``images`` against the pixels of the points.

    Returns
    -------
    reference_border, moving_border : ndarray, shape (M, 2)
        Border vertices closer than a quarter of ``spacing`` to a measured point are left out
        (the measured point is a better vertex), the four corners never.
    """
    ref = np.asarray(reference, dtype=np.float64).reshape(-1, 2)
    mov = np.asarray(moving, dtype=np.float64).reshape(-1, 2)
    short = float(min(shape[0], shape[1]))
    tree = cKDTree(ref)
    if spacing is None:
        nn = tree.query(ref, 2)[0][:, 1] if len(ref) > 1 else np.array([short])
        spacing = float(np.clip(2.0 * np.median(nn), short / 16, short / 4))
    border = border_positions(shape, spacing)
    near = tree.query(border, 1)[0] < 0.25 * spacing
    near[:4] = False
    border = border[~near]
    candidates = extrapolations(ref, mov, border)
    if images is None or len(candidates) == 1:
        return border, candidates[0]

    chosen = choose_by_agreement(
        images, *(to_level(p, scale) for p in (ref, mov, border, candidates)))
    return border, from_level(chosen, scale)


def extrapolations(reference: np.ndarray, moving: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """Moving positions of ``targets`` extrapolated from the pairs: by
    :func:`local_affine_extrapolation`, then (when it can be fitted and maps every target in
    front of the camera) by the pairs' robust global homography.

    Returns
    -------
    ndarray, shape (C, M, 2)
        ``C`` (1 or 2) candidates for each of the ``M`` targets.
    """
    candidates = [local_affine_extrapolation(reference, moving, targets)]
    H = _global_homography(reference, moving)
    if H is not None:
        q = targets @ H[:, :2].T + H[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            mapped = q[:, :2] / q[:, 2:3]
        if np.all(np.isfinite(mapped)) and np.all(q[:, 2] > 0):
            candidates.append(mapped)
    return np.stack(candidates)


def _global_homography(reference: np.ndarray, moving: np.ndarray) -> np.ndarray | None:
    """Robust homography of all pairs (the dominant plane), or None."""
    if len(reference) < 8:
        return None
    H, mask = cv2.findHomography(reference, moving, cv2.USAC_MAGSAC, 3.0)
    if H is None or mask is None or int(mask.sum()) < 8:
        return None
    return H / H[2, 2]


def choose_by_agreement(
    images: ScoringImages,
    reference: np.ndarray,
    moving: np.ndarray,
    border: np.ndarray,
    candidates: np.ndarray,
) -> np.ndarray:
    """For each border vertex, the candidate position under which the images agree best.

    The frame's vertices (measured pairs, then border vertices at their first candidate) are
    Delaunay-triangulated; each border vertex then takes the candidate that maximises the
    mutual information of the pixels of its incident triangles, the other vertices held
    where they are. Extrapolation from the nearest pairs is right where the scene continues
    their surface, a global homography where the border shows the dominant plane (often the
    ground) beyond other surfaces: the images tell which.

    Parameters
    ----------
    images : ScoringImages
    reference, moving : ndarray, shape (N, 2)
        Measured pairs.
    border : ndarray, shape (M, 2)
        Border vertices (reference image).
    candidates : ndarray, shape (C, M, 2)
        Candidate moving positions of each border vertex.

    Returns
    -------
    ndarray, shape (M, 2)
    """
    n, m = len(reference), len(border)
    ref_all = np.concatenate([reference, border])
    mov_all = np.concatenate([moving, candidates[0]])
    tris = Delaunay(ref_all).simplices
    # Where the candidates agree within a pixel there is nothing to choose.
    spread = np.linalg.norm(candidates - candidates[:1], axis=2).max(axis=0)
    chosen = n + np.flatnonzero(spread > 1.0)
    # Every (triangle, border vertex) incidence, in any order: the histograms are summed in
    # integers, exactly.
    slot = np.full(n + m, -1)
    slot[chosen] = np.arange(len(chosen))
    hit = slot[tris]
    t_idx, corner = np.nonzero(hit >= 0)
    s_idx = hit[t_idx, corner]
    if not len(t_idx):
        return candidates[0]
    corners = tris[t_idx]
    moved = corners == chosen[s_idx, None]  # one corner of each row
    ref_tris = [ref_all[corners]] * len(candidates)
    mov_tris, rows = [], []
    for c in range(len(candidates)):
        mov_c = mov_all[corners]
        mov_c[moved] = candidates[c, chosen[s_idx] - n]
        mov_tris.append(mov_c)
        rows.append(c * m + chosen[s_idx] - n)
    summed, _ = group_statistics(images, np.concatenate(ref_tris), np.concatenate(mov_tris),
                                 np.concatenate(rows), len(candidates) * m)
    mi, _ = mutual_information(summed, images.bins)
    best = np.argmax(mi.reshape(len(candidates), m), axis=0)
    return candidates[best, np.arange(m)]
