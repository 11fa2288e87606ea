"""Loader for the real two-view pairs in ``shared/data/real`` and their ground truth.

Every pair folder holds two images and, depending on its family, a ground truth:

* ``strecha_*``: calibrated cameras (``*.camera``, Strecha format); the fundamental matrix follows.
* ``oxford_*``: a homography ``H1toNp`` from the first image to the second.
* ``middlebury*``: a dense disparity map of the reference (left) image.
* ``lightglue_*``: no ground truth.

The first image of a folder is the *reference*, the second the *moving* image. Conventions follow
:mod:`core.imaging`: images are OpenCV arrays (BGR, uint8), pixel coordinates have x to the right,
y down and (0, 0) at the centre of the top-left pixel. Fundamental matrices satisfy
``x_moving^T F x_reference = 0``; homographies map reference pixels to moving pixels.

This module does file I/O and is for benchmarks and tests only; :mod:`core` never imports it.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from pwlreg.core.epipolar import sampson_distance

ENV_VAR = "PWLREG_REAL_DATA"

# folder -> (reference file, moving file, ground-truth family)
PAIRS: dict[str, tuple[str, str, str]] = {
    "strecha_castle_p19": ("0002.jpg", "0003.jpg", "strecha"),
    "strecha_herzjesu_p8": ("0002.jpg", "0004.jpg", "strecha"),
    "strecha_entry_p10": ("0004.jpg", "0005.jpg", "strecha"),
    "oxford_leuven": ("img1.ppm", "img5.ppm", "oxford"),
    "oxford_graf": ("img1.ppm", "img3.ppm", "oxford"),
    "middlebury2001_venus": ("im2.ppm", "im6.ppm", "middlebury"),
    "middlebury2001_sawtooth": ("im2.ppm", "im6.ppm", "middlebury"),
    "middlebury2003_cones": ("im2.ppm", "im6.ppm", "middlebury"),
    "middlebury2003_teddy": ("im2.ppm", "im6.ppm", "middlebury"),
    "lightglue_facade": ("DSC_0410.JPG", "DSC_0411.JPG", "none"),
    "lightglue_sacre_coeur_daynight": ("sacre_coeur1.jpg", "sacre_coeur2.jpg", "none"),
}


@dataclass(frozen=True)
class Camera:
    """A calibrated pinhole camera (Strecha format).

    Attributes
    ----------
    K : np.ndarray
        (3, 3) intrinsic matrix, pixels.
    R : np.ndarray
        (3, 3) camera-to-world rotation (its columns are the camera axes in the world frame).
    C : np.ndarray
        (3,) camera centre in world coordinates, metres.
    size : tuple of int
        Image ``(width, height)`` in pixels.
    """

    K: np.ndarray
    R: np.ndarray
    C: np.ndarray
    size: tuple[int, int]

    @property
    def P(self) -> np.ndarray:  # noqa: N802 - the usual name of a projection matrix
        """(3, 4) projection matrix ``K [R^T | -R^T C]``."""
        Rt = self.R.T
        return self.K @ np.hstack([Rt, (-Rt @ self.C)[:, None]])


@dataclass(frozen=True)
class RealPair:
    """One real image pair with whatever ground truth its folder provides.

    Attributes
    ----------
    name : str
        Folder name, e.g. ``"strecha_castle_p19"``.
    family : str
        ``"strecha"``, ``"oxford"``, ``"middlebury"`` or ``"none"``.
    reference, moving : np.ndarray
        The two images, OpenCV BGR uint8 arrays (possibly of different sizes).
    F : np.ndarray or None
        (3, 3) true fundamental matrix, ``x_moving^T F x_reference = 0`` (Strecha; derived from
        the cameras, unit Frobenius norm).
    H : np.ndarray or None
        (3, 3) true homography mapping reference pixels to moving pixels (Oxford).
    disparity : np.ndarray or None
        (H, W) float64 disparity of the reference image in pixels, NaN where unknown
        (Middlebury); reference pixel (x, y) corresponds to moving pixel (x - d, y).
    cameras : tuple of Camera or None
        Reference and moving cameras (Strecha).
    """

    name: str
    family: str
    reference: np.ndarray
    moving: np.ndarray
    F: np.ndarray | None = None
    H: np.ndarray | None = None
    disparity: np.ndarray | None = None
    cameras: tuple[Camera, Camera] | None = None

    @property
    def has_truth(self) -> bool:
        """True when the pair has a ground truth to score matches against."""
        return self.F is not None or self.H is not None or self.disparity is not None


def default_root() -> Path:
    """Folder of the real pairs: ``$PWLREG_REAL_DATA`` or ``<repo>/../shared/data/real``."""
    env = os.environ.get(ENV_VAR)
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "real"


def available_pairs(root: Path | None = None) -> list[str]:
    """Names of the known pairs present under ``root`` (all of :data:`PAIRS` order)."""
    root = default_root() if root is None else Path(root)
    return [name for name in PAIRS if (root / name).is_dir()]


def read_image(path: Path) -> np.ndarray:
    """Read an image file unchanged (8/16 bit, grey or BGR); raise ``FileNotFoundError``."""
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise FileNotFoundError(f"cannot read image {path}")
    return image


def read_strecha_camera(path: Path) -> Camera:
    """Read a Strecha ``.camera`` file (K, distortion, R, C, size; see the pair's SOURCE.md)."""
    rows = [line.split() for line in Path(path).read_text().splitlines() if line.strip()]
    values = [[float(v) for v in row] for row in rows]
    K = np.array(values[0:3])
    R = np.array(values[4:7])
    C = np.array(values[7])
    size = (int(values[8][0]), int(values[8][1]))
    return Camera(K=K, R=R, C=C, size=size)


def fundamental_from_cameras(ref: Camera, mov: Camera) -> np.ndarray:
    """Fundamental matrix of two calibrated cameras, ``x_mov^T F x_ref = 0``, unit Frobenius norm.

    ``F = K_m^-T [t]_x R K_r^-1`` with ``R = R_m^T R_r`` and ``t = R_m^T (C_r - C_m)`` (the
    reference camera frame expressed in the moving camera frame).
    """
    R = mov.R.T @ ref.R
    t = mov.R.T @ (ref.C - mov.C)
    tx = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    F = np.linalg.inv(mov.K).T @ tx @ R @ np.linalg.inv(ref.K)
    F /= np.linalg.norm(F)
    return F if F[2, 2] <= 0 else -F


def read_homography(path: Path) -> np.ndarray:
    """Read a 3x3 plain-text homography (Oxford ``H1toNp``), normalised to ``H[2, 2] = 1``."""
    H = np.loadtxt(path).reshape(3, 3)
    return H / H[2, 2]


def read_disparity(folder: Path) -> np.ndarray:
    """Reference-image disparity of a Middlebury folder (``gt.json``), pixels, NaN = unknown."""
    folder = Path(folder)
    meta = json.loads((folder / "gt.json").read_text())
    raw = read_image(folder / meta["disparity"]).astype(np.float64)
    disparity = raw / float(meta["scale"])
    disparity[raw == float(meta["invalid"])] = np.nan
    return disparity


def load_pair(name: str, root: Path | None = None) -> RealPair:
    """Load one pair (images and ground truth) by folder name.

    Raises
    ------
    KeyError
        ``name`` is not one of :data:`PAIRS`.
    FileNotFoundError
        The folder or one of its files is missing.
    """
    ref_file, mov_file, family = PAIRS[name]
    folder = (default_root() if root is None else Path(root)) / name
    if not folder.is_dir():
        raise FileNotFoundError(f"no real-data folder {folder}")
    reference = read_image(folder / ref_file)
    moving = read_image(folder / mov_file)
    kwargs: dict = {}
    if family == "strecha":
        cams = (
            read_strecha_camera(folder / f"{ref_file}.camera"),
            read_strecha_camera(folder / f"{mov_file}.camera"),
        )
        kwargs["cameras"] = cams
        kwargs["F"] = fundamental_from_cameras(*cams)
    elif family == "oxford":
        (h_file,) = sorted(folder.glob("H1to*p"))
        kwargs["H"] = read_homography(h_file)
    elif family == "middlebury":
        kwargs["disparity"] = read_disparity(folder)
    return RealPair(name=name, family=family, reference=reference, moving=moving, **kwargs)


# --- errors against the ground truth ------------------------------------------------------------


def transfer_error(H: np.ndarray, ref: np.ndarray, mov: np.ndarray) -> np.ndarray:
    """Distance (pixels, moving image) between ``H ref`` and ``mov`` for each pair."""
    x = np.column_stack([ref, np.ones(len(ref))]) @ H.T
    return np.hypot(x[:, 0] / x[:, 2] - mov[:, 0], x[:, 1] / x[:, 2] - mov[:, 1])


def disparity_error(disparity: np.ndarray, ref: np.ndarray, mov: np.ndarray) -> np.ndarray:
    """Distance (pixels) between ``mov`` and the true match ``(x - d, y)`` of ``ref``.

    The disparity is read at the nearest reference pixel; pairs whose disparity is unknown (or
    outside the map) get NaN.
    """
    h, w = disparity.shape
    col = np.rint(ref[:, 0]).astype(int)
    row = np.rint(ref[:, 1]).astype(int)
    inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
    d = np.full(len(ref), np.nan)
    d[inside] = disparity[row[inside], col[inside]]
    return np.hypot(ref[:, 0] - d - mov[:, 0], ref[:, 1] - mov[:, 1])


def truth_error(pair: RealPair, ref: np.ndarray, mov: np.ndarray) -> tuple[np.ndarray, str] | None:
    """Error of matched pairs against the pair's ground truth, and the name of the measure.

    Returns ``(errors, measure)`` with errors in pixels: the Sampson distance to the true F
    (``"sampson"``, Strecha), the transfer error through the true H (``"transfer"``, Oxford) or
    the distance to the true disparity match (``"disparity"``, Middlebury, NaN where unknown);
    ``None`` when the pair has no ground truth.
    """
    if pair.F is not None:
        return sampson_distance(pair.F, ref, mov), "sampson"
    if pair.H is not None:
        return transfer_error(pair.H, ref, mov), "transfer"
    if pair.disparity is not None:
        return disparity_error(pair.disparity, ref, mov), "disparity"
    return None
