"""The one entry point: register a pair of images (:func:`register`)."""

from __future__ import annotations

import gc
import time
from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from pydantic import ValidationError
from scipy.spatial import ConvexHull, QhullError, cKDTree

from pwlreg.core import compilation
from pwlreg.core.align import align_vertices
from pwlreg.core.correct import (
    REMOVE_MOVE,
    Corrections,
    aligned_vertices,
    border_search,
    contradicted_vertices,
    removed_vertices,
)
from pwlreg.core.errors import InputError, UnreliableResultError
from pwlreg.core.extent import extrapolations, frame_vertices
from pwlreg.core.imaging import matching_image, to_gray8, valid_pixels
from pwlreg.core.matching import ConjugatePoints, find_conjugate_points
from pwlreg.core.mesh import Mesh
from pwlreg.core.moves import MOVES, Search, inserted_mask, insertions
from pwlreg.core.optimize import SearchResult
from pwlreg.core.optimizers import (
    OPTIMIZERS,
    optimize_again,
    optimize_on_level,
)
from pwlreg.core.options import RegistrationOptions
from pwlreg.core.quality import SCORING_BINS, SCORING_SIDE, Quality, assess
from pwlreg.core.raster import quantize
from pwlreg.core.refine import (
    Guide,
    Insertion,
    clearance,
    guide,
    levels,
    on_the_data,
    sharpen_vertices,
)
from pwlreg.core.similarity import (
    prepare_images,
    reduced,
)
from pwlreg.core.tiled import ArrayBands, warp_tiles
from pwlreg.core.triangulation import TriangulationReport, initial_mesh
from pwlreg.core.warp import warp_image

Progress = Callable[[str, float], None]

#: Passes of vertex insertion (:data:`core.moves.MOVES`): the epipolar search corrects the
#: first mesh where it is far off, and the second pass reads the residual flow of that better
#: mesh (where it can follow it) and searches again. The flow once, in the second pass, instead
#: of in both: on Middlebury (``extent=frame``) 0.510 / 0.357 / 0.991 / 1.293 px against 0.524
#: / 0.378 / 1.011 / 1.332, on the synthetic suite's automatic path 39.3 % below Delaunay on
#: average against 38.9 (median 46.1 % both), and one DIS pair less (``python -m
#: bench.beyond --frame`` / ``--automatic``).
INSERTION_ROUNDS = 2
#: Fewest new pairs the insertion may add, however few were matched (a wide baseline leaves a
#: few dozen pairs, and then the largest triangles). On the trust suite's scenes (seeds 0-1 /
#: 2-5, median EPE reduction) 100 gave 36.2 / 39.0 %, 200 46.1 / 43.9 %, 300 47.4 / 42.9 %
#: with 1.33 % of the kept pairs wrong instead of 1.04 % and the synthetic city's automatic
#: path 1.94 x the code at the filing of issue 10 instead of 1.71 x.
MIN_INSERTED = 200
STAGES = ("matching", "triangulating", "optimizing", "rendering")


@dataclass
class RegistrationResult:
    """Everything one registration produces.

    Attributes
    ----------
    reference_vertices, moving_vertices : ndarray, shape (N, 2)
        Mesh vertices in pixels (quantized to 1/256 px), same index = conjugate pair.
    initial_triangles : ndarray, shape (T0, 3)
        Mesh the search started from (after small-triangle removal and patch-reversal repair).
    final_triangles : ndarray, shape (T, 3)
        Optimized mesh.
    search : SearchResult
        Accepted swaps, global MI/NMI before and after, why the search stopped.
    registered : ndarray, shape (H, W, 2) or (H, W, 4)
        Moving image (its :func:`core.imaging.matching_image`: the picture itself, or the
        8-bit band or luminance of a raster) resampled into the reference frame, grey+alpha or
        BGRA, dtype of that picture; alpha is 0 outside the mesh.
    options : RegistrationOptions
        Options used.
    points : ConjugatePoints
        Conjugate points with matching and epipolar-filter results.
    triangulation : TriangulationReport
        Duplicates, small triangles and patch-reversal repairs.
    timings : dict of str to float
        Seconds spent per stage and in total.
    reference_size, moving_size : (int, int)
        ``(width, height)`` of the two images.
    quality : Quality
        Verdict (``good``, ``doubtful``, ``unreliable``), its reasons and figures, and a score
        per final triangle.
    origins : list of str
        Per vertex, what put it there: ``"client"`` (given points), ``"matched"`` (the
        automatic matcher), ``"frame"`` (extrapolated border, ``extent="frame"``) or the name
        of the insertion move of :data:`core.moves.MOVES` that found it.
    insertion : dict of str to int or None
        The counts of the insertion step (None when it did not run).
    corrections : Corrections or None
        The vertices the vertex moves of :data:`core.moves.MOVES` (``correct``, ``border``,
        ``align``) moved after the swaps, and those ``remove`` took out of the final mesh (they
        stay in the vertex lists, which the initial mesh shares, in no final triangle); None
        when they did not run (they run on the path with insertion only).
    """

    reference_vertices: np.ndarray
    moving_vertices: np.ndarray
    initial_triangles: np.ndarray
    final_triangles: np.ndarray
    search: SearchResult
    registered: np.ndarray
    options: RegistrationOptions
    points: ConjugatePoints
    triangulation: TriangulationReport
    timings: dict[str, float]
    reference_size: tuple[int, int]
    moving_size: tuple[int, int]
    quality: Quality
    origins: list[str]
    insertion: dict[str, int] | None
    corrections: Corrections | None = None

    @property
    def inserted(self) -> np.ndarray:
        """Per vertex, whether an insertion move of :data:`core.moves.MOVES` found it."""
        return inserted_mask(self.origins)

    @property
    def extrapolated(self) -> np.ndarray:
        """Per vertex, whether its moving position was extrapolated (``extent="frame"``)."""
        return self.triangulation.extrapolated

    def summary(self) -> str:
        """One line: points, triangles, swaps, global MI before and after, time."""
        s = self.search
        # A vertex moved by two moves (``correct`` then ``align``) is one vertex moved.
        c = self.corrections
        records = [] if c is None else list(zip(c.vertices.tolist(), c.moves, strict=True))
        gone = sum(m == REMOVE_MOVE for _, m in records)
        moved = len({v for v, m in records if m != REMOVE_MOVE})
        return (
            f"{len(self.reference_vertices)} points ({self.points.source}), "
            f"{len(self.final_triangles)} triangles, {len(s.steps)} swaps "
            f"[{self.options.optimizer}/{self.options.cost}], "
            + (f"{moved} vertices moved, " if moved else "")
            + (f"{gone} removed, " if gone else "")
            + f"MI {s.initial_mi:.4f} -> {s.final_mi:.4f} bits, "
            f"NMI {s.initial_nmi:.4f} -> {s.final_nmi:.4f}, "
            f"{self.timings['total_s']:.2f} s, quality {self.quality.verdict}"
        )


def insertion_budget(matched: int) -> int:
    """Most measured vertices after the insertion by the sources that share a budget
    (:attr:`core.moves.Move.own_budget`): twice the matched pairs, at least
    :data:`MIN_INSERTED` more."""
    return max(2 * matched, matched + MIN_INSERTED)


def _add_counts(total: dict[str, int], source: str, counts: dict[str, int]) -> None:
    """Add an insertion source's ``counts`` to ``total`` under ``"<source> <key>"``; its
    ``inserted`` also to the total ``inserted``."""
    for key, n in counts.items():
        total[f"{source} {key}"] = total.get(f"{source} {key}", 0) + n
    total["inserted"] += counts["inserted"]


def in_hull(points: np.ndarray, query: np.ndarray) -> np.ndarray:
    """Whether each ``query`` point lies in the convex hull of ``points`` (all False when the
    points span no area)."""
    try:
        facets = ConvexHull(points).equations  # (F, 3): outward normal and offset
    except QhullError:
        return np.zeros(len(query), bool)
    return (query @ facets[:, :2].T + facets[:, 2] <= 1e-9).all(axis=1)


def _on_the_data(found: Insertion, mesh: Guide,
                 clearances: tuple[np.ndarray | None, np.ndarray | None]) -> Insertion:
    """``found`` without the pairs :func:`core.refine.on_the_data` drops (counted as ``near
    invalid pixels``)."""
    keep = on_the_data(mesh, found.reference, found.moving, clearances)
    if keep.all():
        return found
    counts = {**found.counts, "inserted": int(keep.sum()),
              "near invalid pixels": int(np.count_nonzero(~keep))}
    return Insertion(found.reference[keep], found.moving[keep], counts)


def parse_options(options: RegistrationOptions | Mapping[str, Any] | None) -> RegistrationOptions:
    """Options from a model, a mapping or ``None`` (defaults); ``InputError`` if invalid."""
    if options is None:
        return RegistrationOptions()
    if isinstance(options, RegistrationOptions):
        return options
    if not isinstance(options, Mapping):
        raise InputError("options must be a JSON object (a mapping of names to values)", "options")
    try:
        return RegistrationOptions.model_validate(dict(options))
    except ValidationError as exc:
        err = exc.errors()[0]
        name = ".".join(str(p) for p in err["loc"])
        raise InputError(f"invalid option {name!r}: {err['msg']}", f"options.{name}") from exc


def register(
    reference: np.ndarray,
    moving: np.ndarray,
    points: tuple[np.ndarray, np.ndarray] | None = None,
    options: RegistrationOptions | Mapping[str, Any] | None = None,
    progress: Progress | None = None,
) -> RegistrationResult:
    """Register ``moving`` onto ``reference`` with an optimized piecewise-linear mesh.

    Parameters
    ----------
    reference, moving : ndarray
        Pictures (OpenCV layout: uint8 or uint16; grey, BGR or BGRA) or rasters (bands in file
        order, any of :data:`core.imaging.RASTER_DTYPES`, masked arrays for invalid pixels);
        matching and scoring use :func:`core.imaging.matching_image` of each (``options.band``).
        Sizes may differ.
    points : (ndarray, ndarray), optional
        Conjugate points ``(reference (N, 2), moving (N, 2))`` in pixels. Without them the
        automatic matcher finds them. Either way the epipolar filter applies unless
        ``options.epipolar_filter`` is false.
    options : RegistrationOptions or mapping, optional
        Defaults when omitted.
    progress : callable, optional
        ``progress(stage, fraction)`` with ``stage`` in :data:`STAGES` and ``fraction`` in
        [0, 1]; if it raises, registration stops and the exception propagates (cancellation).

    Returns
    -------
    RegistrationResult

    Raises
    ------
    InputError
        Invalid images, points or options, or too few consistent conjugate points.
    UnreliableResultError
        The verdict is ``unreliable`` and ``options.on_unreliable`` is ``"fail"``.
    """
    opts = parse_options(options)
    reference = matching_image(reference, opts.band, "reference")
    moving = matching_image(moving, opts.band, "moving")

    def report(stage: str, fraction: float) -> None:
        if progress is not None:
            progress(stage, min(max(fraction, 0.0), 1.0))

    timings: dict[str, float] = {}
    t_start = time.perf_counter()

    report("matching", 0.0)
    pts = None
    if points is not None:
        try:
            pts = (np.asarray(points[0], dtype=np.float64), np.asarray(points[1], dtype=np.float64))
        except (TypeError, ValueError, IndexError) as exc:
            raise InputError("points must be two (N, 2) arrays of numbers", "points") from exc
        if pts[0].ndim != 2 or pts[0].shape[1:] != (2,) or pts[1].shape != pts[0].shape:
            raise InputError(
                f"points must be two (N, 2) arrays of the same length, got shapes "
                f"{pts[0].shape} and {pts[1].shape}",
                "points",
            )
        if not (np.isfinite(pts[0]).all() and np.isfinite(pts[1]).all()):
            raise InputError("points contain non-finite coordinates (NaN or infinity)", "points")
    # Given points are never refined by insertion unless asked (``insert_vertices="always"``).
    insert = opts.insert_vertices == "always" or (
        opts.insert_vertices == "automatic" and pts is None)
    with ThreadPoolExecutor(max_workers=1) as pool:
        # The insertion's levels and candidate corners need only the images: made on a second
        # thread while the pairs are matched (OpenCV lets go of the GIL).
        made = pool.submit(levels, to_gray8(reference), to_gray8(moving)) if insert else None
        conjugate = find_conjugate_points(reference, moving, opts, pts)
    timings["matching_s"] = time.perf_counter() - t_start
    report("matching", 1.0)

    t = time.perf_counter()
    report("triangulating", 0.0)
    images = prepare_images(reference, moving, opts.bins)
    # The verdict and the choice of the border vertices look at the images at a scale where
    # 8 pixels mean the same on any photo, and cost a fraction of a full-resolution pass.
    level, scale = reduced(images, SCORING_SIDE, bins=SCORING_BINS)

    def build(ref_pts: np.ndarray, mov_pts: np.ndarray,
              origins: list[str]) -> tuple[Mesh, TriangulationReport]:
        extrapolated = np.zeros(len(ref_pts), bool)
        # A pair of the insertion that makes a triangle too small is left out, not the
        # triangle.
        optional = inserted_mask(origins)
        if opts.extent == "frame":
            border_ref, border_mov = frame_vertices(
                ref_pts, mov_pts, reference.shape[:2], images=level, scale=scale
            )
            ref_pts = np.concatenate([ref_pts, border_ref])
            mov_pts = np.concatenate([mov_pts, border_mov])
            extrapolated = np.concatenate([extrapolated, np.ones(len(border_ref), bool)])
            optional = np.concatenate([optional, np.zeros(len(border_ref), bool)])
        return initial_mesh(ref_pts, mov_pts, opts.min_triangle_area, extrapolated,
                            optional=optional)

    insertion = None
    ref_meas, mov_meas = conjugate.reference, conjugate.moving
    origin = ["client" if conjugate.source == "client" else "matched"] * len(ref_meas)
    mesh, tri_report = build(ref_meas, mov_meas, origin)
    if made is not None:
        grey = made.result()
        clearances = (clearance(valid_pixels(reference)), clearance(valid_pixels(moving)))
        insertion = {"inserted": 0}
        matched = len(conjugate.reference)
        by_source = dict.fromkeys((name for name, _ in insertions()), 0)
        # A source does not search the same mesh twice: after a round that found nothing the
        # next one runs only the sources that have not seen this mesh.
        searched: set[str] = set()
        current = None
        for round_ in range(INSERTION_ROUNDS):
            if current is None:
                current = guide(grey, mesh.reference, mesh.moving, mesh.triangles,
                                extrapolated=tri_report.extrapolated)
            new_ref, new_mov = np.zeros((0, 2)), np.zeros((0, 2))
            for name, move in insertions():
                if name in searched:
                    continue
                if move.own_budget is None:
                    budget = insertion_budget(matched) - matched - sum(
                        n for k, n in by_source.items() if MOVES[k].own_budget is None)
                else:
                    budget = int(move.own_budget * matched) - by_source[name]
                given = Search(
                    images=images, epipolar=conjugate.lines, measured=len(ref_meas),
                    budget=budget, added=(new_ref, new_mov), epsilon=opts.epsilon,
                    epsilon_pixels=opts.epsilon_pixels, round=round_)
                if move.runs is not None and not move.runs(given):
                    continue
                found = move.find(current, given)
                if found is None:
                    continue
                if any(c is not None for c in clearances):
                    found = _on_the_data(found, current, clearances)
                searched.add(name)
                by_source[name] += len(found.reference)
                _add_counts(insertion, name, found.counts)
                new_ref = np.concatenate([new_ref, found.reference])
                new_mov = np.concatenate([new_mov, found.moving])
                origin += [name] * len(found.reference)
            if not len(new_ref):
                continue
            searched.clear()
            current = None
            ref_meas = np.concatenate([ref_meas, new_ref])
            mov_meas = np.concatenate([mov_meas, new_mov])
            mesh, tri_report = build(ref_meas, mov_meas, origin)
    # Which move (or the matcher) put each vertex there: the mesh deduplicated and reordered
    # the measured pairs, and added the extrapolated border.
    _, nearest = cKDTree(quantize(ref_meas)).query(mesh.reference)
    origins = [origin[i] for i in nearest]
    origins = ["frame" if e else o for o, e in zip(origins, tri_report.extrapolated, strict=True)]
    if insertion is not None:
        # The pairs to a fraction of a pixel (the matcher's and the insertion's, never the
        # client's).
        movable = np.array([o not in ("client", "frame") for o in origins])
        sharp = sharpen_vertices(grey, mesh.reference, mesh.moving, mesh.triangles, movable,
                                 model=conjugate.lines)
        moved = (sharp != mesh.moving).any(axis=1)
        insertion["sharpened"] = int(moved.sum())
        if moved.any():
            mesh = Mesh(mesh.reference, sharp, mesh.triangles)
    initial_triangles = mesh.triangles
    timings["triangulation_s"] = time.perf_counter() - t
    report("triangulating", 1.0)

    t = time.perf_counter()
    report("optimizing", 0.0)
    # Without a caller to tell, the compiled search is not interrupted to report.
    optimizing = None if progress is None else (lambda f: report("optimizing", f))
    corrections = None
    if made is None:
        search = OPTIMIZERS[opts.optimizer](mesh, images, opts, optimizing)
    else:
        # Without client points the swaps, as the vertex moves, look at the images at the
        # verdict's scale (and so do the MI figures): the second search after the moves then
        # costs less than the first saves (bench.auto_speed, the 1024 x 768 city: 1.72 x the
        # filing's time, 1.93 x with one search on the images and none after the moves).
        swaps_level = level if level.bins == images.bins else reduced(images, SCORING_SIDE)[0]
        mesh, search = optimize_on_level(mesh, swaps_level, scale, opts, optimizing)
        given = np.array(origins) == "client"
        # Measured and not the client's: the vertices the correct and remove moves may change.
        own = ~tri_report.extrapolated & ~given
        # After the swaps: on the first mesh, whose diagonals cross the depth steps, right
        # vertices' triangles gained by moving with the other surface (Middlebury's frame
        # worse on three pairs of four, cones 0.991 -> 1.036 px; 0.982 after the swaps).
        corrections = contradicted_vertices(
            images, mesh.reference, mesh.moving, mesh.triangles, own,
            witnesses=~tri_report.extrapolated, epsilon=opts.epsilon,
            epsilon_pixels=opts.epsilon_pixels, cost=opts.cost)
        border = tri_report.extrapolated
        moving_v = mesh.moving.copy()
        moving_v[corrections.vertices] = corrections.moving
        # Not along a plane's lines, which hold on the plane only: the insertion's pairs must
        # lie on it (core.epipolar.EpipolarModel.inliers), the border search has no such test.
        lines = conjugate.lines
        if lines is not None and lines.plane is None and border.any():
            # On the level the verdict and the border's first choice look at.
            found = border_search(
                level, mesh.reference, moving_v, mesh.triangles, border,
                extrapolations(mesh.reference[~border], moving_v[~border],
                               mesh.reference[border]),
                lines.matrix, epsilon=opts.epsilon,
                epsilon_pixels=opts.epsilon_pixels, cost=opts.cost, scale=scale)
            moving_v[found.vertices] = found.moving
            corrections = corrections + found
        # Last: the other moves change which surface a vertex follows, this one where on it.
        # On the level the verdict looks at (the images themselves up to 640 px a side).
        aligned = aligned_vertices(
            level, mesh.reference, moving_v,
            align_vertices(level.reference_values.reshape(level.shape), level.moving,
                           mesh.reference, moving_v, mesh.triangles, ~given, scale=scale),
            mesh.triangles, cost=opts.cost, scale=scale)
        moving_v[aligned.vertices] = aligned.moving
        # After the moves: a vertex none of them could place leaves the mesh.
        removed, triangles = removed_vertices(
            swaps_level, mesh.reference, moving_v, mesh.triangles, own, epsilon=opts.epsilon,
            epsilon_pixels=opts.epsilon_pixels, cost=opts.cost, scale=scale)
        corrections = corrections + aligned + removed
        if len(corrections.vertices):
            # The search after the moves scores the whole moved mesh: its final MI is theirs.
            mesh, search = optimize_again(search, Mesh(mesh.reference, moving_v, triangles),
                                          swaps_level, scale, opts,
                                          elapsed=time.perf_counter() - t)
    timings["optimization_s"] = time.perf_counter() - t
    report("optimizing", 1.0)

    t = time.perf_counter()
    report("rendering", 0.0)
    final_triangles = mesh.triangles
    registered = warp_image(
        moving, mesh.reference, mesh.moving, final_triangles, reference.shape[:2]
    )
    timings["rendering_s"] = time.perf_counter() - t

    t = time.perf_counter()
    quality = assess(
        level,
        mesh.reference,
        mesh.moving,
        final_triangles,
        # The verdict's rules were calibrated with the matched pairs' hull as the measured
        # area: vertices inserted beyond it extend the extrapolated border, not the evidence
        # (counted as measured, a border 26 px wrong was called good).
        tri_report.extrapolated
        | (inserted_mask(origins) & ~in_hull(conjugate.reference, mesh.reference)),
        counts=conjugate.counts,
        rejected=conjugate.rejected,
        mi=(search.initial_mi, search.final_mi),
        nmi=(search.initial_nmi, search.final_nmi),
        mapped_coverage=float(np.count_nonzero(registered[:, :, -1])) / registered[:, :, -1].size,
        shape=reference.shape[:2],
        scale=scale,
    )
    timings["quality_s"] = time.perf_counter() - t
    timings["total_s"] = time.perf_counter() - t_start
    report("rendering", 1.0)
    if quality.verdict == "unreliable" and opts.on_unreliable == "fail":
        raise UnreliableResultError(quality.to_dict())

    return RegistrationResult(
        reference_vertices=mesh.reference,
        moving_vertices=mesh.moving,
        initial_triangles=initial_triangles,
        final_triangles=final_triangles,
        search=search,
        registered=registered,
        options=opts,
        points=conjugate,
        triangulation=tri_report,
        timings=timings,
        reference_size=(reference.shape[1], reference.shape[0]),
        moving_size=(moving.shape[1], moving.shape[0]),
        quality=quality,
        origins=origins,
        insertion=insertion,
        corrections=corrections,
    )


def warm_up(*, load: bool = True) -> None:
    """Compile (or load from numba's cache) the kernels for 8- and 16-bit, grey and colour
    images, on both paths.

    A worker process calls this once at start so that its first job does not pay the
    compilation (minutes the first time on a machine, a fraction of a second from the cache).
    Processes compile one at a time (:func:`pwlreg.core.compilation.prepare`); with
    ``load=False`` this compiles only when the cache is not ready, and loads nothing otherwise
    (the kernels then load at their first use). Everything the process holds once the kernels
    are loaded (modules, the compiled kernels) is moved out of the garbage collector's reach
    (:func:`gc.freeze`).
    """
    if compilation.prepare(_compile_kernels, load=load):
        # Those objects (about 144 000) live as long as the process, and each full collection
        # walked them all: 75 ms, every two to four registrations of the 1024x682 facade pair.
        gc.freeze()


def _compile_kernels() -> None:
    levels = np.arange(64 * 64, dtype=np.int64).reshape(64, 64) * 37 % 251
    # Enough points that the first batch of triangles takes the threaded kernel too.
    grid = np.linspace(2.0, 61.0, 8)
    pts = np.array([(x + (y % 3), y) for x in grid for y in grid])
    for dtype in (np.uint8, np.uint16):
        grey = levels.astype(dtype)
        for img in (grey, np.dstack([grey] * 3)):
            register(img, img, (pts, pts + 0.5), {"epipolar_filter": False})
    # The automatic path's kernels (matching, insertion along the epipolar lines): a textured
    # stereo pair whose halves lie at two depths, in 8 and 16 bits.
    rng = np.random.default_rng(0)
    texture = cv2.resize(rng.integers(0, 256, (48, 64), dtype=np.uint8), (256, 192),
                         interpolation=cv2.INTER_CUBIC)
    shifted = np.concatenate([np.roll(texture, 3, axis=1)[:, :128],
                              np.roll(texture, 9, axis=1)[:, 128:]], axis=1)
    for dtype, scale in ((np.uint8, 1), (np.uint16, 257)):
        result = register(texture.astype(dtype) * scale, shifted.astype(dtype) * scale)
    # An 8-bit image against a 16-bit one, both ways (the joint histograms take both types).
    register(texture, shifted.astype(np.uint16) * 257, options={"extent": "hull"})
    register(texture.astype(np.uint16) * 257, shifted, options={"extent": "hull"})
    # The tiled warp of large rasters.
    for _ in warp_tiles(ArrayBands(shifted), result.reference_vertices, result.moving_vertices,
                        result.final_triangles, texture.shape, tile=64):
        pass
