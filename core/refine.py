"""Vertex insertion guided by the current piecewise map.

A mesh over a few hundred matched points leaves large triangles whose affine map is off where
the scene bends inside them, and the edge swaps cannot move a vertex or add one. Once a mesh
exists, the moving image resampled by it (the *registered* image) differs from the reference
only by the mesh's residual error: a small motion, which a dense optical flow (OpenCV's DIS)
measures well even on wide-baseline pairs where it fails on the raw images. Corners of the
reference away from the vertices, where that residual flow is consistent forward and backward
and the correlation check of :func:`core.reliability.uniqueness` confirms it, become new
conjugate pairs; those whose correction is large must also raise the mutual information of the
triangle they split (an occlusion fools the flow, not the joint histogram).

Where the mesh is far off (a triangle across a depth step, or a wide baseline that left few
pairs) the flow fails its forward-backward test; :func:`epipolar_pairs` searches for corners
along their epipolar lines instead, first on the first mesh (the flow then reads the mesh it
corrected) and again after the flow. Where the residual flow jumps, a depth step
crosses a triangle whose affine map follows neither surface; :func:`step_points` puts
candidates on both sides of the jump, searched for along their lines too. The pipeline builds
the mesh again over the old and the new pairs.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import cv2
import numpy as np
from scipy.spatial import cKDTree

from pwlreg.core.epipolar import (
    EpipolarModel,
    epipolar_lines,
    line_direction,
    line_foot,
    on_level,
)
from pwlreg.core.flow import residual_flows
from pwlreg.core.kernels import containing, spaced, strip_correlation, window_fits
from pwlreg.core.optimize import gain_thresholds
from pwlreg.core.raster import affine_maps, cross_fixed, fixed_point
from pwlreg.core.reliability import (
    SCENE_MOTION_PX,
    check_scales,
    fixed_in_frame,
    neighbour_outliers,
    uniqueness,
    unjudged_pairs,
)
from pwlreg.core.similarity import (
    ScoringImages,
    from_level,
    group_statistics,
    mutual_information,
    to_level,
    triangle_statistics,
)
from pwlreg.core.warp import piecewise_map

#: Longer side (pixels) of the level the residual flow is measured on.
REFINE_SIDE = 2048

#: Largest forward-backward disagreement (pixels of the level) of the residual flow.
FB_PX = 0.5

#: Weakest candidate corner, as a share of the strongest one's minimal eigenvalue (OpenCV's
#: ``qualityLevel``). The checks after it judge a candidate, not its strength: at 0.01 the
#: candidates crowded on the strongest texture and left large triangles elsewhere (Middlebury,
#: automatic, extent=hull: mean endpoint error 1.08 px; 0.88 px at 0.001).
CORNER_QUALITY = 0.001

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
        (forward-backward), ``checked`` (of those, the largest corrections the budget reached),
        ``unique`` (correlation check), ``inserted``; ``rejected by mi`` the large corrections
        the mutual information did not confirm.
    """

    reference: np.ndarray
    moving: np.ndarray
    counts: dict[str, int]


@dataclass(frozen=True)
class Levels:
    """Both grey images reduced to at most :data:`REFINE_SIDE` pixels (:func:`levels`), so
    time and memory of the insertion do not grow with the rasters.

    Attributes
    ----------
    scale : float
        Level pixels per image pixel (a power of one half).
    reference, moving : ndarray of uint8
        The levels.
    shape : (int, int)
        ``(height, width)`` of the full reference image.
    corners : ndarray, shape (K, 2)
        Candidate corners of the reference level (pixels of the level), strongest first
        (:func:`corner_candidates`); each source thins them to its own spacing
        (:func:`_corners`).
    """

    scale: float
    reference: np.ndarray
    moving: np.ndarray
    shape: tuple[int, int]
    corners: np.ndarray


def levels(reference_gray: np.ndarray, moving_gray: np.ndarray) -> Levels:
    """The :class:`Levels` of two grey uint8 images (halved together while the reference is
    wider than :data:`REFINE_SIDE`), with the reference level's candidate corners."""
    ref, mov = reference_gray, moving_gray
    scale = 1.0
    while max(ref.shape) * scale > REFINE_SIDE:
        ref, mov, scale = cv2.pyrDown(ref), cv2.pyrDown(mov), scale / 2
    return Levels(scale, ref, mov, reference_gray.shape[:2], corner_candidates(ref))


def corner_candidates(image: np.ndarray, *, quality: float = CORNER_QUALITY) -> np.ndarray:
    """Every candidate corner of OpenCV's ``goodFeaturesToTrack`` (minimum-eigenvalue response,
    3x3 blocks) on a grey uint8 ``image``, in its order: ``(K, 2)`` pixels, strongest first.

    Thinned greedily to a spacing (:func:`core.kernels.spaced`) they are exactly OpenCV's
    corners at that spacing, so one detection serves both insertion sources and both rounds.
    Calling OpenCV uncapped at 2 px cost 16 ms on a 1024x768 level, almost all of it in
    spacing 47 000 corners that each source thins again; this costs 6 ms.
    """
    eig = cv2.cornerMinEigenVal(image, 3)
    strongest = cv2.minMaxLoc(eig)[1]
    eig = cv2.threshold(eig, strongest * quality, 0, cv2.THRESH_TOZERO)[1]
    peak = (eig == cv2.dilate(eig, None)) & (eig > 0)
    peak[[0, -1], :] = False  # OpenCV leaves out the outermost pixels
    peak[:, [0, -1]] = False
    flat = np.flatnonzero(peak)
    # Strongest first, equal responses by decreasing address as OpenCV sorts them: one sort of
    # unique 64-bit keys (a non-negative float32's bits order like its value).
    keys = (eig.ravel()[flat].view(np.int32).astype(np.int64) << 32) | flat
    order = np.sort(keys)[::-1] & 0xFFFFFFFF
    width = image.shape[1]
    return np.column_stack([order % width, order // width]).astype(np.float64)


def _min_distance(shape: tuple[int, ...], scale: float, vertices: int) -> float:
    """Smallest distance (pixels of the level) between candidate corners for a mesh of
    ``vertices`` measured vertices over an image of ``shape``: :data:`MIN_SPACING` of their
    mean spacing, at least 2."""
    return max(np.sqrt(shape[0] * shape[1] / max(vertices, 1)) * scale * MIN_SPACING, 2.0)


def _corners(image_levels: Levels, vertices: int) -> np.ndarray:
    """The strongest ``4 * vertices`` candidate corners at least :func:`_min_distance` apart,
    chosen greedily from :attr:`Levels.corners` as OpenCV's ``goodFeaturesToTrack`` chooses
    from all its corners."""
    distance = _min_distance(image_levels.shape, image_levels.scale, vertices)
    return image_levels.corners[spaced(image_levels.corners, distance, 4 * max(vertices, 1))]


@dataclass(frozen=True)
class Guide:
    """A mesh seen on the :class:`Levels` (:func:`guide`): what both insertion sources start
    from.

    Attributes
    ----------
    levels : Levels
    reference_vertices, moving_vertices : ndarray, shape (N, 2)
        The mesh's vertices (image pixels, float64).
    triangles : ndarray, shape (T, 3)
    map_x, map_y : ndarray of float32
        Position in the moving level of each reference-level pixel; -1 outside the mesh.
    label : ndarray of int32
        Triangle owning each reference-level pixel, -1 outside the mesh.
    measured : ndarray of bool, shape (N,)
        Per vertex, whether its moving position was measured (not extrapolated to the frame's
        border): new pairs keep their distance from these only.
    """

    levels: Levels
    reference_vertices: np.ndarray
    moving_vertices: np.ndarray
    triangles: np.ndarray
    map_x: np.ndarray
    map_y: np.ndarray
    label: np.ndarray
    measured: np.ndarray

    @cached_property
    def residual(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The registered level (the moving level seen through the mesh, 0 outside it) and
        the residual flows from the reference level to it and back
        (:func:`core.flow.residual_flows`): computed once for every source of a round."""
        registered = cv2.remap(self.levels.moving, self.map_x, self.map_y, cv2.INTER_LINEAR,
                               borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        return (registered, *residual_flows(self.levels.reference, registered))


def guide(
    image_levels: Levels,
    reference_vertices: np.ndarray,
    moving_vertices: np.ndarray,
    triangles: np.ndarray,
    *,
    extrapolated: np.ndarray | None = None,
) -> Guide:
    """The :class:`Guide` of a mesh on ``image_levels``; ``extrapolated`` flags the vertices
    whose moving position was not measured (none by default)."""
    ref_v = np.asarray(reference_vertices, dtype=np.float64)
    mov_v = np.asarray(moving_vertices, dtype=np.float64)
    tris = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    scale = image_levels.scale
    map_x, map_y, label = piecewise_map(to_level(ref_v, scale), to_level(mov_v, scale), tris,
                                        image_levels.reference.shape, dtype=np.float32,
                                        outside=-1.0)
    measured = (np.ones(len(ref_v), bool) if extrapolated is None
                else ~np.asarray(extrapolated, bool))
    return Guide(image_levels, ref_v, mov_v, tris, map_x, map_y, label, measured)


def _sample(image: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Bilinear samples of a float32 image (one channel or more) at ``(K, 2)`` points
    (pixels): ``(K,)`` or ``(K, C)``."""
    xy = points.astype(np.float32)
    out = cv2.remap(image, xy[:, 0:1], xy[:, 1:2], cv2.INTER_LINEAR).astype(np.float64)
    return out.reshape(len(points), -1) if image.ndim == 3 else out.ravel()


def guided_pairs(
    mesh: Guide,
    images: ScoringImages,
    *,
    measured: int,
    budget: int,
    epsilon: float,
    epsilon_pixels: float,
) -> Insertion:
    """New conjugate pairs from the residual flow of the registered image.

    Everything but the mutual-information test runs on the guide's levels.

    Parameters
    ----------
    mesh : Guide
        The current mesh on the levels of the grey images.
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
    counts = {"candidates": 0, "consistent": 0, "checked": 0, "unique": 0,
              "fixed in the frame": 0, "rejected by mi": 0, "inserted": 0}
    empty = Insertion(np.zeros((0, 2)), np.zeros((0, 2)), counts)
    if budget <= 0:
        return empty
    h, w = mesh.levels.shape
    scale, ref_l = mesh.levels.scale, mesh.levels.reference
    ref_v, mov_v, tris = mesh.reference_vertices, mesh.moving_vertices, mesh.triangles
    map_x, map_y, inside = mesh.map_x, mesh.map_y, mesh.label >= 0
    registered, forward, backward = mesh.residual

    spacing = np.sqrt(h * w / max(measured, 1)) * scale  # pixels of the level
    points = _corners(mesh.levels, measured)
    if not len(points):
        return empty
    far, _ = cKDTree(to_level(ref_v[mesh.measured], scale)).query(points)
    lh, lw = ref_l.shape
    cells = np.clip(np.rint(points).astype(np.int64), 0, [lw - 1, lh - 1])
    points = points[(far > spacing * MIN_SPACING) & inside[cells[:, 1], cells[:, 0]]]
    counts["candidates"] = len(points)
    if not len(points):
        return empty

    # Both channels at once: a channel's slice would be copied whole for each call.
    fwd = _sample(forward, points)
    back = _sample(backward, points + fwd)
    consistent = np.hypot(*(fwd + back).T) < FB_PX
    points, residual = points[consistent], fwd[consistent]
    counts["consistent"] = len(points)
    if not len(points):
        return empty

    # The largest corrections are kept first, and each check judges a point alone: checked in
    # that order only as far as the budget reaches, the pairs are those of checking them all
    # (after an epipolar round the flow's budget is often a few dozen of hundreds).
    order = np.argsort(-np.hypot(*residual.T), kind="stable")
    points, residual = points[order], residual[order]
    found: list[Insertion] = []
    start = 0
    # The registered image is the moving one seen through the mesh: the correlation check
    # compares patches with almost no distortion there.
    scales = check_scales(ref_l, registered)
    while start < len(points) and budget > 0:
        part = slice(start, start + 2 * budget)
        start = part.stop
        check = uniqueness(ref_l, registered, points[part], points[part] + residual[part], None,
                           scales=scales)
        counts["unique"] += int(check.ok.sum())
        if not check.ok.any():
            continue
        kept, shift = points[part][check.ok], residual[part][check.ok]
        target = kept + shift
        moving = np.column_stack([_sample(map_x, target), _sample(map_y, target)])
        before = np.column_stack([_sample(map_x, kept), _sample(map_y, kept)])
        mapped = moving[:, 0] >= 0  # the corrected point still falls inside the mesh
        size = np.hypot(*shift.T) / scale  # pixels of the reference
        found.append(_chosen(images, ref_v, mov_v, tris, from_level(kept, scale),
                             from_level(moving, scale), from_level(before, scale), size, mapped,
                             {}, budget=budget, epsilon=epsilon,
                             epsilon_pixels=epsilon_pixels))
        budget -= len(found[-1].reference)
    counts["checked"] = min(start, len(points))
    if not found:
        return empty
    for one in found:
        counts["fixed in the frame"] += one.counts["fixed in the frame"]
        counts["rejected by mi"] += one.counts.get("rejected by mi", 0)
        counts["inserted"] += one.counts["inserted"]
    return Insertion(np.concatenate([f.reference for f in found]),
                     np.concatenate([f.moving for f in found]), counts)


def _chosen(
    images: ScoringImages,
    ref_v: np.ndarray,
    mov_v: np.ndarray,
    tris: np.ndarray,
    reference: np.ndarray,
    moving: np.ndarray,
    predicted: np.ndarray,
    size: np.ndarray,
    ok: np.ndarray,
    counts: dict[str, int],
    *,
    budget: int,
    epsilon: float,
    epsilon_pixels: float,
) -> Insertion:
    """The last step of both sources: the candidate pairs ``ok`` that stay at their pixel
    where the mesh (``predicted``, its moving positions) moves them, inside a triangle whose
    every vertex moves, are fixed in the frame (:func:`core.reliability.fixed_in_frame`) and
    dropped; those whose correction ``size`` exceeds :data:`SMALL_PX` must raise the mutual
    information of the triangle they split; then the ``budget`` largest corrections are kept
    (``counts`` updated)."""
    # Only where the whole triangle moves: beside a part of the scene that stays (the still
    # page of an open book) a still pair is the truth the triangle misses.
    owner = _containing(ref_v, tris, reference)
    motion = np.hypot(*(mov_v - ref_v).T)[tris[np.maximum(owner, 0)]].min(axis=1)
    moves = (owner >= 0) & (motion >= SCENE_MOTION_PX)
    fixed = ok & moves & fixed_in_frame(reference, moving, predicted)
    counts["fixed in the frame"] = int(fixed.sum())
    ok = ok & ~fixed
    large = ok & (size > SMALL_PX)
    if large.any():
        confirmed = _raises_mi(images, ref_v, mov_v, tris, reference[large], moving[large],
                               epsilon=epsilon, epsilon_pixels=epsilon_pixels)
        counts["rejected by mi"] = int((~confirmed).sum())
        ok[np.flatnonzero(large)[~confirmed]] = False
    chosen = np.flatnonzero(ok)[np.argsort(size[ok])[::-1]][:budget]  # largest first
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
    # Several points often split one large triangle: its histogram once.
    _, first, each = np.unique(owner_index, return_index=True, return_inverse=True)
    whole, _ = triangle_statistics(images, ref_tri[first], mov_tri[first])
    parts, _ = group_statistics(images, split_ref.reshape(-1, 3, 2),
                                split_mov.reshape(-1, 3, 2), np.repeat(np.arange(k), 3), k)
    whole = whole[each.ravel()]
    before = mutual_information(whole, images.bins)[1]
    after = mutual_information(parts, images.bins)[1]
    pixels = whole.sum(axis=1).astype(np.float64)
    return found & ((after - before) > gain_thresholds(pixels, epsilon, epsilon_pixels))


def _containing(vertices: np.ndarray, tris: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Index of a triangle containing each point (barycentric test; the first in ``tris``
    order), -1 for none (:func:`core.kernels.containing`)."""
    out = np.empty(len(points), dtype=np.int64)
    containing(np.ascontiguousarray(vertices, dtype=np.float64),
               np.ascontiguousarray(tris, dtype=np.int64).reshape(-1, 3),
               np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 2), out)
    return out


#: Half side (pixels of the level) of the patches compared along the epipolar line.
EPI_HALF = 6

#: Smallest zero-mean normalized correlation of an epipolar match.
EPI_NCC = 0.8

#: A second correlation peak along the line this close to the best (ratio) makes a match
#: ambiguous (repeated texture).
EPI_AMBIGUITY = 0.9

#: Distance to the line (pixels of the level) searched on each side around the best match on
#: the line: the epipolar geometry of a few hundred pairs is off by about a pixel away from them.
EPI_BAND = 2

#: Largest lead (correlation) of the best match off the line over the best on it for which
#: the one on the line is taken. An edge crossing the line correlates as well all along
#: itself, and the band searched across the line let the best slide along it (stripes crossed
#: at 45 degrees: 1.4 px off, within the band).
EPI_TIE = 0.01

#: Least fall of the correlation along the line on either side of a match's peak,
#: :data:`EPI_FALL` pixels away (or to the end of the final search window). A flatter profile
#: is an edge, whose position along itself the patch does not measure, and the band searched
#: across the line lets the best slide along it (a tiled floor seen at 0.08 px: such matches
#: were 1-2 px off, diagonally, with correlations of 0.99).
EPI_SHARPNESS = 0.06

#: Distance (pixels of the level) from the peak at which its fall is measured. At two pixels
#: the broad peak of a smooth texture (a concrete roof, blurred brick) did not fall enough
#: although its match was right: on an L-shaped building of the trust suite (seed 3), half of
#: the right matches in triangles more than 10 px off fell by less than 0.035 there.
EPI_FALL = 4

#: Largest departure of a triangle's linear map from the typical one around a point (the
#: median of the :data:`EPI_LOCAL_MAPS` triangles nearest to it), relative to the typical
#: map's norm, for its map to shape the patch searched for at the point. On an L-shaped
#: building of the trust suite (seed 5) the patches shaped by the maps of triangles over its
#: depth steps correlated with their right matches for 8 % of the candidates more than 10 px
#: off, unwarped patches for 35 %. One median over the whole mesh served a two-plane scene
#: badly (an open book: neither page's map).
EPI_ODD_MAP = 0.15

#: The rival ratio (:data:`EPI_AMBIGUITY`) a match must stay under when no other pair stands
#: near enough to judge it and none moves like it (:func:`core.reliability.unjudged_pairs`).
#: On the trust suite's scenes of seeds 1, 9, 12 and 14, 131 of the 317 new pairs that the
#: neighbour check could not judge were more than 3 px off their truth (41 %; 2.2 % of those
#: it judged); of such pairs inserted on seeds 1, 3, 6, 9, 12 and 14, 22 of the 43 wrong ones
#: had a rival of 0.8 or more, 56 of the 178 right ones.
EPI_ALONE_AMBIGUITY = 0.8

#: Triangles (nearest centroids) whose maps' median is the typical map around a point.
EPI_LOCAL_MAPS = 6

#: Search margin (pixels of the level) beyond the neighbours' displacements, and the longest
#: segment searched.
EPI_MARGIN, EPI_LONGEST = 8, 192

#: Least reach (pixels of the level) of the search on either side of the mesh's prediction. A
#: surface with no vertex on it (a building whose faces the matcher missed, among pairs on the
#: ground) moves like none of its neighbours: on an L-shaped building of the trust suite
#: (seed 3) its matches lay 37-57 px (median, 90th percentile) from the prediction, beyond the
#: span of the neighbours' displacements for more than half of them. The longer segment also
#: holds more lookalikes, which the rival test (:data:`EPI_AMBIGUITY`) then rejects.
EPI_REACH = 96

#: Candidates searched per pair the budget allows (a search costs; about one in four to ten
#: passes the checks). Three leave the synthetic suite and Middlebury's frame as four did
#: (``python -m bench.beyond``) and search a quarter fewer candidates on a real facade.
EPI_SEARCHED = 3

#: Nearest vertices whose displacements, applied at a point, span its search segment.
EPI_NEIGHBOURS = 8

#: Largest distance (pixels of the level) between a point and where its match's reverse
#: search along the reference's epipolar line lands.
LR_PX = 1.0

#: A jump of the residual flow: its range over 5x5 pixels of the level exceeds this (pixels).
#: Where the mesh is right the flow is nearly constant; a triangle across a depth step maps
#: like neither surface, and the flow that corrects it changes sides at the step.
STEP_JUMP = 1.0
#: Candidates lie this far (pixels of the level) on either side of a jump, across it.
STEP_OFFSET = 6.0
#: Spacing (pixels of the level) of the points along the jumps that candidates are put beside.
STEP_SPACING = 10.0
#: Jumps nearer the mesh's outline (pixels of the level) are the flow's, at the registered
#: image's edge: DIS's medium preset has 8 px patches at its finest scale.
STEP_MARGIN = 8
#: Step candidates searched, per pair of the budget: on a real facade 4-5 % of them became
#: pairs, on Middlebury 15-50 % (most others fail the correlation: a patch over the step).
STEP_SEARCHED = 2
#: Smallest distance (pixels of the level) of a step candidate to a vertex or another candidate:
#: triangles of less than 25 px (``min_triangle_area``) would be removed, leaving holes.
STEP_NEAR = 8.0
#: A step candidate's correlation patch is centred this much farther from the jump (pixels of
#: the level) than the candidate: centred on it, 6 px from a jump the flow locates to a few
#: pixels, the 13 px patch often reached over the step and failed to correlate (Middlebury:
#: 37-54 step pairs at 0, 49-66 at 4, and the frame error 0.841 -> 0.811 px on average).
STEP_WINDOW = 4.0


def step_points(mesh: Guide) -> tuple[np.ndarray, np.ndarray]:
    """Reference points (pixels of the level) on both sides of the jumps of the residual flow,
    the steepest first, and where each one's correlation patch is centred, relative to it.

    Where the flow's range over 5x5 pixels exceeds :data:`STEP_JUMP` (at least
    :data:`STEP_MARGIN` inside the mesh), the steepest pixel of the flow in each square of
    :data:`STEP_SPACING` pixels is a seed, and the seeds are thinned greedily, steepest first,
    to that spacing; each is moved :data:`STEP_OFFSET` both ways along the gradient of the
    flow component that changes more there. Candidates closer than :data:`STEP_NEAR` to one
    chosen before are dropped. The patch of each is centred :data:`STEP_WINDOW` farther from
    the jump, so that it lies on the candidate's side of the step.
    """
    _, forward, _ = mesh.residual
    flows = cv2.split(forward)
    box = np.ones((5, 5), np.uint8)
    jump = np.maximum(*(cv2.dilate(f, box) - cv2.erode(f, box) for f in flows))
    # Not within STEP_MARGIN of the mesh's outline: the registered image is 0 beyond it, and
    # the flow's patches straddling that edge jump too.
    margin = np.ones((2 * STEP_MARGIN + 1,) * 2, np.uint8)
    inside = cv2.erode((mesh.label >= 0).astype(np.uint8), margin, borderValue=1) > 0
    # Within the band the range marks, the step is where the flow changes fastest.
    slope = np.maximum(*(cv2.magnitude(cv2.Sobel(f, cv2.CV_32F, 1, 0),
                                       cv2.Sobel(f, cv2.CV_32F, 0, 1)) for f in flows))
    steep = np.where(inside & (jump > STEP_JUMP), slope, 0.0)
    # The best of each cell first: the greedy thinning then sorts a few thousand pixels, not
    # every pixel of the jumps (tens of thousands on a city).
    cell = int(STEP_SPACING)
    h, w = steep.shape
    blocks = np.pad(steep, ((0, -h % cell), (0, -w % cell)))
    rows, cols = blocks.shape[0] // cell, blocks.shape[1] // cell
    blocks = blocks.reshape(rows, cell, cols, cell).transpose(0, 2, 1, 3).reshape(rows, cols, -1)
    best = blocks.argmax(axis=2)
    value = np.take_along_axis(blocks, best[..., None], axis=2)[..., 0]
    r, c = np.nonzero(value > 0)
    if not len(r):
        return np.zeros((0, 2)), np.zeros((0, 2))
    k = best[r, c]
    seeds = np.column_stack([c * cell + k % cell, r * cell + k // cell]).astype(np.float64)
    seeds = seeds[np.argsort(-value[r, c], kind="stable")]
    seeds = seeds[spaced(seeds, STEP_SPACING, len(seeds))]
    # The flow's gradient by differences 2 px either side of each seed.
    d = np.array([[2.0, 0.0], [0.0, 2.0]])
    grad = np.stack([_sample(forward, seeds + d[a]) - _sample(forward, seeds - d[a])
                     for a in (0, 1)], axis=2)  # (K, component, axis)
    larger = np.hypot(*grad[:, 0].T) >= np.hypot(*grad[:, 1].T)
    across = np.where(larger[:, None], grad[:, 0], grad[:, 1])
    across /= np.maximum(np.hypot(*across.T), 1e-9)[:, None]
    points = np.concatenate([seeds + STEP_OFFSET * across, seeds - STEP_OFFSET * across])
    away = np.concatenate([across, -across])
    kept = spaced(points, STEP_NEAR, len(points))
    return points[kept], STEP_WINDOW * away[kept]


DATA_MARGIN = 8.0
"""Pixels an inserted pair keeps from the images' invalid pixels (:func:`on_the_data`)."""


def clearance(valid: np.ndarray | None) -> np.ndarray | None:
    """Per pixel, its distance to the nearest invalid pixel (``valid`` False), float32; None
    when every pixel is valid."""
    if valid is None:
        return None
    return cv2.distanceTransform(valid.astype(np.uint8), cv2.DIST_L2, 3)


def on_the_data(
    mesh: Guide,
    reference: np.ndarray,
    moving: np.ndarray,
    clearances: tuple[np.ndarray | None, np.ndarray | None],
    *,
    margin: float = DATA_MARGIN,
) -> np.ndarray:
    """Per pair, whether it keeps ``margin`` pixels from the images' invalid pixels: its
    reference point in the reference, and its moving point and where the mesh maps its
    reference point in the moving image.

    Beyond the edge of the data (a transparent or nodata area, filled smoothly) the residual
    flow breaks down as along a depth step, and the searches there find no true match: a
    reference point whose match lies in the moving image's invalid area is matched somewhere
    else (probed: 50-81 px off, with the verdict ``good``).

    Parameters
    ----------
    mesh : Guide
        The mesh the pairs were found on.
    reference, moving : ndarray, shape (K, 2)
        The pairs (image pixels).
    clearances : (ndarray or None, ndarray or None)
        :func:`clearance` of the reference's and the moving image's valid pixels.
    """
    ok = np.ones(len(reference), bool)
    if not len(reference):
        return ok
    ref_clear, mov_clear = clearances
    if ref_clear is not None:
        ok &= _clear_at(ref_clear, reference, margin)
    if mov_clear is not None:
        scale = mesh.levels.scale
        predicted = from_level(_predicted(mesh, to_level(reference, scale)), scale)
        ok &= _clear_at(mov_clear, moving, margin)
        known = np.isfinite(predicted).all(axis=1)
        ok[known] &= _clear_at(mov_clear, predicted[known], margin)
    return ok


def _clear_at(distance: np.ndarray, points: np.ndarray, margin: float) -> np.ndarray:
    """Whether the nearest pixel of each point lies more than ``margin`` from an invalid one
    (a point beyond the image counts as clear: the searches keep inside it)."""
    h, w = distance.shape
    x, y = np.rint(points).astype(np.int64).T
    inside = (x >= 0) & (x < w) & (y >= 0) & (y < h)
    clear = np.ones(len(points), bool)
    clear[inside] = distance[y[inside], x[inside]] > margin
    return clear


def epipolar_pairs(
    mesh: Guide,
    images: ScoringImages,
    model: EpipolarModel,
    *,
    added: tuple[np.ndarray, np.ndarray],
    measured: int,
    budget: int,
    epsilon: float,
    epsilon_pixels: float,
    candidates: tuple[np.ndarray, np.ndarray] | None = None,
) -> Insertion:
    """New conjugate pairs matched along the epipolar lines, guided by the current mesh.

    Where the mesh is far off (a triangle spans a depth step, or a wide baseline left few
    pairs), the residual flow of :func:`guided_pairs` fails its forward-backward test. The
    epipolar geometry still holds there: each reference corner away from the vertices is
    searched for along its epipolar line, over the segment the displacements of its
    neighbouring vertices span (a point of a piecewise-planar scene moves like one of the
    surfaces around it), with a patch shaped by the local affine map of the mesh. A match must
    have no rival peak along the line (repeated texture), correlate well, peak sharply along
    it (:data:`EPI_SHARPNESS`), come back to its point when searched for the other way, lie
    within the model's threshold of the line (and on the matched pairs' plane when they lie on
    one: :meth:`core.epipolar.EpipolarModel.inliers`), not be contradicted by its neighbours
    (nor, where none stands near enough to judge it and none moves like it, have a rival peak
    reaching :data:`EPI_ALONE_AMBIGUITY`), and -- when it corrects the mesh by more than
    :data:`SMALL_PX` -- raise the mutual information of the triangle it splits.

    Parameters
    ----------
    model : EpipolarModel
        The matcher's epipolar geometry (``x_mov^T F x_ref = 0`` in pixels of the full images)
        and its inlier threshold, the largest Sampson distance of a match.
    added : (ndarray, ndarray)
        Pairs ``(reference (K, 2), moving (K, 2))`` already found for this mesh (by
        :func:`guided_pairs`): new pairs keep their distance and they count as neighbours.
    candidates : (ndarray, ndarray), optional
        Reference points ``(C, 2)`` (pixels of the level) to search for instead of the
        corners, in order of preference, and the offsets ``(C, 2)`` of their patches' centres
        (:func:`step_points`): the patch's match, moved back by the local map, is the point's.
        They keep :data:`STEP_NEAR` from every vertex, extrapolated ones included, and from
        the pairs found already, and :data:`STEP_SEARCHED` of them per pair of the budget are
        searched (of the corners, :data:`EPI_SEARCHED`).

    The other parameters are those of :func:`guided_pairs`.

    Returns
    -------
    Insertion
    """
    counts = {"candidates": 0, "unique": 0, "correlated": 0, "peaked": 0, "confirmed": 0,
              "epipolar": 0, "neighbours": 0, "fixed in the frame": 0, "rejected by mi": 0,
              "inserted": 0}
    empty = Insertion(np.zeros((0, 2)), np.zeros((0, 2)), counts)
    if budget <= 0:
        return empty
    h, w = mesh.levels.shape
    scale = mesh.levels.scale
    ref_l = mesh.levels.reference.astype(np.float32)
    mov_l = mesh.levels.moving.astype(np.float32)
    tris = mesh.triangles
    # The vertices and the pairs found already: new pairs keep away from both.
    ref_v = np.concatenate([mesh.reference_vertices, added[0]])
    mov_v = np.concatenate([mesh.moving_vertices, added[1]])
    ref_lv, mov_lv = to_level(ref_v, scale), to_level(mov_v, scale)
    label = mesh.label
    F = on_level(model.matrix, scale)

    # The spacing of the mesh the budget allows: a sparse mesh (a wide baseline) gets
    # candidates at the density it may reach, not at its own.
    spacing = np.sqrt(h * w / (measured + budget)) * scale
    if candidates is None:
        points = _corners(mesh.levels, measured + budget)
        shifts = np.zeros_like(points)
        # Extrapolated border vertices are no measurement: keeping away from them left the
        # strip along the frame's side to extrapolation (Middlebury teddy, whose floor
        # steepens there: frame mean endpoint error 1.51 -> 1.39 px).
        anchors = ref_lv[np.concatenate([mesh.measured, np.ones(len(added[0]), bool)])]
        nearest = spacing * MIN_SPACING
    else:
        # Beside a step the mesh is as dense as it needs to be there, whatever its spacing
        # elsewhere: only slivers are kept away.
        (points, shifts), anchors, nearest = candidates, ref_lv, STEP_NEAR
    if not len(points):
        return empty
    far, _ = cKDTree(anchors).query(points)
    # From here on the patches' centres are searched for; the sites (the new vertices) take
    # their matches at the end.
    sites, points = points, points + shifts
    # The patch needs one pixel more than its half side inside the image.
    lh, lw = ref_l.shape
    edge = EPI_HALF + 1
    inner = ((points[:, 0] >= edge) & (points[:, 0] < lw - edge) & (points[:, 1] >= edge)
             & (points[:, 1] < lh - edge))
    cells = np.clip(np.rint(points).astype(np.int64), 0, [lw - 1, lh - 1])
    owner = label[cells[:, 1], cells[:, 0]]
    at = np.clip(np.rint(sites).astype(np.int64), 0, [lw - 1, lh - 1])
    keep = np.flatnonzero((far > nearest) & inner & (owner >= 0)
                          & (label[at[:, 1], at[:, 0]] >= 0))
    if candidates is None:
        # The farthest from the vertices first (the largest gaps).
        keep = keep[np.argsort(-far[keep], kind="stable")]
    keep = keep[:(EPI_SEARCHED if candidates is None else STEP_SEARCHED) * budget]
    points, owner, sites = points[keep], owner[keep], sites[keep]
    counts["candidates"] = len(points)
    if not len(points):
        return empty

    maps = affine_maps(ref_lv[tris], mov_lv[tris])[:, :, :2]  # (T, 2, 2)
    linear = maps[owner]
    # A triangle over a depth step maps like neither surface: its map would shape the patch
    # wrongly where a new vertex is needed most. Where it departs from the typical map of the
    # triangles around the point (their median), that one shapes the patch.
    _, around = cKDTree(ref_lv[tris].mean(axis=1)).query(
        points, k=min(EPI_LOCAL_MAPS, len(tris)))
    typical = np.median(maps[around.reshape(len(points), -1)], axis=1)
    odd = (np.linalg.norm(linear - typical, axis=(1, 2))
           > EPI_ODD_MAP * np.linalg.norm(typical, axis=(1, 2)))
    linear = np.where(odd[:, None, None], typical, linear)
    # Where the mesh maps the patches' centres (the search's segment) and the sites (the size
    # of the correction), in one pass.
    predicted, at_sites = np.split(_predicted(mesh, np.concatenate([points, sites])), 2)
    # A point the mesh maps out of the moving image is most likely out of its view: searched
    # for, it finds a lookalike inside (a close-up's border matched 60 px off along its line).
    mh, mw = mov_l.shape
    out_of_view = ~((predicted >= 0) & (predicted <= [mw - 1, mh - 1])).all(axis=1)
    predicted[out_of_view] = np.nan  # not searched
    line = epipolar_lines(F, points)
    foot = line_foot(line, predicted)
    # The segment: the displacements of the nearest vertices applied at the point.
    _, near = cKDTree(ref_lv).query(points, k=min(EPI_NEIGHBOURS, len(ref_lv)))
    near = near.reshape(len(points), -1)
    shifted = points[:, None, :] + (mov_lv - ref_lv)[near]
    along = np.einsum("ikj,ij->ik", shifted - foot[:, None, :], line_direction(line))
    low = np.minimum(along.min(axis=1), -EPI_REACH) - EPI_MARGIN
    high = np.maximum(along.max(axis=1), EPI_REACH) + EPI_MARGIN
    centre = 0.5 * (low + high)
    half_len = np.minimum(0.5 * (high - low), EPI_LONGEST / 2)
    best_xy, best_score, rival, sharpness = _search_lines(
        ref_l, mov_l, points, line, foot, centre - half_len, centre + half_len,
        _inverse(linear), ambiguity=EPI_AMBIGUITY)
    unique = rival < EPI_AMBIGUITY
    counts["unique"] = int(unique.sum())
    correlated = unique & (best_score >= EPI_NCC)
    counts["correlated"] = int(correlated.sum())
    peaked = correlated & (sharpness >= EPI_SHARPNESS)
    counts["peaked"] = int(peaked.sum())
    # Left-right check: the match, searched for along its own epipolar line in the reference
    # near the point, must come back to it.
    idx = np.flatnonzero(peaked)
    back_line = epipolar_lines(F.T, best_xy[idx])
    half = np.full(len(idx), EPI_MARGIN / 2)
    back_xy, _, _, _ = _search_lines(mov_l, ref_l, best_xy[idx], back_line,
                                     line_foot(back_line, points[idx]), -half, half, linear[idx])
    confirmed = peaked.copy()
    confirmed[idx] = np.hypot(*(back_xy - points[idx]).T) <= LR_PX
    counts["confirmed"] = int(confirmed.sum())
    # The patch's match, moved back to the point by the map that shaped the patch (a
    # translation alone: the same Middlebury frame error, fewer gains on the synthetic scenes).
    best_xy = best_xy + np.einsum("kij,kj->ki", linear, sites - points)
    points = sites
    reference = from_level(points, scale)
    moving = from_level(best_xy, scale)
    ok = confirmed.copy()
    ok[confirmed] = model.inliers(reference[confirmed], moving[confirmed])
    counts["epipolar"] = int(ok.sum())
    # The matcher's own last check: a new pair that the local map of its neighbours (the
    # vertices and the other new pairs) contradicts, with fewer than two of them moving like
    # it, is dropped (an occluded point matched to a lookalike on the line).
    idx = np.flatnonzero(ok)
    both_ref = np.concatenate([ref_v, reference[idx]])
    both_mov = np.concatenate([mov_v, moving[idx]])
    new = np.arange(len(both_ref)) >= len(ref_v)
    contradicted = neighbour_outliers(both_ref, both_mov, wanted=new)
    # A pair too far from the others for that test, and that none of them moves like, has its
    # own peak alone for evidence: it must stand out more (EPI_ALONE_AMBIGUITY).
    alone = np.zeros(len(both_ref), bool)
    alone[~contradicted] = unjudged_pairs(both_ref[~contradicted], both_mov[~contradicted],
                                          wanted=new[~contradicted])
    alone, contradicted = alone[len(ref_v):], contradicted[len(ref_v):]
    ok[idx[contradicted | (alone & (rival[idx] >= EPI_ALONE_AMBIGUITY))]] = False
    counts["neighbours"] = int(ok.sum())
    size = np.hypot(*(best_xy - at_sites).T) / scale
    return _chosen(images, ref_v, mov_v, tris, reference, moving, from_level(at_sites, scale),
                   size, ok, counts, budget=budget, epsilon=epsilon,
                   epsilon_pixels=epsilon_pixels)


#: Half side (pixels of the level) of the window a pair is sharpened over (:func:`sharpened`).
#: On the trust suite's scenes of seed 6 the insertion's right pairs were 0.32 px (median) off
#: their truth as matched; 0.24 px after the fit over 21 px windows, 0.17 px over 31 px, 0.15
#: px over 41 px, whose 90th percentile grew beside the depth steps.
SHARP_HALF = 15

#: Most Gauss-Newton steps of a fit, and the move of the window's centre (pixels of the level)
#: under which it stops.
SHARP_ITERATIONS = 5
SHARP_TOLERANCE = 0.02

#: Largest move (pixels of the level) of a sharpened pair: a fit that goes farther found
#: another optimum than the match's, and the pair stays.
SHARP_MOVE = 1.5

#: Least enhanced correlation coefficient of a kept fit. Under a non-monotone change of the
#: grey levels the affine fit of the intensities does not hold and its optimum is biased (an
#: open book of the trust suite, seed 6: its inserted pairs 0.32 -> 0.26 px at the median,
#: 0.61 -> 0.70 px at the 90th percentile, its mean error 0.244 -> 0.254 px).
SHARP_CORRELATION = 0.9

#: Largest departure of a triangle's linear map from the mean of those around a vertex,
#: relative to that mean's norm, for the vertex to be sharpened. A vertex on a crease or a
#: depth step has triangles on two surfaces: its window spans both, and the fit follows
#: neither (Middlebury teddy, automatic, extent=frame: 1.092 px with every vertex sharpened,
#: 0.995 px without those).
SHARP_ODD_MAP = 0.15


def vertex_maps(
    reference: np.ndarray, moving: np.ndarray, triangles: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The linear part of the mesh's affine map around each vertex.

    Returns
    -------
    maps : ndarray, shape (N, 2, 2)
        The mean of the linear maps of the triangles with the vertex as a corner (NaN for a
        vertex of none).
    spread : ndarray, shape (N,)
        The largest departure of one of them from that mean, relative to the mean's norm
        (infinite for a vertex of no triangle).
    """
    maps = affine_maps(reference[triangles], moving[triangles])[:, :, :2]
    good = np.isfinite(maps).all(axis=(1, 2))
    tris, maps = triangles[good], maps[good]
    total = np.zeros((len(reference), 2, 2))
    count = np.zeros(len(reference))
    for corner in range(3):
        np.add.at(total, tris[:, corner], maps)
        np.add.at(count, tris[:, corner], 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        mean = total / count[:, None, None]
    spread = np.where(count > 0, 0.0, np.inf)
    for corner in range(3):
        around = mean[tris[:, corner]]
        departure = (np.linalg.norm(maps - around, axis=(1, 2))
                     / np.maximum(np.linalg.norm(around, axis=(1, 2)), 1e-12))
        np.maximum.at(spread, tris[:, corner], departure)
    return mean, spread


def sharpened(
    image_levels: Levels,
    reference: np.ndarray,
    moving: np.ndarray,
    linear: np.ndarray,
    *,
    model: EpipolarModel | None,
) -> np.ndarray:
    """Moving positions of conjugate pairs refined by an affine fit of their windows.

    The matcher tracks its pairs without their local shape; the insertion finds its pairs at
    whole-pixel steps and a parabola through three correlations: a quarter to a third of a
    pixel off. The reference window of side ``2 SHARP_HALF + 1`` around each pair (on the
    levels) is fitted onto the moving level by :func:`core.kernels.window_fits` (the enhanced
    correlation coefficient of OpenCV's ``findTransformECC``, which gain and offset do not
    change; an affine warp starting from the pair and its local map; on the trust suite's pairs
    as accurate as OpenCV's fit and 6 to 7 times faster: ``python -m bench.sharpen``), and the
    window's centre goes where the fit takes it -- unless it would move more than
    :data:`SHARP_MOVE`, the fit fails or correlates under :data:`SHARP_CORRELATION`, or its new
    position is beyond the model's threshold of its epipolar line.

    Parameters
    ----------
    image_levels : Levels
        The grey levels the insertion searched.
    reference, moving : ndarray, shape (K, 2)
        The pairs (pixels of the full images).
    linear : ndarray, shape (K, 2, 2)
        The local linear map from the reference to the moving image at each pair
        (:func:`vertex_maps`); a pair with a non-finite one stays.
    model : EpipolarModel or None
        The matcher's epipolar geometry (None: no line to keep to).

    Returns
    -------
    ndarray, shape (K, 2)
        The moving positions, sharpened where the fit was kept.
    """
    scale = image_levels.scale
    points, matches = to_level(reference, scale), to_level(moving, scale)
    good = np.flatnonzero(np.isfinite(linear).all(axis=(1, 2)))
    maps = np.concatenate([linear[good], matches[good, :, None]], axis=2)
    centres = np.empty((len(good), 2))
    scores = np.empty(len(good))
    window_fits(np.ascontiguousarray(image_levels.reference, dtype=np.float32),
                np.ascontiguousarray(image_levels.moving, dtype=np.float32),
                np.ascontiguousarray(points[good]), np.ascontiguousarray(maps),
                SHARP_HALF, SHARP_ITERATIONS, SHARP_TOLERANCE, centres, scores)
    keep = ((scores >= SHARP_CORRELATION)
            & (np.hypot(*(centres - matches[good]).T) <= SHARP_MOVE))
    kept, found = good[keep], centres[keep]
    out = moving.copy()
    if not len(kept):
        return out
    new = from_level(found, scale)
    if model is not None:
        on_line = model.inliers(reference[kept], new)
        kept, new = kept[on_line], new[on_line]
    out[kept] = new
    return out


def sharpen_vertices(
    image_levels: Levels,
    reference: np.ndarray,
    moving: np.ndarray,
    triangles: np.ndarray,
    movable: np.ndarray,
    *,
    model: EpipolarModel | None,
) -> np.ndarray:
    """A mesh's moving vertices, the ``movable`` ones :func:`sharpened` where the mesh maps one
    surface around them (:data:`SHARP_ODD_MAP`).

    The triangles stay: a triangle that the moves would fold keeps its corners where they
    were, so the mesh needs no new triangulation or repair.

    Parameters
    ----------
    image_levels : Levels
        The grey levels the insertion searched.
    reference, moving : ndarray, shape (N, 2)
        The mesh's vertices (pixels of the full images).
    triangles : ndarray, shape (T, 3)
        Its triangles, positively oriented in the reference.
    movable : ndarray of bool, shape (N,)
        The vertices that may move (measured by the matcher or the insertion).
    model : EpipolarModel or None
        The matcher's epipolar geometry (None: no line to keep to).

    Returns
    -------
    ndarray, shape (N, 2)
        The moving vertices.
    """
    maps, spread = vertex_maps(reference, moving, triangles)
    which = np.asarray(movable, bool) & (spread <= SHARP_ODD_MAP)
    out = moving.copy()
    out[which] = sharpened(image_levels, reference[which], moving[which], maps[which],
                           model=model)

    def positive(points: np.ndarray) -> np.ndarray:
        return cross_fixed(*np.moveaxis(fixed_point(points)[triangles], 1, 0)) > 0

    was = positive(moving)
    while True:
        folded = was & ~positive(out)
        if not folded.any():
            return out
        corners = triangles[folded].ravel()
        out[corners] = moving[corners]


def _predicted(mesh: Guide, points: np.ndarray) -> np.ndarray:
    """Where the mesh maps ``points`` (pixels of the level); NaN where a point's bilinear
    neighbourhood leaves the mesh (the map is -1 there)."""
    label = mesh.label
    lh, lw = label.shape
    predicted = np.column_stack([_sample(mesh.map_x, points), _sample(mesh.map_y, points)])
    x0, y0 = np.floor(points).astype(np.int64).T
    x1, y1 = np.minimum(x0 + 1, lw - 1), np.minimum(y0 + 1, lh - 1)
    unmapped = (label[y0, x0] < 0) | (label[y0, x1] < 0) | (label[y1, x0] < 0) | (label[y1, x1] < 0)
    predicted[unmapped] = np.nan
    return predicted


def _search_lines(
    source: np.ndarray,
    target: np.ndarray,
    points: np.ndarray,
    line: np.ndarray,
    foot: np.ndarray,
    low: np.ndarray,
    high: np.ndarray,
    to_source: np.ndarray,
    *,
    ambiguity: float = np.inf,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Best match of each source point's patch along its line in ``target``.

    The patch (a square of side ``2 EPI_HALF + 1`` along the line in the target, seen in the
    source through ``to_source``, the local 2x2 map from the target to the source) is
    compared, by zero-mean normalized correlation, with the target at whole-pixel steps on the
    line from ``foot + low * direction`` to ``foot + high * direction``
    (:func:`core.kernels.strip_correlation`);
    around the best, over :data:`EPI_FALL` steps on either side and up to :data:`EPI_BAND`
    pixels off the line, the full patch is compared, and the best on the line is taken unless
    one off it leads by more than :data:`EPI_TIE`.
    Returns the sub-pixel best positions (NaN when not searched), their correlation (-1), the
    ratio of the best rival peak along the line (more than 3 px away) to the best, and how much
    the correlation falls along the line from the best in the final pass, :data:`EPI_FALL`
    steps away or at the window's end, on the side where it falls less (0 when not searched or
    when the best is at the window's end or :data:`EPI_BAND` pixels off the line). A point
    whose rival ratio reaches ``ambiguity`` is not searched further (its match would be
    refused whatever the final pass found): position NaN, correlation -1.
    """
    n = len(points)
    best_xy = np.full((n, 2), np.nan)
    best_score = np.full(n, -1.0)
    rival = np.full(n, 1.0)
    sharpness = np.zeros(n)
    ok = (np.isfinite(low) & np.isfinite(high) & np.isfinite(foot).all(axis=1)
          & np.isfinite(to_source).all(axis=(1, 2)))
    idx = np.flatnonzero(ok)
    if not len(idx):
        return best_xy, best_score, rival, sharpness
    pts = points[idx]
    normal, direction = line[idx, :2], line_direction(line[idx])
    first = np.floor(low[idx])
    lengths = (np.ceil(high[idx]) - first + 1).astype(np.int64)
    # Along the whole segment, on the line, with every other pixel of the patch; then the full
    # patch and every band around the best. Off the line, the lookalikes of a long segment
    # took the best from the right match and raised false rivals (on the trust suite's scenes
    # of seeds 2-5, three bands there cut the median gain of the insertion from 32 to 30 %).
    score, _ = _correlate(source, target, pts, to_source[idx],
                          foot[idx] + first[:, None] * direction, direction, normal, lengths,
                          coarse=True)
    profile = score.max(axis=2)  # (K, S)
    s = np.argmax(profile, axis=1)
    best = profile[np.arange(len(idx)), s]
    steps = np.arange(profile.shape[1])
    padded = np.pad(profile, ((0, 0), (1, 1)), constant_values=-np.inf)
    peaks = (profile >= padded[:, :-2]) & (profile >= padded[:, 2:])
    away = np.abs(steps[None, :] - s[:, None]) > 3
    rival[idx] = np.where(away & peaks, profile, -1.0).max(axis=1) / np.maximum(best, 1e-9)
    # Nearly half the candidates of a real facade stop here: the final pass runs on the
    # others only.
    clear = rival[idx] < ambiguity
    idx, pts, normal, direction = idx[clear], pts[clear], normal[clear], direction[clear]
    first, s = first[clear], s[clear]
    if not len(idx):
        return best_xy, best_score, rival, sharpness

    around = first + s - EPI_FALL
    score, bands = _correlate(source, target, pts, to_source[idx],
                              foot[idx] + around[:, None] * direction, direction, normal,
                              np.full(len(idx), 2 * EPI_FALL + 1), coarse=False)
    rows = np.arange(len(idx))
    flat = score.reshape(len(idx), -1).argmax(axis=1)
    s, b = np.unravel_index(flat, score.shape[1:])
    # Where a position on the line correlates as well, the images do not tell the two apart
    # (an edge crossing the line correlates equally all along itself): the line decides.
    centre = len(bands) // 2
    on_line = score[:, :, centre].argmax(axis=1)
    tie = score[rows, on_line, centre] >= score[rows, s, b] - EPI_TIE
    s, b = np.where(tie, on_line, s), np.where(tie, centre, b)
    best_score[idx] = score[rows, s, b]
    # The correlation must fall on both sides of the peak, EPI_FALL steps away or at the
    # window's end if nearer; a peak at the end is not one (its fall is 0).
    last = score.shape[1] - 1
    sides = np.maximum(score[rows, np.maximum(s - EPI_FALL, 0), b],
                       score[rows, np.minimum(s + EPI_FALL, last), b])
    # Nor is a best at the band's edge: the correlation may keep rising across the line, along
    # an edge that crosses it (the line measured four pixels from the peak falls across such an
    # edge, and the best slides along it: seen 2.8 px off on stripes crossed at 45 degrees).
    sharpness[idx] = np.where((b == 0) | (b == len(bands) - 1), 0.0, best_score[idx] - sides)
    along = around + s + _vertex(score[rows, :, b], s)
    across = bands[b] + _vertex(score[rows, s], b)
    best_xy[idx] = foot[idx] + along[:, None] * direction + across[:, None] * normal
    return best_xy, best_score, rival, sharpness


def _correlate(
    source: np.ndarray,
    target: np.ndarray,
    points: np.ndarray,
    to_source: np.ndarray,
    start: np.ndarray,
    direction: np.ndarray,
    normal: np.ndarray,
    lengths: np.ndarray,
    *,
    coarse: bool,
) -> tuple[np.ndarray, np.ndarray]:
    """Correlations ``(K, max(lengths), B)`` of the points' patches at ``start + s * direction
    + band * normal`` (-1 beyond a point's length), and the bands: ``coarse``, every other
    pixel of the patch and the line only, else the full patch and :data:`EPI_BAND` pixels
    either side.

    The patch is the square of side ``2 EPI_HALF + 1`` around the line in the target, seen in
    the source through ``to_source`` (:func:`core.kernels.strip_correlation`).
    """
    spacing = 2 if coarse else 1
    grid = np.arange(-EPI_HALF, EPI_HALF + 1, spacing, dtype=np.float64)
    ga, gb = np.meshgrid(grid, grid, indexing="ij")  # along, across the line
    # The lattice a * direction + b * normal of the target, seen in the source: a * u + b * v
    # with u, v the images of the two unit vectors.
    u = np.matmul(to_source, direction[:, :, None])[:, :, 0]
    v = np.matmul(to_source, normal[:, :, None])[:, :, 0]
    a, b = ga.ravel()[None, :], gb.ravel()[None, :]
    off_x = a * u[:, 0:1] + b * v[:, 0:1]  # (K, P)
    off_y = a * u[:, 1:2] + b * v[:, 1:2]
    bands = np.zeros(1, np.int64) if coarse else np.arange(-EPI_BAND, EPI_BAND + 1)
    patch = cv2.remap(source, (points[:, 0:1] + off_x).astype(np.float32),
                      (points[:, 1:2] + off_y).astype(np.float32), cv2.INTER_LINEAR)
    score = np.empty((len(points), int(lengths.max()), len(bands)))
    strip_correlation(np.ascontiguousarray(target, dtype=np.float32),
                      patch.astype(np.float64).reshape(len(points), len(grid), len(grid)),
                      spacing, np.ascontiguousarray(start), np.ascontiguousarray(direction),
                      np.ascontiguousarray(normal), lengths, bands, score)
    score[np.arange(score.shape[1])[None, :] >= lengths[:, None]] = -1.0
    return score, bands


def _inverse(maps: np.ndarray) -> np.ndarray:
    """Inverses of ``(K, 2, 2)`` maps, by the adjugate over the determinant: a singular map
    gives non-finite entries (its point is not searched), not an exception."""
    det = maps[:, 0, 0] * maps[:, 1, 1] - maps[:, 0, 1] * maps[:, 1, 0]
    adjugate = np.stack([np.stack([maps[:, 1, 1], -maps[:, 0, 1]], axis=1),
                         np.stack([-maps[:, 1, 0], maps[:, 0, 0]], axis=1)], axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        return adjugate / det[:, None, None]


def _vertex(values: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Offset of the vertex of the parabola through ``values[r, k-1:k+2]`` of each row ``r``
    (0 at an end or where the three do not bend down)."""
    rows = np.arange(len(k))
    inner = (k > 0) & (k < values.shape[1] - 1)
    a = values[rows, np.maximum(k - 1, 0)]
    b = values[rows, k]
    c = values[rows, np.minimum(k + 1, values.shape[1] - 1)]
    den = a - 2 * b + c
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.clip(0.5 * (a - c) / den, -0.5, 0.5)
    return np.where(inner & (den < 0) & np.isfinite(out), out, 0.0)
