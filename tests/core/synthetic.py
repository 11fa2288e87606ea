"""Small synthetic pairs with exact ground truth for core tests.

The *moving* image is a texture; the *reference* image is built by sampling it through a known
piecewise-affine map (an "open book": two planes meeting at the vertical crease ``x = crease``),
so the true correspondence of every reference pixel is known exactly.
"""

from __future__ import annotations

import cv2
import numpy as np


def texture(shape: tuple[int, int], seed: int, sigma: float = 2.0) -> np.ndarray:
    """Band-limited random texture, uint8, full contrast."""
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.random(shape).astype(np.float32), (0, 0), sigma)
    img = (img - img.min()) / (img.max() - img.min())
    return np.round(img * 255).astype(np.uint8)


def captioned(image: np.ndarray) -> np.ndarray:
    """``image`` with a caption (bottom left) and a logo (top right) burned in: the same pixels
    on any image."""
    out = image.copy()
    for k, line in enumerate(["2026-11-29 14:03:17", "CAM 2  ALT 120 m", "N 48.8566 E 2.3522"]):
        for colour, thickness in ((0, 4), (255, 2)):
            cv2.putText(out, line, (10, 300 + 18 * k), cv2.FONT_HERSHEY_SIMPLEX, 0.6, colour,
                        thickness, cv2.LINE_AA)
    cv2.rectangle(out, (400, 10), (470, 40), 255, 2)
    cv2.putText(out, "LOGO", (408, 32), cv2.FONT_HERSHEY_SIMPLEX, 0.6, 255, 2)
    return out


def book_map(x: np.ndarray, y: np.ndarray, crease: float) -> tuple[np.ndarray, np.ndarray]:
    """True position in the moving image of reference pixel (x, y): identity left of the
    crease, a shear and compression right of it (continuous across the crease)."""
    right = x > crease
    d = x - crease
    mx = np.where(right, crease + 0.65 * d, x)
    my = np.where(right, y + 0.35 * d, y)
    return mx, my


def open_book(
    size: tuple[int, int] = (200, 160), crease: float = 100.0, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Reference and moving uint8 images of the open-book scene."""
    w, h = size
    moving = texture((h + 80, w + 40), seed)[:h, :w].copy()
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    mx, my = book_map(xs, ys, crease)
    reference = cv2.remap(
        moving,
        mx.astype(np.float32),
        my.astype(np.float32),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REFLECT,
    )
    return reference, moving


def book_points(crease: float = 100.0) -> tuple[np.ndarray, np.ndarray]:
    """Points whose Delaunay mesh has diagonals crossing the crease.

    Crease vertices are 80 px apart vertically, their left and right neighbours only 60 px apart
    horizontally, so Delaunay prefers the short diagonals, which cross the crease.
    """
    ref = []
    for y in (0, 80, 159):
        ref.append((crease, y))
    for y in (40, 120):
        ref.append((crease - 30, y))
        ref.append((crease + 30, y))
    for y in (0, 80, 159):
        ref.append((20, y))
        ref.append((180, y))
    ref_arr = np.array(ref, dtype=np.float64)
    mx, my = book_map(ref_arr[:, 0], ref_arr[:, 1], crease)
    return ref_arr, np.stack([mx, my], axis=1)


def box_front(
    size: tuple[int, int] = (320, 240),
    box: tuple[int, int, int, int] = (110, 70, 210, 170),
    shifts: tuple[int, int] = (4, 16),
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A box in front of a wall, seen by a rectified stereo pair: reference, moving (uint8) and
    the true disparity of every reference pixel (reference ``(x, y)`` is moving
    ``(x - d, y)``).

    The wall moves ``shifts[0]`` pixels left, the box ``box = (x0, y0, x1, y1)`` (reference
    pixels, end excluded) ``shifts[1]``: depth steps along the box's outline, horizontal
    epipolar lines.
    """
    w, h = size
    x0, y0, x1, y1 = box
    wall_shift, box_shift = shifts
    wall = texture((h, w + wall_shift), seed)  # column c: moving x = c - wall_shift
    front = texture((h, w), seed + 1)  # column c: moving x = c
    reference = wall[:, :w].copy()
    reference[y0:y1, x0:x1] = front[y0:y1, x0 - box_shift:x1 - box_shift]
    moving = wall[:, wall_shift:].copy()
    moving[y0:y1, x0 - box_shift:x1 - box_shift] = front[y0:y1, x0 - box_shift:x1 - box_shift]
    disparity = np.full((h, w), float(wall_shift))
    disparity[y0:y1, x0:x1] = box_shift
    return reference, moving, disparity
