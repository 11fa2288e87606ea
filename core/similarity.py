"""Per-triangle joint histograms and the consistency measures built on them.

The reference pixels of a triangle (the fill rule of :mod:`core.raster`) are paired with the
moving image resampled bilinearly through the triangle's affine map. Each triangle yields a joint
histogram of ``M x M`` grey-level bins and six moments, all additive over disjoint pixel sets:
the statistics of a quad, or of the whole mesh, are sums of its triangles'.

Mutual information is in bits: ``MI = H(A) + H(B) - H(A, B)``; the paper normalises it as
``NMI = MI / H(A, B)`` (not scikit-image's ``(H(A) + H(B)) / H(A, B)``).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache

import cv2
import numpy as np

from pwlreg.core import kernels
from pwlreg.core.imaging import max_value, to_gray

#: :data:`core.kernels.PARALLEL_TRIANGLES`, which the compiled search uses too.
PARALLEL_TRIANGLES = kernels.PARALLEL_TRIANGLES

MOMENTS = ("n", "sum_a", "sum_b", "sum_aa", "sum_bb", "sum_ab")
"""Order of the per-triangle moments (a: reference grey level, b: resampled moving level)."""


@dataclass(frozen=True)
class ScoringImages:
    """Both images prepared once for scoring.

    Attributes
    ----------
    shape : (int, int)
        ``(height, width)`` of the reference image.
    bins : int
        Grey-level bins per image (M).
    reference_bins : ndarray of uint8 or uint16, shape (H * W,)
        Bin of every reference pixel, row-major.
    reference_values : ndarray of uint8 or uint16, shape (H * W,)
        Reference luminance of every pixel, row-major (a view, not a copy, where possible).
    moving : ndarray of uint8 or uint16, shape (H', W')
        Moving luminance.
    reference_scale, moving_scale : float
        ``1 / G`` for each image: multiply a level by it to get a value in [0, 1] (moments).
    moving_bin_offset, moving_bin_scale : float
        A resampled moving level ``v`` falls in bin
        ``floor((v - moving_bin_offset) * moving_bin_scale)``, clipped to ``[0, M - 1]``.
    """

    shape: tuple[int, int]
    bins: int
    reference_bins: np.ndarray
    reference_values: np.ndarray
    moving: np.ndarray
    reference_scale: float
    moving_scale: float
    moving_bin_offset: float
    moving_bin_scale: float


def level_range(gray: np.ndarray, tail: float = 5e-4) -> tuple[np.ndarray, int, int]:
    """Grey levels ``(lo, hi)`` spanned by an image, ignoring a ``tail`` fraction at each end
    and the levels apart from the scene's (:func:`_main_levels`), and the image with those
    clipped to the scene's levels.

    The bins of the joint histogram cover this range rather than the whole dtype: 12-bit data
    stored in 16 bits, or a dark 8-bit photo, would otherwise fall into one or two bins. A
    full-range 8-bit image (with at least 0.05 % of its pixels at each end) keeps the paper's
    bins over 0..255.

    Returns
    -------
    gray : ndarray
        ``gray`` itself, or a copy with its levels apart from the scene's clipped to the
        scene's first or last level, so that no reduced level (:func:`reduced`) spreads them
        over the levels between.
    lo, hi : int
    """
    if gray.dtype in (np.uint8, np.uint16):
        counts = np.zeros(max_value(gray) + 1, dtype=np.int64)
        kernels.level_counts(gray.ravel(), counts)  # np.bincount's counts, 4 x faster
    else:
        counts = np.bincount(gray.ravel(), minlength=max_value(gray) + 1)
    first, last = _main_levels(counts)
    below, above = int(counts[:first].sum()), int(counts[last + 1:].sum())
    if (below or above) and _isolated((gray < first) | (gray > last)):
        gray = np.clip(gray, first, last)
        counts = counts.copy()
        counts[first] += below
        counts[last] += above
        counts[:first] = 0
        counts[last + 1:] = 0
    cdf = np.cumsum(counts)
    total = cdf[-1]
    lo = int(np.searchsorted(cdf, tail * total, side="right"))
    hi = int(np.searchsorted(cdf, (1.0 - tail) * total, side="left"))
    return gray, lo, max(hi, lo)


def _isolated(mask: np.ndarray) -> bool:
    """Whether the pixels of ``mask`` stand mostly alone: on average less than one other of
    them among their 8 neighbours (hot or dead pixels; the lines of a drawing have two)."""
    around = cv2.boxFilter(mask.astype(np.uint8), cv2.CV_16U, (3, 3), normalize=False,
                           borderType=cv2.BORDER_CONSTANT)
    return float(np.mean(around[mask])) < 2.0


GAP_IQRS = 4
"""An empty run of grey levels longer than this many interquartile ranges (and than
:data:`MIN_GAP` levels) parts the levels in use into groups (:func:`_main_levels`)."""
MIN_GAP = 32


def _main_levels(counts: np.ndarray) -> tuple[int, int]:
    """First and last grey level of the group of levels, parted from the others by no empty
    run longer than the gap (:data:`GAP_IQRS`, :data:`MIN_GAP`), that holds the median.

    Hot or dead pixels sit apart from the scene's levels: counted in the range, they stretched
    it over the empty levels between (16-bit data in 1000-1400 with 0.3 % of its pixels at
    65535 fell into one bin of the joint histogram, and the verdict called a 0.5 px result
    unreliable). They fall into the end bins instead, when they stand alone
    (:func:`_isolated`; a drawing's lines, apart from its paper by as wide a gap, keep their
    levels). A photograph's levels have no such gap: its range is unchanged.
    """
    used = np.flatnonzero(counts)
    cdf = np.cumsum(counts[used])
    q1, median, q3 = (used[np.searchsorted(cdf, q * cdf[-1], side="left")]
                      for q in (0.25, 0.5, 0.75))
    gap = max(GAP_IQRS * (q3 - q1), MIN_GAP)
    parted = np.flatnonzero(np.diff(used) > gap + 1)  # last used level of each group but one
    starts = np.concatenate([[0], parted + 1])
    ends = np.concatenate([parted, [len(used) - 1]])
    group = np.searchsorted(used[ends], median, side="left")
    return int(used[starts[group]]), int(used[ends[group]])


def prepare_images(reference: np.ndarray, moving: np.ndarray, bins: int) -> ScoringImages:
    """Luminance of both images, and the bin of every reference pixel.

    With ``(lo, hi)`` the :func:`level_range` of an image, its grey level ``g`` falls in bin
    ``floor((g - lo) * M / (hi - lo + 1))`` clipped to ``[0, M - 1]``; resampled moving levels
    are binned the same way with the moving image's range. Nothing larger than one or two bytes
    per pixel is allocated (32-megapixel pairs stay well under 1 GB).
    """
    ref, r_lo, r_hi = level_range(np.ascontiguousarray(to_gray(reference)))
    mov, m_lo, m_hi = level_range(np.ascontiguousarray(to_gray(moving)))
    levels = np.arange(max_value(ref) + 1, dtype=np.int64)
    lut = np.clip((levels - r_lo) * bins // (r_hi - r_lo + 1), 0, bins - 1).astype(
        np.uint8 if bins <= 256 else np.uint16
    )
    if ref.dtype == np.uint8 and lut.dtype == np.uint8:
        ref_bins = cv2.LUT(ref, lut).ravel()  # lut[ref], 7 x faster
    else:
        ref_bins = lut[ref].ravel()
    return ScoringImages(
        shape=(ref.shape[0], ref.shape[1]),
        bins=bins,
        reference_bins=ref_bins,
        reference_values=ref.ravel(),
        moving=mov,
        reference_scale=1.0 / max_value(ref),
        moving_scale=1.0 / max_value(mov),
        moving_bin_offset=float(m_lo),
        moving_bin_scale=bins / (m_hi - m_lo + 1.0),
    )


def reduced(
    images: ScoringImages, max_side: int, *, bins: int | None = None
) -> tuple[ScoringImages, float]:
    """Both images halved (Gaussian pyramid) until the reference's longer side is at most
    ``max_side`` or it holds at most the pixels of a ``max_side`` x ``3/4 max_side`` image, and
    the scale: a pixel ``p`` of either image is ``p * scale`` there (:func:`to_level`). Both are
    halved the same number of times, so a shift means the same in both. ``bins`` (default:
    those of ``images``) is the joint histogram's size there.

    The second bound changes nothing up to an aspect of 4:3 and keeps a strip's level wide
    enough to judge: a 1600 x 240 pair went down to 400 x 60, where 3 of its 1459 triangles
    held enough pixels to be judged, and a registration 0.16 px off was called unreliable."""
    bins = images.bins if bins is None else bins
    ref = images.reference_values.reshape(images.shape)
    mov = images.moving
    scale = 1.0
    while max(ref.shape) > max_side and ref.size > max_side * max_side * 3 // 4:
        ref, mov = cv2.pyrDown(ref), cv2.pyrDown(mov)
        scale /= 2
    if scale == 1.0 and bins == images.bins:
        return images, 1.0
    return prepare_images(ref, mov, bins), scale


def to_level(points: np.ndarray, scale: float) -> np.ndarray:
    """Pixels of the full images -> of images halved by :func:`cv2.pyrDown` to ``scale``
    (:func:`reduced`): each halving centres its pixel ``i`` on pixel ``2 i`` (not on the
    middle of pixels ``2 i`` and ``2 i + 1``, as an area average does), so the centre of the
    top-left pixel stays where it is and a position is only scaled."""
    return np.asarray(points, dtype=np.float64) * scale


def from_level(points: np.ndarray, scale: float) -> np.ndarray:
    """Pixels of images halved by :func:`cv2.pyrDown` to ``scale`` -> of the full images
    (the inverse of :func:`to_level`)."""
    return np.asarray(points, dtype=np.float64) / scale


def smoothed(images: ScoringImages, sigma: float) -> ScoringImages:
    """Both images blurred by a Gaussian of ``sigma`` pixels, prepared again for scoring."""
    ref = images.reference_values.reshape(images.shape)

    def blur(gray: np.ndarray) -> np.ndarray:
        out = cv2.GaussianBlur(gray.astype(np.float32), (0, 0), sigma)
        return np.clip(np.rint(out), 0, np.iinfo(gray.dtype).max).astype(gray.dtype)

    return prepare_images(blur(ref), blur(images.moving), images.bins)


def triangle_statistics(
    images: ScoringImages,
    reference_triangles: np.ndarray,
    moving_triangles: np.ndarray,
    with_moments: bool = False,
    *,
    hist_out: np.ndarray | None = None,
    moments_out: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray | None]:
    """Joint histograms (and optionally moments) of many triangles in one batched pass.

    Parameters
    ----------
    images : ScoringImages
        From :func:`prepare_images`.
    reference_triangles, moving_triangles : ndarray, shape (T, 3, 2)
        Corresponding triangle vertices in pixels (quantized).
    with_moments : bool
        Also return the six moments of :data:`MOMENTS` (grey levels scaled to [0, 1]).
    hist_out : ndarray of int32 or int64, shape (T, M * M), optional
        Zeroed C-contiguous array the histograms are counted into and returned (a cache's rows:
        no temporary and no copy).
    moments_out : ndarray of float64, shape (T, 6), optional
        Likewise for the moments (with ``with_moments``).

    Returns
    -------
    hist : ndarray of int64, shape (T, M * M)
        Row-major joint histogram ``h[a * M + b]`` (a: reference bin, b: moving bin);
        ``hist_out`` if given.
    moments : ndarray of float64, shape (T, 6) or None
    """
    ref_tri = np.ascontiguousarray(reference_triangles, dtype=np.float64).reshape(-1, 3, 2)
    mov_tri = np.ascontiguousarray(moving_triangles, dtype=np.float64).reshape(-1, 3, 2)
    n_tri = len(ref_tri)
    m = images.bins
    hist = np.zeros((n_tri, m * m), dtype=np.int64) if hist_out is None else hist_out
    if not with_moments:
        moments = np.zeros((0, 6), dtype=np.float64)
    elif moments_out is None:
        moments = np.zeros((n_tri, 6), dtype=np.float64)
    else:
        moments = moments_out
    if n_tri:
        _count(images, ref_tri, mov_tri, hist, moments)
    return hist, (moments if with_moments else None)


def group_statistics(
    images: ScoringImages,
    reference_triangles: np.ndarray,
    moving_triangles: np.ndarray,
    owner: np.ndarray,
    groups: int,
    with_moments: bool = False,
) -> tuple[np.ndarray, np.ndarray | None]:
    """:func:`triangle_statistics` summed by group, without a row per triangle.

    Parameters
    ----------
    images : ScoringImages
    reference_triangles, moving_triangles : ndarray, shape (T, 3, 2)
    owner : ndarray of int, shape (T,)
        Each triangle's group, in ``[0, groups)``.
    groups : int
    with_moments : bool

    Returns
    -------
    hist : ndarray of int64, shape (groups, M * M)
        The sum of the group's triangles' histograms (the same counts).
    moments : ndarray of float64, shape (groups, 6) or None
        The sum of its triangles' moments, added in their order (the same values bit for bit
        as summing :func:`triangle_statistics`' rows in that order).
    """
    ref_tri = np.ascontiguousarray(reference_triangles, dtype=np.float64).reshape(-1, 3, 2)
    mov_tri = np.ascontiguousarray(moving_triangles, dtype=np.float64).reshape(-1, 3, 2)
    owner = np.asarray(owner, dtype=np.int64)
    order = np.argsort(owner, kind="stable")
    starts = np.searchsorted(owner[order], np.arange(groups + 1))
    m = images.bins
    hist = np.zeros((groups, m * m), dtype=np.int64)
    moments = np.zeros((groups if with_moments else 0, 6), dtype=np.float64)
    if len(ref_tri):
        _count(images, ref_tri[order], mov_tri[order], hist, moments, starts)
    return hist, (moments if with_moments else None)


def _count(
    images: ScoringImages,
    ref_tri: np.ndarray,
    mov_tri: np.ndarray,
    hist: np.ndarray,
    moments: np.ndarray,
    starts: np.ndarray | None = None,
) -> None:
    """Count the triangles' histograms (and moments, if ``moments`` has rows) into ``hist``:
    a row each (``starts`` None; on threads from :data:`PARALLEL_TRIANGLES` triangles), or a
    row for each group of consecutive triangles ``starts[g]:starts[g + 1]``."""
    images_args = (images.reference_bins, images.reference_values, images.moving,
                   images.shape[1], images.shape[0], images.bins, images.moving_bin_offset,
                   images.moving_bin_scale, images.reference_scale, images.moving_scale, hist,
                   moments)
    if starts is None and len(ref_tri) < PARALLEL_TRIANGLES:
        kernels.triangle_histograms(ref_tri, mov_tri, *images_args)
    else:
        kernels.group_histograms(ref_tri, mov_tri,
                                 np.arange(len(ref_tri) + 1) if starts is None else starts,
                                 *images_args)


def mutual_information(hist: np.ndarray, bins: int) -> tuple[np.ndarray, np.ndarray]:
    """MI and NMI (bits) of joint histograms.

    Parameters
    ----------
    hist : ndarray, shape (..., M * M)
        Joint counts, row-major ``h[a * M + b]`` (a: reference bin, b: moving bin).
    bins : int
        M.

    Returns
    -------
    mi : ndarray, shape (...)
        ``H(A) + H(B) - H(A, B)`` in bits (0 for empty histograms).
    nmi : ndarray, shape (...)
        ``MI / H(A, B)`` (0 where ``H(A, B) == 0``).
    """
    h = np.asarray(hist)
    lead = h.shape[:-1]
    rows = np.ascontiguousarray(h.reshape(-1, bins * bins), dtype=np.int64)
    # Each histogram as the sum of itself alone: one kernel for both entry points.
    mi, nmi, _ = summed_information(rows, np.arange(len(rows))[:, None], bins)
    return mi.reshape(lead), nmi.reshape(lead)


@cache
def xlogx_table() -> np.ndarray:
    """``c log2 c`` of the counts below :data:`core.kernels.XLOGX_SIZE` (computed once)."""
    return kernels.xlogx_table(kernels.XLOGX_SIZE)


def summed_information(
    hist: np.ndarray, rows: np.ndarray, bins: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`mutual_information` of sums of histograms, without gathering them.

    Parameters
    ----------
    hist : ndarray, shape (R, M * M)
        Joint counts (int32 or int64), e.g. a cache's table.
    rows : ndarray of int, shape (..., S)
        Each output is the sum of ``S`` rows of ``hist``.
    bins : int
        M.

    Returns
    -------
    mi, nmi, pixels : ndarray, shape (...)
        MI and NMI (bits) of ``hist[rows].sum(axis=-2)``, the same values bit for bit, and its
        total count.
    """
    idx = np.ascontiguousarray(rows, dtype=np.int64)
    lead = idx.shape[:-1]
    idx = idx.reshape(-1, idx.shape[-1])
    mi = np.empty(len(idx))
    nmi = np.empty(len(idx))
    pixels = np.empty(len(idx))
    kernels.summed_information(hist, idx, bins, mi, nmi, pixels, xlogx_table())
    return mi.reshape(lead), nmi.reshape(lead), pixels.reshape(lead)


def ncc(moments: np.ndarray) -> np.ndarray:
    """Normalised cross-correlation in [-1, 1] from summed moments ``(..., 6)``.

    0 where either pixel set has no variance.
    """
    m = np.asarray(moments, dtype=np.float64)
    n = np.maximum(m[..., 0], 1.0)
    cov = m[..., 5] - m[..., 1] * m[..., 2] / n
    va = m[..., 3] - m[..., 1] ** 2 / n
    vb = m[..., 4] - m[..., 2] ** 2 / n
    den = np.sqrt(np.maximum(va, 0.0) * np.maximum(vb, 0.0))
    return np.where(den > 1e-12, cov / np.where(den > 1e-12, den, 1.0), 0.0)


def ssd(moments: np.ndarray) -> np.ndarray:
    """Sum of squared differences (grey levels scaled to [0, 1]) from moments ``(..., 6)``."""
    m = np.asarray(moments, dtype=np.float64)
    return np.maximum(m[..., 3] + m[..., 4] - 2.0 * m[..., 5], 0.0)
