"""Checks that tell a confident match from a lucky one.

A tracker or a descriptor matcher returns a position for every point it is given, and a robust
epipolar fit cannot tell a whole field of matches shifted by one period of a repeated pattern
from the truth: a plane of consistently wrong pairs satisfies one epipolar geometry. Two
independent checks follow every automatic matcher here.

* :func:`uniqueness` correlates the reference patch of each pair over a search window of the
  moving image (resampled into the reference frame by the matcher's global homography) on two
  scales. A pair is **ambiguous** when a second correlation peak comes close to the best one
  (a repeated pattern, where no matcher can know which copy is right), and the matcher and the
  correlation **disagree** when the best peak is not where the matcher put the point.
* :func:`fixed_in_frame` names the pairs that do not move where the scene moves: a caption,
  a logo, a grid or a sensor's pattern burned into both images at the same pixels matches
  itself, and its pairs, many and mutually consistent, vouch for each other.
* :func:`neighbour_outliers` predicts each pair from an affine map fitted to its nearest
  neighbours; a pair that its neighbourhood contradicts by much more than the neighbourhood
  contradicts itself is dropped; :func:`unjudged_pairs` names the pairs it cannot judge
  (too few neighbours near them, none moving alike), whose own evidence must then be stronger.

Conventions: 8-bit grey images; point arrays ``(N, 2)`` float64 pixels, x right, y down, (0, 0)
the centre of the top-left pixel.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from pwlreg.core.kernels import template_peaks, trimmed_affine_fits

#: A pair is ambiguous when its second correlation peak reaches this share of the best one.
AMBIGUITY_RATIO = 0.97

#: Largest distance (pixels of the scale checked) between the matcher's position and the best
#: correlation peak for the two to agree.
AGREEMENT_PX = 1.5

#: Template side and search radius (pixels) at full resolution: the matcher's precision and
#: patterns repeating every few pixels.
FINE_TEMPLATE, FINE_RADIUS = 11, 10

#: Template side and search radius (pixels) on the pyramid levels 4, 16, ... times smaller, down
#: to one whose longer side is at most :data:`COARSE_SIDE`: there the radius covers 6-12 % of
#: the image side, the scale of the mistake a global prior locked on the wrong copy of a
#: pattern makes, and the 60-pixel template at 1024 px sees past bricks and tiles.
COARSE_TEMPLATE, COARSE_RADIUS, COARSE_SIDE = 15, 20, 256

#: Neighbours farther than this many times the median nearest-neighbour distance do not judge
#: a pair (and a pair with fewer than five near neighbours is not judged).
LOCAL_REACH = 4.0

#: Added to the diagonal of a local fit's normal equations: a fit with too few weighted
#: points stays solvable.
AFFINE_RIDGE = 1e-6

#: Standard deviation (grey levels) under which a template has no texture to correlate.
MIN_TEMPLATE_STD = 2.0

#: A pair that moves less than this (pixels) where the scene is predicted to move by at least
#: :data:`SCENE_MOTION_PX` is fixed in the frame (:func:`fixed_in_frame`).
STILL_PX = 1.0
SCENE_MOTION_PX = 3.0


@dataclass(frozen=True)
class UniquenessResult:
    """Per pair, what the correlation check found.

    Attributes
    ----------
    ok : ndarray of bool, shape (N,)
        The pair passed both scales.
    cause : ndarray of object, shape (N,)
        ``""`` for kept pairs, else ``"ambiguous"``, ``"disagreement"``, ``"low texture"`` or
        ``"unverifiable"``.
    """

    ok: np.ndarray
    cause: np.ndarray

    def counts(self) -> dict[str, int]:
        """Number of dropped pairs per cause."""
        causes, n = np.unique(self.cause[~self.ok].astype(str), return_counts=True)
        return {str(c): int(k) for c, k in zip(causes, n, strict=True)}


def _check_scale(
    ref: np.ndarray,
    warped: np.ndarray,
    ref_pts: np.ndarray,
    pred_pts: np.ndarray,
    template: int,
    radius: int,
    todo: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Best peak, second/best ratio, peak distance and a low-texture flag for each pair (only
    the pairs of ``todo``, a boolean mask, when given).

    The correlation surfaces and their peaks are those of ``cv2.matchTemplate``
    (``TM_CCOEFF_NORMED``), ``cv2.minMaxLoc`` and a 3x3 ``cv2.dilate``, computed for all pairs
    in one compiled kernel (:func:`core.kernels.template_peaks`; exact where OpenCV rounds).
    """
    n = len(ref_pts)
    best = np.full(n, np.nan)
    ratio = np.full(n, np.nan)
    dist = np.full(n, np.inf)
    flat = np.zeros(n, bool)
    half = template // 2
    h, w = ref.shape
    hw, ww = warped.shape
    # A window that would leave the image is moved inside it, not cut: a repeated pattern near
    # the border must still show its second copy; an image smaller than it checks nothing.
    side = 2 * (radius + half) + 1
    if h < template or w < template or side > ww or side > hw:
        return best, ratio, dist, flat
    # The template is centred on the reference point rounded, and moved inside the image when
    # the point is nearer the border than half a template: its match is expected shifted alike.
    r = np.rint(ref_pts).astype(np.int64)
    r[:, 0] = np.clip(r[:, 0], half, w - 1 - half)
    r[:, 1] = np.clip(r[:, 1], half, h - 1 - half)
    expect = pred_pts + (r - ref_pts)
    p = np.rint(expect).astype(np.int64)
    inside = np.all(np.abs(r - ref_pts) <= half + 1, axis=1)
    if todo is not None:
        inside &= todo
    idx = np.flatnonzero(inside)
    if not len(idx):
        return best, ratio, dist, flat
    corners = r[idx] - half
    windows = np.minimum(np.maximum(p[idx] - radius - half, 0), [ww - side, hw - side])
    top, second = np.zeros(len(idx)), np.zeros(len(idx))
    peak, low = np.zeros((len(idx), 2), np.int64), np.zeros(len(idx), bool)
    template_peaks(np.ascontiguousarray(ref), np.ascontiguousarray(warped), corners, windows,
                   template, radius, MIN_TEMPLATE_STD, top, second, peak, low)
    flat[idx] = low
    done = ~low
    best[idx[done]] = top[done]
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio[idx[done]] = np.where(top[done] > 0, second[done] / top[done], np.inf)
    # Position of the prediction in the surface (top-left template corner convention). Python's
    # math.hypot, not the C library's (numpy's, numba's): they differ in the last bit at times.
    centre = expect[idx[done]] - half - windows[done]
    dist[idx[done]] = [math.hypot(x, y) for x, y in (peak[done] - centre).tolist()]
    return best, ratio, dist, flat


def _on_check_level(points: np.ndarray, scale: float) -> np.ndarray:
    """Positions on a level of :func:`check_scales`, placed as an area average places them,
    ``(p + 0.5) * scale - 0.5``, not where :func:`cv2.pyrDown` puts them (``p * scale``).

    Both images of a check share the reference frame, so the placement moves a template and
    the window it is sought in alike and biases no pair; it does decide which whole pixel a
    template starts on, and so which pairs fall either side of the agreement and ambiguity
    bounds, which were set with this placement. The pyramid's placement, measured: Middlebury
    automatic, ``extent=hull``, teddy 0.873 -> 0.954 px (``python -m bench.beyond --frame``);
    the trust suite's seeds 0-1 without points, final error worse on 14 scenes of 29 and
    better on 5 (``python -m bench.beyond --automatic --configs default --seeds 0,1``).
    """
    return (np.asarray(points, dtype=np.float64) + 0.5) * scale - 0.5


def check_scales(ref_gray: np.ndarray, warped: np.ndarray) -> list[tuple]:
    """The scales :func:`uniqueness` correlates on: ``(reference, warped moving, scale,
    template, radius)``, the images themselves and a coarse pyramid level. A caller that
    checks several batches of pairs on the same images makes them once."""
    levels = [(ref_gray, warped, 1.0, FINE_TEMPLATE, FINE_RADIUS)]
    a, b, scale = ref_gray, warped, 1.0
    while max(a.shape) > COARSE_SIDE or scale == 1.0:
        for _ in range(2):
            a, b, scale = cv2.pyrDown(a), cv2.pyrDown(b), scale / 2
        levels.append((a, b, scale, COARSE_TEMPLATE, COARSE_RADIUS))
    return levels


def uniqueness(
    ref_gray: np.ndarray,
    mov_gray: np.ndarray,
    reference: np.ndarray,
    moving: np.ndarray,
    homography: np.ndarray | None,
    *,
    scales: list[tuple] | None = None,
) -> UniquenessResult:
    """Correlation check of conjugate pairs on a fine and a coarse scale.

    The moving image is resampled into the reference frame by ``homography`` (reference ->
    moving, the matcher's global prior), so the patches compare with little distortion; each
    pair's moving point is mapped there too. At each scale the reference patch of the pair is
    correlated (zero-mean normalized cross-correlation) over a window of the resampled image
    centred on that point. A pair is kept when, at both scales, the best peak lies within
    :data:`AGREEMENT_PX` of the point and no other local maximum reaches
    :data:`AMBIGUITY_RATIO` of the best.

    Parameters
    ----------
    ref_gray, mov_gray : ndarray of uint8
        Grey images (photometrically normalised if the matcher did so).
    reference, moving : ndarray, shape (N, 2)
        Pairs in pixels of each image.
    homography : ndarray, shape (3, 3), optional
        ``x_mov ~ H x_ref``; the identity when None.
    scales : list, optional
        :func:`check_scales` of ``ref_gray`` and the moving image resampled by
        ``homography``, if the caller has them.

    Returns
    -------
    UniquenessResult
        Pairs whose windows leave the image at a scale are judged on the other scale alone.
    """
    ref_pts = np.asarray(reference, dtype=np.float64).reshape(-1, 2)
    mov_pts = np.asarray(moving, dtype=np.float64).reshape(-1, 2)
    n = len(ref_pts)
    H = np.eye(3) if homography is None else np.asarray(homography, dtype=np.float64)
    h, w = ref_gray.shape
    if scales is None:
        if homography is None and mov_gray.shape == (h, w):
            warped = mov_gray  # what the identity warp returns, without its copy
        else:
            warped = cv2.warpPerspective(
                mov_gray, H, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                borderMode=cv2.BORDER_CONSTANT, borderValue=0,
            )
        scales = check_scales(ref_gray, warped)
    q = np.column_stack([mov_pts, np.ones(n)]) @ np.linalg.inv(H).T
    with np.errstate(divide="ignore", invalid="ignore"):
        pred = q[:, :2] / q[:, 2:3]
    pred = np.where(np.isfinite(pred), pred, -1e6)
    checked = np.zeros(n, bool)
    flat = np.zeros(n, bool)
    disagree = np.zeros(n, bool)
    ratio = np.full(n, -np.inf)
    for a, b, scale, template, radius in scales:
        # A pair already rejected on a finer scale costs no more correlations.
        alive = ~(disagree | (ratio >= AMBIGUITY_RATIO))
        best_s, ratio_s, dist_s, flat_s = _check_scale(
            a, b, _on_check_level(ref_pts, scale), _on_check_level(pred, scale), template,
            radius,
            alive,
        )
        done = np.isfinite(best_s)
        checked |= done
        flat |= flat_s
        disagree |= done & (dist_s > AGREEMENT_PX)
        ratio = np.where(done, np.fmax(ratio, ratio_s), ratio)
    ratio[~checked] = np.nan
    cause = np.full(n, "", dtype=object)
    cause[~checked] = "unverifiable"
    cause[~checked & flat] = "low texture"
    cause[checked & disagree] = "disagreement"
    cause[checked & (ratio >= AMBIGUITY_RATIO)] = "ambiguous"
    return UniquenessResult(ok=cause == "", cause=cause)


def fixed_in_frame(
    reference: np.ndarray,
    moving: np.ndarray,
    predicted: np.ndarray,
    *,
    still_px: float = STILL_PX,
    motion_px: float = SCENE_MOTION_PX,
) -> np.ndarray:
    """Pairs that stay at their pixel where the scene around them moves.

    A pattern at the same pixels of both images (a burned-in caption or logo, a reticle, a
    sensor's fixed pattern) matches itself with no motion, whatever the scene does. With the
    camera moved, a point of the scene stays at its pixel only by coincidence.

    Parameters
    ----------
    reference, moving : ndarray, shape (N, 2)
        Pairs in pixels.
    predicted : ndarray, shape (N, 2)
        Where the scene takes each reference point (a mesh, or a homography fitted to the
        pairs that move; NaN: unknown).
    still_px, motion_px : float
        A pair moving less than ``still_px`` where the prediction moves at least
        ``motion_px`` is fixed in the frame.

    Returns
    -------
    ndarray of bool, shape (N,)
    """
    ref = np.asarray(reference, dtype=np.float64).reshape(-1, 2)
    still = np.hypot(*(np.asarray(moving, dtype=np.float64).reshape(-1, 2) - ref).T) < still_px
    with np.errstate(invalid="ignore"):
        scene = np.hypot(*(np.asarray(predicted, dtype=np.float64).reshape(-1, 2) - ref).T)
        return still & (scene >= motion_px)


def neighbour_outliers(
    reference: np.ndarray,
    moving: np.ndarray,
    *,
    k: int = 10,
    min_px: float = 3.0,
    factor: float = 4.0,
    rounds: int = 2,
    wanted: np.ndarray | None = None,
) -> np.ndarray:
    """Pairs that the affine map of their nearest neighbours contradicts.

    For every pair, an affine map reference -> moving is fitted by least squares to its ``k``
    nearest neighbours in the reference image (not the pair itself) and predicts its moving
    point (the fit is trimmed, so one wrong neighbour does not bend it). The pair is an outlier
    when the prediction misses by more than ``min_px`` pixels and by more than ``factor`` times
    the median miss of the same map on its neighbours, and fewer than two neighbours move like
    it (displacements within ``min_px`` or 10 % of their distance): a pair just beyond a depth
    step, which the majority's map misses, has the neighbours of its own side for witnesses.
    The test is repeated ``rounds`` times without the outliers found so far.

    Parameters
    ----------
    reference, moving : ndarray, shape (N, 2)
        Pairs in pixels.
    k : int
        Neighbours per fit (at least 3).
    min_px, factor : float
        Absolute (pixels) and relative thresholds.
    rounds : int
        Passes.
    wanted : ndarray of bool, shape (N,), optional
        The pairs whose verdict is wanted (default all). The earlier passes judge every pair
        (an outlier among the others is no witness in the next pass); the last judges only
        these, and the others come out False unless an earlier pass found them.

    Returns
    -------
    ndarray of bool, shape (N,)
        True for the outliers.
    """
    ref = np.asarray(reference, dtype=np.float64).reshape(-1, 2)
    mov = np.asarray(moving, dtype=np.float64).reshape(-1, 2)
    out = np.zeros(len(ref), bool)
    wanted = np.ones(len(ref), bool) if wanted is None else np.asarray(wanted, bool)
    for n in range(rounds):
        idx = np.flatnonzero(~out)
        if len(idx) < 5:
            break
        r, m = ref[idx], mov[idx]
        # The query points are pairs of the fitted set: the nearest of each is itself.
        query = np.arange(len(idx)) if n < rounds - 1 else np.flatnonzero(wanted[idx])
        if not len(query):
            break
        fit = _local_fits(r, m, r[query], k=k, min_px=min_px, exclude_self=True)
        miss = np.linalg.norm(fit.predict(r[query]) - m[query], axis=1)
        support = _support(r, m, query, fit, min_px)
        bad = fit.judged & (miss > min_px) & (miss > factor * fit.spread) & (support < 2)
        if not np.any(bad):
            break
        out[idx[query[bad]]] = True
    return out


def unjudged_pairs(
    reference: np.ndarray,
    moving: np.ndarray,
    *,
    wanted: np.ndarray,
    k: int = 10,
    min_px: float = 3.0,
) -> np.ndarray:
    """The ``wanted`` pairs that :func:`neighbour_outliers` (same ``k`` and ``min_px``) cannot
    judge: fewer than five neighbours near enough to fit their map, and fewer than two of them
    moving like the pair.

    Such a pair stands alone in a gap of the others (a surface no other pair is on, or a
    lookalike on a repeated texture whose neighbours are all far): nothing around it confirms
    or contradicts it.

    Returns
    -------
    ndarray of bool, shape (N,)
        True for the wanted pairs that stand alone.
    """
    ref = np.asarray(reference, dtype=np.float64).reshape(-1, 2)
    mov = np.asarray(moving, dtype=np.float64).reshape(-1, 2)
    out = np.zeros(len(ref), bool)
    query = np.flatnonzero(np.asarray(wanted, bool))
    if not len(query) or len(ref) < 2:
        return out
    fit = _local_fits(ref, mov, ref[query], k=k, min_px=min_px, exclude_self=True)
    out[query] = ~fit.judged & (_support(ref, mov, query, fit, min_px) < 2)
    return out


def _support(
    ref: np.ndarray, mov: np.ndarray, query: np.ndarray, fit: _LocalFits, min_px: float
) -> np.ndarray:
    """Per query pair, its near neighbours moving like it (displacements within ``min_px`` or
    10 % of their distance): points beyond a depth step have their own side's neighbours for
    witnesses."""
    disp = mov - ref
    gap = np.linalg.norm(disp[fit.nb] - disp[query, None, :], axis=2)
    reach = np.maximum(min_px, 0.1 * np.linalg.norm(ref[fit.nb] - ref[query, None, :], axis=2))
    return np.count_nonzero(fit.near & (gap <= reach), axis=1)


def resolved_by_anchors(
    anchor_reference: np.ndarray,
    anchor_moving: np.ndarray,
    reference: np.ndarray,
    moving: np.ndarray,
    *,
    k: int = 8,
    tolerance: float = 1.5,
) -> np.ndarray:
    """Ambiguous pairs that their unambiguous neighbours confirm.

    On a repeated pattern the correlation cannot tell the copies apart, but the unambiguous
    pairs around it can: a trimmed affine map fitted to the ``k`` nearest anchors (within the
    local reach) must predict the pair within ``tolerance`` pixels (or twice its own misfit on
    the anchors, which must stay under a pixel). A pattern seen off by a period, or a pair
    beyond a depth step from its anchors, is not confirmed.

    Parameters
    ----------
    anchor_reference, anchor_moving : ndarray, shape (A, 2)
        Pairs that passed the uniqueness check.
    reference, moving : ndarray, shape (N, 2)
        Ambiguous pairs.
    k : int
        Anchors per fit.
    tolerance : float
        Largest miss, pixels.

    Returns
    -------
    ndarray of bool, shape (N,)
    """
    ar = np.asarray(anchor_reference, dtype=np.float64).reshape(-1, 2)
    am = np.asarray(anchor_moving, dtype=np.float64).reshape(-1, 2)
    qr = np.asarray(reference, dtype=np.float64).reshape(-1, 2)
    qm = np.asarray(moving, dtype=np.float64).reshape(-1, 2)
    if len(ar) < 5 or not len(qr):
        return np.zeros(len(qr), bool)
    fit = _local_fits(ar, am, qr, k=k, min_px=tolerance, exclude_self=False)
    miss = np.linalg.norm(fit.predict(qr) - qm, axis=1)
    return fit.judged & (fit.spread <= 1.0) & (miss <= np.maximum(tolerance, 2 * fit.spread))


@dataclass(frozen=True)
class _LocalFits:
    """Trimmed affine maps fitted around query points; see :func:`_local_fits`."""

    A: np.ndarray  # (n, 3, 2)
    centre: np.ndarray  # (n, 2)
    nb: np.ndarray  # (n, k) neighbour indices (the query's own index where not near)
    near: np.ndarray  # (n, k) the neighbour is within reach
    judged: np.ndarray  # (n,) at least five near neighbours
    spread: np.ndarray  # (n,) median miss of the map on its near neighbours

    def predict(self, points: np.ndarray) -> np.ndarray:
        xs = np.concatenate([points - self.centre, np.ones((len(points), 1))], axis=1)
        return np.matmul(xs[:, None, :], self.A)[:, 0]


def _local_fits(
    ref: np.ndarray,
    mov: np.ndarray,
    query: np.ndarray,
    *,
    k: int,
    min_px: float,
    exclude_self: bool,
) -> _LocalFits:
    """Per query point, an affine map ``ref -> mov`` fitted to its ``k`` nearest pairs within
    :data:`LOCAL_REACH` times the pairs' median spacing, by least squares trimmed twice of the
    pairs it misses by over ``max(min_px, 2.5 x median miss)``: a wrong neighbour must not bend
    the map that judges."""
    skip = 1 if exclude_self else 0
    kk = min(k, len(ref) - skip)
    tree = cKDTree(ref)
    spacing = float(np.median(tree.query(ref, 2)[0][:, 1]))
    dist, nb = tree.query(query, kk + skip)
    dist = dist.reshape(len(query), -1)[:, skip:]
    nb = nb.reshape(len(query), -1)[:, skip:]
    # Only near neighbours are witnesses: far apart, sparse points may lie on different
    # surfaces that no affine map joins.
    near = dist <= LOCAL_REACH * spacing
    nb = np.where(near, nb, nb[:, :1])
    A, spread = trimmed_affine_fits(ref[nb] - query[:, None, :], mov[nb], near, float(min_px),
                                    AFFINE_RIDGE)
    return _LocalFits(A, query, nb, near, near.sum(axis=1) >= 5, spread)
