"""Compiled inner loops (numba): the fill rule, per-triangle histograms and the warp; and the
matchers' loops over points: correlation surfaces and their peaks (:func:`template_peaks`),
correlation along epipolar lines (:func:`strip_correlation`), the affine fits of windows that
sharpen the pairs (:func:`window_fits`) and the thinning of corners (:func:`spaced`).

These are the hot paths of pwlreg. Each loops over the pixels of each triangle once, computing
the affine map, the bilinear sample and the histogram bin on the fly, so no per-pixel array is
ever materialized: the cost is a few nanoseconds per pixel and a few microseconds per call, which
is what lets the greedy search re-score a quad after every swap cheaply. Callers are in
:mod:`core.raster`, :mod:`core.similarity` and :mod:`core.warp`; the conventions are theirs:
vertices are int64 fixed-point coordinates (``SUBPIXEL`` units per pixel), pixel ``(x, y)`` is
the centre of column ``x``, row ``y``.

The fill rule lives in :func:`row_span` alone; every triangle kernel calls it.
"""

from __future__ import annotations

import heapq
import os
import time

# numba's threaded kernels run on OpenMP, whose idle threads by default spin for a while after
# each parallel region, burning a core that OpenCV's threads, the main thread or another worker
# could use. Waiting passively cut the automatic path's CPU time by 19-25 % for the same wall
# time, within 3 % (1024x768 city and facade, registrations of the two settings alternated).
# It must be set before numba starts its threads; a policy the user chose is kept.
os.environ.setdefault("OMP_WAIT_POLICY", "passive")

import numba  # noqa: E402
import numpy as np  # noqa: E402
from numba import njit, objmode, prange, types  # noqa: E402
from numba.np.numpy_support import from_dtype  # noqa: E402
from numba.typed import Dict, List  # noqa: E402

SUBPIXEL = 256

# Safety margin (pixels) of the clamp-free sampling path against rounding in the row stepping.
_MARGIN = 1e-6


def set_threads(n: int) -> None:
    """Use at most ``n`` threads (and at most numba's ``NUMBA_NUM_THREADS``) in the threaded
    kernels of this process."""
    numba.set_num_threads(max(1, min(int(n), numba.config.NUMBA_NUM_THREADS)))


@njit(cache=True, inline="always")
def to_fixed(value: float) -> int:
    """Nearest multiple of ``1 / SUBPIXEL`` (ties up), in ``SUBPIXEL`` units."""
    return int(np.floor(value * SUBPIXEL + 0.5))


@njit(cache=True, inline="always")
def _load_triangle(tri: np.ndarray, q: np.ndarray) -> int:
    """Fixed-point copy of a float ``(3, 2)`` triangle into ``q``, positively oriented.

    Returns 0 for a degenerate triangle, -1 if the vertices were reordered, 1 otherwise.
    """
    for v in range(3):
        q[v, 0] = to_fixed(tri[v, 0])
        q[v, 1] = to_fixed(tri[v, 1])
    return _orient_triangle(q)


@njit(cache=True, inline="always")
def _affine(src: np.ndarray, dst: np.ndarray, out: np.ndarray) -> None:
    """Affine map ``out`` (2, 3) with ``dst = out @ [x, y, 1]`` for the three vertex pairs.

    Solved relative to the first vertex (better conditioned for large images); NaN for a
    degenerate source triangle.
    """
    d1x = src[1, 0] - src[0, 0]
    d1y = src[1, 1] - src[0, 1]
    d2x = src[2, 0] - src[0, 0]
    d2y = src[2, 1] - src[0, 1]
    det = d1x * d2y - d1y * d2x
    if det == 0.0:
        out[:] = np.nan
        return
    for r in range(2):
        e1 = dst[1, r] - dst[0, r]
        e2 = dst[2, r] - dst[0, r]
        a = (e1 * d2y - e2 * d1y) / det
        b = (e2 * d1x - e1 * d2x) / det
        out[r, 0] = a
        out[r, 1] = b
        out[r, 2] = dst[0, r] - a * src[0, 0] - b * src[0, 1]


@njit(cache=True)
def affine_maps(src_tris, dst_tris, out):  # type: ignore[no-untyped-def]
    """``out[t]`` (2, 3): the affine map taking ``src_tris[t]`` onto ``dst_tris[t]``."""
    for t in range(src_tris.shape[0]):
        _affine(src_tris[t], dst_tris[t], out[t])


@njit(cache=True, inline="always")
def _orient_triangle(q: np.ndarray) -> int:
    """Make the fixed-point triangle ``q`` positively oriented in place.

    Returns 0 if it is degenerate, -1 if its vertices 1 and 2 were swapped, 1 otherwise.
    """
    cross = (q[1, 0] - q[0, 0]) * (q[2, 1] - q[0, 1]) - (q[1, 1] - q[0, 1]) * (q[2, 0] - q[0, 0])
    if cross < 0:
        for c in range(2):
            tmp = q[1, c]
            q[1, c] = q[2, c]
            q[2, c] = tmp
        return -1
    return 1 if cross > 0 else 0


@njit(cache=True, inline="always")
def _row_range(q: np.ndarray, height: int) -> tuple[int, int]:
    ymin = min(q[0, 1], q[1, 1], q[2, 1])
    ymax = max(q[0, 1], q[1, 1], q[2, 1])
    lo = -((-ymin) // SUBPIXEL)
    hi = ymax // SUBPIXEL
    return max(lo, 0), min(hi, height - 1)


@njit(cache=True, inline="always")
def row_span(q: np.ndarray, y: int, width: int, closed: int = 0) -> tuple[int, int]:
    """First and last column owned on row ``y`` by the positively oriented triangle ``q``.

    Inside means every edge function ``E`` is positive; ``E == 0`` counts as inside when the
    pixel centre displaced by an infinitesimal ``(d, d**2)`` enters the triangle, or when bit
    ``e`` of ``closed`` is set for edge ``e`` (from vertex ``e`` to ``e + 1``): the rendering
    pass closes the mesh's outer edges this way. Empty rows give ``hi < lo``.
    """
    py = y * SUBPIXEL
    lo = 0
    hi = width - 1
    for e in range(3):
        ax = q[e, 0]
        ay = q[e, 1]
        bx = q[(e + 1) % 3, 0]
        by = q[(e + 1) % 3, 1]
        dx = bx - ax
        dy = by - ay
        k = dx * (py - ay) + dy * ax
        if dy < 0:
            lower = -(k // (-dy * SUBPIXEL))
            if lower > lo:
                lo = lower
        elif dy > 0:
            if (closed >> e) & 1:
                upper = k // (dy * SUBPIXEL)
            else:
                upper = -((-k) // (dy * SUBPIXEL)) - 1
            if upper < hi:
                hi = upper
        elif not (k > 0 or (k == 0 and (dx > 0 or (closed >> e) & 1))):
            return 0, -1
    return lo, hi


@njit(cache=True)
def spans(tris: np.ndarray, height: int, width: int):  # type: ignore[no-untyped-def]
    """Runs ``(triangle, y, x0, length)`` of pixels owned by each triangle (T, 3, 2)."""
    n_tri = tris.shape[0]
    q = np.empty((3, 2), dtype=np.int64)
    rows = 0  # an upper bound on the number of runs: every row of every bounding box
    for t in range(n_tri):
        _load_triangle(tris[t], q)
        y0, y1 = _row_range(q, height)
        rows += max(y1 - y0 + 1, 0)
    tri = np.empty(rows, dtype=np.intp)
    ys = np.empty(rows, dtype=np.intp)
    x0 = np.empty(rows, dtype=np.intp)
    length = np.empty(rows, dtype=np.intp)
    i = 0
    for t in range(n_tri):
        if _load_triangle(tris[t], q) == 0:
            continue
        y0, y1 = _row_range(q, height)
        for y in range(y0, y1 + 1):
            lo, hi = row_span(q, y, width)
            if lo <= hi:
                tri[i] = t
                ys[i] = y
                x0[i] = lo
                length[i] = hi - lo + 1
                i += 1
    return tri[:i], ys[:i], x0[:i], length[:i]


@njit(cache=True, parallel=True)
def fill_spans(tri, ys, x0, length, maps, map_x, map_y, label):  # type: ignore[no-untyped-def]
    """Write each run's triangle into ``label`` and, when ``maps`` (T, 2, 3) has rows, the
    triangle's affine map of every pixel into ``map_x``/``map_y`` (``m x + m y + m``, the
    expression of :func:`core.warp.piecewise_map`). The runs share no pixel, so threads
    write them in any order."""
    with_maps = maps.shape[0] > 0
    for i in prange(tri.shape[0]):
        t = tri[i]
        y = ys[i]
        yf = float(y)
        for x in range(x0[i], x0[i] + length[i]):
            label[y, x] = t
            if with_maps:
                xf = float(x)
                map_x[y, x] = maps[t, 0, 0] * xf + maps[t, 0, 1] * yf + maps[t, 0, 2]
                map_y[y, x] = maps[t, 1, 0] * xf + maps[t, 1, 1] * yf + maps[t, 1, 2]


@njit(cache=True)
def level_counts(gray, counts):  # type: ignore[no-untyped-def]
    """Add to ``counts`` the number of pixels of each level of the flat unsigned ``gray``.

    ``np.bincount`` without its conversion to intp; four interleaved counters, so a run of equal
    levels does not serialize on one memory cell (0.27 against 1.05 ms for 0.8 megapixels).
    """
    n = gray.shape[0]
    size = counts.shape[0]
    part = np.zeros((4, size), dtype=np.int64)
    i = 0
    while i + 4 <= n:
        part[0, gray[i]] += 1
        part[1, gray[i + 1]] += 1
        part[2, gray[i + 2]] += 1
        part[3, gray[i + 3]] += 1
        i += 4
    while i < n:
        part[0, gray[i]] += 1
        i += 1
    for v in range(size):
        counts[v] += part[0, v] + part[1, v] + part[2, v] + part[3, v]


#: Size of the table of ``c log2 c`` that the summed-histogram kernel reads instead of a
#: logarithm per cell (a quad's counts are far below it; larger ones are computed).
XLOGX_SIZE = 1 << 16


@njit(cache=True, inline="always")
def _xlogx(c: float) -> float:
    """``c log2 c`` of a count, 0 for counts of 0 or 1."""
    return c * np.log2(c) if c > 1.0 else 0.0


@njit(cache=True)
def xlogx_table(size: int) -> np.ndarray:
    """``_xlogx`` of the counts ``0 .. size - 1``: the same values bit for bit."""
    table = np.empty(size)
    for c in range(size):
        table[c] = _xlogx(float(c))
    return table


@njit(cache=True, inline="always")
def _counted_xlogx(c: int, table: np.ndarray) -> float:
    if c < table.shape[0]:
        return table[c]
    return _xlogx(float(c))


@njit(cache=True, inline="always")
def _information(s_ab: float, s_a: float, s_b: float, n: float):  # type: ignore[no-untyped-def]
    """MI and NMI in bits from the sums of ``c log2 c`` over the joint cells and over each
    marginal of ``n`` pixels, as ``H = log2 n - sum(c log2 c) / n``: one logarithm per cell
    fewer than ``-sum(p log2 p)``, and none where a table holds ``c log2 c``.

    MI is clamped to [0, min(H(A), H(B))]; a histogram with no or a single occupied cell has
    ``H(A, B) = 0`` and gets MI = NMI = 0 (no information, not a perfect match).
    """
    if n == 0.0:
        return 0.0, 0.0
    log_n = np.log2(n)
    h_ab = log_n - s_ab / n
    if h_ab <= 1e-12:
        return 0.0, 0.0
    h_a = log_n - s_a / n
    h_b = log_n - s_b / n
    value = min(max(h_a + h_b - h_ab, 0.0), h_a, h_b)
    return value, value / h_ab


@njit(cache=True)
def summed_information(hist, rows, bins, mi, nmi, pixels, table):  # type: ignore[no-untyped-def]
    """MI and NMI in bits (:func:`_information`) of sums of rows of the joint counts ``hist``
    (R, bins * bins), without gathering them first.

    Output ``k`` is for ``hist[rows[k]].sum(axis=0)``, ``rows`` (K, S) int64 (S = 1: the rows
    themselves); ``pixels[k]`` gets its total count; ``table`` is :func:`xlogx_table`. The sums
    are exact integers, so the values depend on the summed counts only, bit for bit.
    """
    nb = bins * bins
    counts = np.empty(nb, dtype=np.int64)
    ca = np.empty(bins, dtype=np.int64)
    cb = np.empty(bins, dtype=np.int64)
    for k in range(rows.shape[0]):
        counts[:] = 0
        for s in range(rows.shape[1]):
            src = hist[rows[k, s]]
            for c in range(nb):
                counts[c] += src[c]
        # The marginals and the total summed as integers: exact.
        ca[:] = 0
        cb[:] = 0
        s_ab = 0.0
        for a in range(bins):
            for b in range(bins):
                c = counts[a * bins + b]
                ca[a] += c
                cb[b] += c
                s_ab += _counted_xlogx(c, table)
        total = 0
        s_a = 0.0
        s_b = 0.0
        for a in range(bins):
            total += ca[a]
            s_a += _counted_xlogx(ca[a], table)
            s_b += _counted_xlogx(cb[a], table)
        pixels[k] = float(total)
        mi[k], nmi[k] = _information(s_ab, s_a, s_b, float(total))


@njit(cache=True, inline="always")
def _triangle_histogram(  # type: ignore[no-untyped-def]
    t, r, ref_tris, ref_bins, ref_values, flat, mh, mw, width, height, bins, bin_offset,
    bin_scale, ref_scale, mov_scale, hist, moments, with_moments, mov_tris
):
    """Histogram (and moments) of triangle ``t`` added to ``hist[r]`` (``moments[r]``): the
    body of :func:`triangle_histograms` and :func:`group_histograms`."""
    xmax = mw - 1.0
    ymax = mh - 1.0
    q = np.empty((3, 2), dtype=np.int64)
    m = np.empty((2, 3))
    if _load_triangle(ref_tris[t], q) == 0:
        return
    _affine(ref_tris[t], mov_tris[t], m)
    h_t = hist[r]
    # The steps and the moment sums in locals, not re-read from the arrays: every histogram
    # increment is a store the compiler cannot prove apart from them (-20 % time). The
    # triangle's moments are summed on their own, then added to the row's: a group's moments
    # are the sum of its triangles', in their order.
    m00 = m[0, 0]
    m10 = m[1, 0]
    s0 = s1 = s2 = s3 = s4 = s5 = 0.0
    y0, y1 = _row_range(q, height)
    for y in range(y0, y1 + 1):
        lo, hi = row_span(q, y, width)
        row = y * width
        # The map is affine: step along the row instead of re-evaluating it.
        mx = m00 * lo + m[0, 1] * y + m[0, 2]
        my = m10 * lo + m[1, 1] * y + m[1, 2]
        if hi < lo:
            continue
        ex = mx + m00 * (hi - lo)
        ey = my + m10 * (hi - lo)
        if not with_moments and (
            min(mx, ex) >= _MARGIN
            and min(my, ey) >= _MARGIN
            and max(mx, ex) <= xmax - _MARGIN
            and max(my, ey) <= ymax - _MARGIN
        ):
            # The whole run samples strictly inside the image: no clamping needed (the
            # common case; the general loop below gives the same values). Every index is
            # then non-negative: unsigned, numba drops its negative-index wraparound (-16 %).
            umw = np.uint64(mw)
            one = np.uint64(1)
            ubins = np.uint64(bins)
            for x in range(lo, hi + 1):
                xi = int(mx)
                yi = int(my)
                fx = mx - xi
                fy = my - yi
                i00 = np.uint64(yi * mw + xi)
                p00 = float(flat[i00])
                p10 = float(flat[i00 + umw])
                top = p00 + fx * (flat[i00 + one] - p00)
                bottom = p10 + fx * (flat[i00 + umw + one] - p10)
                b = int((top + fy * (bottom - top) - bin_offset) * bin_scale)
                if b >= bins:
                    b = bins - 1
                elif b < 0:
                    b = 0
                h_t[np.uint64(ref_bins[np.uint64(row + x)]) * ubins + np.uint64(b)] += 1
                mx += m00
                my += m10
            continue
        for x in range(lo, hi + 1):
            sx = min(max(mx, 0.0), xmax)
            sy = min(max(my, 0.0), ymax)
            xi = int(sx)
            yi = int(sy)
            fx = sx - xi
            fy = sy - yi
            i00 = yi * mw + xi
            i01 = i00 + 1 if xi < mw - 1 else i00
            i10 = i00 + mw if yi < mh - 1 else i00
            i11 = i10 + 1 if xi < mw - 1 else i10
            p00 = float(flat[i00])
            p10 = float(flat[i10])
            top = p00 + fx * (flat[i01] - p00)
            bottom = p10 + fx * (flat[i11] - p10)
            v = top + fy * (bottom - top)
            b = int((v - bin_offset) * bin_scale)
            if b >= bins:
                b = bins - 1
            elif b < 0:
                b = 0
            h_t[ref_bins[row + x] * bins + b] += 1
            if with_moments:
                a = ref_values[row + x] * ref_scale
                v *= mov_scale
                s0 += 1.0
                s1 += a
                s2 += v
                s3 += a * a
                s4 += v * v
                s5 += a * v
            mx += m00
            my += m10
    if with_moments:
        moments[r, 0] += s0
        moments[r, 1] += s1
        moments[r, 2] += s2
        moments[r, 3] += s3
        moments[r, 4] += s4
        moments[r, 5] += s5


@njit(cache=True)
def triangle_histograms(  # type: ignore[no-untyped-def]
    ref_tris,
    mov_tris,
    ref_bins,
    ref_values,
    moving,
    width,
    height,
    bins,
    bin_offset,
    bin_scale,
    ref_scale,
    mov_scale,
    hist,
    moments,
):
    """Accumulate joint histograms (and moments when ``moments`` has rows) of triangles.

    ``ref_tris``/``mov_tris``: (T, 3, 2) vertices in pixels; ``ref_bins``/``ref_values``: flat
    reference bins and grey levels; ``moving``: 2-D grey levels; a resampled level ``v`` falls in
    bin ``floor((v - bin_offset) * bin_scale)``, clipped to ``[0, bins - 1]``. ``hist`` is
    ``(T, bins * bins)`` int32 or int64, ``moments`` ``(T, 6)`` or ``(0, 6)`` float64, of
    levels times ``ref_scale`` / ``mov_scale``. Resampling: bilinear, border replicated.
    """
    with_moments = moments.shape[0] > 0
    mh, mw = moving.shape
    flat = moving.ravel()
    for t in range(ref_tris.shape[0]):
        _triangle_histogram(t, t, ref_tris, ref_bins, ref_values, flat, mh, mw, width, height, bins,
                            bin_offset, bin_scale, ref_scale, mov_scale, hist, moments,
                            with_moments, mov_tris)


@njit(cache=True, parallel=True)
def group_histograms(  # type: ignore[no-untyped-def]
    ref_tris,
    mov_tris,
    starts,
    ref_bins,
    ref_values,
    moving,
    width,
    height,
    bins,
    bin_offset,
    bin_scale,
    ref_scale,
    mov_scale,
    hist,
    moments,
):
    """:func:`triangle_histograms` summed by group, the groups shared among threads: the
    triangles ``starts[g]:starts[g + 1]`` into ``hist[g]`` (and ``moments[g]``, each
    triangle's moments added in their order). With ``starts = 0, 1, ..., T`` each triangle
    is its own group: :func:`triangle_histograms` on threads (each writes only its own row,
    so the result is the same)."""
    with_moments = moments.shape[0] > 0
    mh, mw = moving.shape
    flat = moving.ravel()
    for g in prange(starts.shape[0] - 1):
        for t in range(starts[g], starts[g + 1]):
            _triangle_histogram(t, g, ref_tris, ref_bins, ref_values, flat, mh, mw, width,
                                height, bins, bin_offset, bin_scale, ref_scale, mov_scale,
                                hist, moments, with_moments, mov_tris)


@njit(cache=True, inline="always")
def _warp_triangle(ref_tri, mov_tri, moving, out, full, mask, owned):  # type: ignore[no-untyped-def]
    """Resample the pixels of one triangle that the fill rule (and the outer edges of ``mask``)
    give it and no earlier pass took (``owned``); see :func:`warp`."""
    height, width = out.shape[0], out.shape[1]
    mh, mw, nb = moving.shape
    colour = 3 if nb == 4 else nb
    q = np.empty((3, 2), dtype=np.int64)
    maps = np.empty((2, 3))
    flip = _load_triangle(ref_tri, q)
    if flip == 0:
        return
    if flip < 0:  # vertices 1 and 2 swapped: edges 0 and 2 trade places
        mask = (mask & 2) | ((mask & 1) << 2) | ((mask >> 2) & 1)
    _affine(ref_tri, mov_tri, maps)
    y0, y1 = _row_range(q, height)
    for y in range(y0, y1 + 1):
        lo, hi = row_span(q, y, width, mask)
        for x in range(lo, hi + 1):
            if owned[y, x]:
                continue
            owned[y, x] = 1
            mx = maps[0, 0] * x + maps[0, 1] * y + maps[0, 2]
            my = maps[1, 0] * x + maps[1, 1] * y + maps[1, 2]
            if not (mx >= 0.0 and my >= 0.0 and mx <= mw - 1 and my <= mh - 1):
                continue
            xi = int(mx)
            yi = int(my)
            xj = min(xi + 1, mw - 1)
            yj = min(yi + 1, mh - 1)
            fx = mx - xi
            fy = my - yi
            for c in range(nb):
                p00 = float(moving[yi, xi, c])
                p10 = float(moving[yj, xi, c])
                top = p00 + fx * (moving[yi, xj, c] - p00)
                bottom = p10 + fx * (moving[yj, xj, c] - p10)
                val = top + fy * (bottom - top) + 0.5
                if c < colour:
                    out[y, x, c] = val
                else:
                    out[y, x, colour] = min(val, full)
            if nb != 4:
                out[y, x, colour] = full


@njit(cache=True, parallel=True)
def warp(ref_tris, mov_tris, moving, out, full, closed):  # type: ignore[no-untyped-def]
    """Resample ``moving`` (H', W', C) into ``out`` (H, W, C + 1) through each triangle's map.

    Colour bands are bilinear samples rounded to the nearest level; the last band of ``out`` is
    ``full`` where the mapped point lies inside the moving image, else 0 (colour left at 0). A
    4-band ``moving`` has its alpha resampled and multiplied in (min).

    ``closed[t]`` flags, bit ``e`` for the edge from vertex ``e`` to ``e + 1`` of ``ref_tris[t]``,
    the mesh's outer edges: a second pass gives the pixel centres lying exactly on them (which
    the fill rule leaves to a neighbour that does not exist on the bottom and right sides) to
    their only triangle. The fill rule gives every pixel to one triangle at most, so the first
    pass runs the triangles on all threads.
    """
    owned = np.zeros((out.shape[0], out.shape[1]), dtype=np.uint8)
    for t in prange(ref_tris.shape[0]):
        _warp_triangle(ref_tris[t], mov_tris[t], moving, out, full, 0, owned)
    for t in range(ref_tris.shape[0]):
        if closed[t] != 0:
            _warp_triangle(ref_tris[t], mov_tris[t], moving, out, full, closed[t], owned)


#: The corners of the unit triangle: the affine map onto it gives a pixel's barycentric
#: coordinates of the first two vertices.
_UNIT = np.array([[1.0, 0.0], [0.0, 1.0], [0.0, 0.0]])


@njit(cache=True, parallel=True)
def align_sums(ref_tris, mov_tris, ref, mov, gain, bias, scale, moments, system,
               vector):  # type: ignore[no-untyped-def]
    """Per triangle, the sums of the photometric alignment of its moving vertices
    (:func:`core.align.align_vertices`), over the reference pixels it owns, sampled bilinearly
    in ``mov`` (float32) where its map takes them inside the moving image; the slopes are the
    bilinear sample's own.

    ``moments[t]`` (6,): the count and the sums of ``m``, ``r``, ``m * m``, ``m * r`` and
    ``r * r`` (``r`` the reference level, ``m`` the moving sample). With ``scale > 0`` (else
    ``gain``, ``bias``, ``system`` and ``vector`` are not read nor written) also the
    Gauss-Newton sums of ``gain[t] * m + bias[t] - r`` under Cauchy weights of that scale:
    ``system[t]`` (6, 6) and ``vector[t]`` (6,) over the unknowns ``(x0, x1, x2, y0, y1, y2)``,
    the moving coordinates of the triangle's vertices. Each thread writes its triangles' rows
    only; the sums stay in locals (a store per term and pixel took twice the time).
    """
    mh, mw = mov.shape
    height, width = ref.shape
    xmax = mw - 1.0
    ymax = mh - 1.0
    solve = scale > 0.0
    inverse = 1.0 / scale if solve else 0.0
    for t in prange(ref_tris.shape[0]):
        q = np.empty((3, 2), dtype=np.int64)
        m = np.empty((2, 3))
        b = np.empty((2, 3))
        if _load_triangle(ref_tris[t], q) == 0:
            continue
        _affine(ref_tris[t], mov_tris[t], m)
        _affine(ref_tris[t], _UNIT, b)
        a_t = gain[t] if solve else 1.0
        c_t = bias[t] if solve else 0.0
        m00, m01, m02, m10, m11, m12 = m[0, 0], m[0, 1], m[0, 2], m[1, 0], m[1, 1], m[1, 2]
        b00, b01, b02, b10, b11, b12 = b[0, 0], b[0, 1], b[0, 2], b[1, 0], b[1, 1], b[1, 2]
        n = s_m = s_r = s_mm = s_mr = s_rr = 0.0
        g0 = g1 = g2 = g3 = g4 = g5 = 0.0
        h00 = 0.0
        h01 = 0.0
        h02 = 0.0
        h03 = 0.0
        h04 = 0.0
        h05 = 0.0
        h11 = 0.0
        h12 = 0.0
        h13 = 0.0
        h14 = 0.0
        h15 = 0.0
        h22 = 0.0
        h23 = 0.0
        h24 = 0.0
        h25 = 0.0
        h33 = 0.0
        h34 = 0.0
        h35 = 0.0
        h44 = 0.0
        h45 = 0.0
        h55 = 0.0
        y0, y1 = _row_range(q, height)
        for y in range(y0, y1 + 1):
            lo, hi = row_span(q, y, width)
            for x in range(lo, hi + 1):
                sx = m00 * x + m01 * y + m02
                sy = m10 * x + m11 * y + m12
                if not (0.0 <= sx <= xmax and 0.0 <= sy <= ymax):
                    continue
                xi = min(int(sx), mw - 2)
                yi = min(int(sy), mh - 2)
                fx = sx - xi
                fy = sy - yi
                w00 = (1.0 - fx) * (1.0 - fy)
                w01 = fx * (1.0 - fy)
                w10 = (1.0 - fx) * fy
                w11 = fx * fy
                p00 = float(mov[yi, xi])
                p01 = float(mov[yi, xi + 1])
                p10 = float(mov[yi + 1, xi])
                p11 = float(mov[yi + 1, xi + 1])
                v = w00 * p00 + w01 * p01 + w10 * p10 + w11 * p11
                r = float(ref[y, x])
                n += 1.0
                s_m += v
                s_r += r
                s_mm += v * v
                s_mr += v * r
                s_rr += r * r
                if not solve:
                    continue
                # The derivatives of the bilinear sample itself: the residual's own slope.
                gx = (1.0 - fy) * (p01 - p00) + fy * (p11 - p10)
                gy = (1.0 - fx) * (p10 - p00) + fx * (p11 - p01)
                res = a_t * v + c_t - r
                u = res * inverse
                weight = 1.0 / (1.0 + u * u)
                b0 = b00 * x + b01 * y + b02
                b1 = b10 * x + b11 * y + b12
                b2 = 1.0 - b0 - b1
                j0 = a_t * b0 * gx
                j1 = a_t * b1 * gx
                j2 = a_t * b2 * gx
                j3 = a_t * b0 * gy
                j4 = a_t * b1 * gy
                j5 = a_t * b2 * gy
                wj0 = weight * j0
                wj1 = weight * j1
                wj2 = weight * j2
                wj3 = weight * j3
                wj4 = weight * j4
                wj5 = weight * j5
                g0 += wj0 * res
                g1 += wj1 * res
                g2 += wj2 * res
                g3 += wj3 * res
                g4 += wj4 * res
                g5 += wj5 * res
                h00 += wj0 * j0
                h01 += wj0 * j1
                h02 += wj0 * j2
                h03 += wj0 * j3
                h04 += wj0 * j4
                h05 += wj0 * j5
                h11 += wj1 * j1
                h12 += wj1 * j2
                h13 += wj1 * j3
                h14 += wj1 * j4
                h15 += wj1 * j5
                h22 += wj2 * j2
                h23 += wj2 * j3
                h24 += wj2 * j4
                h25 += wj2 * j5
                h33 += wj3 * j3
                h34 += wj3 * j4
                h35 += wj3 * j5
                h44 += wj4 * j4
                h45 += wj4 * j5
                h55 += wj5 * j5
        moments[t, 0] = n
        moments[t, 1] = s_m
        moments[t, 2] = s_r
        moments[t, 3] = s_mm
        moments[t, 4] = s_mr
        moments[t, 5] = s_rr
        if not solve:
            continue
        vector[t, 0] = g0
        vector[t, 1] = g1
        vector[t, 2] = g2
        vector[t, 3] = g3
        vector[t, 4] = g4
        vector[t, 5] = g5
        system[t, 0, 0] = h00
        system[t, 0, 1] = h01
        system[t, 1, 0] = h01
        system[t, 0, 2] = h02
        system[t, 2, 0] = h02
        system[t, 0, 3] = h03
        system[t, 3, 0] = h03
        system[t, 0, 4] = h04
        system[t, 4, 0] = h04
        system[t, 0, 5] = h05
        system[t, 5, 0] = h05
        system[t, 1, 1] = h11
        system[t, 1, 2] = h12
        system[t, 2, 1] = h12
        system[t, 1, 3] = h13
        system[t, 3, 1] = h13
        system[t, 1, 4] = h14
        system[t, 4, 1] = h14
        system[t, 1, 5] = h15
        system[t, 5, 1] = h15
        system[t, 2, 2] = h22
        system[t, 2, 3] = h23
        system[t, 3, 2] = h23
        system[t, 2, 4] = h24
        system[t, 4, 2] = h24
        system[t, 2, 5] = h25
        system[t, 5, 2] = h25
        system[t, 3, 3] = h33
        system[t, 3, 4] = h34
        system[t, 4, 3] = h34
        system[t, 3, 5] = h35
        system[t, 5, 3] = h35
        system[t, 4, 4] = h44
        system[t, 4, 5] = h45
        system[t, 5, 4] = h45
        system[t, 5, 5] = h55


# Candidates per block of :func:`strip_correlation`: a thread's scratch arrays are allocated
# once per block, not once per candidate.
_STRIP_BLOCK = 16


@njit(cache=True, parallel=True)
def strip_correlation(target, patch, step, start, direction, normal, lengths, bands,
                      out):  # type: ignore[no-untyped-def]
    """Zero-mean normalized correlation of patches along lines (:func:`core.refine`).

    Candidate ``i``'s patch ``patch[i]`` (``n x n``, ``n = 2 m + 1``) holds the source's
    values at the lattice ``a * direction[i] + b * normal[i]`` of the *target*'s line frame,
    ``a, b`` in ``step * (-m .. m)``. The target is sampled (bilinear) once per candidate on
    the strip of whole steps around its line, ``start[i] + u * direction[i] + v * normal[i]``,
    and ``out[i, s, q]`` is the correlation of the patch with the strip's values at
    ``u = s + a``, ``v = bands[q] + b`` (``bands`` consecutive integers), for ``s <
    lengths[i]``: -1 where a sample falls outside the target or either side is flat.

    Each strip value serves every position and band that covers it: about ``(L + 2 m step)
    (B + 2 m)`` samples a candidate instead of ``L B n^2`` when the target is sampled through
    the patch's map at every position. Candidates are shared among numba's threads in blocks
    (each writes its own rows).
    """
    h, w = target.shape
    xmax = w - 1.0
    ymax = h - 1.0
    n = patch.shape[1]
    reach = (n // 2) * step
    n_bands = bands.shape[0]
    n_cand = start.shape[0]
    cols = n_bands + 2 * reach
    size = n * n
    # The strip's columns some band and lattice column read (every other one for a single
    # band at step 2).
    used = np.zeros(cols, dtype=np.bool_)
    for q in range(n_bands):
        for jb in range(n):
            used[q + step * jb] = True
    rows = out.shape[1] + 2 * reach
    for block in prange((n_cand + _STRIP_BLOCK - 1) // _STRIP_BLOCK):
        # Column-major: a column's samples along the line are contiguous, so the sums below
        # run over the positions in the innermost loop (each position its own accumulator:
        # the loop vectorizes, and every sum is taken in lattice order).
        strip = np.zeros((cols, rows))
        inside = np.ones((cols, rows), dtype=np.bool_)
        zero_mean = np.empty((n, n))
        sx = np.empty(out.shape[1])
        sxx = np.empty(out.shape[1])
        sxp = np.empty(out.shape[1])
        for i in range(block * _STRIP_BLOCK, min((block + 1) * _STRIP_BLOCK, n_cand)):
            pm = 0.0
            for ja in range(n):
                for jb in range(n):
                    pm += patch[i, ja, jb]
            pm /= size
            pv = 0.0
            for ja in range(n):
                for jb in range(n):
                    zero_mean[ja, jb] = patch[i, ja, jb] - pm
                    pv += zero_mean[ja, jb] ** 2
            length = lengths[i]
            whole = True
            for v in range(cols):
                if not used[v]:
                    continue
                across = bands[0] - reach + v
                for u in range(length + 2 * reach):
                    along = u - reach
                    x = start[i, 0] + along * direction[i, 0] + across * normal[i, 0]
                    y = start[i, 1] + along * direction[i, 1] + across * normal[i, 1]
                    if x >= 0.0 and y >= 0.0 and x <= xmax and y <= ymax:
                        x0 = min(int(x), w - 2)
                        y0 = min(int(y), h - 2)
                        fx = x - x0
                        fy = y - y0
                        strip[v, u] = ((target[y0, x0] * (1.0 - fx) + target[y0, x0 + 1] * fx)
                                       * (1.0 - fy)
                                       + (target[y0 + 1, x0] * (1.0 - fx)
                                          + target[y0 + 1, x0 + 1] * fx) * fy)
                        inside[v, u] = True
                    else:
                        strip[v, u] = 0.0
                        inside[v, u] = False
                        whole = False
            for q in range(n_bands):
                sx[:length] = 0.0
                sxx[:length] = 0.0
                sxp[:length] = 0.0
                for ja in range(n):
                    for jb in range(n):
                        z = zero_mean[ja, jb]
                        column = strip[q + step * jb, step * ja:step * ja + length]
                        for s in range(length):
                            value = column[s]
                            sx[s] += value
                            sxx[s] += value * value
                            sxp[s] += value * z
                for s in range(length):
                    ok = True
                    if not whole:
                        for ja in range(n):
                            for jb in range(n):
                                if not inside[q + step * jb, s + step * ja]:
                                    ok = False
                    var = sxx[s] - sx[s] * sx[s] / size
                    if not ok or var <= 1e-9 or pv <= 1e-9:
                        out[i, s, q] = -1.0
                    else:
                        out[i, s, q] = sxp[s] / np.sqrt(var * pv)

# Points per block of :func:`template_peaks`: a thread's scratch arrays are allocated once per
# block, not once per point.
_PEAK_BLOCK = 16

# Template pixels per pass over the correlation accumulators (the taps padded with zeros to a
# multiple): each pass loads and stores the accumulators once; 8 ran 10-20 % faster than 4 (the
# window's unaligned loads bound it then).
_TAPS = 8


@njit(cache=True)
def _correlations(win, tpl, offsets, acc):  # type: ignore[no-untyped-def]
    """Sums ``acc[j] = sum_i win[offsets[i] + j] * tpl[i]``: the template (its pixels ``tpl``
    at flat offsets ``offsets`` into the window, padded with zero taps to a multiple of
    :data:`_TAPS`) times the flat window ``win`` at every flat position ``j``.

    The window's rows are swept at full width (the columns past the surface are never read), so
    each group of taps is one long contiguous loop, which vectorizes.
    """
    acc[:] = 0.0
    span = acc.shape[0]
    for g in range(0, tpl.shape[0], _TAPS):
        # Slices, not offset indices: numba's wraparound of negative indices would keep the
        # loop from vectorizing (8 x slower).
        w0 = win[offsets[g] : offsets[g] + span]
        w1 = win[offsets[g + 1] : offsets[g + 1] + span]
        w2 = win[offsets[g + 2] : offsets[g + 2] + span]
        w3 = win[offsets[g + 3] : offsets[g + 3] + span]
        w4 = win[offsets[g + 4] : offsets[g + 4] + span]
        w5 = win[offsets[g + 5] : offsets[g + 5] + span]
        w6 = win[offsets[g + 6] : offsets[g + 6] + span]
        w7 = win[offsets[g + 7] : offsets[g + 7] + span]
        t0, t1, t2, t3 = tpl[g], tpl[g + 1], tpl[g + 2], tpl[g + 3]
        t4, t5, t6, t7 = tpl[g + 4], tpl[g + 5], tpl[g + 6], tpl[g + 7]
        for j in range(span):
            acc[j] += (w0[j] * t0 + w1[j] * t1 + w2[j] * t2 + w3[j] * t3
                       + w4[j] * t4 + w5[j] * t5 + w6[j] * t6 + w7[j] * t7)


@njit(cache=True, error_model="numpy")
def _normalized(acc, sums, squares, side, size, s, var_t, surface):  # type: ignore[no-untyped-def]
    """``surface`` from the cross sums ``acc`` (:func:`_correlations`), the integral images of
    the window and its squares, the template's sum ``s`` and ``var_t``, ``count`` times the sum
    of its squared deviations.

    The numerator and the window's ``var_w`` are OpenCV's scaled by ``count``: whole numbers,
    exact in float64. Numpy's error model: the division of a flat window (0 / 0) is computed
    and discarded without a branch, so the row loop vectorizes.
    """
    count = size * size
    m = surface.shape[0]
    for dy in range(m):
        top_s = sums[dy]
        bottom_s = sums[dy + size]
        top_q = squares[dy]
        bottom_q = squares[dy + size]
        row = acc[dy * side : dy * side + m]
        out = surface[dy]
        for dx in range(m):
            sw = np.float64(bottom_s[dx + size] - top_s[dx + size] - bottom_s[dx] + top_s[dx])
            sww = np.float64(bottom_q[dx + size] - top_q[dx + size] - bottom_q[dx] + top_q[dx])
            var_w = count * sww - sw * sw
            c = (count * np.float64(row[dx]) - sw * s) / np.sqrt(var_w * var_t)
            # OpenCV clips rounding past +-1 to +-1 and gives a flat window 0.
            c = min(max(c, -1.0), 1.0)
            out[dx] = c if var_w > 0.0 else 0.0


@njit(cache=True)
def _surface_peaks(surface, rows):  # type: ignore[no-untyped-def]
    """Best value of ``surface``, its position (the first in row-major order, as
    ``cv2.minMaxLoc``) and the largest local maximum outside the diamond ``|dx| + |dy| <= 2``
    around it (-1 without one); ``rows`` is scratch of the surface's shape."""
    m = surface.shape[0]
    best = surface[0, 0]
    bx = 0
    by = 0
    for y in range(m):
        row = surface[y]
        for x in range(m):
            if row[x] > best:
                best = row[x]
                bx = x
                by = y
    # Maxima of three along the rows (a loop that vectorizes): a pixel is a local maximum
    # (no neighbour greater, as a comparison with cv2.dilate's default border) when it reaches
    # those of its row and of the rows above and below.
    for y in range(m):
        row = surface[y]
        out = rows[y]
        out[0] = max(row[0], row[1])
        for x in range(1, m - 1):
            out[x] = max(max(row[x - 1], row[x]), row[x + 1])
        out[m - 1] = max(row[m - 2], row[m - 1])
    second = -np.inf
    for y in range(m):
        row = surface[y]
        up = rows[max(y - 1, 0)]
        mid = rows[y]
        down = rows[min(y + 1, m - 1)]
        near = 2 - abs(y - by)
        for x in range(m):
            v = row[x]
            if v > second and v >= mid[x] and v >= up[x] and v >= down[x] and abs(x - bx) > near:
                second = v
    return float(best), bx, by, float(second) if second > -np.inf else -1.0


@njit(cache=True, parallel=True)
def template_peaks(ref, warped, corners, windows, size, radius, min_std, best, second, peak,
                   flat):  # type: ignore[no-untyped-def]
    """Correlation peaks of templates of ``ref`` over windows of ``warped``, 8-bit images
    (:func:`core.reliability.uniqueness`).

    Template ``k`` is the ``size x size`` block of ``ref`` at top-left ``corners[k]`` (x, y);
    its window the square of ``warped`` of side ``2 radius + size`` at ``windows[k]``, both
    inside their images. A template whose standard deviation (population, computed as
    ``cv2.meanStdDev`` does, bit for bit) is under ``min_std`` gets ``flat[k] = True`` and
    nothing else. Otherwise its surface, of side ``2 radius + 1``, is that of
    ``cv2.matchTemplate(window, template, cv2.TM_CCOEFF_NORMED)`` but exact: the sums are of
    whole numbers, exact in the arithmetic used, where OpenCV's cross sums are float32 with
    rounding errors (its correlations are off by up to 2e-3 on the real pairs of the benchmarks,
    by 1e-2 in a dim window of a bright image); it is kept in float32, as OpenCV's.

    Written: ``best[k]`` the surface's maximum, ``peak[k]`` the first position (x, y) of it in
    row-major order, ``second[k]`` the largest local maximum (no 3x3 neighbour greater) outside
    the diamond ``|dx| + |dy| <= 2`` around the best (the pixels ``cv2.circle`` of radius 2
    fills), -1 if none. Points are shared among numba's threads in blocks.
    """
    n = corners.shape[0]
    count = size * size
    side = 2 * radius + size
    m = 2 * radius + 1
    scale = 1.0 / count
    # Template pixel i lies at flat offset offsets[i] of the window; the padded taps (weight 0)
    # read its first pixels.
    taps = -(-count // _TAPS) * _TAPS
    offsets = np.zeros(taps, dtype=np.int64)
    for i in range(count):
        offsets[i] = (i // size) * side + i % size
    for block in prange((n + _PEAK_BLOCK - 1) // _PEAK_BLOCK):
        tpl = np.zeros(taps, dtype=np.float32)
        win = np.empty(side * side, dtype=np.float32)
        acc = np.empty((m - 1) * side + m, dtype=np.float32)
        # Integral images in integers: their running sums have no float latency chain.
        sums = np.zeros((side + 1, side + 1), dtype=np.int64)
        squares = np.zeros((side + 1, side + 1), dtype=np.int64)
        surface = np.empty((m, m), dtype=np.float32)
        rows = np.empty((m, m), dtype=np.float32)
        for k in range(block * _PEAK_BLOCK, min((block + 1) * _PEAK_BLOCK, n)):
            tx = corners[k, 0]
            ty = corners[k, 1]
            s = 0.0
            sq = 0.0
            for y in range(size):
                for x in range(size):
                    v = float(ref[ty + y, tx + x])
                    tpl[y * size + x] = v
                    s += v
                    sq += v * v
            # cv2.meanStdDev's expression on the same (exact) sums: its value bit for bit.
            mean = s * scale
            if np.sqrt(max(sq * scale - mean * mean, 0.0)) < min_std:
                flat[k] = True
                continue
            wx = windows[k, 0]
            wy = windows[k, 1]
            for y in range(side):
                row_s = 0
                row_q = 0
                for x in range(side):
                    v = np.int64(warped[wy + y, wx + x])
                    win[y * side + x] = v
                    row_s += v
                    row_q += v * v
                    sums[y + 1, x + 1] = sums[y, x + 1] + row_s
                    squares[y + 1, x + 1] = squares[y, x + 1] + row_q
            # Products of 8-bit levels summed over at most 258 of them stay whole numbers
            # under 2**24: exact in float32, in any order.
            _correlations(win, tpl, offsets, acc)
            _normalized(acc, sums, squares, side, size, s, count * sq - s * s, surface)
            best[k], peak[k, 0], peak[k, 1], second[k] = _surface_peaks(surface, rows)


@njit(cache=True, inline="always")
def _near_kept(points, i, head, nxt, cx, cy, cols, rows, d2):  # type: ignore[no-untyped-def]
    """Whether a kept point in the cells around ``(cx, cy)`` lies closer than ``sqrt(d2)`` to
    point ``i``; returning at the first one found is what makes the dropped points cheap."""
    for yy in range(max(cy - 1, 0), min(cy + 2, rows)):
        for xx in range(max(cx - 1, 0), min(cx + 2, cols)):
            j = head[yy * cols + xx]
            while j >= 0:
                dx = points[j, 0] - points[i, 0]
                dy = points[j, 1] - points[i, 1]
                if dx * dx + dy * dy < d2:
                    return True
                j = nxt[j]
    return False


@njit(cache=True)
def spaced(points, distance, count):  # type: ignore[no-untyped-def]
    """Indices of the points kept by a greedy pass in their order: a point is kept when no
    kept one lies closer than ``distance`` (at most ``count``; OpenCV's ``goodFeaturesToTrack``
    chooses its corners so; :func:`core.refine.levels`). A grid of ``distance`` cells holds the
    kept points, so each point looks at nine cells."""
    n = points.shape[0]
    keep = np.empty(n, np.int64)
    if n == 0 or count <= 0:
        return keep[:0]
    x0 = points[:, 0].min()
    y0 = points[:, 1].min()
    inv = 1.0 / distance
    cols = int((points[:, 0].max() - x0) * inv) + 1
    rows = int((points[:, 1].max() - y0) * inv) + 1
    head = np.full(rows * cols, -1, np.int64)
    nxt = np.full(n, -1, np.int64)
    d2 = distance * distance
    kept = 0
    for i in range(n):
        cx = int((points[i, 0] - x0) * inv)
        cy = int((points[i, 1] - y0) * inv)
        if not _near_kept(points, i, head, nxt, cx, cy, cols, rows, d2):
            nxt[i] = head[cy * cols + cx]
            head[cy * cols + cx] = i
            keep[kept] = i
            kept += 1
            if kept == count:
                break
    return keep[:kept]

@njit(cache=True, error_model="numpy")
def containing(vertices, tris, points, out):  # type: ignore[no-untyped-def]
    """Index of the first triangle of ``tris`` (T, 3) whose barycentric test holds for each of
    ``points`` (K, 2), into ``out`` (K,), -1 for none. The same float64 operations as the
    numpy form it replaced (IEEE results where a degenerate triangle divides by 0), which
    tested every point against every triangle: 26 x slower on 300 points and 800 triangles."""
    n_tri = tris.shape[0]
    ax = np.empty(n_tri)
    ay = np.empty(n_tri)
    v0x = np.empty(n_tri)
    v0y = np.empty(n_tri)
    v1x = np.empty(n_tri)
    v1y = np.empty(n_tri)
    d00 = np.empty(n_tri)
    d01 = np.empty(n_tri)
    d11 = np.empty(n_tri)
    den = np.empty(n_tri)
    for t in range(n_tri):
        a, b, c = tris[t, 0], tris[t, 1], tris[t, 2]
        ax[t], ay[t] = vertices[a, 0], vertices[a, 1]
        v0x[t], v0y[t] = vertices[c, 0] - ax[t], vertices[c, 1] - ay[t]
        v1x[t], v1y[t] = vertices[b, 0] - ax[t], vertices[b, 1] - ay[t]
        d00[t] = v0x[t] * v0x[t] + v0y[t] * v0y[t]
        d01[t] = v0x[t] * v1x[t] + v0y[t] * v1y[t]
        d11[t] = v1x[t] * v1x[t] + v1y[t] * v1y[t]
        den[t] = d00[t] * d11[t] - d01[t] * d01[t]
    for k in range(points.shape[0]):
        out[k] = -1
        for t in range(n_tri):
            v2x, v2y = points[k, 0] - ax[t], points[k, 1] - ay[t]
            d20 = v2x * v0x[t] + v2y * v0y[t]
            d21 = v2x * v1x[t] + v2y * v1y[t]
            u = (d11[t] * d20 - d01[t] * d21) / den[t]
            v = (d00[t] * d21 - d01[t] * d20) / den[t]
            if u >= 0 and v >= 0 and u + v <= 1:
                out[k] = t
                break

@njit(cache=True, inline="always")
def _affine_fit(offsets, moving, weight, ridge, m, out):  # type: ignore[no-untyped-def]
    """Weighted least-squares affine map ``moving ~ [offsets, 1] out`` of one point's ``k``
    neighbours into ``out`` (3, 2): the normal equations (in the workspace ``m`` (3, 5)) with
    ``ridge`` on their diagonal, solved by elimination with partial pivoting."""
    m[:] = 0.0
    for j in range(offsets.shape[0]):
        w = weight[j]
        if w == 0.0:
            continue
        x0, x1, y0, y1 = offsets[j, 0], offsets[j, 1], moving[j, 0], moving[j, 1]
        for a in range(3):
            wa = w * (x0 if a == 0 else x1 if a == 1 else 1.0)
            m[a, 0] += wa * x0
            m[a, 1] += wa * x1
            m[a, 2] += wa
            m[a, 3] += wa * y0
            m[a, 4] += wa * y1
    for a in range(3):
        m[a, a] += ridge
    for c in range(3):
        p = c
        for r in range(c + 1, 3):
            if abs(m[r, c]) > abs(m[p, c]):
                p = r
        if p != c:
            for q in range(5):
                m[c, q], m[p, q] = m[p, q], m[c, q]
        for r in range(c + 1, 3):
            f = m[r, c] / m[c, c]
            for q in range(c, 5):
                m[r, q] -= f * m[c, q]
    for col in range(2):
        for c in range(2, -1, -1):
            v = m[c, 3 + col]
            for q in range(c + 1, 3):
                v -= m[c, q] * out[q, col]
            out[c, col] = v / m[c, c]


@njit(cache=True, inline="always")
def _fit_misses(offsets, moving, near, fit, res, kept):  # type: ignore[no-untyped-def]
    """Each neighbour's miss by the map ``fit`` into ``res``; their median over the ``near``
    ones (0 for none), sorted in the workspace ``kept``."""
    c = 0
    for j in range(offsets.shape[0]):
        px = offsets[j, 0] * fit[0, 0] + offsets[j, 1] * fit[1, 0] + fit[2, 0] - moving[j, 0]
        py = offsets[j, 0] * fit[0, 1] + offsets[j, 1] * fit[1, 1] + fit[2, 1] - moving[j, 1]
        r = np.sqrt(px * px + py * py)
        res[j] = r
        if near[j]:
            q = c  # insertion into the sorted prefix
            while q > 0 and kept[q - 1] > r:
                kept[q] = kept[q - 1]
                q -= 1
            kept[q] = r
            c += 1
    if c == 0:
        return 0.0
    return 0.5 * (kept[(c - 1) // 2] + kept[c // 2])


@njit(cache=True)
def affine_fits(offsets, moving, weight, ridge):  # type: ignore[no-untyped-def]
    """Per point, the weighted least-squares affine map ``moving ~ [offsets, 1] A`` of its
    neighbours (``offsets`` and ``moving`` (N, K, 2), ``weight`` (N, K)), ``ridge`` added to
    the normal equations' diagonal: the maps (N, 3, 2)."""
    maps = np.empty((offsets.shape[0], 3, 2))
    m = np.empty((3, 5))
    for i in range(offsets.shape[0]):
        _affine_fit(offsets[i], moving[i], weight[i], ridge, m, maps[i])
    return maps


@njit(cache=True)
def trimmed_affine_fits(offsets, moving, near, min_px, ridge):  # type: ignore[no-untyped-def]
    """Per point, the affine map of :func:`core.reliability._local_fits`: fitted to its ``near``
    neighbours (``offsets`` (N, K, 2) from the point, their ``moving`` (N, K, 2) positions),
    then twice to those it misses by at most ``max(min_px, 2.5 x median miss)``. Returns the
    maps (N, 3, 2) and the median miss of the last over the near neighbours (N,). The numpy
    form (batched normal equations, LAPACK's solve) took 1.2-5.6 ms a call on 30-490 points."""
    n, k = offsets.shape[0], offsets.shape[1]
    maps = np.empty((n, 3, 2))
    spread = np.empty(n)
    weight = np.empty(k)
    res = np.empty(k)
    kept = np.empty(k)
    m = np.empty((3, 5))
    for i in range(n):
        for j in range(k):
            weight[j] = 1.0 if near[i, j] else 0.0
        for _ in range(2):
            _affine_fit(offsets[i], moving[i], weight, ridge, m, maps[i])
            median = _fit_misses(offsets[i], moving[i], near[i], maps[i], res, kept)
            bound = max(min_px, 2.5 * median)
            for j in range(k):
                weight[j] = 1.0 if near[i, j] and res[j] <= bound else 0.0
        _affine_fit(offsets[i], moving[i], weight, ridge, m, maps[i])
        spread[i] = _fit_misses(offsets[i], moving[i], near[i], maps[i], res, kept)
    return maps, spread


@njit(cache=True, inline="always")
def _bilinear_at(image, x, y):  # type: ignore[no-untyped-def]
    """``image`` at ``(x, y)``, bilinear; the caller keeps ``(x, y)`` inside."""
    x0 = min(int(x), image.shape[1] - 2)
    y0 = min(int(y), image.shape[0] - 2)
    fx = x - x0
    fy = y - y0
    top = image[y0, x0] + fx * (image[y0, x0 + 1] - image[y0, x0])
    bottom = image[y0 + 1, x0] + fx * (image[y0 + 1, x0 + 1] - image[y0 + 1, x0])
    return top + fy * (bottom - top)


# numba's np.linalg.cholesky raises on a system that is not positive definite, which a window
# too flat to fix the map gives (an exception inside a parallel loop), and allocates per call.
@njit(cache=True)
def _cholesky(system, factor):  # type: ignore[no-untyped-def]
    """Cholesky factor (lower) of the symmetric ``system``; False where a pivot falls under
    ``1e-9`` of its diagonal (a window whose gradients leave a direction of the map open)."""
    n = system.shape[0]
    for j in range(n):
        s = system[j, j]
        for k in range(j):
            s -= factor[j, k] * factor[j, k]
        if s <= 1e-9 * system[j, j] or s <= 0.0:
            return False
        factor[j, j] = np.sqrt(s)
        for i in range(j + 1, n):
            s = system[i, j]
            for k in range(j):
                s -= factor[i, k] * factor[j, k]
            factor[i, j] = s / factor[j, j]
    return True


@njit(cache=True)
def _cholesky_solve(factor, rhs, out):  # type: ignore[no-untyped-def]
    n = rhs.shape[0]
    for i in range(n):
        s = rhs[i]
        for k in range(i):
            s -= factor[i, k] * out[k]
        out[i] = s / factor[i, i]
    for i in range(n - 1, -1, -1):
        s = out[i]
        for k in range(i + 1, n):
            s -= factor[k, i] * out[k]
        out[i] = s / factor[i, i]


@njit(cache=True, parallel=True, error_model="numpy")
def window_fits(reference, moving, points, maps, half, iterations, tolerance, centres,
                scores):  # type: ignore[no-untyped-def]
    """Affine fits of reference windows onto the moving image (:func:`core.refine.sharpened`).

    Pair ``k``'s window is the reference sampled at ``points[k] + (u, v)``, ``u, v`` in
    ``-half .. half``; ``maps[k]`` (2 x 3) takes ``(u, v, 1)`` to its first guess in the moving
    image. The fit maximises the zero-mean normalised correlation of the window with the moving
    image under an affine map by Gauss-Newton steps of the inverse compositional form (Baker
    and Matthews 2004), the gain and offset eliminated as in Evangelidis and Psarakis's
    enhanced correlation coefficient (which OpenCV's ``findTransformECC`` maximises by forward
    steps, each resampling the image's gradients): the window's gradients and the 6 x 6 system
    are computed once per pair, and a step samples the moving image once per window pixel. It
    stops after ``iterations`` steps or when a step moves the window's centre by less than
    ``tolerance``. ``centres[k]`` is where the fit takes ``(0, 0)`` and ``scores[k]`` its
    correlation there: -1 for a window too flat to fix the map, -2 where a sample leaves the
    images. Pairs are shared among numba's threads.
    """
    side = 2 * half + 1
    size = side * side
    h, w = moving.shape
    rh, rw = reference.shape
    for k in prange(points.shape[0]):
        centres[k, 0] = maps[k, 0, 2]
        centres[k, 1] = maps[k, 1, 2]
        scores[k] = -2.0
        px, py = points[k, 0], points[k, 1]
        if (px - half - 1 < 0 or py - half - 1 < 0 or px + half + 1 > rw - 1
                or py + half + 1 > rh - 1):
            continue
        # The window with a pixel of margin, sampled once: the gradients are its central
        # differences.
        patch = np.empty((side + 2, side + 2))
        for a in range(side + 2):
            for b in range(side + 2):
                patch[a, b] = _bilinear_at(reference, px - half - 1 + b, py - half - 1 + a)
        # Per pixel the window's value and its steepest-descent row, the map's derivative
        # (columns: x by u, v, 1, then y by u, v, 1); their sums give the means that the
        # zero-mean correlation takes off.
        tpl = np.empty(size)
        sd = np.empty((size, 6))
        system = np.zeros((6, 6))
        sd_sum = np.zeros(6)
        sd_t = np.zeros(6)
        t_sum = 0.0
        t_sq = 0.0
        i = 0
        for a in range(side):
            v = float(a - half)
            for b in range(side):
                u = float(b - half)
                t = patch[a + 1, b + 1]
                gx = 0.5 * (patch[a + 1, b + 2] - patch[a + 1, b])
                gy = 0.5 * (patch[a + 2, b + 1] - patch[a, b + 1])
                tpl[i] = t
                sd[i, 0], sd[i, 1], sd[i, 2] = gx * u, gx * v, gx
                sd[i, 3], sd[i, 4], sd[i, 5] = gy * u, gy * v, gy
                t_sum += t
                t_sq += t * t
                for j in range(6):
                    sd_sum[j] += sd[i, j]
                    sd_t[j] += sd[i, j] * t
                    for m in range(j + 1):
                        system[j, m] += sd[i, j] * sd[i, m]
                i += 1
        t_var = t_sq - t_sum * t_sum / size
        for j in range(6):
            sd_t[j] -= sd_sum[j] * t_sum / size
            for m in range(j + 1):
                system[j, m] -= sd_sum[j] * sd_sum[m] / size
                system[m, j] = system[j, m]
        factor = np.zeros((6, 6))
        if t_var <= 1e-9 * size or not _cholesky(system, factor):
            scores[k] = -1.0
            continue
        a00, a01, tx = maps[k, 0, 0], maps[k, 0, 1], maps[k, 0, 2]
        a10, a11, ty = maps[k, 1, 0], maps[k, 1, 1], maps[k, 1, 2]
        sd_i = np.empty(6)
        delta = np.empty(6)
        last = iterations
        for step in range(iterations + 1):
            # The window's corners bound where it samples under an affine map.
            outside = False
            for cu in (-half, half):
                for cv in (-half, half):
                    x = a00 * cu + a01 * cv + tx
                    y = a10 * cu + a11 * cv + ty
                    if x < 0.0 or y < 0.0 or x > w - 1.0 or y > h - 1.0:
                        outside = True
            if outside:
                scores[k] = -2.0
                break
            s_i = 0.0
            s_ii = 0.0
            s_ti = 0.0
            sd_i[:] = 0.0
            i = 0
            for a in range(side):
                v = float(a - half)
                x = a01 * v + tx - a00 * half
                y = a11 * v + ty - a10 * half
                for _ in range(side):
                    value = _bilinear_at(moving, x, y)
                    s_i += value
                    s_ii += value * value
                    s_ti += tpl[i] * value
                    for j in range(6):
                        sd_i[j] += sd[i, j] * value
                    x += a00
                    y += a10
                    i += 1
            i_var = s_ii - s_i * s_i / size
            if i_var <= 1e-9 * size:
                scores[k] = -1.0
                break
            s_ti -= t_sum * s_i / size
            scores[k] = s_ti / np.sqrt(t_var * i_var)
            centres[k, 0], centres[k, 1] = tx, ty
            if step == last:
                break
            # The gain that best takes the moving samples onto the window, then the step of
            # the window's map that best explains what is left.
            gain = s_ti / i_var
            for j in range(6):
                sd_i[j] = gain * (sd_i[j] - sd_sum[j] * s_i / size) - sd_t[j]
            _cholesky_solve(factor, sd_i, delta)
            # The moving map composed with the inverse of the window's step.
            d00, d01, d10, d11 = 1.0 + delta[0], delta[1], delta[3], 1.0 + delta[4]
            det = d00 * d11 - d01 * d10
            i00, i01, i10, i11 = d11 / det, -d01 / det, -d10 / det, d00 / det
            dx = -(i00 * delta[2] + i01 * delta[5])
            dy = -(i10 * delta[2] + i11 * delta[5])
            n00 = a00 * i00 + a01 * i10
            n01 = a00 * i01 + a01 * i11
            n10 = a10 * i00 + a11 * i10
            n11 = a10 * i01 + a11 * i11
            ntx = a00 * dx + a01 * dy + tx
            nty = a10 * dx + a11 * dy + ty
            moved = np.hypot(ntx - tx, nty - ty)
            a00, a01, a10, a11, tx, ty = n00, n01, n10, n11, ntx, nty
            if moved < tolerance:
                # One more pass scores the final map.
                last = step + 1


# --- the greedy edge-swap search ------------------------------------------------------------------
#
# The body of :func:`core.optimize.greedy_search`. The search is sequential: every swap changes
# the scores of the four edges around it before the next best is chosen, and in Python each
# swap cost 50-100 microseconds of bookkeeping (the quad's preconditions, the cache's dictionary,
# the heap), more than the histograms it scores. Here the mesh's topology, the triangle cache's
# index, the scores and the heap live in numba's typed containers and one call runs the search.
# Every decision is the one of the Python search it replaced, bit for bit: the same
# preconditions on the same fixed-point coordinates, the same histograms (each triangle counted
# with its vertices in increasing order), the same sums and thresholds, the heap ordered by
# gain over the threshold and then by edge, the look-ahead's pairs in the same order,
# stable-sorted. The owners of an edge keep the order of :class:`core.mesh.Mesh` (the triangle
# added first is first), which decides which apex is ``k`` and which slot a new triangle takes.
#
# The arguments travel in four tuples:
# ``mesh = (tris, owners, ref_fixed, mov_fixed, n, reference, moving, stamps)``: the triangles
# by slot (rows of -1 for empty slots), ``edge code -> packed owner slots``
# (:func:`owners_dict`), the fixed-point and the float vertices, ``n`` vertices, the slots'
# stamps (:meth:`core.mesh.Mesh.slot_triangles`); an edge ``(i, j)``, ``i < j``, has the code
# ``i n + j``.
# ``cache = (index, hist_box, mom_box, images, params, use_ncc, xtable)``: ``triangle key ->
# row`` (the key of ``a < b < c`` is ``(a n + b) n + c``), the histogram and moment tables in
# one-element lists (:func:`search_box`; they grow), the scoring images ``(reference bins,
# reference values, moving)`` and their parameters ``(width, height, bins, bin offset, bin
# scale, reference scale, moving scale)``, whether the cost is NCC (else NMI), the
# :func:`xlogx_table`.
# ``search = (best, gain, heap, retired, epsilon, epsilon_pixels, low, high)``: per edge its
# gain over its threshold and its gain, the heap of ``(-margin, edge)``, the retired edges, the
# threshold's parameters (:func:`core.optimize.gain_thresholds`).
# ``state``: the integer state (``STATE_*``).

#: Batches of at least this many triangles are shared among numba's threads (its
#: ``NUMBA_NUM_THREADS``; the service's workers set it to their ``worker_threads``); the few
#: triangles a swap rescores are not worth a thread launch. The histograms are the same either
#: way.
PARALLEL_TRIANGLES = 64

#: Why a search stopped, by the index :func:`search_run` leaves in ``state[STATE_STOPPED]``.
SEARCH_STOPS = ("no swap raises the consistency by more than epsilon", "max_iterations reached")

# The integer state: the cache rows used, the swaps taken, the edges over their threshold, the
# gains scored, why it stopped, whether the look-ahead has begun noting changed vertices.
STATE_USED, STATE_TAKEN, STATE_POSITIVE, STATE_EVALUATIONS, STATE_STOPPED, STATE_MOVED = range(6)
STATE_STAMP = 6  # the next triangle's stamp
STATE_REPORT = 7  # when the search next stops to report progress: microseconds from its start

#: Most vertices of a searched mesh: a triangle's key ``(a n + b) n + c`` must fit in int64.
SEARCH_MAX_VERTICES = 2**21 - 1

#: A pair's six triangles, as columns of its row ``(i, j, k, l, m, p, r, p', r')``: the three
#: before, ``(i, j, k), (i, j, l), (p, r, m)``, and the three after, ``(k, l, p'), (r', m, p),
#: (r', m, r)``.
PAIR_TRIANGLES = np.array([[0, 1, 2], [0, 1, 3], [5, 6, 4], [2, 3, 7], [8, 4, 5], [8, 4, 6]])

_PACK = np.int64(1) << 32


def search_state(next_stamp: int) -> np.ndarray:
    """The integer state of a search that has not started on a mesh whose next triangle gets
    the stamp ``next_stamp``."""
    state = np.zeros(8, dtype=np.int64)
    state[STATE_STAMP] = next_stamp
    return state


def owners_dict(codes: np.ndarray, owners: np.ndarray) -> Dict:
    """The typed ``edge code -> owner slots`` of a mesh (:meth:`core.mesh.Mesh.edge_owners`)."""
    return _owners_dict(np.ascontiguousarray(codes, dtype=np.int64),
                        np.ascontiguousarray(owners, dtype=np.int64))


def empty_index() -> Dict:
    """A typed ``triangle key -> cache row`` index."""
    return Dict.empty(types.int64, types.int64)


def empty_scores() -> Dict:
    """A typed ``edge code -> value`` map."""
    return Dict.empty(types.int64, types.float64)


def empty_set() -> Dict:
    """A typed set of edge codes (``code -> 1``; the index's type: one type fewer to
    compile)."""
    return Dict.empty(types.int64, types.int64)


def empty_heap() -> List:
    """A typed heap of ``(-margin, edge code)``."""
    return List.empty_list(types.Tuple((types.float64, types.int64)))


def search_box(array: np.ndarray) -> List:
    """A typed one-element list holding ``array``: the search grows it in place."""
    out = List.empty_list(types.Array(from_dtype(array.dtype), array.ndim, "C"))
    out.append(array)
    return out


def search_steps(capacity: int = 256) -> List:
    """The search's record of accepted swaps (:func:`search_box`; it grows), a row each:
    edge, new edge, kind (0 alone, 1 in a pair), gain, seconds since the start, and the cache
    rows of the quad's two triangles before and two after. Every value is exact in float64
    (codes and rows are far below 2**53); one array, not a typed list per column: each typed
    container's type costs numba seconds to compile."""
    return search_box(np.zeros((capacity, 9)))


@njit(cache=True)
def _owners_dict(codes, owners):  # type: ignore[no-untyped-def]
    out = Dict.empty(types.int64, types.int64)
    for e in range(codes.shape[0]):
        out[codes[e]] = owners[e, 0] * _PACK + owners[e, 1] + 1
    return out


@njit(cache=True, inline="always")
def _unpack(v):  # type: ignore[no-untyped-def]
    return v // _PACK, v % _PACK - 1


@njit(cache=True, inline="always")
def _edge(a, b, n):  # type: ignore[no-untyped-def]
    return a * n + b if a < b else b * n + a


@njit(cache=True, inline="always")
def _cross(fixed, a, b, c):  # type: ignore[no-untyped-def]
    return ((fixed[b, 0] - fixed[a, 0]) * (fixed[c, 1] - fixed[a, 1])
            - (fixed[b, 1] - fixed[a, 1]) * (fixed[c, 0] - fixed[a, 0]))


@njit(cache=True, inline="always")
def _sign(v):  # type: ignore[no-untyped-def]
    return (v > 0) - (v < 0)


@njit(cache=True)
def _quad(mesh, code):  # type: ignore[no-untyped-def]
    """``(i, j, k, l)`` of an internal edge (as :meth:`Mesh.quad`) and its two slots."""
    tris, owners, n = mesh[0], mesh[1], mesh[4]
    s0, s1 = _unpack(owners[code])
    i, j = code // n, code % n
    k = tris[s0, 0] + tris[s0, 1] + tris[s0, 2] - i - j
    l = tris[s1, 0] + tris[s1, 1] + tris[s1, 2] - i - j  # noqa: E741
    return i, j, k, l, s0, s1


@njit(cache=True)
def _swappable(mesh, code):  # type: ignore[no-untyped-def]
    """:meth:`Mesh.swappable_quad`: whether the edge may be swapped, and its ``i, j, k, l``."""
    owners, ref_fixed, mov_fixed, n = mesh[1], mesh[2], mesh[3], mesh[4]
    v = owners.get(code, -1)
    if v < 0 or v % _PACK == 0:  # no edge, or a boundary edge
        return False, 0, 0, 0, 0
    i, j, k, l, _, _ = _quad(mesh, code)  # noqa: E741
    if _edge(k, l, n) in owners:
        return False, 0, 0, 0, 0
    flips = np.zeros(2, dtype=np.bool_)
    for f in range(2):
        fixed = ref_fixed if f == 0 else mov_fixed
        ijk, ijl = _cross(fixed, i, j, k), _cross(fixed, i, j, l)
        kli, klj = _cross(fixed, k, l, i), _cross(fixed, k, l, j)
        # Strictly convex: each diagonal separates the other's ends.
        if not ((ijk > 0 and ijl < 0) or (ijk < 0 and ijl > 0)):
            return False, 0, 0, 0, 0
        if not ((kli > 0 and klj < 0) or (kli < 0 and klj > 0)):
            return False, 0, 0, 0, 0
        flips[f] = kli > 0
    # The new triangles turn the same way in both images.
    if flips[0] != flips[1]:
        return False, 0, 0, 0, 0
    return True, i, j, k, l


@njit(cache=True)
def _eligible(mesh, retired, code):  # type: ignore[no-untyped-def]
    """:func:`_swappable`, and the edge it would create has not been swapped away before."""
    ok, i, j, k, l = _swappable(mesh, code)  # noqa: E741
    return ok and _edge(k, l, mesh[4]) not in retired, i, j, k, l


@njit(cache=True)
def _drop(mesh, slot):  # type: ignore[no-untyped-def]
    tris, owners, n = mesh[0], mesh[1], mesh[4]
    for c in range(3):
        code = _edge(tris[slot, c], tris[slot, (c + 1) % 3], n)
        s0, s1 = _unpack(owners[code])
        if s0 == slot:
            s0, s1 = s1, -1
        elif s1 == slot:
            s1 = -1
        if s0 < 0:
            del owners[code]
        else:
            owners[code] = s0 * _PACK + s1 + 1
    tris[slot, 0] = tris[slot, 1] = tris[slot, 2] = -1


@njit(cache=True)
def _add(mesh, slot, a, b, c, state):  # type: ignore[no-untyped-def]
    """Store triangle ``(a, b, c)`` in ``slot``, positively oriented in the reference."""
    tris, owners, ref_fixed, n, stamps = mesh[0], mesh[1], mesh[2], mesh[4], mesh[7]
    if _cross(ref_fixed, a, b, c) < 0:
        b, c = c, b
    tris[slot, 0], tris[slot, 1], tris[slot, 2] = a, b, c
    stamps[slot] = state[STATE_STAMP]
    state[STATE_STAMP] += 1
    for e in range(3):
        code = _edge(tris[slot, e], tris[slot, (e + 1) % 3], n)
        v = owners.get(code, -1)
        owners[code] = slot * _PACK if v < 0 else (v // _PACK) * _PACK + slot + 1


@njit(cache=True)
def _swap(mesh, code, state):  # type: ignore[no-untyped-def]
    """:meth:`Mesh.swap` without the check; returns the new edge's code."""
    i, j, k, l, s0, s1 = _quad(mesh, code)  # noqa: E741
    _drop(mesh, s0)
    _drop(mesh, s1)
    _add(mesh, s0, k, l, i, state)
    _add(mesh, s1, k, l, j, state)
    return _edge(k, l, mesh[4])


@njit(cache=True, inline="always")
def _sorted3(a, b, c):  # type: ignore[no-untyped-def]
    if a > b:
        a, b = b, a
    if b > c:
        b, c = c, b
        if a > b:
            a, b = b, a
    return a, b, c


@njit(cache=True)
def _cache_rows(tri, mesh, cache, state):  # type: ignore[no-untyped-def]
    """Cache rows of the triangles ``tri`` (K, 3), any vertex order; those not cached yet are
    counted first, in one batch, with their vertices in increasing order."""
    n, reference, moving = mesh[4], mesh[5], mesh[6]
    index, hist_box, mom_box, images, params = cache[0], cache[1], cache[2], cache[3], cache[4]
    k = tri.shape[0]
    start = state[STATE_USED]
    rows = np.empty(k, dtype=np.int64)
    missing = np.empty((k, 3), dtype=np.int64)
    m = 0
    for t in range(k):
        a, b, c = _sorted3(tri[t, 0], tri[t, 1], tri[t, 2])
        key = (a * n + b) * n + c
        r = index.get(key, -1)
        if r < 0:
            r = start + m
            index[key] = r
            missing[m, 0], missing[m, 1], missing[m, 2] = a, b, c
            m += 1
        rows[t] = r
    if m == 0:
        return rows
    hist = hist_box[0]
    if start + m > hist.shape[0]:
        grown = np.empty((max(start + m, 2 * hist.shape[0]), hist.shape[1]), dtype=hist.dtype)
        grown[:start] = hist[:start]
        hist_box[0] = grown
        hist = grown
    moments = mom_box[0]
    with_moments = moments.shape[0] > 0
    if with_moments and start + m > moments.shape[0]:
        grown_m = np.empty((hist.shape[0], 6))
        grown_m[:start] = moments[:start]
        mom_box[0] = grown_m
        moments = grown_m
    ref_tris = np.empty((m, 3, 2))
    mov_tris = np.empty((m, 3, 2))
    for t in range(m):
        for c in range(3):
            ref_tris[t, c, 0] = reference[missing[t, c], 0]
            ref_tris[t, c, 1] = reference[missing[t, c], 1]
            mov_tris[t, c, 0] = moving[missing[t, c], 0]
            mov_tris[t, c, 1] = moving[missing[t, c], 1]
    out = hist[start:start + m]
    out[:] = 0
    out_m = moments[start:start + m] if with_moments else moments
    if with_moments:
        out_m[:] = 0.0
    ref_bins, ref_values, moving_image = images
    width, height, bins, bin_offset, bin_scale, ref_scale, mov_scale = params
    if m >= PARALLEL_TRIANGLES:
        group_histograms(ref_tris, mov_tris, np.arange(m + 1), ref_bins, ref_values,
                         moving_image, width, height, bins, bin_offset, bin_scale, ref_scale,
                         mov_scale, out, out_m)
    else:
        triangle_histograms(ref_tris, mov_tris, ref_bins, ref_values, moving_image, width,
                            height, bins, bin_offset, bin_scale, ref_scale, mov_scale, out, out_m)
    state[STATE_USED] = start + m
    return rows


@njit(cache=True)
def gain_threshold(pixels, epsilon, epsilon_pixels, low, high):  # type: ignore[no-untyped-def]
    """:func:`core.optimize.gain_thresholds` of one quad of ``pixels`` pixels (``low``,
    ``high``: :data:`core.optimize.THRESHOLD_RANGE`), the same value bit for bit: the same
    IEEE operations in the same order."""
    if epsilon_pixels <= 0:
        return epsilon
    scaled = epsilon * np.sqrt(epsilon_pixels / max(pixels, 1.0))
    return min(max(scaled, low * epsilon), high * epsilon)


@njit(cache=True, inline="always")
def _threshold(pixels, search):  # type: ignore[no-untyped-def]
    return gain_threshold(pixels, search[4], search[5], search[6], search[7])


@njit(cache=True)
def _values(rows, cache):  # type: ignore[no-untyped-def]
    """Consistency (NMI, or NCC) and pixel count of the sums of the rows ``rows`` (K, S)."""
    hist_box, mom_box, params, use_ncc, xtable = cache[1], cache[2], cache[4], cache[5], cache[6]
    k = rows.shape[0]
    mi = np.empty(k)
    nmi = np.empty(k)
    pixels = np.empty(k)
    summed_information(hist_box[0], rows, params[2], mi, nmi, pixels, xtable)
    if not use_ncc:
        return nmi, pixels
    # core.similarity.ncc of the summed moments.
    moments = mom_box[0]
    value = np.empty(k)
    m = np.empty(6)
    for r in range(k):
        m[:] = moments[rows[r, 0]]
        for s in range(1, rows.shape[1]):
            m += moments[rows[r, s]]
        n = max(m[0], 1.0)
        cov = m[5] - m[1] * m[2] / n
        va = m[3] - m[1] * m[1] / n
        vb = m[4] - m[2] * m[2] / n
        den = np.sqrt(max(va, 0.0) * max(vb, 0.0))
        value[r] = cov / den if den > 1e-12 else 0.0
    return value, pixels


@njit(cache=True)
def _gains(tri, side, mesh, cache, state):  # type: ignore[no-untyped-def]
    """Gain (after minus before) of each move whose ``side`` triangles before and ``side``
    after are consecutive rows of ``tri``, and the pixel count of its triangles."""
    rows = _cache_rows(tri, mesh, cache, state)
    value, pixels = _values(rows.reshape(-1, side), cache)  # before, after, ...
    return value[1::2] - value[0::2], pixels[0::2]


@njit(cache=True)
def _quad_triangles(quads):  # type: ignore[no-untyped-def]
    """Each quad's ``(i, j, k), (i, j, l)`` (before the swap) and ``(k, l, i), (k, l, j)``
    (after), ``(4 E, 3)``, of quads ``(i, j, k, l)`` (E, 4)."""
    e = quads.shape[0]
    tri = np.empty((4 * e, 3), dtype=np.int64)
    for q in range(e):
        i, j, k, l = quads[q, 0], quads[q, 1], quads[q, 2], quads[q, 3]  # noqa: E741
        tri[4 * q, 0], tri[4 * q, 1], tri[4 * q, 2] = i, j, k
        tri[4 * q + 1, 0], tri[4 * q + 1, 1], tri[4 * q + 1, 2] = i, j, l
        tri[4 * q + 2, 0], tri[4 * q + 2, 1], tri[4 * q + 2, 2] = k, l, i
        tri[4 * q + 3, 0], tri[4 * q + 3, 1], tri[4 * q + 3, 2] = k, l, j
    return tri


@njit(cache=True)
def _score_quads(quads, mesh, cache, state):  # type: ignore[no-untyped-def]
    """Gain of swapping each quad ``(i, j, k, l)`` of ``quads`` (E, 4) and its pixel count
    (:meth:`core.optimize.QuadScorer.deltas`)."""
    return _gains(_quad_triangles(quads), 2, mesh, cache, state)


@njit(cache=True)
def _internal_edges(owners):  # type: ignore[no-untyped-def]
    """Codes of the internal edges, sorted."""
    codes = np.empty(len(owners), dtype=np.int64)
    count = 0
    for code, v in owners.items():
        if v % _PACK > 0:
            codes[count] = code
            count += 1
    return np.sort(codes[:count])


@njit(cache=True)
def pair_moves(mesh, retired, moved, moved_only):  # type: ignore[no-untyped-def]
    """Every valid pair of swaps of the look-ahead: rows ``(i, j, k, l, m, p, r, p', r')``
    int64, in the order of the first swap's edge, then of ``p`` in ``(i, j)`` and ``r`` in
    ``(k, l)``.

    Swapping ``e = (i, j)`` of quad ``(i, j; k, l)`` makes triangles ``(k, l, i)`` and
    ``(k, l, j)``; a second swap then turns one of the quad's sides ``b = (p, r)`` over the
    outer triangle ``(p, r, m)`` into ``(r', m)``, ``r'`` the other of ``k, l``. Both swaps meet
    the preconditions of :meth:`Mesh.swap_blocker` on the mesh they apply to and neither
    creates an edge of ``retired``; with ``moved_only``, the first swap's edge has an end
    flagged in ``moved`` (per vertex).
    """
    tris, owners, ref_fixed, mov_fixed, n = mesh[0], mesh[1], mesh[2], mesh[3], mesh[4]
    codes = _internal_edges(owners)
    out = np.empty((4 * len(codes), 9), dtype=np.int64)
    count = 0
    for code in codes:
        if moved_only and moved[code // n] == 0 and moved[code % n] == 0:
            continue
        ok, i, j, k, l = _eligible(mesh, retired, code)  # noqa: E741
        if not ok:
            continue
        for choice in range(4):
            p, p2 = (i, j) if choice < 2 else (j, i)
            r, r2 = (k, l) if choice % 2 == 0 else (l, k)
            t0, t1 = _unpack(owners[_edge(p, r, n)])
            if t1 < 0:
                continue
            a0 = tris[t0, 0] + tris[t0, 1] + tris[t0, 2] - p - r
            a1 = tris[t1, 0] + tris[t1, 1] + tris[t1, 2] - p - r
            # The outer triangle over the side (p, r) is the one of its two without p'.
            if a0 == p2 and a1 != p2:
                m = a1
            elif a1 == p2 and a0 != p2:
                m = a0
            else:
                continue
            if m == r2 or m == p2 or _edge(r2, m, n) in owners or _edge(r2, m, n) in retired:
                continue
            # The quad (p, r; r', m) of the second swap is strictly convex in both images, and
            # its new triangles turn the same way in both.
            new_p = _sign(_cross(ref_fixed, r2, m, p))
            new_r = _sign(_cross(ref_fixed, r2, m, r))
            if new_p != _sign(_cross(mov_fixed, r2, m, p)):
                continue
            if new_r != _sign(_cross(mov_fixed, r2, m, r)):
                continue
            good = new_p * new_r < 0
            for fixed in (ref_fixed, mov_fixed):
                good = good and _sign(_cross(fixed, p, r, r2)) * _sign(_cross(fixed, p, r, m)) < 0
            if not good:
                continue
            row = out[count]
            row[0], row[1], row[2], row[3], row[4] = i, j, k, l, m
            row[5], row[6], row[7], row[8] = p, r, p2, r2
            count += 1
    return out[:count]


@njit(cache=True)
def _now():  # type: ignore[no-untyped-def]
    with objmode(t="float64"):
        t = time.perf_counter()
    return t


@njit(cache=True)
def _record(code, added, delta, move, mesh, moved, state, out, t0):  # type: ignore[no-untyped-def]
    """Note an accepted swap (its quad noted first): its edges, gain, kind (0 alone, 1 in a
    pair) and time."""
    n = mesh[4]
    if state[STATE_MOVED]:
        moved[code // n] = moved[code % n] = moved[added // n] = moved[added % n] = 1
    row = out[0][state[STATE_TAKEN]]
    row[0], row[1], row[2], row[3], row[4] = code, added, move, delta, _now() - t0
    state[STATE_TAKEN] += 1


@njit(cache=True)
def _note_quad(i, j, k, l, mesh, cache, state, out):  # type: ignore[no-untyped-def]  # noqa: E741
    """Note the cache rows of a quad about to be swapped: the global histogram's change."""
    rows = _cache_rows(_quad_triangles(np.array([[i, j, k, l]], dtype=np.int64)), mesh, cache,
                       state)
    steps = out[0]
    taken = state[STATE_TAKEN]
    if taken >= steps.shape[0]:
        grown = np.zeros((2 * steps.shape[0] + 16, steps.shape[1]))
        grown[:taken] = steps[:taken]
        out[0] = grown
        steps = grown
    steps[taken, 5], steps[taken, 6], steps[taken, 7], steps[taken, 8] = (
        rows[0], rows[1], rows[2], rows[3])


@njit(cache=True)
def _rescore(edges, mesh, cache, search, state):  # type: ignore[no-untyped-def]
    """Score again the edges ``edges`` (in order, each once) whose quads a swap changed;
    those that may no longer be swapped leave the heap."""
    best, gain, heap, retired = search[0], search[1], search[2], search[3]
    ring = np.empty(len(edges), dtype=np.int64)
    quads = np.empty((len(edges), 4), dtype=np.int64)
    count = 0
    for x in range(len(edges)):
        b = edges[x]
        seen = False
        for y in range(x):
            seen = seen or edges[y] == b
        if seen:
            continue
        if best.pop(b, 0.0) > 0.0:
            state[STATE_POSITIVE] -= 1
        ok, i, j, k, l = _eligible(mesh, retired, b)  # noqa: E741
        if ok:
            ring[count] = b
            quads[count, 0], quads[count, 1], quads[count, 2], quads[count, 3] = i, j, k, l
            count += 1
    if count == 0:
        return
    gains, pixels = _score_quads(quads[:count], mesh, cache, state)
    for q in range(count):
        d = gains[q] - _threshold(pixels[q], search)
        best[ring[q]] = d
        if d > 0.0:
            state[STATE_POSITIVE] += 1
        gain[ring[q]] = gains[q]
        heapq.heappush(heap, (-d, ring[q]))
    state[STATE_EVALUATIONS] += count


@njit(cache=True, inline="always")
def _boundary(i, j, k, l, n):  # type: ignore[no-untyped-def]  # noqa: E741
    """The quad's four outer edges (:attr:`core.mesh.Quad.boundary`)."""
    return np.array([_edge(i, k, n), _edge(k, j, n), _edge(j, l, n), _edge(l, i, n)])


@njit(cache=True)
def _take_pairs(mesh, cache, search, state, moved, max_iterations, out,
                t0):  # type: ignore[no-untyped-def]
    """One pass of pair moves; True if any was taken. After the first pass over the whole
    mesh, only edges touching a quad changed since the previous pass are tried again."""
    n = mesh[4]
    retired = search[3]
    pairs = pair_moves(mesh, retired, moved, state[STATE_MOVED] != 0)
    moved[:] = 0
    state[STATE_MOVED] = 1
    count = pairs.shape[0]
    if count == 0:
        return False
    tri = np.empty((6 * count, 3), dtype=np.int64)
    for t in range(count):
        for s in range(6):
            for c in range(3):
                tri[6 * t + s, c] = pairs[t, PAIR_TRIANGLES[s, c]]
    pair_gain, pixels = _gains(tri, 3, mesh, cache, state)
    over = np.empty(count)
    for t in range(count):
        over[t] = pair_gain[t] - _threshold(pixels[t], search)
    state[STATE_EVALUATIONS] += count
    touched = np.zeros(n, dtype=np.bool_)
    taken = False
    for t in np.argsort(-over, kind="mergesort"):
        if over[t] <= 0.0 or state[STATE_TAKEN] + 2 > max_iterations:
            break
        i, j, k, l, m = pairs[t, 0], pairs[t, 1], pairs[t, 2], pairs[t, 3], pairs[t, 4]  # noqa: E741
        p, r, r2 = pairs[t, 5], pairs[t, 6], pairs[t, 8]
        if touched[i] or touched[j] or touched[k] or touched[l] or touched[m]:
            continue  # scored on a mesh that has changed around it since
        e, b = _edge(i, j, n), _edge(p, r, n)
        qi, qj, qk, ql, _, _ = _quad(mesh, e)
        added = _swap(mesh, e, state)
        bi, bj, bk, bl, _, _ = _quad(mesh, b)
        if not ((bk == r2 and bl == m) or (bk == m and bl == r2)) or not _eligible(
                mesh, retired, b)[0]:
            _swap(mesh, added, state)  # the pair's second swap is not there: undo
            continue
        _note_quad(qi, qj, qk, ql, mesh, cache, state, out)
        retired[e] = 1
        _record(e, added, pair_gain[t], 1, mesh, moved, state, out, t0)
        _note_quad(bi, bj, bk, bl, mesh, cache, state, out)
        added_b = _swap(mesh, b, state)
        retired[b] = 1
        _record(b, added_b, pair_gain[t], 1, mesh, moved, state, out, t0)
        touched[i] = touched[j] = touched[k] = touched[l] = touched[m] = True
        _rescore(np.concatenate((_boundary(qi, qj, qk, ql, n), _boundary(bi, bj, bk, bl, n))),
                 mesh, cache, search, state)
        taken = True
    return taken


@njit(cache=True)
def search_start(mesh, cache, search, state, global_hist):  # type: ignore[no-untyped-def]
    """The search's first pass: every swappable edge scored and the heap built; the joint
    histogram of the whole mesh summed into ``global_hist`` (int64, ``bins * bins``)."""
    tris, owners = mesh[0], mesh[1]
    best, gain, heap = search[0], search[1], search[2]
    current = _cache_rows(tris[np.flatnonzero(tris[:, 0] >= 0)], mesh, cache, state)
    codes = _internal_edges(owners)
    quads = np.empty((len(codes), 4), dtype=np.int64)
    candidates = np.empty(len(codes), dtype=np.int64)
    count = 0
    for code in codes:
        ok, i, j, k, l = _swappable(mesh, code)  # noqa: E741
        if ok:
            quads[count, 0], quads[count, 1], quads[count, 2], quads[count, 3] = i, j, k, l
            candidates[count] = code
            count += 1
    gains, pixels = _score_quads(quads[:count], mesh, cache, state)
    hist = cache[1][0]
    for r in current:
        for c in range(hist.shape[1]):
            global_hist[c] += hist[r, c]
    for q in range(count):
        d = gains[q] - _threshold(pixels[q], search)
        best[candidates[q]] = d
        gain[candidates[q]] = gains[q]
        heap.append((-d, candidates[q]))
        if d > 0.0:
            state[STATE_POSITIVE] += 1
    heapq.heapify(heap)
    state[STATE_EVALUATIONS] = count


@njit(cache=True)
def search_run(mesh, cache, search, state, moved, max_iterations, lookahead, report_every,
               out, t0):  # type: ignore[no-untyped-def]
    """Swap the best edge while a gain exceeds its threshold (:func:`core.optimize.greedy_search`),
    after :func:`search_start`.

    ``moved`` flags per vertex those of quads changed since the last pass of pairs; ``out`` is
    :func:`search_steps`; ``t0`` the search's start (:func:`time.perf_counter`). Returns True
    when it stopped to report progress (at most every ``report_every`` seconds, the first time
    at ``state[STATE_REPORT]`` microseconds; never when negative): call it again to go on.
    ``state[STATE_STOPPED]`` indexes :data:`SEARCH_STOPS`.
    """
    n = mesh[4]
    best, gain, heap, retired = search[0], search[1], search[2], search[3]
    while True:
        while len(heap) > 0 and best.get(heap[0][1], np.nan) != -heap[0][0]:
            heapq.heappop(heap)
        if len(heap) == 0 or -heap[0][0] <= 0.0:
            if lookahead and _take_pairs(mesh, cache, search, state, moved, max_iterations,
                                         out, t0):
                continue
            state[STATE_STOPPED] = 0
            return False
        if state[STATE_TAKEN] >= max_iterations:
            state[STATE_STOPPED] = 1
            return False
        e = heapq.heappop(heap)[1]
        del best[e]
        state[STATE_POSITIVE] -= 1  # it was the best, over its threshold
        ok, i, j, k, l = _eligible(mesh, retired, e)  # noqa: E741
        if not ok:
            continue  # a swap elsewhere created, or retired, the edge this one would add
        _note_quad(i, j, k, l, mesh, cache, state, out)
        added = _swap(mesh, e, state)
        retired[e] = 1
        _record(e, added, gain[e], 0, mesh, moved, state, out, t0)
        _rescore(_boundary(i, j, k, l, n), mesh, cache, search, state)
        elapsed = out[0][state[STATE_TAKEN] - 1, 4]  # seconds since t0, noted by _record
        if report_every >= 0.0 and elapsed * 1e6 >= state[STATE_REPORT]:
            state[STATE_REPORT] = int((elapsed + report_every) * 1e6)
            return True
