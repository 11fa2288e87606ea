"""Conjugate points: automatic matching, validation of client points, outlier filter, spread.

Two matchers find pairs when the client sends none.

* ``"lk"`` (the paper's): Harris corners in the reference image, tracked into the moving image by
  pyramidal Lucas-Kanade (Bouguet) with a forward-backward consistency check. To survive
  viewpoint changes larger than the LK search range, a global homography is first estimated by
  the same tracker on a coarse pyramid level (at most :data:`COARSE_SIDE` pixels), the moving
  image is warped into the reference frame by it, and the full-resolution tracking then only
  recovers the residual (parallax) motion; tracked points are mapped back through the
  homography, so the pairs keep full-resolution sub-pixel accuracy. Both images are histogram
  equalised before tracking, which makes LK tolerate global monotonic lighting changes.
* ``"sift"`` (wide baseline): SIFT keypoints (OpenCV) in both images, Lowe's ratio test and a
  mutual nearest-neighbour check.

``"auto"`` runs ``"lk"`` and falls back to ``"sift"`` when fewer than
:data:`AUTO_MIN_CONSISTENT` tracked pairs pass the epipolar filter (or fewer than half of
the forward-backward consistent tracks do, the sign of a wrong global prior). It then also
retries the tracking from the homography of the SIFT matches (usually denser and more accurate
than SIFT itself, since LK works at full resolution). Of the tracked, SIFT and SIFT-guided
tracked pairs it keeps the largest epipolar-consistent set, preferring those that pass both
criteria; ``source`` names the matcher of the
kept pairs, and the counts of a tracking attempt that lost carry an ``lk_`` prefix
(``prior_sift_pairs`` marks tracking started from SIFT). When none, one or two kept pairs lie
off the plane of the others, SIFT's pairs off that plane may fix the epipole instead of the
robust fit or the plane's model (:func:`_parallax_lines`).

Automatic pairs are first checked by correlation (:func:`core.reliability.uniqueness`: a pair
on a repeated pattern, or whose correlation peak is not where the matcher put it, is dropped),
then go through the robust epipolar filter (:mod:`core.epipolar`), a check against the local map
of their neighbours (:func:`core.reliability.neighbour_outliers`) and a spatial suppression that
keeps the strongest pairs with a minimum distance between reference points and at most
``max_points`` of them, spread over the overlap by a grid. Every pair these steps drop (and
every client pair the validation or the filter drops) stays in the result with its cause
(:class:`DroppedPairs`), for the tie-point listing of ``tiepoints.geojson``.

Conventions: images are OpenCV arrays (grey ``(H, W)`` or BGR(A) ``(H, W, C)``, uint8 or
uint16); matching runs on their 8-bit luminance (:func:`core.imaging.to_gray8`). Point arrays are
``(N, 2)`` float64 pixel coordinates, x to the right, y down, (0, 0) at the centre of the
top-left pixel.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import Delaunay, QhullError, cKDTree

from pwlreg.core.epipolar import (
    MIN_PAIRS,
    PARALLAX_PAIRS,
    PLANE_PX,
    EpipolarModel,
    apply_homography,
    estimate_fundamental,
    parallax_fundamental,
    plane_fundamental,
    plane_homography,
    transfer_distance,
    usac_params,
)
from pwlreg.core.errors import InputError, NotEnoughPointsError
from pwlreg.core.imaging import check_image, to_gray8
from pwlreg.core.kernels import spaced
from pwlreg.core.options import RegistrationOptions
from pwlreg.core.raster import first_occurrences
from pwlreg.core.reliability import (
    STILL_PX,
    fixed_in_frame,
    neighbour_outliers,
    resolved_by_anchors,
    uniqueness,
)
from pwlreg.core.similarity import from_level

#: Pairs needed for a mesh (one triangle).
MIN_MESH_PAIRS = 3

#: ``auto`` falls back to SIFT when fewer tracked pairs than this pass the epipolar filter. A
#: mesh of about 100 well-spread vertices (roughly 180 triangles) is the smallest that still
#: follows the planes of a building-sized scene; below it, SIFT usually does better.
AUTO_MIN_CONSISTENT = 100

#: ``auto`` also falls back when fewer than this share of the forward-backward consistent tracks
#: pass the epipolar filter: good tracks are consistent with one epipolar geometry.
AUTO_MIN_INLIER_SHARE = 0.5

#: At most this many times ``max_points`` candidates are checked for uniqueness (the spread step
#: thins denser sets first): enough for the later filters to choose from.
VERIFY_BUDGET = 1.5

#: Longer side (pixels) of the coarse level on which the global prior is tracked.
COARSE_SIDE = 512

#: Longer side (pixels) above which corners are detected on a pyramid level (then refined at
#: full resolution) and SIFT runs on a pyramid level.
DETECT_SIDE = 2048

#: SIFT's contrast threshold (OpenCV's default is 0.04). SIFT is the fallback where tracking
#: fails, often a view turned far around the scene, whose textures then show weaker extrema: at
#: 0.04 such synthetic pairs kept 116-333 keypoints and 12-27 mutual matches, most of them
#: wrong; at 0.02, 688-1500 keypoints and 65-188 matches, 35-85 % of them within 3 px. Where
#: ``max_features`` stronger ones exist the strongest are kept, so textured images are not
#: changed.
SIFT_CONTRAST = 0.02

#: Tolerance (pixels) beyond the image border for client points.
BORDER_TOLERANCE = 1.0

#: The neighbourhood check's least miss (pixels) for a client's pair to be unverified
#: (:func:`unverified_pairs`): a gross error only.
#: Sparse true points of a perspective view are farther from the affine map of their
#: neighbours than the matcher's dense pairs: 30 points of a flat scene through a strong
#: homography lost 1.3 true pairs a set to the matcher's 3 px, none at 20 px; 30 and 100
#: true points of the Middlebury pairs (0.3 px noise, 20 sets each) lost 0-42 at 3 px, 0-12
#: at 10 px, none at 20 px. Random outliers are hundreds of pixels off.
CLIENT_NEIGHBOUR_PX = 20.0


#: Largest share of the matcher's pairs, those the uniqueness check confirmed, that the
#: epipolar filter may reject for the images to follow one epipolar geometry. Measured: at
#: most 1.5 % on every real pair of the data folder (Strecha, Oxford, Middlebury, the facade),
#: 4.8 % on the trust suite's scenes of seeds 0-3, median 0; 46 and 54 % on two photographs
#: through a smooth non-rigid map, where 15 pairs inserted along the lines were 3-20 px off and
#: the verdict good.
GEOMETRY_REJECTED = 0.2


def geometry_rejected(counts: dict[str, int], rejected: dict[str, int]) -> float:
    """Share of the matcher's checked pairs (those that passed its uniqueness check) that the
    epipolar filter rejected; 0 for client points (whose outliers nothing checked before) and
    without the filter."""
    if "unique" not in counts or "epipolar" not in rejected:
        return 0.0
    reached = counts.get("epipolar", 0) + rejected["epipolar"]
    return rejected["epipolar"] / reached if reached else 0.0


#: Causes for which :class:`ConjugatePoints` lists the automatic pairs one by one in
#: ``dropped``: the checks after a matcher. Its own losses (``"lost"``,
#: ``"forward-backward"``, ``"outside image"`` of a tracked corner, ``"ratio test"``,
#: ``"mutual check"``) are counted only: a failed track or a descriptor without a mutual
#: match is not a pair.
LISTED_AUTOMATIC = (
    "thinned", "fixed in the frame", "ambiguous", "disagreement", "low texture", "unverifiable",
    "epipolar", "neighbours", "spread",
)

#: Causes for which the client's pairs are listed one by one: all of them.
LISTED_CLIENT = ("not finite", "outside image", "duplicate", "epipolar")


@dataclass(frozen=True)
class DroppedPairs:
    """Pairs dropped on the way to the mesh, one row each, with why.

    Attributes
    ----------
    reference, moving : np.ndarray
        (M, 2) float64 positions in reference and moving image pixels (NaN where a client
        gave no finite number).
    reason : np.ndarray
        (M,) str, the cause: a key of :attr:`ConjugatePoints.rejected` among
        :data:`LISTED_AUTOMATIC` or :data:`LISTED_CLIENT` (``"thinned"``: over the checks'
        budget, thinned by the spread rule before them).
    residuals : np.ndarray
        (M,) float64 epipolar residual, pixels; NaN where no epipolar geometry judged the pair
        (dropped before the filter, or the filter off).
    """

    reference: np.ndarray
    moving: np.ndarray
    reason: np.ndarray
    residuals: np.ndarray

    @classmethod
    def none(cls) -> DroppedPairs:
        """No dropped pair."""
        return cls(np.empty((0, 2)), np.empty((0, 2)), np.empty(0, dtype=str), np.empty(0))

    def __len__(self) -> int:
        return len(self.reference)

    def plus(
        self,
        reference: np.ndarray,
        moving: np.ndarray,
        reason: str | np.ndarray,
        residuals: np.ndarray | None = None,
    ) -> DroppedPairs:
        """These rows followed by ``reference`` / ``moving`` pairs dropped for ``reason`` (one
        cause for all, or one per pair), with their epipolar ``residuals`` if known."""
        ref = np.asarray(reference, np.float64).reshape(-1, 2)
        n = len(ref)
        why = np.broadcast_to(np.asarray(reason, dtype=str), (n,))
        res = np.full(n, np.nan) if residuals is None else np.asarray(residuals, np.float64)
        return DroppedPairs(
            np.concatenate([self.reference, ref]),
            np.concatenate([self.moving, np.asarray(moving, np.float64).reshape(-1, 2)]),
            np.concatenate([self.reason, why]),
            np.concatenate([self.residuals, res]),
        )


@dataclass(frozen=True)
class ConjugatePoints:
    """Conjugate point pairs kept for the mesh and how they were obtained.

    Attributes
    ----------
    reference : np.ndarray
        (N, 2) float64 kept points, reference image pixels.
    moving : np.ndarray
        (N, 2) float64 matching points, moving image pixels.
    source : str
        ``"client"``, ``"lk"`` or ``"sift"``.
    counts : dict of str to int
        Pairs left after each stage, in order. Automatic: ``detected`` (reference corners or
        keypoints), ``tracked`` / ``matched``, ``consistent`` (forward-backward check, or ratio
        and mutual checks), ``unique`` (correlation check: unambiguous, and the correlation
        peak where the matcher put the point; ``resolved by neighbours`` of them were ambiguous
        but confirmed by the local map of unambiguous pairs around them), ``epipolar``
        (epipolar inliers), ``neighbours`` (not contradicted by the local map of their
        neighbours), ``kept``. Client: ``given``, ``valid``, ``epipolar``, ``unverified``
        (kept pairs the filter could not check: :func:`unverified_pairs`), ``kept``. When
        ``auto`` fell back to SIFT, the tracker's own numbers are kept with an ``lk_`` prefix.
    rejected : dict of str to int
        Reason -> number of pairs rejected for it (``"lost"``, ``"outside image"``,
        ``"forward-backward"``, ``"ratio test"``, ``"mutual check"``, ``"ambiguous"``,
        ``"disagreement"``, ``"low texture"``, ``"unverifiable"``, ``"epipolar"``,
        ``"neighbours"``, ``"not finite"``, ``"duplicate"``, ``"spread"``, ``"thinned"``).
    epipolar : EpipolarModel or None
        The estimated epipolar geometry; None when the filter is off.
    residuals : np.ndarray
        (N,) epipolar residual of each kept pair, pixels (NaN when the filter is off).
    notes : tuple of str
        What the client should know, e.g. that the filter was skipped and why.
    dropped : DroppedPairs
        The pairs dropped for one of :data:`LISTED_AUTOMATIC` (or :data:`LISTED_CLIENT`), one
        by one: as many of each cause as ``rejected`` counts (of the matcher whose pairs were
        kept, when ``auto`` tried several).
    unverified : np.ndarray or None
        (N,) bool: the client's kept pairs the filter could not check
        (:func:`unverified_pairs`); None when it judged none (automatic pairs, no filter).
    """

    reference: np.ndarray
    moving: np.ndarray
    source: str
    counts: dict[str, int]
    rejected: dict[str, int]
    epipolar: EpipolarModel | None
    residuals: np.ndarray
    notes: tuple[str, ...] = ()
    dropped: DroppedPairs = field(default_factory=DroppedPairs.none)
    unverified: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.reference)

    @property
    def lines(self) -> EpipolarModel | None:
        """The epipolar model to search along, or None: without a filter, or when it rejected
        more than :data:`GEOMETRY_REJECTED` of the matcher's checked pairs
        (:func:`geometry_rejected`): its lines are wrong then."""
        if geometry_rejected(self.counts, self.rejected) > GEOMETRY_REJECTED:
            return None
        return self.epipolar

    def to_dict(self) -> dict:
        """JSON-able record (lists and floats; NaN residuals become None)."""
        return {
            "source": self.source,
            "num_pairs": len(self.reference),
            "counts": {k: int(v) for k, v in self.counts.items()},
            "rejected": {k: int(v) for k, v in self.rejected.items()},
            "epipolar": None if self.epipolar is None else self.epipolar.to_dict(),
            "reference": [[float(x), float(y)] for x, y in self.reference],
            "moving": [[float(x), float(y)] for x, y in self.moving],
            "residuals_px": [None if math.isnan(r) else float(r) for r in self.residuals],
            "notes": list(self.notes),
        }


@dataclass
class Matches:
    """Candidate pairs from one matcher, before the epipolar filter and the spread step.

    Attributes
    ----------
    reference, moving : np.ndarray
        (N, 2) float64 pixel coordinates.
    score : np.ndarray
        (N,) strength, larger is better (used to choose among close points).
    source : str
        ``"lk"`` or ``"sift"``.
    counts, rejected : dict of str to int
        Stage counts and rejections so far (see :class:`ConjugatePoints`).
    prior : np.ndarray, optional
        (3, 3) global homography reference -> moving the matcher worked from (the tracker's
        prior), used to compare patches with little distortion.
    dropped : DroppedPairs
        Pairs the checks dropped so far (see :meth:`drop`).
    """

    reference: np.ndarray
    moving: np.ndarray
    score: np.ndarray
    source: str
    counts: dict[str, int] = field(default_factory=dict)
    rejected: dict[str, int] = field(default_factory=dict)
    prior: np.ndarray | None = None
    dropped: DroppedPairs = field(default_factory=DroppedPairs.none)

    def subset(self, keep: np.ndarray) -> Matches:
        """Same matches restricted to a boolean mask or index array."""
        return Matches(
            self.reference[keep],
            self.moving[keep],
            self.score[keep],
            self.source,
            dict(self.counts),
            dict(self.rejected),
            self.prior,
            self.dropped,
        )

    def drop(
        self, keep: np.ndarray, reason: str | np.ndarray, residuals: np.ndarray | None = None
    ) -> Matches:
        """The matches of the boolean mask ``keep``; the others are added to ``dropped`` for
        ``reason`` (one cause, or one per match) with their epipolar ``residuals`` (per match,
        if known). The counts are the caller's."""
        out = ~keep
        why = reason if isinstance(reason, str) else np.asarray(reason)[out]
        kept = self.subset(keep)
        kept.dropped = self.dropped.plus(
            self.reference[out], self.moving[out], why,
            None if residuals is None else residuals[out],
        )
        return kept


# --- small image helpers ------------------------------------------------------------------------


def _downscale(gray: np.ndarray, max_side: int) -> tuple[np.ndarray, float]:
    """Halve ``gray`` (Gaussian pyramid) until its longer side is at most ``max_side``.

    Returns the level and its scale factor ``s`` (level pixel = ``s`` * full pixel; pyrDown
    keeps (0, 0) at the centre of the top-left pixel: :func:`core.similarity.to_level` /
    :func:`core.similarity.from_level`).
    """
    scale = 1.0
    while max(gray.shape) > max_side:
        gray = cv2.pyrDown(gray)
        scale *= 0.5
    return gray, scale


def _pad_to(gray: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Pad ``gray`` with zeros at the bottom and right to ``shape`` (no-op if it is that big)."""
    dh, dw = shape[0] - gray.shape[0], shape[1] - gray.shape[1]
    if dh == 0 and dw == 0:
        return gray
    return cv2.copyMakeBorder(gray, 0, dh, 0, dw, cv2.BORDER_CONSTANT, value=0)


def inside_image(points: np.ndarray, shape: tuple[int, ...], margin: float = 0.0) -> np.ndarray:
    """Mask of the points inside ``[-0.5 - margin, size - 0.5 + margin]`` in x and y."""
    h, w = shape[:2]
    x, y = points[:, 0], points[:, 1]
    return (
        np.isfinite(x)
        & np.isfinite(y)
        & (x >= -0.5 - margin)
        & (x <= w - 0.5 + margin)
        & (y >= -0.5 - margin)
        & (y <= h - 0.5 + margin)
    )


_LK_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01)


def _lk_pair(
    a: np.ndarray, b: np.ndarray, points: np.ndarray, win: int, levels: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Track ``points`` from ``a`` to ``b`` and back with pyramidal LK (same-size images).

    Returns the tracked points (N, 2), a success mask (both directions converged) and the
    forward-backward error (N,) in pixels of ``a`` (infinite where the forward track failed).
    """
    if len(points) == 0:
        return np.empty((0, 2)), np.zeros(0, bool), np.empty(0)
    p0 = points.astype(np.float32).reshape(-1, 1, 2)
    p1, st1, _ = cv2.calcOpticalFlowPyrLK(
        a, b, p0, None, winSize=(win, win), maxLevel=levels, criteria=_LK_CRITERIA
    )
    # LK tracks each point on its own: only the forward successes are tracked back (a fifth
    # to a third of the coarse prior's corners are lost forward).
    forward = np.flatnonzero(st1.ravel() == 1)
    ok = np.zeros(len(points), bool)
    fb = np.full(len(points), np.inf)
    if len(forward):
        p2, st2, _ = cv2.calcOpticalFlowPyrLK(
            b, a, p1[forward], None, winSize=(win, win), maxLevel=levels, criteria=_LK_CRITERIA
        )
        ok[forward] = st2.ravel() == 1
        fb[forward] = np.linalg.norm((p2 - p0[forward]).reshape(-1, 2), axis=1)
    return p1.reshape(-1, 2).astype(np.float64), ok, fb


# --- matcher 1: Harris + pyramidal Lucas-Kanade ---------------------------------------------------


def detect_corners(
    gray: np.ndarray, max_corners: int, min_distance: float, quality: float = 0.001
) -> np.ndarray:
    """Harris corners, strongest first, with sub-pixel positions at full resolution.

    On images whose longer side exceeds :data:`DETECT_SIDE` the corners are detected on the
    first pyramid level below it and refined at full resolution with ``cv2.cornerSubPix``.

    Parameters
    ----------
    gray : np.ndarray
        8-bit grey image.
    max_corners : int
        Most corners returned.
    min_distance : float
        Minimum distance between corners, full-resolution pixels.
    quality : float
        Weakest corner kept, as a fraction of the strongest Harris response.

    Returns
    -------
    np.ndarray
        (N, 2) float64 corner positions, sorted by decreasing Harris response.
    """
    level, scale = _downscale(gray, DETECT_SIDE)
    corners = cv2.goodFeaturesToTrack(
        level,
        maxCorners=int(max_corners),
        qualityLevel=quality,
        minDistance=max(1.0, min_distance * scale),
        blockSize=3,
        useHarrisDetector=True,
        k=0.04,
    )
    if corners is None:
        return np.empty((0, 2))
    pts = from_level(corners.reshape(-1, 2).astype(np.float64), scale)
    h, w = gray.shape
    # cornerSubPix needs the search window inside the image, and an image of at least twice
    # the window and 5 more pixels a side (a 5000x200 pair's coarse level has 13 rows).
    pts = pts[(pts[:, 0] >= 6) & (pts[:, 0] <= w - 7) & (pts[:, 1] >= 6) & (pts[:, 1] <= h - 7)]
    if len(pts) and min(h, w) >= 2 * 5 + 5:
        refined = (
            cv2.cornerSubPix(
                gray,
                pts.astype(np.float32).reshape(-1, 1, 2),
                (5, 5),
                (-1, -1),
                (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.01),
            )
            .reshape(-1, 2)
            .astype(np.float64)
        )
        # A refinement that leaves its 11x11 window found no corner there: keep the detection.
        moved = np.linalg.norm(refined - pts, axis=1) > 5.0
        pts = np.where(moved[:, None], pts, refined)
    return pts


def estimate_global_prior(
    ref_gray: np.ndarray, mov_gray: np.ndarray, seed: int = 0, min_inliers: int = 12
) -> np.ndarray | None:
    """Global homography reference -> moving tracked on a coarse pyramid level.

    Harris corners of the coarse reference level (longer side at most :data:`COARSE_SIDE`) are
    tracked into the coarse moving level by pyramidal LK with a forward-backward check, and a
    homography is fitted to them with OpenCV's USAC.

    Parameters
    ----------
    ref_gray, mov_gray : np.ndarray
        8-bit grey images (already photometrically normalised if needed), any sizes.
    seed : int
        Seed of the robust fit.
    min_inliers : int
        Fewest inliers for the homography to be trusted.

    Returns
    -------
    np.ndarray or None
        (3, 3) homography in full-resolution pixels (``x_mov ~ H x_ref``), or None when the
        coarse tracking does not support one.
    """
    a, sa = _downscale(ref_gray, COARSE_SIDE)
    b, sb = _downscale(mov_gray, COARSE_SIDE)
    shape = (max(a.shape[0], b.shape[0]), max(a.shape[1], b.shape[1]))
    corners = detect_corners(a, 500, 5.0, quality=0.005)
    if len(corners) < min_inliers:
        return None
    tracked, ok, fb = _lk_pair(_pad_to(a, shape), _pad_to(b, shape), corners, 21, 4)
    ok &= (fb < 0.5) & inside_image(tracked, b.shape)
    if np.count_nonzero(ok) < min_inliers:
        return None
    src = from_level(corners[ok], sa)
    dst = from_level(tracked[ok], sb)
    return _robust_homography(src, dst, 2.0 / sb, 2000, seed, min_inliers)


def _robust_homography(
    src: np.ndarray,
    dst: np.ndarray,
    threshold: float,
    max_iterations: int,
    seed: int,
    min_inliers: int,
) -> np.ndarray | None:
    """USAC (MSAC score, inner local optimisation) homography ``dst ~ H src``, normalised so
    that ``H[2, 2] == 1``; None with fewer than ``min_inliers`` inliers."""
    params = usac_params(threshold, seed, 0.999, max_iterations, score="msac")
    H, mask = cv2.findHomography(src, dst, params)
    if H is None or mask is None or int(mask.sum()) < min_inliers:
        return None
    return H / H[2, 2]


def match_lk(
    ref_gray: np.ndarray,
    mov_gray: np.ndarray,
    max_candidates: int,
    min_distance: float,
    fb_threshold: float = 0.5,
    seed: int = 0,
    win: int = 21,
    levels: int = 3,
    prior: np.ndarray | None = None,
    equalized: tuple[np.ndarray, np.ndarray] | None = None,
) -> Matches:
    """Harris corners tracked by pyramidal Lucas-Kanade with a forward-backward check.

    The moving image is first resampled into the reference frame through a global homography
    (``prior`` or, by default, :func:`estimate_global_prior`; the identity if that fails), so
    that LK only has to recover the residual motion; tracked points are mapped back through it.

    Parameters
    ----------
    ref_gray, mov_gray : np.ndarray
        8-bit grey images, any sizes.
    max_candidates : int
        Corners detected in the reference image.
    min_distance : float
        Minimum distance between detected corners, pixels.
    fb_threshold : float
        Largest forward-backward error (pixels, reference image) of a consistent track.
    seed : int
        Seed of the global prior's robust fit.
    win, levels : int
        LK window side (pixels) and number of pyramid levels above full resolution.
    prior : np.ndarray, optional
        (3, 3) homography reference -> moving (full-resolution pixels) to start from.
    equalized : (np.ndarray, np.ndarray), optional
        Both images through ``cv2.equalizeHist``, if the caller has them already.

    Returns
    -------
    Matches
        ``source="lk"``; score = Harris rank (strongest highest).
    """
    a, b = equalized if equalized is not None else (cv2.equalizeHist(ref_gray),
                                                    cv2.equalizeHist(mov_gray))
    # The corners do not depend on the prior: found on a second thread while it is tracked
    # (OpenCV lets go of the GIL; the prior's tracking keeps two cores only partly busy).
    with ThreadPoolExecutor(max_workers=1) as pool:
        detected = pool.submit(detect_corners, ref_gray, max_candidates, min_distance)
        H = estimate_global_prior(a, b, seed=seed) if prior is None else np.asarray(prior, float)
        corners = detected.result()
    if H is None:
        H = np.eye(3)
    h, w = a.shape
    # Moving image resampled into the reference frame: warped(x) = moving(H x).
    warped = cv2.warpPerspective(
        b,
        H,
        (w, h),
        flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=0,
    )
    counts: dict[str, int] = {}
    rejected: dict[str, int] = {}
    counts["detected"] = len(corners)
    score = np.linspace(1.0, 0.0, len(corners), endpoint=False) if len(corners) else np.empty(0)
    # Corners whose prior position falls outside the moving image cannot be tracked.
    inside = inside_image(apply_homography(H, corners), mov_gray.shape, margin=-2.0)
    rejected["outside image"] = int(np.count_nonzero(~inside))
    corners, score = corners[inside], score[inside]
    tracked, ok, fb = _lk_pair(a, warped, corners, win, levels)
    moving = apply_homography(H, tracked)
    ok_in = ok & inside_image(moving, mov_gray.shape)
    rejected["lost"] = int(np.count_nonzero(~ok))
    rejected["outside image"] += int(np.count_nonzero(ok & ~ok_in))
    counts["tracked"] = int(np.count_nonzero(ok_in))
    good = ok_in & (fb <= fb_threshold)
    rejected["forward-backward"] = int(np.count_nonzero(ok_in & ~good))
    counts["consistent"] = int(np.count_nonzero(good))
    return Matches(corners[good], moving[good], score[good], "lk", counts, rejected, H)


# --- matcher 2: SIFT ------------------------------------------------------------------------------


def match_sift(
    ref_gray: np.ndarray,
    mov_gray: np.ndarray,
    max_features: int,
    ratio: float = 0.8,
) -> Matches:
    """SIFT keypoints matched with Lowe's ratio test and a mutual nearest-neighbour check.

    Images whose longer side exceeds :data:`DETECT_SIDE` are processed on the first pyramid level
    below it (SIFT's cost grows quickly with size); coordinates are returned at full resolution.

    Parameters
    ----------
    ref_gray, mov_gray : np.ndarray
        8-bit grey images, any sizes.
    max_features : int
        Most keypoints per image (the strongest).
    ratio : float
        Largest ratio of the best to the second-best descriptor distance.

    Returns
    -------
    Matches
        ``source="sift"``; score = ``1 - ratio`` of the match.
    """
    a, sa = _downscale(ref_gray, DETECT_SIDE)
    b, sb = _downscale(mov_gray, DETECT_SIDE)
    # Precise upscaling keeps OpenCV's pixel-centre convention (the default 2x upscale of the
    # first octave shifts keypoints by about 0.2 px at scale changes).
    sift = cv2.SIFT_create(nfeatures=int(max_features), contrastThreshold=SIFT_CONTRAST,
                           enable_precise_upscale=True)
    ka, da = sift.detectAndCompute(a, None)
    kb, db = sift.detectAndCompute(b, None)
    counts = {"detected": len(ka), "detected_moving": len(kb)}
    rejected: dict[str, int] = {}
    empty = Matches(np.empty((0, 2)), np.empty((0, 2)), np.empty(0), "sift", counts, rejected)
    if da is None or db is None or len(ka) < 2 or len(kb) < 2:
        counts.update(matched=0, consistent=0)
        return empty
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    knn = matcher.knnMatch(da, db, k=2)
    qi = np.array([m[0].queryIdx for m in knn if len(m) == 2])
    ti = np.array([m[0].trainIdx for m in knn if len(m) == 2])
    d1 = np.array([m[0].distance for m in knn if len(m) == 2])
    d2 = np.array([m[1].distance for m in knn if len(m) == 2])
    passed = d1 < ratio * d2
    rejected["ratio test"] = int(np.count_nonzero(~passed))
    counts["matched"] = int(np.count_nonzero(passed))
    back = matcher.match(db, da)
    best_back = np.full(len(kb), -1)
    best_back[[m.queryIdx for m in back]] = [m.trainIdx for m in back]
    mutual = passed & (best_back[ti] == qi)
    rejected["mutual check"] = int(np.count_nonzero(passed & ~mutual))
    counts["consistent"] = int(np.count_nonzero(mutual))
    pa = np.array([kp.pt for kp in ka], dtype=np.float64).reshape(-1, 2)
    pb = np.array([kp.pt for kp in kb], dtype=np.float64).reshape(-1, 2)
    ref = from_level(pa[qi[mutual]], sa)
    mov = from_level(pb[ti[mutual]], sb)
    score = 1.0 - d1[mutual] / np.maximum(d2[mutual], 1e-12)
    return Matches(ref, mov, score, "sift", counts, rejected)


# --- spread ---------------------------------------------------------------------------------------


def spread_points(
    points: np.ndarray, score: np.ndarray, max_points: int, min_distance: float
) -> np.ndarray:
    """Choose well-spread, strong points: minimum distance, then grid-based thinning.

    1. Greedy suppression, strongest first: a point closer than ``min_distance`` to a kept
       point is dropped (exact duplicates always are).
    2. If more than ``max_points`` remain, the bounding box of the points is cut into square
       cells of side ``sqrt(area / max_points)``; points are ranked within their cell by score,
       and the first ``max_points`` in the order (rank in cell, decreasing score) are kept: every
       occupied cell gets its best point before any cell gets a second one.

    Parameters
    ----------
    points : np.ndarray
        (N, 2) pixel coordinates.
    score : np.ndarray
        (N,) strength, larger is better.
    max_points : int
        Most points kept.
    min_distance : float
        Minimum distance between kept points, pixels.

    Returns
    -------
    np.ndarray
        Sorted indices of the kept points.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    n = len(points)
    if n == 0:
        return np.empty(0, dtype=np.intp)
    order = np.lexsort((np.arange(n), -np.asarray(score, dtype=np.float64)))
    keep = _min_distance_greedy(points, order, min_distance)
    if len(keep) > max_points:
        sub = points[keep]
        lo, hi = sub.min(axis=0), sub.max(axis=0)
        area = max(float(np.prod(np.maximum(hi - lo, 1.0))), 1.0)
        cell = math.sqrt(area / max_points)
        ij = np.floor((sub - lo) / cell).astype(np.int64)
        cell_id = ij[:, 0] * (int(ij[:, 1].max()) + 1) + ij[:, 1]
        # keep is in decreasing score order, so the rank within a cell is the running count.
        _, inverse = np.unique(cell_id, return_inverse=True)
        rank = np.zeros(len(keep), dtype=np.int64)
        seen: dict[int, int] = {}
        for k, c in enumerate(inverse.tolist()):
            rank[k] = seen.get(c, 0)
            seen[c] = rank[k] + 1
        chosen = np.lexsort((np.arange(len(keep)), rank))[:max_points]
        keep = keep[chosen]
    return np.sort(keep)


def _min_distance_greedy(points: np.ndarray, order: np.ndarray, min_distance: float) -> np.ndarray:
    """Indices (in ``order``) of points kept by greedy minimum-distance suppression."""
    if min_distance <= 0:
        # Only exact duplicates go.
        return order[np.sort(first_occurrences(points[order]))]
    ordered = np.ascontiguousarray(points[order], dtype=np.float64)
    return order[spaced(ordered, float(min_distance), len(order))].astype(np.intp)


# --- the filter and the entry point ---------------------------------------------------------------


def _epipolar(
    ref: np.ndarray, mov: np.ndarray, options: RegistrationOptions, stage: str, *,
    checked: bool
) -> tuple[EpipolarModel, np.ndarray, np.ndarray, np.ndarray | None]:
    """Robust epipolar fit; returns the model, the inlier mask, all residuals and the
    homography of the plane most inliers lie on (None when none fits).

    When the inliers lie on one plane (:func:`core.epipolar.plane_homography`) the model
    carries it. Fewer than :data:`core.epipolar.PARALLAX_PAIRS` inliers off that plane chose
    its lines alone: the model keeps its lines if other tests ``checked`` them (the
    matcher's, whose epipole SIFT's pairs may fix afterwards: :func:`_parallax_lines`), and is
    a plane otherwise (a client's, which nothing else checked).
    """
    needed = MIN_PAIRS[options.epipolar_model]
    if len(ref) < needed:
        raise NotEnoughPointsError(
            len(ref),
            needed,
            f"{stage} (the {options.epipolar_model} epipolar filter cannot reject outliers "
            f"robustly from fewer pairs; set epipolar_filter to false to use them unfiltered)",
        )
    try:
        model = estimate_fundamental(
            ref, mov, options.epipolar_model, options.epipolar_threshold, options.seed
        )
    except InputError as exc:
        # OpenCV's USAC finds no model for pairs on one plane with a few outliers among them
        # (28 true pairs of a flat facade and 2 outliers): their plane is the model then.
        plane = plane_homography(ref, mov, seed=options.seed)
        residuals = (np.full(len(ref), np.inf) if plane is None
                     else transfer_distance(plane, ref, mov))
        on_plane = residuals <= PLANE_PX
        if np.count_nonzero(on_plane) < needed:
            raise NotEnoughPointsError(0, needed, f"{stage} ({exc})") from exc
        rms = float(np.sqrt(np.mean(residuals[on_plane] ** 2)))
        model = EpipolarModel(options.epipolar_model, plane_fundamental(plane), PLANE_PX,
                              len(ref), int(np.count_nonzero(on_plane)), 0, rms, plane)
        return model, on_plane, residuals, plane
    residuals = model.residuals(ref, mov)
    inliers = residuals <= model.threshold
    plane = plane_homography(ref[inliers], mov[inliers], seed=options.seed)
    if plane is None:
        return model, inliers, residuals, None
    off = inliers & (transfer_distance(plane, ref, mov) > PLANE_PX)
    if np.count_nonzero(off) >= PARALLAX_PAIRS or (checked and off.any()):
        return model, inliers, residuals, plane
    return replace(model, plane=plane), inliers, residuals, plane


_CHECK_CAUSES = ("ambiguous", "disagreement", "low texture", "unverifiable")
_MATCHER_NAMES = {"lk": "tracking", "sift": "SIFT"}


def _verify(matches: Matches, images: tuple[np.ndarray, np.ndarray], seed: int) -> Matches:
    """Drop the pairs :func:`core.reliability.uniqueness` finds ambiguous or contradicted."""
    prior = matches.prior
    if prior is None:
        prior = _homography_from_matches(matches, seed)
    check = uniqueness(images[0], images[1], matches.reference, matches.moving, prior)
    keep = check.ok.copy()
    ambiguous = np.flatnonzero(check.cause == "ambiguous")
    resolved = resolved_by_anchors(
        matches.reference[keep], matches.moving[keep],
        matches.reference[ambiguous], matches.moving[ambiguous],
    )
    keep[ambiguous[resolved]] = True
    out = matches.drop(keep, check.cause)
    for cause, n in check.counts().items():
        n -= int(resolved.sum()) if cause == "ambiguous" else 0
        out.rejected[cause] = out.rejected.get(cause, 0) + n
    out.counts["unique"] = len(out.reference)
    out.counts["resolved by neighbours"] = int(resolved.sum())
    return out


def _filter_matches(
    matches: Matches, options: RegistrationOptions, images: tuple[np.ndarray, np.ndarray]
) -> tuple[Matches, EpipolarModel | None, np.ndarray]:
    """Uniqueness check, epipolar filter and neighbourhood check of automatic matches; returns
    the pairs kept, the epipolar model and the pairs' epipolar residuals."""
    # The checks cost a correlation per pair: thin a very dense candidate set first.
    budget = int(VERIFY_BUDGET * options.max_points)
    if len(matches.reference) > budget:
        keep = spread_points(matches.reference, matches.score, budget, options.min_distance)
        n = len(matches.reference)
        matches = matches.drop(_mask(keep, n), "thinned")
        # Counted apart from the final "spread": the verdict's inlier share counts that one
        # as passed (core.quality), and these pairs never reached the checks.
        matches.rejected["thinned"] = n - len(keep)
    matches.counts["checked"] = len(matches.reference)
    fixed = fixed_in_frame_pairs(matches.reference, matches.moving, seed=options.seed)
    matches = matches.drop(~fixed, "fixed in the frame")
    matches.rejected["fixed in the frame"] = int(np.count_nonzero(fixed))
    matches = _verify(matches, images, options.seed)
    needed = MIN_PAIRS[options.epipolar_model] if options.epipolar_filter else MIN_MESH_PAIRS
    if len(matches.reference) < needed:
        dropped = {c: matches.rejected.get(c, 0) for c in _CHECK_CAUSES}
        listed = ", ".join(f"{c} {n}" for c, n in dropped.items() if n) or "none dropped"
        found = len(matches.reference) + sum(dropped.values())
        raise NotEnoughPointsError(
            len(matches.reference),
            needed,
            f"the uniqueness check of the {found} pairs {_MATCHER_NAMES[matches.source]} "
            f"found ({listed})",
        )
    if not options.epipolar_filter:
        matches.counts["epipolar"] = len(matches.reference)
        residuals = np.full(len(matches.reference), np.nan)
        model = None
    else:
        model, inl, res, _ = _epipolar(
            matches.reference, matches.moving, options, f"matching ({matches.source})",
            checked=True)
        matches = matches.drop(inl, "epipolar", res)
        matches.counts["epipolar"] = int(np.count_nonzero(inl))
        matches.rejected["epipolar"] = int(np.count_nonzero(~inl))
        residuals = res[inl]
    outliers = neighbour_outliers(matches.reference, matches.moving)
    out = matches.drop(~outliers, "neighbours", residuals)
    out.rejected["neighbours"] = int(np.count_nonzero(outliers))
    out.counts["neighbours"] = len(out.reference)
    return out, model, residuals[~outliers]


#: Fewest moving pairs whose homography predicts the still ones (:func:`fixed_in_frame_pairs`).
FIXED_MIN_FIT = 15

#: Still pairs closer than this many times the median distance between neighbouring still
#: pairs form one group; a group spanning :data:`FIXED_AREA` of the pairs' hull or more may be
#: a part of the scene that stays, not a pattern of the frame (:func:`fixed_in_frame_pairs`).
FIXED_LINK = 4.0
FIXED_AREA = 0.25

#: Share of the pairs inside a large group's hull that move, from which the group is a
#: pattern over the scene rather than a part of it (:func:`fixed_in_frame_pairs`).
FIXED_AMONG = 0.25


def fixed_in_frame_pairs(reference: np.ndarray, moving: np.ndarray, *, seed: int = 0
                         ) -> np.ndarray:
    """The pairs :func:`core.reliability.fixed_in_frame` finds still where a homography fitted
    to the pairs that move (OpenCV's USAC) predicts motion, but for a part of the scene that
    stays (:func:`_without_scene_parts`); none when the still pairs are half or more (a scene
    that mostly stays is a camera that stayed) or the others fit no homography.

    Parameters
    ----------
    reference, moving : ndarray, shape (N, 2)
        Pairs in pixels.
    seed : int
        Seed of the robust fit.

    Returns
    -------
    ndarray of bool, shape (N,)
    """
    ref = np.asarray(reference, dtype=np.float64).reshape(-1, 2)
    mov = np.asarray(moving, dtype=np.float64).reshape(-1, 2)
    still = np.hypot(*(mov - ref).T) < STILL_PX
    fixed = np.zeros(len(ref), bool)
    if not still.any() or 2 * np.count_nonzero(still) >= len(ref):
        return fixed
    moves = ~still
    H = (_robust_homography(ref[moves], mov[moves], 3.0, 5000, seed, FIXED_MIN_FIT)
         if np.count_nonzero(moves) >= FIXED_MIN_FIT else None)
    if H is not None:
        fixed[still] = fixed_in_frame(ref[still], mov[still], apply_homography(H, ref[still]))
    return _without_scene_parts(ref, fixed)


def _without_scene_parts(points: np.ndarray, chosen: np.ndarray) -> np.ndarray:
    """The ``chosen`` points but those of a group that is a part of the scene: linked within
    :data:`FIXED_LINK` times the median distance between neighbouring chosen points, spanning
    :data:`FIXED_AREA` of the area all the points span or more, with under
    :data:`FIXED_AMONG` of the other points inside (the still page of an open book, against a
    caption, a logo or the crossings of a grid over a scene that moves)."""
    idx = np.flatnonzero(chosen)
    if len(idx) < 3:
        return chosen
    tree = cKDTree(points[idx])
    spacing = float(np.median(tree.query(points[idx], 2)[0][:, 1]))
    links = tree.query_pairs(FIXED_LINK * spacing, output_type="ndarray")
    graph = coo_matrix((np.ones(len(links)), (links[:, 0], links[:, 1])),
                       shape=(len(idx), len(idx)))
    _, group = connected_components(graph, directed=False)
    whole = cv2.contourArea(cv2.convexHull(points.astype(np.float32)))
    others = points[~chosen]
    out = chosen.copy()
    for g in np.unique(group):
        members = points[idx[group == g]]
        if (len(members) < 3 or cv2.contourArea(cv2.convexHull(members.astype(np.float32)))
                < FIXED_AREA * whole):
            continue
        try:
            inside = np.count_nonzero(Delaunay(members).find_simplex(others) >= 0)
        except QhullError:  # members on a line: no area
            continue
        if inside < FIXED_AMONG * (inside + len(members)):
            out[idx[group == g]] = False
    return out


def _homography_from_matches(
    matches: Matches, seed: int, min_inliers: int = 15
) -> np.ndarray | None:
    """Robust homography reference -> moving of a match set (a prior for guided tracking)."""
    if len(matches.reference) < min_inliers:
        return None
    return _robust_homography(matches.reference, matches.moving, 3.0, 5000, seed, min_inliers)


Filtered = tuple[Matches, "EpipolarModel | None", np.ndarray]


def _try_filter(
    matches: Matches, options: RegistrationOptions, images: tuple[np.ndarray, np.ndarray]
) -> Filtered | NotEnoughPointsError:
    try:
        return _filter_matches(matches, options, images)
    except NotEnoughPointsError as exc:
        return exc


def _is_coherent(result: Filtered | NotEnoughPointsError) -> bool:
    """Whether at least :data:`AUTO_MIN_INLIER_SHARE` of the matcher's unambiguous pairs are
    epipolar and neighbourhood inliers (a wrong global prior gives forward-backward consistent
    but incoherent tracks)."""
    if isinstance(result, NotEnoughPointsError):
        return False
    matches = result[0]
    n = len(matches.reference)
    return n >= AUTO_MIN_INLIER_SHARE * matches.counts.get("unique", n)


def _is_enough(result: Filtered | NotEnoughPointsError, options: RegistrationOptions) -> bool:
    """Whether tracked pairs are numerous and coherent enough for ``auto`` to stop."""
    target = min(AUTO_MIN_CONSISTENT, options.max_points)
    return _is_coherent(result) and _size(result) >= target


def _size(result: Filtered | NotEnoughPointsError) -> int:
    return -1 if isinstance(result, NotEnoughPointsError) else len(result[0].reference)


def _automatic(
    ref_gray: np.ndarray, mov_gray: np.ndarray, options: RegistrationOptions
) -> ConjugatePoints:
    # Enough candidates that the spread step can still choose after tracking/filter losses.
    candidates = int(min(max(3 * options.max_points, 500), 60_000))
    seed = options.seed

    images = (cv2.equalizeHist(ref_gray), cv2.equalizeHist(mov_gray))

    def lk(prior: np.ndarray | None = None) -> Matches:
        return match_lk(ref_gray, mov_gray, candidates, options.min_distance, seed=seed,
                        prior=prior, equalized=images)

    # SIFT's matches when a step below has them (the epipole's fix reuses them).
    sift_matches: Matches | None = None
    if options.matcher == "lk":
        result = _try_filter(lk(), options, images)
    elif options.matcher == "sift":
        sift_matches = match_sift(ref_gray, mov_gray, candidates)
        result = _try_filter(sift_matches, options, images)
    else:
        tracked = _try_filter(lk(), options, images)
        result = tracked
        if not _is_enough(tracked, options):
            sift_matches = match_sift(ref_gray, mov_gray, candidates)
            attempts = [tracked, _try_filter(sift_matches, options, images)]
            # Tracking restarted from the SIFT geometry is usually denser and more accurate than
            # SIFT itself (LK at full resolution). The robust fit takes the SIFT matches before
            # the checks, which thin them too much for it; the tracks are checked in turn.
            H = _homography_from_matches(sift_matches, seed)
            if H is not None:
                guided = _try_filter(lk(prior=H), options, images)
                if not isinstance(guided, NotEnoughPointsError):
                    guided[0].counts["prior_sift_pairs"] = len(sift_matches.reference)
                attempts.append(guided)
            found = [a for a in attempts if not isinstance(a, NotEnoughPointsError)]
            if found:
                # Sets that are large and coherent first, then the largest; ties go to the
                # earlier attempt.
                result = max(found, key=lambda a: (_is_enough(a, options), _size(a)))
            else:
                closest = max(attempts, key=lambda e: e.found)
                result = NotEnoughPointsError(
                    closest.found, closest.needed, "; ".join(a.stage for a in attempts)
                )
            if (
                not isinstance(result, NotEnoughPointsError)
                and not isinstance(tracked, NotEnoughPointsError)
                and result[0] is not tracked[0]
            ):
                for k in ("detected", "tracked", "consistent", "checked", "unique", "epipolar"):
                    result[0].counts[f"lk_{k}"] = tracked[0].counts.get(k, 0)
            elif not isinstance(result, NotEnoughPointsError) and isinstance(
                tracked, NotEnoughPointsError
            ):
                result[0].counts["lk_consistent"] = tracked.found
    if isinstance(result, NotEnoughPointsError):
        if "uniqueness check" in result.stage:
            raise NotEnoughPointsError(
                result.found,
                result.needed,
                f"{result.stage}: the images share no unambiguous detail (a repeated pattern, "
                "a change too strong to match, or different scenes)",
            )
        raise result
    matches, model, residuals = result
    keep = spread_points(matches.reference, matches.score, options.max_points, options.min_distance)
    counts = dict(matches.counts)
    rejected = dict(matches.rejected)
    rejected["spread"] = len(matches.reference) - len(keep)
    counts["kept"] = len(keep)
    if len(keep) < MIN_MESH_PAIRS:
        stage = "the epipolar filter" if options.epipolar_filter else f"matching ({matches.source})"
        raise NotEnoughPointsError(len(keep), MIN_MESH_PAIRS, stage)
    final = matches.drop(_mask(keep, len(matches.reference)), "spread", residuals)
    residuals = residuals[keep]
    lines = _parallax_lines(
        model, final.reference, final.moving, options.seed,
        lambda: sift_matches if sift_matches is not None
        else match_sift(ref_gray, mov_gray, candidates),
        threshold=options.epipolar_threshold)
    if lines is not model:
        model, residuals = lines, lines.residuals(final.reference, final.moving)
    return ConjugatePoints(
        reference=final.reference,
        moving=final.moving,
        source=matches.source,
        counts=counts,
        rejected=rejected,
        epipolar=model,
        residuals=residuals,
        dropped=final.dropped,
    )


def _parallax_lines(
    model: EpipolarModel | None,
    reference: np.ndarray,
    moving: np.ndarray,
    seed: int,
    sift: Callable[[], Matches],
    *,
    threshold: float,
) -> EpipolarModel | None:
    """``model`` with the epipole SIFT's pairs fix (:func:`core.epipolar.parallax_fundamental`)
    when none, one or two of the matcher's pairs lie off the plane of the others, or ``model``
    itself.

    Then no pair or those pairs alone chose the lines off the plane. With one or two, the line
    search found lookalikes along them (a box whose pairs all stood on the ground but one: its
    lines 20 px from the true matches at the 90th percentile, and 28 of 87 pairs inserted on
    its striped face 12-65 px off). With none, the model is the plane's, whose lines hold on
    it only: the insertion keeps to the plane and leaves the surfaces above it to the
    triangles spanning them (boxes and prisms on the ground 15-135 px from their lines). The
    tracker keeps few pairs off the plane because the prior homography leaves their motion
    beyond its reach; SIFT matches them wherever they are, mostly wrongly, and the right ones
    (and lookalikes along their lines) agree on one epipole. The one or two pairs may be wrong
    themselves (corners of an edge matched over other ground); SIFT's pairs then overrule them
    if they clearly outnumber the support of any epipole on those pairs' lines (prisms and
    boxes on the ground: lines 7-57 px from their true matches at the 90th percentile, 0.2-10
    px after), or SIFT's support found with one of two such pairs alone fixes the epipole.
    ``sift()`` gives SIFT's matches of the two images, called in these cases only;
    ``threshold`` is the epipolar filter's.
    """
    if model is None or model.kind != "projective":
        return model
    H = plane_homography(reference, moving, seed=seed)
    if H is None:
        return model
    off = transfer_distance(H, reference, moving) > PLANE_PX
    if np.count_nonzero(off) >= PARALLAX_PAIRS or (model.plane is None) != off.any():
        return model
    matches = sift()
    found = parallax_fundamental(H, (reference[off], moving[off]),
                                 (matches.reference, matches.moving), model.matrix,
                                 threshold=threshold, seed=seed)
    if found is None:
        return model
    return replace(model, matrix=found[0], plane=None, parallax=found[1])


def _mask(indices: np.ndarray, n: int) -> np.ndarray:
    """Boolean mask of length ``n``, True at ``indices``."""
    mask = np.zeros(n, bool)
    mask[indices] = True
    return mask


def _client(
    reference: np.ndarray,
    moving: np.ndarray,
    points: tuple[np.ndarray, np.ndarray],
    options: RegistrationOptions,
) -> ConjugatePoints:
    try:
        ref = np.asarray(points[0], dtype=np.float64)
        mov = np.asarray(points[1], dtype=np.float64)
    except (TypeError, ValueError, IndexError) as exc:
        raise InputError("points must be two (N, 2) arrays of numbers", "points") from exc
    if ref.ndim != 2 or ref.shape[1:] != (2,) or mov.shape != ref.shape:
        raise InputError(
            f"points must be two (N, 2) arrays of the same length, got shapes {ref.shape} and "
            f"{mov.shape}",
            "points",
        )
    counts = {"given": len(ref)}
    rejected: dict[str, int] = {}
    finite = np.all(np.isfinite(ref), axis=1) & np.all(np.isfinite(mov), axis=1)
    rejected["not finite"] = int(np.count_nonzero(~finite))
    inside = finite & inside_image(ref, reference.shape, BORDER_TOLERANCE)
    inside &= inside_image(mov, moving.shape, BORDER_TOLERANCE)
    rejected["outside image"] = int(np.count_nonzero(finite & ~inside))
    idx = np.flatnonzero(inside)
    # A reference point given twice cannot be a mesh vertex twice: keep its first pair.
    unique = idx[np.sort(first_occurrences(ref[idx]))]
    rejected["duplicate"] = len(idx) - len(unique)
    reason = np.where(finite, "outside image", "not finite")
    reason[idx] = "duplicate"
    gone = ~_mask(unique, len(ref))
    dropped = DroppedPairs.none().plus(ref[gone], mov[gone], reason[gone])
    ref, mov = ref[unique], mov[unique]
    counts["valid"] = len(ref)
    if len(ref) < MIN_MESH_PAIRS:
        raise NotEnoughPointsError(len(ref), MIN_MESH_PAIRS, "validation of the client points")
    model: EpipolarModel | None = None
    residuals = np.full(len(ref), np.nan)
    unverified = None
    notes: tuple[str, ...] = ()
    needed = MIN_PAIRS[options.epipolar_model]
    if options.epipolar_filter and len(ref) < needed:
        # A hand-picked handful of points is a normal request: register it, and say the filter
        # could not check it rather than refusing the job.
        notes = (
            f"epipolar filter skipped: {len(ref)} client pairs, the {options.epipolar_model} "
            f"model needs at least {needed} to reject outliers robustly",
        )
    elif options.epipolar_filter:
        model, inl, res, plane = _epipolar(ref, mov, options,
                                           "validation of the client points", checked=False)
        rejected["epipolar"] = int(np.count_nonzero(~inl))
        dropped = dropped.plus(ref[~inl], mov[~inl], "epipolar", res[~inl])
        ref, mov, residuals = ref[inl], mov[inl], res[inl]
        counts["epipolar"] = len(ref)
        if len(ref) < MIN_MESH_PAIRS:
            raise NotEnoughPointsError(len(ref), MIN_MESH_PAIRS, "the epipolar filter")
        unverified = unverified_pairs(ref, mov, plane)
        counts["unverified"] = int(np.count_nonzero(unverified))
    counts["kept"] = len(ref)
    return ConjugatePoints(ref, mov, "client", counts, rejected, model, residuals, notes, dropped,
                           unverified)


def unverified_pairs(ref: np.ndarray, mov: np.ndarray, plane: np.ndarray | None) -> np.ndarray:
    """The client's pairs that passed the epipolar filter but that it could not check, given
    the homography of the plane most of them lie on (:func:`core.epipolar.plane_homography`;
    None when none fits: every pair is off it).

    Those off the plane most pairs lie on (:func:`core.epipolar.plane_homography`) when fewer
    than :data:`core.epipolar.PARALLAX_PAIRS` are: they alone chose the filter's lines (on a
    flat scene two random outliers among 28 points passed on 7 seeds of 12). And those off it
    that the local affine map of their neighbours misses by over :data:`CLIENT_NEIGHBOUR_PX`
    and four times its own misfit, with fewer than two of them moving alike
    (:func:`core.reliability.neighbour_outliers`): an outlier that lies on its own line (on a
    rectified pair's horizontal lines, one 275 px off passed). Nothing tells such a pair from
    a true one on a roof or a column among ground points (a probe dropping them lost 98 true
    points of 229 cases): they are kept, and the verdict says so.
    """
    off = (np.ones(len(ref), bool) if plane is None
           else transfer_distance(plane, ref, mov) > PLANE_PX)
    alone = off if np.count_nonzero(off) < PARALLAX_PAIRS else np.zeros(len(ref), bool)
    return alone | (neighbour_outliers(ref, mov, min_px=CLIENT_NEIGHBOUR_PX, wanted=off) & off)


def find_conjugate_points(
    reference: np.ndarray,
    moving: np.ndarray,
    options: RegistrationOptions,
    points: tuple[np.ndarray, np.ndarray] | None = None,
) -> ConjugatePoints:
    """Conjugate point pairs of two images, filtered by their epipolar geometry.

    Parameters
    ----------
    reference, moving : np.ndarray
        OpenCV-layout images (uint8 or uint16; grey ``(H, W)`` or BGR/BGRA ``(H, W, C)``),
        possibly of different sizes.
    options : RegistrationOptions
        Uses ``matcher``, ``epipolar_model``, ``epipolar_filter``, ``epipolar_threshold``,
        ``max_points``, ``min_distance`` and ``seed``.
    points : tuple of np.ndarray, optional
        Client pairs ``(reference_points, moving_points)``, each (N, 2) pixels. They are
        validated (finite, inside their image within :data:`BORDER_TOLERANCE` pixels, no
        repeated reference point), filtered if ``options.epipolar_filter``, never thinned.
        Without them the matcher of ``options.matcher`` runs, then the filter and the spread step.

    Returns
    -------
    ConjugatePoints
        Kept pairs, their residuals, the model and the counts of every stage.

    Raises
    ------
    NotEnoughPointsError
        Fewer than 3 pairs remain, or fewer than the filter needs (6 for the affine model, 10 for
        the projective one) reach it; the message says how many were found and needed.
    InputError
        An image or the points are malformed.

    Notes
    -----
    Deterministic: the same images, points and options (including ``seed``) give the same pairs.
    """
    check_image(reference, "reference")
    check_image(moving, "moving")
    if points is not None:
        return _client(reference, moving, points, options)
    return _automatic(to_gray8(reference), to_gray8(moving), options)
