"""Registration of images too large to hold at full resolution: the search on reduced levels,
the geometry at full resolution.

:func:`register` is :func:`pwlreg.core.pipeline.register` for images of any size. Under
:data:`LEVEL_PIXELS` it is that function. Above, both images are read reduced (area average) by
the same whole factor, the one that leaves the larger at most :data:`LEVEL_PIXELS` pixels (so
that the pair's relative scale is the one the client gave), window by window when from a file
(:class:`pwlreg.core.tiled.BandSource`), and the whole method (matching, triangulation, search,
verdict) runs on the two levels: the mutual information that steers the search is a statistic
of the image content, which a level of millions of pixels estimates as well as the full image.
The geometry then returns to full resolution: vertices scaled back, the client's points
restored exactly, automatic points refined by correlation on full-resolution windows
(:func:`refine_pairs`). The registered raster is resampled from the full-resolution file tile
by tile by the writers (:func:`pwlreg.core.tiled.warp_tiles`), so the memory is that of the
levels and a few tiles, whatever the size of the images.

Coordinates: pixels, x right, y down, (0, 0) the centre of the top-left pixel; a level pixel
covers ``s`` full pixels, so ``x_full = (x_level + 0.5) * s - 0.5``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from scipy.spatial import cKDTree

from pwlreg.core.epipolar import EpipolarModel, pixel_scaling
from pwlreg.core.imaging import LUMINANCE, PictureRecipe, check_raster, matching_picture
from pwlreg.core.matching import ConjugatePoints
from pwlreg.core.options import RegistrationOptions
from pwlreg.core.pipeline import Progress, RegistrationResult, parse_options, warm_up
from pwlreg.core.pipeline import register as register_level
from pwlreg.core.raster import quantize
from pwlreg.core.tiled import LEVEL_PIXELS, ArrayBands, BandSource

REFINE_RADIUS = 12
"""Half side (full-resolution pixels) of the template that refines an automatic pair."""


@dataclass
class ScaledResult(RegistrationResult):
    """A :class:`~pwlreg.core.pipeline.RegistrationResult` whose search ran on reduced levels.

    The vertices, sizes, points and timings are at full resolution; ``registered`` is at the
    reference level's size (the writers resample the full-resolution one tile by tile).

    Attributes
    ----------
    reference_level, moving_level : ndarray
        The pictures of the two levels (:func:`pwlreg.core.imaging.matching_image`).
    moving_recipe : PictureRecipe or None
        How the moving raster's bands make its picture (None when it is a picture).
    scales : ndarray, shape (2, 2)
        Full-resolution pixels per level pixel, ``(sx, sy)`` of the reference then the moving
        image (whole factors, the same on both axes).
    refined : dict of str to int or None
        Automatic pairs refined at full resolution (``refined``, ``kept at level``), None for
        the client's points.
    paths : (path or None, path or None)
        The files of images read window by window (the writers read them again).
    moving_image : ndarray or None
        The moving image at full resolution when it was in memory (an array, or a file other
        than a TIFF, decoded whole): the writers resample it.
    """

    reference_level: np.ndarray | None = None
    moving_level: np.ndarray | None = None
    moving_recipe: PictureRecipe | None = None
    scales: np.ndarray | None = None
    refined: dict[str, int] | None = None
    paths: tuple[Path | None, Path | None] = (None, None)
    moving_image: np.ndarray | None = None


def level_factor(height: int, width: int, level_pixels: int = LEVEL_PIXELS) -> int:
    """The whole factor an image is reduced by: 1 up to ``level_pixels`` pixels, else the
    smallest one leaving at most that many (a whole factor makes each level pixel the mean of
    a block of pixels, and a level can be read window by window without seams)."""
    if height * width <= level_pixels:
        return 1
    return math.ceil(math.sqrt(height * width / level_pixels))


def register(
    reference: np.ndarray | BandSource,
    moving: np.ndarray | BandSource,
    points: tuple[np.ndarray, np.ndarray] | None = None,
    options: RegistrationOptions | Mapping[str, Any] | None = None,
    progress: Progress | None = None,
    *,
    level_pixels: int = LEVEL_PIXELS,
) -> RegistrationResult:
    """Register ``moving`` onto ``reference``, of any size.

    Parameters
    ----------
    reference, moving : ndarray or BandSource
        Pictures or rasters (:func:`pwlreg.core.pipeline.register`), or images read window by
        window (:class:`pwlreg.core.formats.geotiff.RasterFile`).
    points, options, progress
        As for :func:`pwlreg.core.pipeline.register`, at full resolution.
    level_pixels : int
        Images up to this many pixels are registered at full resolution.

    Returns
    -------
    RegistrationResult
        A :class:`ScaledResult` when either image was over ``level_pixels``.
    """
    opts = parse_options(options)
    warm_up(load=False)  # a cold cache: compile in one process at a time
    for image, field in ((reference, "reference"), (moving, "moving")):
        if isinstance(image, np.ndarray):
            check_raster(image, field)
    sources = [image if not isinstance(image, np.ndarray) else None
               for image in (reference, moving)]
    shapes = [(s.height, s.width) if s is not None else image.shape[:2]
              for s, image in zip(sources, (reference, moving), strict=True)]
    if all(s is None for s in sources) and all(h * w <= level_pixels for h, w in shapes):
        return register_level(reference, moving, points, opts, progress)

    t = time.perf_counter()
    levels, recipes, scales = [], [], []
    factor = max(level_factor(h, w, level_pixels) for h, w in shapes)
    for image, source, name in zip((reference, moving), sources, ("reference", "moving"),
                                   strict=True):
        if source is None:
            source = ArrayBands(image) if factor > 1 else None
        # The level's picture, not the level: a multi-band level is 10x its picture's size.
        level = image if source is None else source.level(factor)
        picture, recipe = matching_picture(level, opts.band, name)
        del level
        levels.append(picture)
        recipes.append(recipe)
        scales.append((factor, factor))
    scale = np.array(scales, np.float64)
    level_time = time.perf_counter() - t

    level_points = None
    if points is not None:
        pts = [np.asarray(p, np.float64) for p in points]
        if pts[0].ndim == 2 and pts[0].shape[1:] == (2,) and pts[1].shape == pts[0].shape:
            level_points = (down(pts[0], scale[0]), down(pts[1], scale[1]))
        else:
            level_points = points  # the pipeline says what is wrong with them
    # The level's pictures are the chosen band already.
    level_opts = opts.model_copy(
        update={"min_triangle_area": opts.min_triangle_area / float(np.prod(scale[0])),
                "band": LUMINANCE}
    )
    result = register_level(levels[0], levels[1], level_points, level_opts, progress)

    ref_v, mov_v = up(result.reference_vertices, scale[0]), up(result.moving_vertices, scale[1])
    refined = None
    if points is not None:
        ref_v, mov_v = _restore(ref_v, mov_v, pts, scale)
    else:
        t_refine = time.perf_counter()
        full = [s if s is not None else ArrayBands(image)
                for s, image in zip(sources, (reference, moving), strict=True)]
        measured = ~np.asarray(result.extrapolated, bool)
        moved, refined = refine_pairs(full[0], full[1], ref_v, mov_v, measured,
                                      radius=REFINE_RADIUS, search=int(np.ceil(2 * scale.max())))
        mov_v = _unfolded(ref_v, mov_v, moved, result.final_triangles, result.initial_triangles)
        result.timings["refinement_s"] = time.perf_counter() - t_refine
    timings = dict(result.timings, level_s=level_time)
    timings["total_s"] = timings.get("total_s", 0.0) + level_time + timings.get(
        "refinement_s", 0.0)
    return ScaledResult(
        **{**vars(result),
           "reference_vertices": quantize(ref_v), "moving_vertices": quantize(mov_v),
           "options": opts, "points": _scaled_points(result.points, scale),
           "corrections": None if result.corrections is None else replace(
               result.corrections, moving=up(result.corrections.moving, scale[1]),
               before=up(result.corrections.before, scale[1])),
           "timings": timings,
           "reference_size": (shapes[0][1], shapes[0][0]),
           "moving_size": (shapes[1][1], shapes[1][0])},
        reference_level=levels[0], moving_level=levels[1], moving_recipe=recipes[1],
        scales=scale, refined=refined,
        paths=tuple(getattr(s, "path", None) for s in sources),
        moving_image=moving if sources[1] is None else None,
    )


def down(points: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """Full-resolution positions ``(N, 2)`` on a level ``scale = (sx, sy)`` times smaller."""
    return (np.asarray(points, np.float64) + 0.5) / scale - 0.5


def up(points: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """Level positions ``(N, 2)`` at full resolution (the inverse of :func:`down`)."""
    return (np.asarray(points, np.float64) + 0.5) * scale - 0.5


def _restore(ref_v: np.ndarray, mov_v: np.ndarray, points: list[np.ndarray], scale: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
    """The client's own coordinates for the vertices that are its points (the level's
    quantization moved them by up to ``scale / 512`` px)."""
    ref_v, mov_v = ref_v.copy(), mov_v.copy()
    # Nearest in both images: of two client pairs with one reference point (the pipeline
    # keeps the first), the one the vertex stands for.
    distance, index = cKDTree(np.hstack(points)).query(np.hstack([ref_v, mov_v]))
    near = distance <= float(scale.max()) / 256 * np.sqrt(2)
    ref_v[near] = points[0][index[near]]
    mov_v[near] = points[1][index[near]]
    return ref_v, mov_v


def refine_pairs(
    reference: BandSource,
    moving: BandSource,
    reference_vertices: np.ndarray,
    moving_vertices: np.ndarray,
    measured: np.ndarray,
    *,
    radius: int = REFINE_RADIUS,
    search: int = 4,
    min_correlation: float = 0.8,
) -> tuple[np.ndarray, dict[str, int]]:
    """Refine the moving position of each measured vertex at full resolution.

    A pair found on levels ``s`` times smaller is known to about ``s / 4`` pixels. Around each
    measured vertex, the moving image is resampled into the reference's frame through the
    local affine map of the vertex's neighbours (so that a rotation, a scale or a shear
    between the views does not blur the correlation), and the reference's template (side
    ``2 radius + 1``) is correlated (zero-mean NCC) over a shift of up to ``search`` pixels;
    the peak, located to a fraction of a pixel by a parabola through its neighbours, moves the
    vertex. A peak on the border of the search area, under ``min_correlation``, or on a flat
    template keeps the level's position.

    Returns
    -------
    moving_vertices : ndarray, shape (N, 2)
    counts : dict
        ``refined`` and ``kept at level``.
    """
    ref = np.asarray(reference_vertices, np.float64)
    mov = np.asarray(moving_vertices, np.float64).copy()
    tree = cKDTree(ref)
    k = min(len(ref), 8)
    side = 2 * (radius + search) + 1
    offsets = np.arange(side, dtype=np.float64) - (radius + search)
    counts = {"refined": 0, "kept at level": 0}
    todo = np.flatnonzero(measured)
    # In bands of 512 rows (a usual block height), left to right: neighbouring windows share
    # the file's blocks, which then come from GDAL's cache instead of being decoded again
    # (3.5x faster on a 100 MP 4-band file than in the matcher's order).
    todo = todo[np.lexsort((ref[todo, 0], np.floor(ref[todo, 1] / 512)))]
    for i in todo:
        x, y = ref[i]
        template = _window(reference, x, y, radius)
        _, near = tree.query(ref[i], k=k)
        affine = _local_affine(ref[near], mov[near])
        if template is None or affine is None or template.std() < 2.0:
            counts["kept at level"] += 1
            continue
        gx, gy = np.meshgrid(offsets + round(x), offsets + round(y))
        mx = affine[0, 0] * gx + affine[0, 1] * gy + affine[0, 2]
        my = affine[1, 0] * gx + affine[1, 1] * gy + affine[1, 2]
        area = _resampled(moving, mx, my)
        if area is None:
            counts["kept at level"] += 1
            continue
        score = cv2.matchTemplate(area, template, cv2.TM_CCOEFF_NORMED)
        _, best, _, (px, py) = cv2.minMaxLoc(score)
        if best < min_correlation or not (0 < px < score.shape[1] - 1
                                          and 0 < py < score.shape[0] - 1):
            counts["kept at level"] += 1
            continue
        dx = px - search + _vertex(score[py, px - 1:px + 2])
        dy = py - search + _vertex(score[py - 1:py + 2, px])
        # The template sits at the rounded position: the vertex is (x, y), its match the map
        # of (x, y) shifted by the peak's offset.
        qx, qy = x + dx, y + dy
        mov[i] = affine[:, :2] @ (qx, qy) + affine[:, 2]
        counts["refined"] += 1
    return mov, counts


def _unfolded(ref: np.ndarray, before: np.ndarray, after: np.ndarray,
              *meshes: np.ndarray) -> np.ndarray:
    """``after``, but with the level's positions back on the vertices of any triangle the
    refinement turned over (a patch reversal), in any of ``meshes``."""
    out = after.copy()
    for _ in range(3):
        flipped = np.zeros(len(ref), bool)
        for tris in meshes:
            t = np.asarray(tris, np.int64).reshape(-1, 3)
            flipped[t[_orientation(ref, t) != _orientation(out, t)].ravel()] = True
        flipped &= (out != before).any(axis=1)
        if not flipped.any():
            break
        out[flipped] = before[flipped]
    return out


def _orientation(points: np.ndarray, tris: np.ndarray) -> np.ndarray:
    a, b, c = points[tris[:, 0]], points[tris[:, 1]], points[tris[:, 2]]
    return np.sign((b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1])
                   - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0]))


def _vertex(three: np.ndarray) -> float:
    """Offset of a parabola's apex through three equally spaced values, in [-0.5, 0.5]."""
    left, centre, right = (float(v) for v in three)
    curvature = left - 2.0 * centre + right
    return 0.0 if curvature >= 0 else float(np.clip(0.5 * (left - right) / curvature, -0.5, 0.5))


def _local_affine(ref: np.ndarray, mov: np.ndarray) -> np.ndarray | None:
    """The least-squares affine map ``(2, 3)`` from ``ref`` to ``mov`` (None if degenerate)."""
    design = np.column_stack([ref, np.ones(len(ref))])
    if len(ref) < 3 or np.linalg.matrix_rank(design) < 3:
        return None
    solution, *_ = np.linalg.lstsq(design, mov, rcond=None)
    return solution.T


def _grey(bands: np.ndarray) -> np.ndarray:
    # The mean of the bands: the correlation is blind to each band's gain and offset.
    return bands.astype(np.float32).mean(axis=2)


def _window(source: BandSource, x: float, y: float, radius: int) -> np.ndarray | None:
    """The grey template of side ``2 radius + 1`` centred on the pixel nearest ``(x, y)``."""
    cx, cy = round(x), round(y)
    x0, y0, x1, y1 = cx - radius, cy - radius, cx + radius + 1, cy + radius + 1
    if x0 < 0 or y0 < 0 or x1 > source.width or y1 > source.height:
        return None
    bands, valid = source.read(x0, y0, x1, y1)
    if valid is not None:
        return None
    return _grey(bands)


def _resampled(source: BandSource, mx: np.ndarray, my: np.ndarray) -> np.ndarray | None:
    """The source's grey values at float positions ``mx``, ``my`` (bilinear; None when the
    area leaves the image or touches an invalid pixel)."""
    x0, y0 = int(np.floor(mx.min())), int(np.floor(my.min()))
    x1, y1 = int(np.floor(mx.max())) + 2, int(np.floor(my.max())) + 2
    if x0 < 0 or y0 < 0 or x1 > source.width or y1 > source.height:
        return None
    bands, valid = source.read(x0, y0, x1, y1)
    if valid is not None:
        return None
    grey = _grey(bands)
    return cv2.remap(grey, (mx - x0).astype(np.float32), (my - y0).astype(np.float32),
                     cv2.INTER_LINEAR)


def _scaled_points(points: ConjugatePoints, scale: np.ndarray) -> ConjugatePoints:
    """The level's conjugate points at full resolution."""
    mean = float(np.prod(scale) ** 0.25)
    model = points.epipolar
    if model is not None:
        model = _scaled_model(model, scale, mean)
    dropped = points.dropped
    return replace(
        points,
        reference=up(points.reference, scale[0]),
        moving=up(points.moving, scale[1]),
        residuals=np.asarray(points.residuals, np.float64) * mean,
        epipolar=model,
        dropped=replace(dropped, reference=up(dropped.reference, scale[0]),
                        moving=up(dropped.moving, scale[1]),
                        residuals=np.asarray(dropped.residuals, np.float64) * mean),
    )


def _scaled_model(model: EpipolarModel, scale: np.ndarray, mean: float) -> EpipolarModel:
    """The epipolar model of the levels for full-resolution pixels (distances scaled by the
    mean factor, exact when both images were reduced alike)."""

    # x_level = (x + 0.5) / s - 0.5 in each image.
    f = pixel_scaling(scale[1]).T @ model.matrix @ pixel_scaling(scale[0])
    if model.kind == "affine":
        f = f / np.sqrt(f[2, 0] ** 2 + f[2, 1] ** 2 + f[0, 2] ** 2 + f[1, 2] ** 2)
    else:
        f = f / np.linalg.norm(f)
    plane = model.plane
    if plane is not None:
        plane = np.linalg.inv(pixel_scaling(scale[1])) @ plane @ pixel_scaling(scale[0])
        plane = plane / plane[2, 2]
    return replace(model, matrix=f, threshold=model.threshold * mean, rms=model.rms * mean,
                   plane=plane)
