"""Pixel-type conventions shared by matching, scoring and warping.

Images are numpy arrays as OpenCV holds them: ``(H, W)`` grey or ``(H, W, C)`` with channels in
BGR(A) order, dtype ``uint8`` or ``uint16``. Pixel coordinates: x to the right, y down, (0, 0) is
the centre of the top-left pixel.
"""

from __future__ import annotations

import cv2
import numpy as np

from pwlreg.core.errors import InputError

SUPPORTED_DTYPES = (np.uint8, np.uint16)


def check_image(image: np.ndarray, field: str) -> None:
    """Raise :class:`InputError` unless ``image`` is a 2-D or 3-D uint8/uint16 array."""
    if not isinstance(image, np.ndarray) or image.ndim not in (2, 3):
        raise InputError(f"{field} must be a 2-D (grey) or 3-D (colour) image array", field)
    if image.dtype not in SUPPORTED_DTYPES:
        raise InputError(f"{field} must be 8- or 16-bit, got dtype {image.dtype}", field)
    if image.ndim == 3 and image.shape[2] not in (1, 3, 4):
        raise InputError(f"{field} must have 1, 3 or 4 channels, got {image.shape[2]}", field)
    if min(image.shape[:2]) < 2:
        raise InputError(f"{field} is too small: {image.shape[1]}x{image.shape[0]} pixels", field)


def max_value(image: np.ndarray) -> int:
    """Largest representable value of the image's dtype (255 or 65535)."""
    return int(np.iinfo(image.dtype).max)


def to_gray(image: np.ndarray) -> np.ndarray:
    """Luminance of a grey, BGR or BGRA image, same dtype (ITU-R BT.601 weights, OpenCV's)."""
    if image.ndim == 2:
        return image
    if image.shape[2] == 1:
        return image[:, :, 0]
    if image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY)
    return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)


def to_gray8(image: np.ndarray) -> np.ndarray:
    """8-bit luminance, for matching (16-bit values are scaled by 255/65535 and rounded)."""
    gray = to_gray(image)
    if gray.dtype == np.uint8:
        return gray
    return np.round(gray.astype(np.float32) * (255.0 / 65535.0)).astype(np.uint8)
