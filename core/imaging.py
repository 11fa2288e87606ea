"""Pixel-type conventions shared by matching, scoring and warping.

Matching, scoring and the registered image work on *pictures*: numpy arrays as OpenCV holds
them, ``(H, W)`` grey or ``(H, W, C)`` with channels in BGR(A) order, dtype ``uint8`` or
``uint16``. Any other input is a *raster*: ``(H, W)`` or ``(H, W, C)`` with its bands in file
order, of any of :data:`RASTER_DTYPES`, possibly a :class:`numpy.ma.MaskedArray` whose mask marks
the invalid pixels (nodata, mask band; NaN samples are invalid too). A masked array is always a
raster, whatever its dtype and band count (so a 3- or 4-band multispectral GeoTIFF is not taken
for BGR(A)). :func:`matching_image` turns either into the picture that matching and scoring use.
Pixel coordinates: x to the right, y down, (0, 0) is the centre of the top-left pixel.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from pwlreg.core.errors import InputError

SUPPORTED_DTYPES = (np.uint8, np.uint16)
RASTER_DTYPES = (np.uint8, np.uint16, np.int16, np.uint32, np.int32, np.float32, np.float64)
"""Sample types a raster may have (GeoTIFF's usual ones)."""
LUMINANCE = "luminance"
RESCALE_PERCENTILES = (0.5, 99.5)
"""Percentiles of the valid samples mapped to 0 and 255 by :func:`matching_image`'s rescale."""
_RESCALE_SAMPLES = 1 << 20
"""Valid samples (on a regular grid) the percentiles are estimated from."""
PICTURE_BAND = {1: (0,), 3: (2, 1, 0), 4: (2, 1, 0, 3)}
"""Array channel of file band 1, 2, ... of a picture (OpenCV keeps colour as BGR(A))."""


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
    """8-bit luminance, for matching: 16-bit luminance is stretched linearly from its 0.5 and
    99.5 percentiles (:data:`RESCALE_PERCENTILES`) to 0 and 255, so that 10- to 14-bit data
    stored in 16 bits (most satellite and aerial rasters) keep their contrast."""
    gray = to_gray(image)
    if gray.dtype == np.uint8:
        return gray
    return np.round(_rescaled(gray, None) * 255.0).astype(np.uint8)


def is_picture(image: np.ndarray) -> bool:
    """Whether ``image`` is a picture (see the module's docstring) rather than a raster."""
    return (
        isinstance(image, np.ndarray)
        and not isinstance(image, np.ma.MaskedArray)
        and image.dtype in SUPPORTED_DTYPES
        and (image.ndim == 2 or (image.ndim == 3 and image.shape[2] in PICTURE_BAND))
    )


def file_bands(image: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """The bands of a picture or raster in file order, and its validity.

    Returns
    -------
    bands : ndarray, shape (H, W, C)
        A view where possible (a picture's BGR(A) channels as R, G, B(, A)).
    valid : ndarray of bool, shape (H, W), or None
        False where any band is masked or not finite, or where a picture's alpha is 0
        (:func:`valid_pixels`); None when every pixel is valid.
    """
    data = np.ma.getdata(image)
    bands = data if data.ndim == 3 else data[:, :, None]
    if is_picture(image):
        return bands[:, :, list(PICTURE_BAND[bands.shape[2]])], valid_pixels(image)
    mask = np.ma.getmask(image)
    invalid = None
    if mask is not np.ma.nomask:
        invalid = mask if mask.ndim == 2 else mask.any(axis=2)
    if bands.dtype.kind == "f":
        nan = ~np.isfinite(bands).all(axis=2)
        invalid = nan if invalid is None else invalid | nan
    return bands, (~invalid if invalid is not None and invalid.any() else None)


def valid_pixels(picture: np.ndarray) -> np.ndarray | None:
    """Where a picture holds data: False where a BGRA picture is fully transparent (alpha 0,
    which is also how :func:`matching_image` marks a raster's invalid pixels); None when every
    pixel is valid."""
    if picture.ndim != 3 or picture.shape[2] != 4:
        return None
    valid = picture[:, :, 3] != 0
    return None if valid.all() else valid


def _filled_transparent(picture: np.ndarray, field: str) -> np.ndarray:
    """A BGRA picture whose colour under alpha 0 is :func:`fill_invalid`'s smooth extension of
    the rest, as a raster's invalid pixels are: what a transparent area happens to hold (black,
    noise, a stale copy of the scene) would otherwise be matched and scored like the image."""
    valid = valid_pixels(picture)
    if valid is None:
        return picture
    if not valid.any():
        raise InputError(f"{field} has no valid pixel (alpha is 0 everywhere)", field)
    out = picture.copy()
    top = max_value(picture)
    for c in range(3):
        filled = fill_invalid(picture[:, :, c].astype(np.float32), valid)
        out[:, :, c] = np.clip(np.round(filled), 0, top)
    return out


def check_raster(image: np.ndarray, field: str) -> None:
    """Raise :class:`InputError` unless ``image`` is a picture or a raster (module docstring)."""
    if not isinstance(image, np.ndarray) or image.ndim not in (2, 3):
        raise InputError(f"{field} must be a 2-D (one band) or 3-D (bands last) array", field)
    if image.dtype not in RASTER_DTYPES:
        names = ", ".join(np.dtype(d).name for d in RASTER_DTYPES)
        raise InputError(f"{field} must have samples of {names}; got {image.dtype}", field)
    if image.ndim == 3 and image.shape[2] < 1:
        raise InputError(f"{field} has no band", field)
    if min(image.shape[:2]) < 2:
        raise InputError(f"{field} is too small: {image.shape[1]}x{image.shape[0]} pixels", field)


def matching_image(image: np.ndarray, band: str = LUMINANCE, field: str = "image") -> np.ndarray:
    """The picture matching and scoring use, from a picture or a raster.

    * A picture with ``band="luminance"`` is used as it is (matching and scoring take its
      luminance, the registered image keeps its colour), except under alpha 0: a BGRA
      picture's fully transparent pixels are invalid, filled as a raster's are (below).
    * A picture with a band number gives that band (1 = red of a colour picture), same dtype
      (as BGRA, the band in B, G and R, when the picture has transparent pixels).
    * A raster gives an 8-bit grey picture: the chosen band, or with ``"luminance"`` the mean
      of all its bands after each is rescaled (so that no band dominates by its units); the
      rescale maps the 0.5 and 99.5 percentiles of the valid samples to 0 and 255
      (:data:`RESCALE_PERCENTILES`, estimated on up to 2**20 valid pixels), clipping the tails
      (specular glints, saturated or dead pixels). 8 bits lose nothing the scoring uses: its
      joint histogram has at most 256 bins per image, and matching works on 8 bits anyway.
    * Invalid pixels (masked, or NaN) are filled with a smooth extension of the valid ones
      (:func:`fill_invalid`), so they hold no edge or corner for the matcher and only
      low-information counts for the joint histograms: the scoring has no validity mask. A
      raster with invalid pixels gives a BGRA picture (grey in B, G and R, alpha 0 where
      invalid), so that they stay transparent in registered.png.

    Parameters
    ----------
    image : ndarray or numpy.ma.MaskedArray
        Picture or raster (module docstring).
    band : str
        ``"luminance"`` or a 1-based band number (as a string or an int).
    field : str
        Name used in error messages.

    Raises
    ------
    InputError
        Not an image, a band it does not have, or no valid pixel.
    """
    return matching_picture(image, band, field)[0]


def matching_picture(image: np.ndarray, band: str = LUMINANCE, field: str = "image"
                     ) -> tuple[np.ndarray, PictureRecipe | None]:
    """:func:`matching_image` and, for a raster, the :class:`PictureRecipe` that made it (None
    for a picture), to make the same picture of other windows of the raster."""
    check_raster(image, field)
    count = 1 if image.ndim == 2 else image.shape[2]
    number = None if band == LUMINANCE else int(band)
    if number is not None and not 1 <= number <= count:
        raise InputError(
            f"option band is {number} but {field} has {count} band(s)", "options.band"
        )
    if is_picture(image):
        # numba compiles its kernels anew for read-only arrays (np.frombuffer, memory maps),
        # outside the warm-up and its lock (core.compilation).
        image = _filled_transparent(image if image.flags.writeable else image.copy(), field)
        if number is None or image.ndim == 2:
            return image, None
        chosen = np.ascontiguousarray(image[:, :, PICTURE_BAND[count][number - 1]])
        valid = valid_pixels(image)
        if valid is None or number == 4:
            return chosen, None
        return np.dstack([chosen, chosen, chosen, image[:, :, 3]]), None
    bands, valid = file_bands(image)
    if valid is not None and not valid.any():
        raise InputError(f"{field} has no valid pixel (all nodata or masked)", field)
    recipe = _recipe(bands, valid, number)
    return apply_recipe(recipe, bands, valid, fill=True), recipe


@dataclass(frozen=True)
class PictureRecipe:
    """How :func:`matching_image` turns a raster's bands into its 8-bit picture, kept so that
    the same picture can be made window by window (:mod:`pwlreg.core.tiled`).

    Attributes
    ----------
    chosen : tuple of int
        0-based bands averaged (one band, or all of them for ``"luminance"``).
    limits : tuple of (float, float)
        Per chosen band, the samples mapped to 0 and 1 (:data:`RESCALE_PERCENTILES`).
    grey_limits : (float, float) or None
        The same for the mean of several bands, None for one band.
    """

    chosen: tuple[int, ...]
    limits: tuple[tuple[float, float], ...]
    grey_limits: tuple[float, float] | None


def _recipe(bands: np.ndarray, valid: np.ndarray | None, number: int | None) -> PictureRecipe:
    """The :class:`PictureRecipe` of a raster's bands (band ``number``, 1-based, or None for
    the luminance), its percentiles estimated on the valid samples."""
    chosen = tuple(range(bands.shape[2])) if number is None else (number - 1,)
    limits = tuple(_limits(bands[:, :, b], valid) for b in chosen)
    grey_limits = None
    if len(chosen) > 1:
        grey = _grey(bands, chosen, limits)
        grey_limits = _limits(grey, valid)
    return PictureRecipe(chosen, limits, grey_limits)


def apply_recipe(recipe: PictureRecipe, bands: np.ndarray, valid: np.ndarray | None, *,
                 fill: bool = False) -> np.ndarray:
    """The 8-bit picture of ``bands`` ``(H, W, C)`` in file order: grey, or BGRA (grey in B, G
    and R, alpha 0 where invalid) when ``valid`` marks invalid pixels; with ``fill`` the
    invalid pixels hold :func:`fill_invalid`'s smooth extension, else 0."""
    grey = _grey(bands, recipe.chosen, recipe.limits)
    if recipe.grey_limits is not None:
        grey = _scaled(grey, *recipe.grey_limits)
    if valid is not None and valid.any():
        grey = fill_invalid(grey, valid) if fill else np.where(valid, grey, 0.0)
    grey8 = np.round(grey * 255.0).astype(np.uint8)
    if valid is None:
        return grey8
    return np.dstack([grey8, grey8, grey8, valid.astype(np.uint8) * np.uint8(255)])


def _grey(bands: np.ndarray, chosen: tuple[int, ...],
          limits: tuple[tuple[float, float], ...]) -> np.ndarray:
    grey = np.zeros(bands.shape[:2], np.float32)
    for b, (lo, hi) in zip(chosen, limits, strict=True):
        grey += _scaled(bands[:, :, b], lo, hi)
    return grey


def _limits(band: np.ndarray, valid: np.ndarray | None) -> tuple[float, float]:
    """The :data:`RESCALE_PERCENTILES` of ``band``'s valid samples (up to 2**20 of them)."""
    step = max(1, int(np.ceil(np.sqrt(band.size / _RESCALE_SAMPLES))))
    sample = band[::step, ::step]
    sample = sample[valid[::step, ::step]] if valid is not None else sample.ravel()
    sample = sample[np.isfinite(sample)] if sample.dtype.kind == "f" else sample
    if sample.size == 0:
        return 0.0, 0.0
    lo, hi = np.percentile(sample, RESCALE_PERCENTILES)
    return float(lo), float(hi)


def _scaled(band: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """``band`` as float32 in [0, 1], ``lo`` and ``hi`` mapped to 0 and 1."""
    span = float(hi - lo) or 1.0
    with np.errstate(invalid="ignore"):
        out = (band.astype(np.float32) - np.float32(lo)) * np.float32(1.0 / span)
    return np.clip(np.nan_to_num(out, copy=False, nan=0.0), 0.0, 1.0, out=out)


def _rescaled(band: np.ndarray, valid: np.ndarray | None) -> np.ndarray:
    """``band`` as float32 in [0, 1], its valid samples' percentiles mapped to 0 and 1."""
    return _scaled(band, *_limits(band, valid))


def fill_invalid(values: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """``values`` with its invalid pixels filled by a smooth extension of the valid ones.

    Push-pull: the valid samples and their weights are averaged down a Gaussian pyramid until
    every pixel of the coarsest level has some weight, then each level's gaps are filled from the
    level below, upsampled (a valid pixel keeps its value). The fill has no edge along the
    border of the valid area and no texture inside it.

    Parameters
    ----------
    values : ndarray of float32, shape (H, W)
    valid : ndarray of bool, shape (H, W)
        At least one pixel valid.
    """
    weight = valid.astype(np.float32)
    level = np.where(valid, values, 0).astype(np.float32)  # weighted: value * weight
    levels = []
    while not (weight > 0).all() and min(level.shape) > 1:
        levels.append((level, weight))
        level, weight = cv2.pyrDown(level), cv2.pyrDown(weight)
    filled = np.where(weight > 0, level / np.maximum(weight, 1e-12), 0.0).astype(np.float32)
    if not (weight > 0).all():
        filled[weight <= 0] = float(values[valid].mean())
    for level, weight in reversed(levels):
        up = cv2.pyrUp(filled, dstsize=(level.shape[1], level.shape[0]))
        filled = level + (1.0 - np.minimum(weight, 1.0)) * up
    return filled
