"""Robust epipolar geometry of two views: the outlier filter of conjugate points.

Two models are offered.

* **Affine** fundamental matrix (the paper's; Hartley & Zisserman, *Multiple View Geometry*,
  2nd ed., ch. 14). For affine cameras ``F_A = [[0, 0, a], [0, 0, b], [c, d, e]]`` and every
  pair satisfies ``a x' + b y' + c x + d y + e = 0``: a hyperplane in the 4-D space
  ``(x', y', x, y)``. The Gold Standard error of a pair is its perpendicular distance to that
  hyperplane (the smallest joint displacement of both points, in pixels, that makes the pair
  consistent); 4 pairs in general position are a minimal sample; the maximum-likelihood fit of
  many pairs is the total-least-squares hyperplane (H&Z Algorithm 14.1). It is estimated here by
  MSAC with an adaptive number of iterations (many minimal samples evaluated at once with numpy),
  then refitted on its inliers.
* **Projective** fundamental matrix (perspective cameras), estimated with OpenCV's USAC
  framework (MAGSAC++ scoring, local optimisation, final polishing); the error of a pair is its
  Sampson distance, the first-order approximation of the same Gold Standard error.

Conventions: ``ref`` and ``mov`` are ``(N, 2)`` arrays of pixel coordinates in the reference and
moving images (x to the right, y down, (0, 0) at the centre of the top-left pixel). A fundamental
matrix ``F`` satisfies ``x_mov^T F x_ref = 0`` with homogeneous ``x = (x, y, 1)``; this is
OpenCV's ``findFundamentalMat(ref, mov)`` convention. Residuals are in pixels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np

from pwlreg.core.errors import InputError

#: Fewest pairs each model is estimated from: a minimal sample plus at least two pairs that can
#: vote against a wrong sample (affine: 4 + 2; projective: 7 + 3, OpenCV needs 8 for polishing).
MIN_PAIRS = {"affine": 6, "projective": 10}

EpipolarKind = Literal["affine", "projective"]


@dataclass(frozen=True)
class EpipolarModel:
    """An estimated epipolar geometry and the statistics of its robust fit.

    Attributes
    ----------
    kind : {"affine", "projective"}
        Camera model.
    matrix : np.ndarray
        (3, 3) fundamental matrix with ``x_mov^T F x_ref = 0``. Affine models are scaled so that
        ``a^2 + b^2 + c^2 + d^2 = 1`` (then ``x_mov^T F x_ref`` is the signed Gold Standard
        distance); projective models have unit Frobenius norm.
    threshold : float
        Inlier threshold used in the fit, pixels.
    num_pairs : int
        Number of pairs the model was estimated from.
    num_inliers : int
        Pairs whose residual is at most ``threshold``.
    iterations : int
        Number of minimal samples drawn (affine) or reported 0 when OpenCV does not say.
    rms : float
        Root mean square residual of the inliers, pixels.
    plane : np.ndarray or None
        (3, 3) homography reference -> moving when the pairs lie on one plane
        (:func:`plane_homography`): every ``[e']_x H`` then fits them, ``matrix`` is one of
        those, and its lines hold only on that plane.
    parallax : int
        Pairs of a second matcher whose displacements from the plane of the fitted pairs fixed
        the epipole of ``matrix`` (:func:`parallax_fundamental`) where none, one or two of the
        fitted pairs lay off that plane; 0 when ``matrix`` is the robust fit's (or the plane's).
    """

    kind: EpipolarKind
    matrix: np.ndarray
    threshold: float
    num_pairs: int
    num_inliers: int
    iterations: int
    rms: float
    plane: np.ndarray | None = None
    parallax: int = 0

    def residuals(self, ref: np.ndarray, mov: np.ndarray) -> np.ndarray:
        """Residual of each pair, pixels.

        Affine: the perpendicular (Gold Standard) distance to the hyperplane, exact. Projective:
        the Sampson distance. Both are joint displacements of the two points, so they share a
        threshold scale.
        """
        return sampson_distance(self.matrix, ref, mov)

    def inliers(self, ref: np.ndarray, mov: np.ndarray) -> np.ndarray:
        """Boolean mask of the pairs whose residual is at most :attr:`threshold` and, when the
        model is a :attr:`plane`, that lie within :data:`PLANE_PX` of it: its lines hold only
        there."""
        ok = self.residuals(ref, mov) <= self.threshold
        if self.plane is not None:
            ok &= transfer_distance(self.plane, ref, mov) <= PLANE_PX
        return ok

    def to_dict(self) -> dict:
        """JSON-able summary (``matrix`` as nested lists, convention ``x_mov^T F x_ref = 0``)."""
        return {
            "kind": self.kind,
            "matrix": [[float(v) for v in row] for row in self.matrix],
            "convention": "x_moving^T F x_reference = 0, pixels, (0,0) = centre of top-left pixel",
            "threshold_px": float(self.threshold),
            "num_pairs": int(self.num_pairs),
            "num_inliers": int(self.num_inliers),
            "iterations": int(self.iterations),
            "rms_px": float(self.rms),
            "plane": None if self.plane is None else [[float(v) for v in row]
                                                      for row in self.plane],
            "parallax_pairs": int(self.parallax),
        }


def sampson_distance(F: np.ndarray, ref: np.ndarray, mov: np.ndarray) -> np.ndarray:
    """Sampson distance of each pair to ``x_mov^T F x_ref = 0``, pixels.

    ``|x'^T F x| / sqrt((F x)_1^2 + (F x)_2^2 + (F^T x')_1^2 + (F^T x')_2^2)``. For an affine
    ``F`` the constraint is linear in ``(x', y', x, y)`` and this is exactly the perpendicular
    distance to its hyperplane.

    Parameters
    ----------
    F : np.ndarray
        (3, 3) fundamental matrix, or a stack (..., 3, 3) of them.
    ref, mov : np.ndarray
        (N, 2) pixel coordinates in the reference and moving images.

    Returns
    -------
    np.ndarray
        (..., N) float64 distances (``inf`` where the denominator vanishes).
    """
    ref = np.asarray(ref, dtype=np.float64).reshape(-1, 2)
    mov = np.asarray(mov, dtype=np.float64).reshape(-1, 2)
    F = np.asarray(F, dtype=np.float64)
    Fx = ref @ np.swapaxes(F[..., :, :2], -1, -2) + F[..., None, :, 2]  # F [x, y, 1]^T
    Ftxp = mov @ F[..., :2, :] + F[..., None, 2, :]  # F^T [x', y', 1]^T
    num = np.abs(np.sum(mov * Fx[..., :2], axis=-1) + Fx[..., 2])
    den = np.sqrt(Fx[..., 0] ** 2 + Fx[..., 1] ** 2 + Ftxp[..., 0] ** 2 + Ftxp[..., 1] ** 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        d = num / den
    return np.where(den > 0, d, np.inf)


# --- the planar degeneracy -----------------------------------------------------------------------

#: Largest distance (pixels of the moving image) of a pair from the homography of the others
#: for it to lie on their plane: twice the default epipolar threshold.
PLANE_PX = 3.0

#: Fewest pairs off the plane of the others that check each other: the epipole lies where the
#: lines of their displacements from the plane meet, and two of them meet anywhere. On the
#: trust suite's scenes of seeds 70-73 (automatic pairs), the true matches of the pixels 10 px
#: or more off the pairs' plane lay a median 5-95 px from their estimated epipolar lines when
#: no pair was off it (15 scenes), 0.9-65 px with one or two (11 scenes), and 0.02-2.3 px
#: with three or more (0.3 px or less on 27 of 33 scenes).
PARALLAX_PAIRS = 3


def apply_homography(H: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Map (N, 2) points through a 3x3 homography (NaN or infinite where it sends them to
    infinity)."""
    q = np.asarray(points, np.float64) @ H[:, :2].T + H[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        return q[:, :2] / q[:, 2:3]


def transfer_distance(H: np.ndarray, ref: np.ndarray, mov: np.ndarray) -> np.ndarray:
    """Distance (pixels) of each moving point from where ``H`` maps its reference point."""
    with np.errstate(invalid="ignore"):
        d = np.hypot(*(apply_homography(H, ref) - np.asarray(mov, np.float64)).T)
    return np.where(np.isfinite(d), d, np.inf)


def plane_homography(ref: np.ndarray, mov: np.ndarray, *, seed: int = 0) -> np.ndarray | None:
    """The homography reference -> moving of the plane most pairs lie on, or None.

    Pairs on one plane (a flat scene, or matches found on the ground only) fit every
    fundamental matrix ``[e']_x H`` (Hartley & Zisserman, *Multiple View Geometry*, 2nd ed.,
    sec. 11.9): a robust fit picks one of them, whose lines pass through the plane's points in
    an arbitrary direction. Off the plane they miss the true matches by as much as those move
    apart from it, and a search along them finds lookalikes; and an outlier that happens to
    lie on the chosen lines passes the filter. The pairs farther than :data:`PLANE_PX` from
    this homography (OpenCV's USAC, MAGSAC++ score, fitted to all of them) are those that
    determine the epipole.

    Parameters
    ----------
    ref, mov : np.ndarray
        (N, 2) pixel coordinates of the pairs.
    seed : int
        State of the fit's random generator.

    Returns
    -------
    np.ndarray or None
        (3, 3) homography with ``H[2, 2] = 1``; None when fewer than 4 pairs are given or no
        homography fits.
    """
    ref = np.ascontiguousarray(ref, np.float64).reshape(-1, 2)
    mov = np.ascontiguousarray(mov, np.float64).reshape(-1, 2)
    if len(ref) < 4:
        return None
    try:
        H, _ = cv2.findHomography(ref, mov, usac_params(PLANE_PX, seed, 0.999, 10_000))
    except cv2.error:  # USAC asserts on some degenerate samples
        return None
    if H is None or H.shape != (3, 3) or not np.isfinite(H).all() or H[2, 2] == 0:
        return None
    return H / H[2, 2]


def plane_fundamental(H: np.ndarray) -> np.ndarray:
    """One fundamental matrix a plane allows, ``[e']_x H`` with the epipole at infinity along
    x (horizontal lines in the moving image), unit Frobenius norm."""
    F = _cross_matrix(np.array([1.0, 0.0, 0.0])) @ np.asarray(H, np.float64)
    return F / np.linalg.norm(F)


#: Fewest pairs besides the fixed ones whose displacements from the plane point to the epipole
#: :func:`parallax_fundamental` picks, at least :data:`PARALLAX_SHARE` of the candidates off
#: the plane, and how many times the support of the matrix it replaces that must be. Two lines
#: meet anywhere, and a lookalike lies on a given epipole's line by chance: with one fixed
#: pair and pairs placed at random in both 640 x 480 images (3000 sets each), the best
#: proposal gathered 4 or more besides the fixed pair in 35 % of the sets of 60 pairs, 6 in
#: 0.7 %, 8 in none; 12 in none of the sets of 120 (8 in 0.5 %), 24 in none of 240 (12 in
#: 0.1 %).
PARALLAX_SUPPORT = 6
PARALLAX_SHARE = 0.125
PARALLAX_GAIN = 2.0

#: Least spread (pixels, root mean square about their mean) of the displacements from the
#: plane of the pairs that fix an epipole without a fixed pair (:func:`parallax_fundamental`):
#: a pattern repeated on the plane and matched one period off moves every pair alike. Boxes,
#: prisms and gables on the ground (trust suite, seeds 100-103): 30-115 px.
PARALLAX_SPREAD = 2 * PLANE_PX

#: Most proposals of an epipole drawn from two pairs each when no fixed pair pins it
#: (:func:`parallax_fundamental`): 200 pairs off the plane make 19 900.
PARALLAX_PROPOSALS = 4000


def parallax_fundamental(
    H: np.ndarray,
    fixed: tuple[np.ndarray, np.ndarray],
    pairs: tuple[np.ndarray, np.ndarray],
    current: np.ndarray,
    *,
    threshold: float,
    seed: int = 0,
) -> tuple[np.ndarray, int] | None:
    """The fundamental matrix ``[e']_x H`` that more pairs off the plane ``H`` support than
    ``current`` does, its epipole fixed by the pairs themselves; None when none does clearly.

    A pair off a plane moves away from where the plane maps it along its epipolar line, so the
    line through both points passes through the epipole ``e'`` (plane plus parallax; Hartley &
    Zisserman, *Multiple View Geometry*, 2nd ed., sec. 13.3). With no, one or two such pairs
    the epipole is anywhere, anywhere on one line, or where two nearly parallel lines meet, and
    a robust fit picks it at random: its lines then miss the true matches away from the plane
    by tens of pixels. Here the epipole must lie on the lines of every ``fixed`` pair (the
    checked pairs off the plane); each other pair off the plane proposes where (its line's
    intersection with the first fixed pair's, or that line's point at infinity), or, without
    a fixed pair, each two of them do (where their lines meet; at most
    :data:`PARALLAX_PROPOSALS` of them, drawn with ``seed``). The proposal most pairs support
    (Sampson distance at most ``threshold``, the fixed pairs among them) wins, refitted by
    least squares to its supporters' lines. It must be supported by at least
    :data:`PARALLAX_SUPPORT` pairs besides the fixed ones (besides the two that proposed it,
    without) and :data:`PARALLAX_SHARE` of the candidates off the plane, and by
    :data:`PARALLAX_GAIN` times as many pairs as ``current``; without a fixed pair, also
    :data:`PARALLAX_GAIN` times as many as its best rival (the best proposal that shares at
    most two supporters with it), and its supporters' displacements from the plane must spread
    over :data:`PARALLAX_SPREAD` (root mean square about their mean): lookalikes of a texture
    meet near some point together and as well near others, and those of a pattern repeated on
    the plane, all one period off, meet where their parallel lines do.

    The fixed pairs may be wrong themselves: a corner of an occluding edge over the plane,
    matched where the two surfaces make the same corner, moves off the plane with no depth
    of its own. When no epipole on their lines passes, the other pairs alone propose one
    (as without a fixed pair), which must also gather :data:`PARALLAX_GAIN` times as many
    pairs as the best epipole on the fixed pairs' lines, those counted; failing that, each
    fixed pair is tried alone (all of the above with that pair as the only fixed one), and
    a result found for one of them only is kept.

    Parameters
    ----------
    H : np.ndarray
        (3, 3) homography reference -> moving of the plane.
    fixed : (np.ndarray, np.ndarray)
        ``(reference (K, 2), moving (K, 2))`` pairs off the plane that the epipole's lines must
        pass through, K >= 0.
    pairs : (np.ndarray, np.ndarray)
        Candidate pairs ``(reference (M, 2), moving (M, 2))``, of another matcher, on the plane
        or off it (those within :data:`PLANE_PX` of it are left out: they fit every epipole).
    current : np.ndarray
        (3, 3) fundamental matrix to improve on.
    threshold : float
        Largest Sampson distance (pixels) of a supporting pair.
    seed : int
        State of the draw of the proposals without a fixed pair.

    Returns
    -------
    (np.ndarray, int) or None
        The (3, 3) matrix (unit Frobenius norm, the sign of ``current``) and the number of
        supporting pairs besides the fixed ones.
    """
    f_ref = np.asarray(fixed[0], np.float64).reshape(-1, 2)
    f_mov = np.asarray(fixed[1], np.float64).reshape(-1, 2)
    c_ref = np.asarray(pairs[0], np.float64).reshape(-1, 2)
    c_mov = np.asarray(pairs[1], np.float64).reshape(-1, 2)
    off = transfer_distance(H, c_ref, c_mov) > PLANE_PX
    ref = np.concatenate([f_ref, c_ref[off]])
    mov = np.concatenate([f_mov, c_mov[off]])
    k = len(f_ref)
    ones = np.ones((len(ref), 1))
    lines = np.cross(np.hstack([apply_homography(H, ref), ones]), np.hstack([mov, ones]))
    with np.errstate(invalid="ignore", divide="ignore"):
        lines /= np.hypot(lines[:, 0], lines[:, 1])[:, None]
    usable = np.isfinite(lines).all(axis=1)
    # Without the fixed pairs, which may be wrong (and so are left out of its count).
    free = _epipole(H, ref[k:], mov[k:], lines[k:], usable[k:], 0, threshold=threshold,
                    seed=seed)
    if free is not None and not _passes(free, H, ref[k:], mov[k:], 0, current, threshold):
        free = None

    def fixing(rows: np.ndarray) -> tuple[np.ndarray, int] | None:
        """The epipole on the lines of the fixed pairs ``rows``, else ``free`` if it gathers
        PARALLAX_GAIN times the support of the best on them."""
        pick = np.concatenate([rows, np.arange(k, len(ref))])
        n = len(rows)
        pinned = None
        if n and usable[rows].all():
            pinned = _epipole(H, ref[pick], mov[pick], lines[pick], usable[pick], n,
                              threshold=threshold, seed=seed)
            if pinned is not None and _passes(pinned, H, ref[pick], mov[pick], n, current,
                                              threshold):
                return _signed(pinned.matrix, current), int(pinned.support.sum()) - n
        if free is not None and (pinned is None
                                 or free.support.sum() >= PARALLAX_GAIN * pinned.support.sum()):
            return _signed(free.matrix, current), int(free.support.sum())
        return None

    found = fixing(np.arange(k))
    if found is not None or k < 2:
        return found
    # One of the fixed pairs may be right: the one for which alone an epipole passes.
    alone = [a for a in (fixing(np.array([i])) for i in range(k)) if a is not None]
    return alone[0] if len(alone) == 1 else None


@dataclass(frozen=True)
class _Epipole:
    """The best proposal of :func:`_epipole`: its matrix, which pairs support it, the support
    of its best rival and the spread of its supporters' displacements (both without a fixed
    pair only; else 0 and infinity)."""

    matrix: np.ndarray
    support: np.ndarray
    rival: int
    spread: float


def _epipole(H: np.ndarray, ref: np.ndarray, mov: np.ndarray, lines: np.ndarray,
             usable: np.ndarray, k: int, *, threshold: float, seed: int) -> _Epipole | None:
    """The epipole most of the pairs support among the proposals of
    :func:`parallax_fundamental` (through the first ``k`` pairs' lines, or where two lines
    meet), refitted; None without a proposal."""
    if len(ref) - k < PARALLAX_SUPPORT + (0 if k else 2):
        return None
    if k:
        first = lines[0]
        proposals = np.vstack([[first[1], -first[0], 0.0],
                               np.cross(first, lines[k:][usable[k:]])])
    else:
        candidates = lines[usable]
        i, j = _couples(len(candidates), PARALLAX_PROPOSALS, seed)
        proposals = np.cross(candidates[i], candidates[j])
    norm = np.linalg.norm(proposals, axis=1)
    proposals = proposals[norm > 1e-12] / norm[norm > 1e-12, None]
    supports = _supports(proposals, H, ref, mov, threshold)
    pinned = supports[:, :k].all(axis=1)
    proposals, supports = proposals[pinned], supports[pinned]
    if not len(supports):
        return None
    counts = supports.sum(axis=1)
    chosen = int(np.argmax(counts))
    best = supports[chosen]
    rival, spread = 0, np.inf
    if not k:
        apart = (supports & best).sum(axis=1) <= 2
        rival = int(counts[apart].max()) if apart.any() else 0
        shift = mov[best] - apply_homography(H, ref[best])
        spread = float(np.sqrt(np.mean(np.sum((shift - shift.mean(axis=0)) ** 2, axis=1))))
    # The point nearest every supporter's line (the right singular vector of least weight),
    # unless it leaves a fixed pair off its lines or fewer pairs on them.
    F = _cross_matrix(proposals[chosen]) @ H
    refitted = _cross_matrix(np.linalg.svd(lines[best])[2][-1]) @ H
    kept = sampson_distance(refitted, ref, mov) <= threshold
    if kept[:k].all() and kept.sum() >= best.sum():
        F, best = refitted, kept
    return _Epipole(F, best, rival, spread)


def _passes(found: _Epipole, H: np.ndarray, ref: np.ndarray, mov: np.ndarray, k: int,
            current: np.ndarray, threshold: float) -> bool:
    """Whether ``found`` meets the support, share, gain, rival and spread tests of
    :func:`parallax_fundamental`, with ``k`` fixed pairs first in ``ref``/``mov``."""
    count = int(found.support.sum())
    return not (count - k < max(PARALLAX_SUPPORT + (0 if k else 2),
                                PARALLAX_SHARE * (len(ref) - k))
                or count < PARALLAX_GAIN * np.count_nonzero(
                    sampson_distance(current, ref, mov) <= threshold)
                or count < PARALLAX_GAIN * found.rival or found.spread < PARALLAX_SPREAD)


def _signed(F: np.ndarray, current: np.ndarray) -> np.ndarray:
    """``F`` at unit Frobenius norm, with the sign of ``current``."""
    F = F / np.linalg.norm(F)
    return -F if np.sum(F * current) < 0 else F


def _couples(n: int, most: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """The couples ``i < j`` of ``n`` items in the order of :func:`numpy.triu_indices`, or
    ``most`` of them drawn with ``seed`` when there are more, without listing them all (a
    raster's thousands of pairs make millions of couples)."""
    count = n * (n - 1) // 2
    k = (np.arange(count) if count <= most
         else np.sort(np.random.default_rng(seed).choice(count, most, replace=False)))
    rows = np.arange(n)
    first = rows * n - rows * (rows + 1) // 2  # index of the couple (i, i + 1)
    i = np.searchsorted(first, k, side="right") - 1
    return i, k - first[i] + i + 1


def _supports(epipoles: np.ndarray, H: np.ndarray, ref: np.ndarray, mov: np.ndarray,
              threshold: float) -> np.ndarray:
    """(P, N) whether each pair is within ``threshold`` (Sampson distance, pixels) of the
    lines of ``[e']_x H`` for each of the P ``epipoles``, in blocks of about a million
    distances (a few tens of MB)."""
    out = np.empty((len(epipoles), len(ref)), bool)
    block = max(1, 2**20 // max(len(ref), 1))
    for start in range(0, len(epipoles), block):
        F = _cross_matrix(epipoles[start:start + block]) @ H
        out[start:start + block] = sampson_distance(F, ref, mov) <= threshold
    return out


def _cross_matrix(v: np.ndarray) -> np.ndarray:
    """``[v]_x``: the matrix of the cross product with ``v`` (3,), or a stack (..., 3, 3)
    of them for vectors (..., 3)."""
    v = np.asarray(v, np.float64)
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    zero = np.zeros_like(x)
    return np.stack([np.stack([zero, -z, y], axis=-1), np.stack([z, zero, -x], axis=-1),
                     np.stack([-y, x, zero], axis=-1)], axis=-2)


# --- epipolar lines -------------------------------------------------------------------------------


def epipolar_lines(F: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Epipolar lines ``F x`` of ``points`` (N, 2), scaled so that ``(a, b)`` is a unit normal
    (NaN for a degenerate line)."""
    line = np.column_stack([points, np.ones(len(points))]) @ np.asarray(F).T
    with np.errstate(divide="ignore", invalid="ignore"):
        return line / np.hypot(line[:, 0], line[:, 1])[:, None]


def line_direction(line: np.ndarray) -> np.ndarray:
    """Unit direction of each line (its normal turned a quarter)."""
    return np.column_stack([-line[:, 1], line[:, 0]])


def line_foot(line: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Orthogonal projection of each point on its line."""
    distance = np.einsum("ij,ij->i", line[:, :2], points) + line[:, 2]
    return points - distance[:, None] * line[:, :2]


def pixel_scaling(factor: float | np.ndarray) -> np.ndarray:
    """The homogeneous map ``p -> (p + 0.5) / factor - 0.5``: a pixel's position in the image
    scaled by ``1 / factor`` (one number, or one per axis ``(fx, fy)``), pixel centres kept as
    an area average keeps them (:func:`cv2.resize` with ``INTER_AREA``, the blocks of
    :func:`pwlreg.core.tiled.reduce_area`)."""
    fx, fy = np.broadcast_to(np.asarray(factor, dtype=np.float64), (2,))
    return np.array([[1 / fx, 0, 0.5 / fx - 0.5], [0, 1 / fy, 0.5 / fy - 0.5], [0, 0, 1.0]])


def on_level(F: np.ndarray, scale: float) -> np.ndarray:
    """``F`` for pixels of images halved by :func:`cv2.pyrDown` to ``scale`` (a pixel ``p``
    there is ``p / scale`` in the full images: :func:`pwlreg.core.similarity.from_level`)."""
    to_full = np.diag([1.0 / scale, 1.0 / scale, 1.0])
    return to_full.T @ np.asarray(F) @ to_full


# --- affine model ---------------------------------------------------------------------------------


def _stack(ref: np.ndarray, mov: np.ndarray) -> np.ndarray:
    """(N, 4) points ``(x', y', x, y)`` of the joint image space."""
    ref = np.asarray(ref, dtype=np.float64).reshape(-1, 2)
    mov = np.asarray(mov, dtype=np.float64).reshape(-1, 2)
    if len(ref) != len(mov):
        raise InputError(f"{len(ref)} reference points but {len(mov)} moving points", "points")
    return np.hstack([mov, ref])


def _affine_matrix(normal: np.ndarray, offset: float) -> np.ndarray:
    """``F_A`` of the hyperplane ``normal . (x', y', x, y) + offset = 0``."""
    a, b, c, d = normal
    return np.array([[0.0, 0.0, a], [0.0, 0.0, b], [c, d, offset]])


def _tls_hyperplane(X: np.ndarray) -> tuple[np.ndarray, float]:
    """Total-least-squares hyperplane of (N, 4) points: unit normal and offset."""
    centroid = X.mean(axis=0)
    _, _, vt = np.linalg.svd(X - centroid, full_matrices=False)
    normal = vt[-1]
    return normal, -float(normal @ centroid)


def fit_affine_fundamental(ref: np.ndarray, mov: np.ndarray) -> np.ndarray:
    """Least-squares affine fundamental matrix of (at least 4) pairs, no outlier rejection.

    Minimises the sum of squared Gold Standard distances (total least squares of the points
    ``(x', y', x, y)``; Hartley & Zisserman Algorithm 14.1).

    Parameters
    ----------
    ref, mov : np.ndarray
        (N, 2) pixel coordinates, N >= 4.

    Returns
    -------
    np.ndarray
        (3, 3) ``F_A`` with ``x_mov^T F_A x_ref = 0`` and ``a^2 + b^2 + c^2 + d^2 = 1``.
    """
    X = _stack(ref, mov)
    if len(X) < 4:
        raise InputError(f"an affine fundamental matrix needs at least 4 pairs, got {len(X)}")
    normal, offset = _tls_hyperplane(X)
    return _affine_matrix(normal, offset)


def _sample_hyperplanes(X: np.ndarray, samples: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Hyperplanes through each 4-point sample, vectorised.

    ``X`` is (N, 4) (centred and scaled), ``samples`` (S, 4) indices. Returns unit normals (S, 4)
    and offsets (S,); degenerate samples (points not spanning a hyperplane) get a zero normal.
    """
    P = X[samples]  # (S, 4, 4)
    D = P[:, 1:, :] - P[:, :1, :]  # (S, 3, 4) spanning directions
    # Generalised cross product: n_k = (-1)^k det(D without column k).
    cols = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])
    minors = D[:, :, cols]  # (S, 3, 4, 3)
    minors = np.moveaxis(minors, 2, 1)  # (S, 4, 3, 3)
    n = np.linalg.det(minors) * np.array([1.0, -1.0, 1.0, -1.0])
    norm = np.linalg.norm(n, axis=1)
    # Relative degeneracy test: the volume spanned versus the product of the edge lengths.
    scale = np.prod(np.linalg.norm(D, axis=2), axis=1)
    good = norm > 1e-6 * np.maximum(scale, 1e-300)
    n = np.where(good[:, None], n / np.where(norm > 0, norm, 1.0)[:, None], 0.0)
    offset = -np.einsum("sk,sk->s", n, P[:, 0, :])
    return n, offset


def _required_iterations(inlier_ratio: float, confidence: float, sample_size: int) -> float:
    """Samples needed to draw one all-inlier sample with the given confidence."""
    p_good = inlier_ratio**sample_size
    if p_good <= 0.0:
        return math.inf
    if p_good >= 1.0:
        return 0.0
    return math.log(1.0 - confidence) / math.log(1.0 - p_good)


def estimate_affine_fundamental(
    ref: np.ndarray,
    mov: np.ndarray,
    threshold: float = 1.5,
    seed: int = 0,
    confidence: float = 0.999,
    max_iterations: int = 10_000,
    batch: int = 128,
) -> EpipolarModel:
    """Robust affine fundamental matrix: MSAC with adaptive iterations, then inlier refit.

    Minimal samples of 4 pairs are drawn ``batch`` at a time; each defines the hyperplane through
    its 4 points in ``(x', y', x, y)`` and is scored by the MSAC cost
    ``sum(min(r_i^2, threshold^2))`` over all pairs (r = perpendicular distance). Sampling stops
    once the best model's inlier ratio ``w`` makes one more all-inlier sample unlikely
    (``iterations >= log(1 - confidence) / log(1 - w^4)``) or at ``max_iterations``. The best
    model is then refitted by total least squares on its inliers, repeatedly until the inlier
    set stops changing (at most 10 times). When every sample is degenerate (all pairs related
    by one 2-D affine map, so that no hyperplane is determined), the total-least-squares
    hyperplane of all pairs is returned: it fits them all.

    Parameters
    ----------
    ref, mov : np.ndarray
        (N, 2) pixel coordinates of the pairs, N >= 6 (:data:`MIN_PAIRS`).
    threshold : float
        Inlier threshold on the Gold Standard distance, pixels.
    seed : int
        Seed of the sampler; the same input and seed give the same model.
    confidence : float
        Probability of having drawn at least one all-inlier sample.
    max_iterations : int
        Upper bound on the number of minimal samples.
    batch : int
        Samples evaluated together (memory ``batch * N`` floats).

    Returns
    -------
    EpipolarModel
        ``kind="affine"``; call :meth:`EpipolarModel.inliers` for the inlier mask.
    """
    X = _stack(ref, mov)
    n_pairs = len(X)
    if n_pairs < MIN_PAIRS["affine"]:
        raise InputError(
            f"the affine epipolar filter needs at least {MIN_PAIRS['affine']} pairs, got {n_pairs}",
            "points",
        )
    if not np.all(np.isfinite(X)):
        raise InputError("point coordinates must be finite", "points")
    # Isotropic normalisation (same shift and scale for all four coordinates keeps distances).
    centre = X.mean(axis=0)
    spread = float(np.sqrt(np.mean(np.sum((X - centre) ** 2, axis=1)))) or 1.0
    Xn = (X - centre) / spread
    tn2 = (threshold / spread) ** 2

    rng = np.random.default_rng(seed)
    best_cost = math.inf
    best: tuple[np.ndarray, float] | None = None
    needed = float(max_iterations)
    done = 0
    while done < min(needed, max_iterations):
        k = int(min(batch, max_iterations - done))
        samples = rng.integers(0, n_pairs, size=(k, 4))
        s = np.sort(samples, axis=1)
        distinct = np.all(s[:, 1:] != s[:, :-1], axis=1)
        done += k
        samples = samples[distinct]
        if len(samples) == 0:
            continue
        normals, offsets = _sample_hyperplanes(Xn, samples)
        ok = np.any(normals != 0.0, axis=1)
        if not np.any(ok):
            continue
        normals, offsets = normals[ok], offsets[ok]
        r2 = (Xn @ normals.T + offsets) ** 2  # (N, S)
        cost = np.minimum(r2, tn2).sum(axis=0)
        i = int(np.argmin(cost))
        if cost[i] < best_cost:
            best_cost = float(cost[i])
            best = (normals[i], float(offsets[i]))
            w = float(np.count_nonzero(r2[:, i] <= tn2)) / n_pairs
            needed = _required_iterations(w, confidence, 4)
    if best is None:
        # Every sample was degenerate: the pairs are related by one 2-D affine map (no parallax),
        # so they lie on a 2-plane of (x', y', x, y) and any hyperplane through it fits them.
        # The total-least-squares hyperplane of all pairs is one of those.
        best = _tls_hyperplane(Xn)
        best_cost = float(np.minimum((Xn @ best[0] + best[1]) ** 2, tn2).sum())

    normal, offset = best
    inl = np.abs(Xn @ normal + offset) ** 2 <= tn2
    for _ in range(10):
        if np.count_nonzero(inl) < 4:
            break
        cand_normal, cand_offset = _tls_hyperplane(Xn[inl])
        cand_r2 = (Xn @ cand_normal + cand_offset) ** 2
        cand_cost = float(np.minimum(cand_r2, tn2).sum())
        cand_inl = cand_r2 <= tn2
        if cand_cost > best_cost:
            break
        best_cost, normal, offset = cand_cost, cand_normal, cand_offset
        if np.array_equal(cand_inl, inl):
            break
        inl = cand_inl

    # Back to pixels: n . (X - c) / s + o = 0  <=>  n . X + (s o - n . c) = 0.
    offset_px = spread * offset - float(normal @ centre)
    matrix = _affine_matrix(normal, offset_px)
    return _finish("affine", matrix, threshold, ref, mov, done)


# --- projective model -----------------------------------------------------------------------------


#: OpenCV's USAC settings besides the threshold, confidence, iterations and seed, by score:
#: MAGSAC++ with sigma-consensus local optimisation and MAGSAC polishing (the epipolar fits and
#: the plane), or MSAC with inner local optimisation and least-squares polishing (the matcher's
#: global homographies). Always one thread: the same input and seed give the same model.
USAC_SCORES = {
    "magsac": (cv2.SCORE_METHOD_MAGSAC, cv2.LOCAL_OPTIM_SIGMA, 50, cv2.MAGSAC, 10),
    "msac": (cv2.SCORE_METHOD_MSAC, cv2.LOCAL_OPTIM_INNER_LO, 14, cv2.LSQ_POLISHER, 3),
}


def usac_params(threshold: float, seed: int, confidence: float, max_iterations: int, *,
                score: Literal["magsac", "msac"] = "magsac") -> cv2.UsacParams:
    """OpenCV's USAC settings of a robust fit (:data:`USAC_SCORES`)."""
    method, local, local_sample, polisher, polishing = USAC_SCORES[score]
    params = cv2.UsacParams()
    params.threshold = float(threshold)
    params.confidence = float(confidence)
    params.maxIterations = int(max_iterations)
    params.randomGeneratorState = int(seed)
    params.sampler = cv2.SAMPLING_UNIFORM
    params.score = method
    params.loMethod = local
    params.loIterations = 10
    params.loSampleSize = local_sample
    params.final_polisher = polisher
    params.final_polisher_iterations = polishing
    params.isParallel = False
    return params


def estimate_projective_fundamental(
    ref: np.ndarray,
    mov: np.ndarray,
    threshold: float = 1.5,
    seed: int = 0,
    confidence: float = 0.999,
    max_iterations: int = 10_000,
) -> EpipolarModel:
    """Robust projective fundamental matrix with OpenCV's USAC (MAGSAC++ score, polished).

    Parameters
    ----------
    ref, mov : np.ndarray
        (N, 2) pixel coordinates, N >= 10 (:data:`MIN_PAIRS`).
    threshold : float
        Inlier threshold on the Sampson distance, pixels.
    seed : int
        State of OpenCV's random generator; the same input and seed give the same model.
    confidence : float
        Confidence of the adaptive stopping rule.
    max_iterations : int
        Upper bound on the number of minimal samples.

    Returns
    -------
    EpipolarModel
        ``kind="projective"``, unit Frobenius norm.
    """
    X = _stack(ref, mov)
    n_pairs = len(X)
    if n_pairs < MIN_PAIRS["projective"]:
        raise InputError(
            f"the projective epipolar filter needs at least {MIN_PAIRS['projective']} pairs, "
            f"got {n_pairs}",
            "points",
        )
    if not np.all(np.isfinite(X)):
        raise InputError("point coordinates must be finite", "points")
    params = usac_params(threshold, seed, confidence, max_iterations)
    r = np.ascontiguousarray(X[:, 2:], dtype=np.float64)
    m = np.ascontiguousarray(X[:, :2], dtype=np.float64)
    try:
        F, _ = cv2.findFundamentalMat(r, m, params)
    except cv2.error:
        # OpenCV's USAC asserts on some degenerate samples (pairs repeated, all on one plane)
        # where it would otherwise find no model.
        F = None
    if F is None or F.shape != (3, 3) or not np.all(np.isfinite(F)):
        raise InputError("no projective fundamental matrix fits the point pairs", "points")
    F = F / np.linalg.norm(F)
    return _finish("projective", F, threshold, ref, mov, 0)


def estimate_fundamental(
    ref: np.ndarray,
    mov: np.ndarray,
    kind: EpipolarKind = "affine",
    threshold: float = 1.5,
    seed: int = 0,
) -> EpipolarModel:
    """Robust fundamental matrix of the given kind (see :func:`estimate_affine_fundamental` and
    :func:`estimate_projective_fundamental`)."""
    if kind == "affine":
        return estimate_affine_fundamental(ref, mov, threshold=threshold, seed=seed)
    if kind == "projective":
        return estimate_projective_fundamental(ref, mov, threshold=threshold, seed=seed)
    raise InputError(f"unknown epipolar model {kind!r}", "options.epipolar_model")


def _finish(
    kind: EpipolarKind,
    matrix: np.ndarray,
    threshold: float,
    ref: np.ndarray,
    mov: np.ndarray,
    iterations: int,
) -> EpipolarModel:
    r = sampson_distance(matrix, ref, mov)
    inl = r <= threshold
    rms = float(np.sqrt(np.mean(r[inl] ** 2))) if np.any(inl) else math.nan
    return EpipolarModel(
        kind=kind,
        matrix=matrix,
        threshold=float(threshold),
        num_pairs=len(r),
        num_inliers=int(np.count_nonzero(inl)),
        iterations=int(iterations),
        rms=rms,
    )
