"""Direct photometric alignment of a mesh's moving vertices, its triangulation fixed.

The matcher and the insertion place each vertex by a patch around it alone; the mesh, though,
maps every pixel of its triangles by the vertices' positions. :func:`align_vertices` moves the
free vertices together so that the reference, mapped through the mesh, matches the moving image
over all the triangles' pixels (Gauss-Newton with Levenberg-Marquardt damping, coarse to fine).
Each triangle has its own gain and bias (a face's light and exposure) and the images are first
locally normalized (a monotone tone curve is locally affine); the residuals are weighted by a
Cauchy function (occluded pixels and surfaces the triangle does not follow). The result is a
proposal: :func:`core.correct.aligned_vertices` keeps a vertex's new position only where its
star's consistency (the swaps' cost) does not fall.

Measured (``python -m bench.beyond --frame``, automatic points): Middlebury's frame mean
endpoint error 0.510 / 0.342 / 0.973 / 1.146 -> 0.494 / 0.325 / 0.924 / 1.105 px. Told the
truth, the best positions for the same triangles would give 0.196 / 0.126 / 0.716 / 0.616 px:
most of the mesh's error on planes is its vertices' own sub-pixel error (a quarter of a pixel
at the median there, where the images themselves disagree by about as much across the rows).
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy.sparse.linalg import LinearOperator, cg

from pwlreg.core.kernels import align_sums
from pwlreg.core.similarity import to_level

#: Blur (pixels) of the successive levels and the Gauss-Newton steps on each, the images
#: themselves last: the blur widens the capture range, the images decide.
SCHEDULE = ((1.5, 1), (0.0, 2))

#: Scale (pixels) of the local normalization, and its floor on the local deviation (grey
#: levels of 8 bits): flat areas are not amplified into noise.
NORMALIZE_SIGMA = 3.0
NORMALIZE_FLOOR = 4.0

#: Levenberg-Marquardt damping (times the diagonal), and a floor on every unknown's weight
#: (times the median diagonal): a vertex no pixel sees stays where it is.
DAMPING = 1.0
PRIOR = 0.01

#: A vertex the alignment takes farther than this (pixels) stays where it was: larger errors
#: are the other moves' work, and a long move is most often a vertex following a surface it
#: does not belong to.
REACH = 2.0

#: Cauchy scale in units of the residuals' deviation (95 % efficiency under Gaussian noise).
CAUCHY = 2.385

#: Bounds of a triangle's gain (moving to reference): outside, the triangle's pixels hardly
#: constrain its vertices.
GAIN_RANGE = (0.2, 5.0)


def normalized(image: np.ndarray, *, sigma: float = NORMALIZE_SIGMA,
               floor: float = NORMALIZE_FLOOR) -> np.ndarray:
    """``image`` less its local mean over its local deviation (Gaussian windows of ``sigma``),
    the deviation at least ``floor``; float32 levels of 8 bits (a 16-bit image is scaled)."""
    img = np.asarray(image, dtype=np.float32)
    if image.dtype == np.uint16:
        img = img * np.float32(255.0 / 65535.0)
    mean = cv2.GaussianBlur(img, (0, 0), sigma)
    var = cv2.GaussianBlur(img * img, (0, 0), sigma) - mean * mean
    return (img - mean) / np.sqrt(np.maximum(var, 0.0) + floor * floor)


def align_vertices(
    reference: np.ndarray,
    moving: np.ndarray,
    reference_vertices: np.ndarray,
    moving_vertices: np.ndarray,
    triangles: np.ndarray,
    movable: np.ndarray,
    *,
    scale: float = 1.0,
    schedule: tuple[tuple[float, int], ...] = SCHEDULE,
    reach: float = REACH,
) -> np.ndarray:
    """Moving positions of the ``movable`` vertices that align the images through the mesh.

    Parameters
    ----------
    reference, moving : ndarray, shape (H, W) and (H', W')
        Grey images (uint8 or uint16 luminance), reduced by ``scale``
        (:func:`core.similarity.reduced`).
    reference_vertices, moving_vertices : ndarray, shape (N, 2)
        The mesh's vertices in both full images (pixels).
    triangles : ndarray of int, shape (T, 3)
        The mesh's triangles.
    movable : ndarray of bool, shape (N,)
        The vertices that may move; the others stay (given points).
    schedule : tuple of (float, int)
        Blur (pixels) of each level, coarse to fine, and its Gauss-Newton steps.
    scale : float
        Pixels of the images given per pixel of the full images.
    reach : float
        Longest move kept (pixels); a vertex moved farther stays where it was.

    Returns
    -------
    ndarray, shape (N, 2)
        The new moving positions in the full images (a copy; the vertices that did not move
        as they were).
    """
    ref_v = np.asarray(reference_vertices, dtype=np.float64)
    start = np.asarray(moving_vertices, dtype=np.float64)
    tris = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    free = np.flatnonzero(np.asarray(movable, bool))
    out = start.copy()
    if not len(tris) or not len(free):
        return out
    n = len(ref_v)
    # Unknowns: the x then y of each free vertex; the fixed ones' columns drop out.
    unknown = np.full(2 * n, -1, np.int64)
    unknown[2 * free] = np.arange(len(free))
    unknown[2 * free + 1] = len(free) + np.arange(len(free))
    index = unknown[np.concatenate([2 * tris, 2 * tris + 1], axis=1)]  # (T, 6)
    # Every pixel counts: sampling every other one biased the vertices by a few tenths of a
    # pixel on synthetic scenes whose matcher was within 0.07 px.
    ref_n, mov_n = normalized(reference), normalized(moving)

    def level(points: np.ndarray) -> np.ndarray:
        return np.ascontiguousarray(to_level(points, scale))

    ref_tris = level(ref_v[tris])
    m = start.copy()
    for sigma, iterations in schedule:
        ref_l = cv2.GaussianBlur(ref_n, (0, 0), sigma) if sigma > 0 else ref_n
        mov_l = cv2.GaussianBlur(mov_n, (0, 0), sigma) if sigma > 0 else mov_n
        moments = None
        for _ in range(iterations):
            step, moments = _step(ref_l, mov_l, ref_tris, level(m[tris]), index, 2 * len(free),
                                  moments)
            if step is None:
                break
            m[free, 0] += step[:len(free)] / scale
            m[free, 1] += step[len(free):] / scale
    keep = np.hypot(*(m - start).T) <= reach
    out[keep] = m[keep]
    return out


def _step(
    ref_l: np.ndarray, mov_l: np.ndarray, ref_tris: np.ndarray, mov_tris: np.ndarray,
    index: np.ndarray, size: int, moments: np.ndarray | None,
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """One damped Gauss-Newton step of the unknowns (None when no pixel constrains them), and
    the triangles' moments at the positions it started from.

    The triangles' gains and biases come from ``moments`` (the last step's, None to measure
    them first): a pass over the pixels fewer per step, the gains a step behind.

    The normal equations stay as the triangles' 6 x 6 blocks, ``index`` (T, 6) their unknowns
    (-1 for a fixed vertex's): conjugate gradients multiply by them block by block, without
    assembling the sparse matrix (a sparse LU of Middlebury's 1340 unknowns took 3 ms a step).
    """
    count = len(ref_tris)
    if moments is None:
        # The moments alone (scale 0): the kernel reads no gain and writes no system.
        moments = np.zeros((count, 6))
        align_sums(ref_tris, mov_tris, ref_l, mov_l, np.zeros(0), np.zeros(0), 0.0, moments,
                   np.zeros((0, 6, 6)), np.zeros((0, 6)))
    k, sm, sr, smm, smr, srr = moments.T
    seen = k >= 3
    kk = np.maximum(k, 1.0)
    var_m = smm - sm * sm / kk
    cov = smr - sm * sr / kk
    gain = np.where(seen & (var_m > 1e-9 * kk), cov / np.maximum(var_m, 1e-12), 1.0)
    gain = np.clip(gain, *GAIN_RANGE)
    bias = (sr - gain * sm) / kk
    # The residuals' deviation: the median over the triangles of each one's own, after its gain
    # and bias.
    spread = (srr - 2 * gain * smr - 2 * bias * sr + gain * gain * smm + 2 * gain * bias * sm
              + bias * bias * k) / kk
    if not seen.any():
        return None, None
    deviation = float(np.median(np.sqrt(np.maximum(spread[seen], 0.0))))
    if deviation <= 0.0:
        return None, None
    system, vector, moments = np.zeros((count, 6, 6)), np.zeros((count, 6)), np.zeros((count, 6))
    align_sums(ref_tris, mov_tris, ref_l, mov_l, gain, bias,
               CAUCHY * deviation, moments, system, vector)
    has = index >= 0
    # A fixed vertex's rows and columns are zero: its unknown is a padding slot, dropped.
    slot = np.where(has, index, size)
    system[~has, :] = 0.0
    system.transpose(0, 2, 1)[~has, :] = 0.0
    grad = np.bincount(slot.ravel(), weights=vector.ravel(), minlength=size + 1)[:size]
    diagonal = np.bincount(slot.ravel(), weights=np.diagonal(system, axis1=1, axis2=2).ravel(),
                           minlength=size + 1)[:size]
    if not np.any(diagonal > 0):
        return None, None
    regular = (1.0 + DAMPING) * diagonal + PRIOR * float(np.median(diagonal[diagonal > 0]))

    def product(x: np.ndarray) -> np.ndarray:
        blocks = np.einsum("tij,tj->ti", system, np.append(x, 0.0)[slot])
        return (np.bincount(slot.ravel(), weights=blocks.ravel(), minlength=size + 1)[:size]
                - diagonal * x + regular * x)

    operator = LinearOperator((size, size), matvec=product, dtype=np.float64)
    jacobi = LinearOperator((size, size), matvec=lambda x: x / regular, dtype=np.float64)
    step, _ = cg(operator, -grad, M=jacobi, rtol=1e-4, maxiter=200)
    return step, moments
