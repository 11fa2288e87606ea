"""Dense ground truth of the Middlebury stereo pairs, and conjugate points drawn from it.

The folders ``middlebury*`` of the real-data directory hold rectified stereo pairs (``im2.ppm``
left = reference, ``im6.ppm`` right = moving) with the disparity of both views (see each folder's
``SOURCE.md`` and ``gt.json``). Reference pixel ``(x, y)`` truly corresponds to the moving point
``(x - d(x, y), y)``, where ``d = value / scale`` and ``value == invalid`` (0) means unknown.

Conventions: images are OpenCV arrays (grey ``(H, W)`` or BGR ``(H, W, 3)``, uint8); pixel
coordinates have x to the right, y down, (0, 0) at the centre of the top-left pixel.

The data are located at ``$PWLREG_REAL_DATA`` if set, else at ``<repo>/../shared/data/real``.
They are read in place, never copied. This module does file I/O and is for benchmarks and tests
only; :mod:`core` never imports it.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

__all__ = [
    "ENV_VAR",
    "MIDDLEBURY_PAIRS",
    "StereoTruth",
    "available_middlebury",
    "load_middlebury",
    "real_data_root",
    "sample_points",
]

ENV_VAR = "PWLREG_REAL_DATA"
"""Environment variable overriding the real-data directory."""

MIDDLEBURY_PAIRS: tuple[str, ...] = (
    "middlebury2001_sawtooth",
    "middlebury2001_venus",
    "middlebury2003_cones",
    "middlebury2003_teddy",
)
"""Folder names of the known Middlebury pairs."""


def real_data_root() -> Path:
    """Real-data directory: ``$PWLREG_REAL_DATA`` or ``<repo>/../shared/data/real``."""
    env = os.environ.get(ENV_VAR)
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"


def available_middlebury(root: Path | None = None) -> list[str]:
    """Names of the Middlebury pairs whose folder (with ``gt.json``) exists under ``root``."""
    root = real_data_root() if root is None else Path(root)
    return [n for n in MIDDLEBURY_PAIRS if (root / n / "gt.json").is_file()]


@dataclass(frozen=True, eq=False)
class StereoTruth:
    """A rectified stereo pair with its dense correspondence.

    Attributes
    ----------
    name : str
        Folder name, e.g. ``"middlebury2001_sawtooth"``.
    reference, moving : ndarray of uint8
        Left and right images, grey ``(H, W)`` or BGR ``(H, W, 3)``.
    disparity : ndarray of float64, shape (H, W)
        Reference disparity in pixels; NaN where unknown.
    truth_x, truth_y : ndarray of float64, shape (H, W)
        True position in the moving image of each reference pixel: ``(x - d, y)``; NaN where
        the disparity is unknown.
    valid : ndarray of bool, shape (H, W)
        Pixels to score: known disparity, true position inside ``[0, W - 1]`` of the moving
        image and, when the pair has a moving-view disparity, consistent with it (left-right
        check, i.e. not occluded in the moving view).
    known : ndarray of bool, shape (H, W)
        Pixels with a known disparity.
    mapped : ndarray of bool, shape (H, W)
        ``valid`` without the left-right check: known disparity, true position inside the
        moving image (pixels occluded in the moving view included).
    """

    name: str
    reference: np.ndarray
    moving: np.ndarray
    disparity: np.ndarray
    truth_x: np.ndarray
    truth_y: np.ndarray
    valid: np.ndarray
    known: np.ndarray
    mapped: np.ndarray

    @property
    def shape(self) -> tuple[int, int]:
        """``(H, W)`` of the reference image."""
        return self.disparity.shape


def _read(path: Path, flags: int) -> np.ndarray:
    image = cv2.imread(str(path), flags)
    if image is None:
        raise FileNotFoundError(f"cannot read image {path}")
    return image


def _disparity(folder: Path, file: str, meta: dict) -> np.ndarray:
    raw = _read(folder / file, cv2.IMREAD_UNCHANGED).astype(np.float64)
    if raw.ndim == 3:
        raw = raw[:, :, 0]
    disparity = raw / float(meta["scale"])
    disparity[raw == float(meta["invalid"])] = np.nan
    return disparity


def load_middlebury(
    name: str,
    root: Path | None = None,
    color: Literal["gray", "bgr"] = "gray",
    occlusion_tolerance: float | None = 1.0,
) -> StereoTruth:
    """Load a Middlebury pair and its dense truth.

    Parameters
    ----------
    name : str
        One of :data:`MIDDLEBURY_PAIRS` (any folder with a ``gt.json`` works).
    root : Path, optional
        Real-data directory; default :func:`real_data_root`.
    color : {"gray", "bgr"}
        Image format returned (grey uses OpenCV's BT.601 luminance).
    occlusion_tolerance : float or None
        Left-right check (pixels): a reference pixel is valid only if the moving-view disparity
        at its match (nearest pixel) differs from its own by at most this. None disables the
        check (then ``valid`` includes pixels occluded in the moving view).

    Returns
    -------
    StereoTruth

    Raises
    ------
    FileNotFoundError
        The folder, its ``gt.json`` or one of its images is missing.
    """
    folder = (real_data_root() if root is None else Path(root)) / name
    meta_file = folder / "gt.json"
    if not meta_file.is_file():
        raise FileNotFoundError(f"no Middlebury ground truth at {meta_file}")
    meta = json.loads(meta_file.read_text())
    flags = cv2.IMREAD_GRAYSCALE if color == "gray" else cv2.IMREAD_COLOR
    reference = _read(folder / meta["reference"], flags)
    moving = _read(folder / meta["moving"], flags)
    disparity = _disparity(folder, meta["disparity"], meta)
    height, width = disparity.shape
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float64)
    truth_x = xs - disparity
    truth_y = np.where(np.isfinite(disparity), ys, np.nan)
    known = np.isfinite(disparity)
    w2 = moving.shape[1]
    with np.errstate(invalid="ignore"):
        mapped = known & (truth_x >= 0) & (truth_x <= w2 - 1)
    valid = mapped.copy()
    if occlusion_tolerance is not None and meta.get("disparity_moving"):
        d6 = _disparity(folder, meta["disparity_moving"], meta)
        col = np.clip(np.rint(np.nan_to_num(truth_x, nan=0.0)).astype(np.int64), 0, w2 - 1)
        back = d6[ys.astype(np.int64), col]
        with np.errstate(invalid="ignore"):
            valid &= np.abs(back - disparity) <= occlusion_tolerance
    return StereoTruth(
        name=name,
        reference=reference,
        moving=moving,
        disparity=disparity,
        truth_x=truth_x,
        truth_y=truth_y,
        valid=valid,
        known=known,
        mapped=mapped,
    )


def sample_points(
    pair: StereoTruth,
    n: int = 100,
    seed: int = 0,
    method: Literal["corners", "grid"] = "corners",
    noise: float = 0.0,
    min_distance: float = 8.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Conjugate points drawn from the truth, deterministic from ``seed``.

    Reference points are pixel centres (so their truth is exact), chosen among pixels whose
    3x3 neighbourhood is ``valid``; each is mapped to the moving image by the truth.

    Parameters
    ----------
    pair : StereoTruth
    n : int
        Number of points wanted (fewer if the image has fewer candidates).
    seed : int
        Seed of the random choices and of the noise.
    method : {"corners", "grid"}
        ``"corners"``: Shi-Tomasi corners of the reference (``cv2.goodFeaturesToTrack``, at
        least ``min_distance`` apart), ``n`` of them drawn at random (what a corner detector
        plus a perfect tracker would give). ``"grid"``: one random valid pixel in each cell of a
        grid of about ``n`` cells (the folders' ``dense_check`` baseline).
    noise : float
        Standard deviation (pixels) of Gaussian noise added independently to every coordinate
        of both point sets.
    min_distance : float
        Minimum distance between corners (pixels), ``"corners"`` only.

    Returns
    -------
    points_reference, points_moving : ndarray of float64, shape (N, 2)
        Pixel coordinates, x right, y down.
    """
    if n < 1:
        raise ValueError("n must be >= 1")
    rng = np.random.default_rng(seed)
    height, width = pair.shape
    ok = cv2.erode(pair.valid.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    if method == "corners":
        gray = pair.reference if pair.reference.ndim == 2 else cv2.cvtColor(
            pair.reference, cv2.COLOR_BGR2GRAY)
        corners = cv2.goodFeaturesToTrack(
            gray, maxCorners=0, qualityLevel=0.01, minDistance=float(min_distance),
            mask=ok.astype(np.uint8), blockSize=5,
        )
        xy = np.zeros((0, 2)) if corners is None else corners.reshape(-1, 2).astype(np.float64)
        xy = np.rint(xy)
        xy = xy[ok[xy[:, 1].astype(int), xy[:, 0].astype(int)]]
        if len(xy) > n:
            xy = xy[np.sort(rng.choice(len(xy), size=n, replace=False))]
    elif method == "grid":
        cell = np.sqrt(height * width / n)
        rows = max(1, int(round(height / cell)))
        cols = max(1, int(round(width / cell)))
        ys, xs = np.nonzero(ok)
        cell_id = (ys * rows // height) * cols + (xs * cols // width)
        order = rng.permutation(len(xs))
        _, first = np.unique(cell_id[order], return_index=True)
        pick = order[first]
        xy = np.column_stack([xs[pick], ys[pick]]).astype(np.float64)
    else:
        raise ValueError(f"unknown method {method!r}; expected 'corners' or 'grid'")
    col, row = xy[:, 0].astype(np.int64), xy[:, 1].astype(np.int64)
    mov = np.column_stack([pair.truth_x[row, col], pair.truth_y[row, col]])
    ref = xy
    if noise > 0:
        ref = ref + rng.normal(0.0, noise, ref.shape)
        mov = mov + rng.normal(0.0, noise, mov.shape)
    return ref, mov
