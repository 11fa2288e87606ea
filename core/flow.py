"""The residual optical flow of a registration: what is left between the reference and the
moving image resampled by a mesh (the *registered* image).

Where the mesh is right the two differ by little, a small motion that a dense optical flow
(OpenCV's DIS) measures well even on wide-baseline pairs where it fails on the raw images. The
vertex insertion (:mod:`core.refine`) reads new pairs from it; the verdict (:mod:`core.quality`)
measures with it how much of the mesh the images contradict.
"""

from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor

import cv2
import numpy as np

#: Longest side (pixels) of the finest scale of the residual flow. DIS's medium preset stops at
#: half the level's side: on the 1024x682 facade level 22.5 ms a pass, against 5-7 ms at a
#: quarter, for the same result (synthetic 1024x768 scenes, seeds 1-2, 19 cases: mean endpoint
#: error 13.55 px at half the side, 13.53 px at a quarter; 1083 and 1072 pairs inserted).
FLOW_SIDE = 320

#: Side (pixels) of the patches of DIS's medium preset.
DIS_PATCH = 8


def coarsest_scale(shape: tuple[int, ...], patch: int = DIS_PATCH) -> int:
    """The coarsest scale DIS starts from on an image of ``shape``, as OpenCV computes it: a
    search range of a quarter of the longer side, and no level shorter than a patch. A finest
    scale above it leaves DIS with no level to run (OpenCV 5.0 then reads memory it did not
    write: a 40x1500 image crashed the process); negative on images DIS cannot measure (a
    side under a patch, where OpenCV's rounding toward zero says 0 and DIS crashes too)."""
    longer, shorter = max(shape[:2]), min(shape[:2])
    return min(int(math.log2(longer / (4.0 * patch)) + 0.5), math.floor(math.log2(shorter / patch)))


def flow_scale(shape: tuple[int, ...], side: int = FLOW_SIDE) -> int:
    """DIS's finest scale (a power of two) that brings an image of ``shape`` to at most
    ``side`` pixels a side: at least 1 as in its medium preset, but never above
    :func:`coarsest_scale` (0 on images too short for scale 1)."""
    scale = 1
    while max(shape[:2]) / 2**scale > side:
        scale += 1
    return max(min(scale, coarsest_scale(shape)), 0)


def residual_flows(
    reference: np.ndarray, registered: np.ndarray, *, side: int = FLOW_SIDE
) -> tuple[np.ndarray, np.ndarray]:
    """DIS flow (medium preset, finest scale :func:`flow_scale` for ``side``) from the
    reference to the registered image and back: two float32 ``(H, W, 2)`` arrays of
    ``(dx, dy)`` pixels.

    Both images are grey uint8 of the same shape. On an image too small for DIS
    (:func:`coarsest_scale` negative: a side under 8 pixels or both under 12) the flows are NaN:
    nothing measured.
    """
    if coarsest_scale(reference.shape) < 0:
        unmeasured = np.full((*reference.shape[:2], 2), np.nan, np.float32)
        return unmeasured, unmeasured.copy()
    finest = flow_scale(reference.shape, side)

    def flow(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
        dis.setFinestScale(finest)
        return dis.calc(a, b, None)

    # OpenCV lets go of the GIL, and one flow keeps the second core only partly busy: the two
    # directions side by side took 15-23 % less time on two cores (1024x768 and 512x384), with
    # the same flows.
    with ThreadPoolExecutor(max_workers=1) as pool:
        backward = pool.submit(flow, registered, reference)
        return flow(reference, registered), backward.result()


def forward_backward_error(forward: np.ndarray, backward: np.ndarray) -> np.ndarray:
    """Per pixel, how far the backward flow at the forward flow's end misses the start
    (pixels, float32 ``(H, W)``): near 0 where the flow is trustworthy."""
    h, w = forward.shape[:2]
    end_x = forward[..., 0] + np.arange(w, dtype=np.float32)
    end_y = forward[..., 1] + np.arange(h, dtype=np.float32)[:, None]
    back = [cv2.remap(np.ascontiguousarray(backward[..., k]), end_x, end_y, cv2.INTER_LINEAR,
                      borderMode=cv2.BORDER_REPLICATE) for k in (0, 1)]
    return np.hypot(forward[..., 0] + back[0], forward[..., 1] + back[1])
