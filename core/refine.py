"""Vertex insertion guided by the current piecewise map.

A mesh over a few hundred matched points leaves large triangles whose affine map is off where
the scene bends inside them, and the edge swaps cannot move a vertex or add one. Once a mesh
exists, the moving image resampled by it (the *registered* image) differs from the reference
only by the mesh's residual error: a small motion, which a dense optical flow (OpenCV's DIS)
measures well even on wide-baseline pairs where it fails on the raw images. Corners of the
reference away from the vertices, where that residual flow is consistent forward and backward
and the correlation check of :func:`core.reliability.uniqueness` confirms it, become new
conjugate pairs; those whose correction is large must also raise the mutual information of the
triangle they split (an occlusion fools the flow, not the joint histogram). The pipeline then
builds the mesh again over the old and the new pairs.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from pwlreg.core.optimize import gain_thresholds
from pwlreg.core.reliability import uniqueness
from pwlreg.core.similarity import ScoringImages, mutual_information, triangle_statistics
from pwlreg.core.warp import piecewise_map

#: Longer side (pixels) of the level the residual flow is measured on.
REFINE_SIDE = 2048

#: Largest forward-backward disagreement (pixels of the level) of the residual flow.
FB_PX = 0.5

#: Corrections up to this many pixels are taken on the correlation check alone; larger ones
#: must also raise the mutual information of the triangle they split.
SMALL_PX = 1.5

#: Smallest distance of a new pair to a vertex, and between new pairs, as a share of the mean
#: vertex spacing: closer ones would make slivers that the small-triangle rule removes (holes).
MIN_SPACING = 0.5


@dataclass(frozen=True)
class Insertion:
    """New conjugate pairs found by :func:`guided_pairs`.

    Attributes
    ----------
    reference, moving : ndarray, shape (K, 2)
        The new pairs (pixels).
    counts : dict of str to int
        ``candidates`` (corners away from the vertices, inside the mesh), ``consistent``
        (forward-backward), ``unique`` (correlation check), ``inserted``; ``rejected by mi``
        the large corrections the mutual information did not confirm.
    """

    reference: np.ndarray
    moving: np.ndarray
    counts: dict[str, int]


def _level(image: np.ndarray, halvings: int) -> np.ndarray:
    for _ in range(halvings):
        image = cv2.pyrDown(image)
    return image


def _to_level(points: np.ndarray, scale: float) -> np.ndarray:
    return (points + 0.5) * scale - 0.5


def _from_level(points: np.ndarray, scale: float) -> np.ndarray:
    return (points + 0.5) / scale - 0.5


def _sample(image: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Bilinear samples of a float32 image at ``(K, 2)`` points (pixels)."""
    xy = points.astype(np.float32)
    return cv2.remap(image, xy[:, 0:1], xy[:, 1:2], cv2.INTER_LINEAR).ravel().astype(np.float64)


def guided_pairs(
    reference_gray: np.ndarray,
    moving_gray: np.ndarray,
    reference_vertices: np.ndarray,
    moving_vertices: np.ndarray,
    triangles: np.ndarray,
    images: ScoringImages,
    *,
    measured: int,
    budget: int,
    epsilon: float,
    epsilon_pixels: float,
) -> Insertion:
    """New conjugate pairs from the residual flow of the registered image.

    Everything but the mutual-information test runs on a level of both images at most
    :data:`REFINE_SIDE` pixels wide, so time and memory do not grow with the rasters.

    Parameters
    ----------
    reference_gray, moving_gray : ndarray of uint8
        Grey images.
    reference_vertices, moving_vertices : ndarray, shape (N, 2)
        The mesh's vertices (pixels).
    triangles : ndarray, shape (T, 3)
        The mesh.
    images : ScoringImages
        For the mutual-information test of large corrections (full resolution).
    measured : int
        Number of measured (not extrapolated) vertices: sets the spacing.
    budget : int
        Most new pairs returned (the largest corrections first).
    epsilon, epsilon_pixels : float
        The swaps' gain threshold (:func:`core.optimize.gain_thresholds`), used for the
        triangles split by large corrections.

    Returns
    -------
    Insertion
    """
    counts = {"candidates": 0, "consistent": 0, "unique": 0, "rejected by mi": 0, "inserted": 0}
    empty = Insertion(np.zeros((0, 2)), np.zeros((0, 2)), counts)
    if budget <= 0:
        return empty
    h, w = reference_gray.shape
    halvings = 0
    while max(h, w) / 2**halvings > REFINE_SIDE:
        halvings += 1
    scale = 0.5**halvings
    ref_l = _level(reference_gray, halvings)
    mov_l = _level(moving_gray, halvings)
    ref_v = np.asarray(reference_vertices, dtype=np.float64)
    mov_v = np.asarray(moving_vertices, dtype=np.float64)
    tris = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    # The map of the level's reference grid into the level's moving image: the same mesh.
    map_x, map_y, label = piecewise_map(_to_level(ref_v, scale), _to_level(mov_v, scale), tris,
                                        ref_l.shape)
    inside = label >= 0
    map_x = np.where(inside, map_x, -1.0).astype(np.float32)
    map_y = np.where(inside, map_y, -1.0).astype(np.float32)
    registered = cv2.remap(mov_l, map_x, map_y, cv2.INTER_LINEAR,
                           borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    forward = dis.calc(ref_l, registered, None)
    backward = dis.calc(registered, ref_l, None)

    spacing = np.sqrt(h * w / max(measured, 1)) * scale  # pixels of the level
    corners = cv2.goodFeaturesToTrack(ref_l, int(4 * max(measured, 1)), 0.01,
                                      max(spacing * MIN_SPACING, 2.0))
    if corners is None:
        return empty
    points = corners.reshape(-1, 2).astype(np.float64)
    far, _ = cKDTree(_to_level(ref_v, scale)).query(points)
    lh, lw = ref_l.shape
    cells = np.clip(np.rint(points).astype(np.int64), 0, [lw - 1, lh - 1])
    points = points[(far > spacing * MIN_SPACING) & inside[cells[:, 1], cells[:, 0]]]
    counts["candidates"] = len(points)
    if not len(points):
        return empty

    fwd = np.column_stack([_sample(forward[..., k], points) for k in (0, 1)])
    back = np.column_stack([_sample(backward[..., k], points + fwd) for k in (0, 1)])
    consistent = np.hypot(*(fwd + back).T) < FB_PX
    points, residual = points[consistent], fwd[consistent]
    counts["consistent"] = len(points)
    if not len(points):
        return empty

    # The registered image is the moving one seen through the mesh: the correlation check
    # compares patches with almost no distortion there.
    target = points + residual
    check = uniqueness(ref_l, registered, points, target, None)
    points, target, residual = points[check.ok], target[check.ok], residual[check.ok]
    counts["unique"] = len(points)
    if not len(points):
        return empty
    moving = np.column_stack([_sample(map_x, target), _sample(map_y, target)])
    mapped = moving[:, 0] >= 0  # the corrected point still falls inside the mesh
    reference = _from_level(points, scale)
    moving = _from_level(moving, scale)
    size = np.hypot(*residual.T) / scale  # pixels of the reference

    large = mapped & (size > SMALL_PX)
    if large.any():
        confirmed = _raises_mi(images, ref_v, mov_v, tris, reference[large], moving[large],
                               epsilon=epsilon, epsilon_pixels=epsilon_pixels)
        counts["rejected by mi"] = int((~confirmed).sum())
        mapped[np.flatnonzero(large)[~confirmed]] = False
    order = np.argsort(size[mapped])[::-1]  # largest corrections first
    chosen = np.flatnonzero(mapped)[order][:budget]
    counts["inserted"] = len(chosen)
    return Insertion(reference[chosen], moving[chosen], counts)


def _raises_mi(
    images: ScoringImages,
    ref_v: np.ndarray,
    mov_v: np.ndarray,
    tris: np.ndarray,
    points: np.ndarray,
    moving: np.ndarray,
    *,
    epsilon: float,
    epsilon_pixels: float,
) -> np.ndarray:
    """Whether splitting each point's triangle at it raises that triangle's NMI enough (a
    point in no triangle is not confirmed)."""
    owner_index = _containing(ref_v, tris, points)
    found = owner_index >= 0
    owner = tris[np.maximum(owner_index, 0)]  # (K, 3)
    k = len(points)
    ref_tri = ref_v[owner]
    mov_tri = mov_v[owner]
    # Split (a, b, c) at p into (p, b, c), (a, p, c), (a, b, p): the same pixels as the whole.
    split_ref = np.repeat(ref_tri[:, None], 3, axis=1).copy()
    split_mov = np.repeat(mov_tri[:, None], 3, axis=1).copy()
    for corner in range(3):
        split_ref[:, corner, corner] = points
        split_mov[:, corner, corner] = moving
    whole, _ = triangle_statistics(images, ref_tri, mov_tri)
    parts, _ = triangle_statistics(images, split_ref.reshape(-1, 3, 2),
                                   split_mov.reshape(-1, 3, 2))
    parts = parts.reshape(k, 3, -1).sum(axis=1)
    before = mutual_information(whole, images.bins)[1]
    after = mutual_information(parts, images.bins)[1]
    pixels = whole.sum(axis=1).astype(np.float64)
    return found & ((after - before) > gain_thresholds(pixels, epsilon, epsilon_pixels))


def _containing(vertices: np.ndarray, tris: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Index of a triangle containing each point (barycentric test), -1 for none."""
    a, b, c = (vertices[tris[:, k]] for k in range(3))
    out = np.full(len(points), -1, dtype=np.int64)
    for n, p in enumerate(points):
        v0, v1, v2 = c - a, b - a, p - a
        d00 = (v0 * v0).sum(1)
        d01 = (v0 * v1).sum(1)
        d11 = (v1 * v1).sum(1)
        d20 = (v2 * v0).sum(1)
        d21 = (v2 * v1).sum(1)
        den = d00 * d11 - d01 * d01
        with np.errstate(divide="ignore", invalid="ignore"):
            u = (d11 * d20 - d01 * d21) / den
            v = (d00 * d21 - d01 * d20) / den
        hit = np.flatnonzero((u >= 0) & (v >= 0) & (u + v <= 1))
        if len(hit):
            out[n] = hit[0]
    return out
