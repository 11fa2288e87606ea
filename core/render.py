"""Pictures of a registration: the meshes drawn on both images, checkerboard and difference of the
reference against the registered image, the per-triangle consistency and the convergence curve.

Pure functions from arrays to 8-bit BGR(A) arrays (or SVG text), drawn with OpenCV at a bounded
size: the longest side of a picture is at most ``max_side`` pixels (images are reduced, never
enlarged). Coordinates are pixels, x right, y down, (0, 0) the centre of the top-left pixel; a
point keeps that convention when reduced (:func:`scale_points`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from xml.sax.saxutils import escape

import cv2
import numpy as np

from pwlreg.core.imaging import to_gray
from pwlreg.core.raster import label_image
from pwlreg.core.warp import warp_image

MAX_SIDE = 1600
"""Default bound of a picture's longest side, in pixels."""

KEPT = (0, 215, 255)
"""BGR colour of the edges both meshes share (amber)."""
REMOVED = (40, 40, 230)
"""BGR colour of the initial mesh's edges the optimizer swapped away (red)."""
ADDED = (60, 200, 20)
"""BGR colour of the final mesh's edges the optimizer's swaps created (green)."""
VERTEX_REMOVED = (255, 0, 255)
"""BGR colour of the ring around a vertex of the initial mesh the final one no longer uses."""
VERTEX_ADDED = (255, 255, 0)
"""BGR colour of the ring around a vertex only the final mesh uses."""
VERTEX = (255, 255, 255)
"""BGR colour of a measured vertex (dot) and of an extrapolated one (ring)."""
OUTSIDE = (128, 128, 128)
"""BGR colour of the pixels outside the mesh in the difference image."""
DIFFERENCE_GAIN = 4
"""The difference image shows ``|reference - registered| * DIFFERENCE_GAIN`` (grey levels)."""


# --- sizes and conversions -------------------------------------------------------------------


def fit(size: tuple[int, int], max_side: int = MAX_SIDE) -> tuple[int, int]:
    """``(width, height)`` of a picture of an image of ``size = (width, height)`` whose longest
    side is at most ``max_side`` (the image's own size when it is small enough)."""
    width, height = int(size[0]), int(size[1])
    s = min(1.0, max_side / max(width, height))
    return max(1, round(width * s)), max(1, round(height * s))


def scale_points(points: np.ndarray, size: tuple[int, int], shown: tuple[int, int]
                 ) -> np.ndarray:
    """Positions in a picture ``shown = (width, height)`` of points of an image of ``size``
    (pixel centres map as :func:`cv2.resize` maps them)."""
    factor = np.array([shown[0] / size[0], shown[1] / size[1]])
    return (np.asarray(points, dtype=np.float64) + 0.5) * factor - 0.5


def to_display(image: np.ndarray, shown: tuple[int, int] | None = None) -> np.ndarray:
    """8-bit BGR copy of an OpenCV-layout image (grey, BGR or BGRA; 8 or 16 bit), reduced to
    ``shown = (width, height)`` (area averaging). 16-bit images are stretched to their own
    maximum, so that 10- or 12-bit data is not drawn black; alpha is dropped."""
    img = image if image.ndim == 3 else image[:, :, None]
    if img.shape[2] == 4:
        img = img[:, :, :3]
    if shown is not None and (img.shape[1], img.shape[0]) != tuple(shown):
        img = cv2.resize(img, tuple(shown), interpolation=cv2.INTER_AREA)
        img = img if img.ndim == 3 else img[:, :, None]
    if img.dtype != np.uint8:
        top = max(int(img.max()), 1)
        img = np.clip(np.round(img.astype(np.float32) * (255.0 / top)), 0, 255).astype(np.uint8)
    if img.shape[2] == 1:
        return cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    return np.ascontiguousarray(img)


LINE_WIDTH = 2
"""Width of the mesh's edges, pixels: with antialiasing, the narrowest at which the pixels along
an edge's centre line keep its full colour."""


def _fixed(points: np.ndarray) -> np.ndarray:
    # OpenCV draws with 4 fractional bits (shift=4): sub-pixel positions in integers.
    return np.round(np.asarray(points) * 16).astype(np.int32)


# --- meshes ----------------------------------------------------------------------------------


def edges(triangles: np.ndarray) -> set[tuple[int, int]]:
    """Undirected edges ``(i, j)``, ``i < j``, of a triangle list."""
    tris = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    pairs = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
    pairs.sort(axis=1)
    return set(map(tuple, np.unique(pairs, axis=0).tolist()))


def mesh_overlay(
    image: np.ndarray,
    vertices: np.ndarray,
    initial_triangles: np.ndarray,
    final_triangles: np.ndarray,
    *,
    extrapolated: np.ndarray | None = None,
    max_side: int = MAX_SIDE,
) -> np.ndarray:
    """The initial and the final mesh drawn on one image.

    Edges both meshes share are drawn in :data:`KEPT`, the initial mesh's edges that were
    swapped away in :data:`REMOVED`, the edges the swaps created in :data:`ADDED` (on top).
    Vertices are white dots (rings for extrapolated ones, e.g. the frame's border vertices);
    a vertex only the initial mesh uses gets a :data:`VERTEX_REMOVED` ring, one only the final
    mesh uses a :data:`VERTEX_ADDED` ring.

    Parameters
    ----------
    image : ndarray
        The image the vertices belong to (any layout :func:`to_display` takes).
    vertices : ndarray, shape (N, 2)
        Vertex positions in this image, pixels.
    initial_triangles, final_triangles : ndarray, shape (T, 3)
        The two meshes (vertex indices).
    extrapolated : ndarray of bool, shape (N,), optional
        Vertices whose position was extrapolated rather than measured.
    max_side : int
        Bound of the picture's longest side.

    Returns
    -------
    ndarray of uint8, shape (h, w, 3)
        BGR picture of size :func:`fit` of the image's.
    """
    size = (image.shape[1], image.shape[0])
    shown = fit(size, max_side)
    canvas = to_display(image, shown)
    # Border vertices on the frame's outer edge (-0.5, size - 0.5) are drawn on the outermost
    # pixels, where a line is seen whole.
    xy = scale_points(vertices, size, shown)
    inner = np.clip(xy, 0, np.array(shown) - 1)
    pts = _fixed(np.where(np.abs(xy - inner) <= 0.5, inner, xy))
    before, after = edges(initial_triangles), edges(final_triangles)
    width = LINE_WIDTH
    for group, colour in ((before & after, KEPT), (before - after, REMOVED),
                          (after - before, ADDED)):
        lines = [pts[[i, j]] for i, j in sorted(group)]
        if lines:
            cv2.polylines(canvas, lines, False, colour, width, cv2.LINE_AA, shift=4)
    used_before = np.unique(np.asarray(initial_triangles, dtype=np.int64))
    used_after = np.unique(np.asarray(final_triangles, dtype=np.int64))
    used = np.union1d(used_before, used_after)
    extra = np.zeros(len(pts), bool) if extrapolated is None else np.asarray(extrapolated, bool)
    radius = 3 * 16  # pixels, in OpenCV's fixed point
    for v in used:
        centre = tuple(int(c) for c in pts[v])
        if extra[v]:
            cv2.circle(canvas, centre, radius, VERTEX, 1, cv2.LINE_AA, shift=4)
        else:
            cv2.circle(canvas, centre, radius // 2, VERTEX, -1, cv2.LINE_AA, shift=4)
    for ring, colour in ((np.setdiff1d(used_before, used_after), VERTEX_REMOVED),
                         (np.setdiff1d(used_after, used_before), VERTEX_ADDED)):
        for v in ring:
            centre = tuple(int(c) for c in pts[v])
            cv2.circle(canvas, centre, radius * 2, colour, width, cv2.LINE_AA, shift=4)
    return canvas


# --- registered image, checkerboard, difference ----------------------------------------------


def registered_preview(
    moving: np.ndarray,
    reference_vertices: np.ndarray,
    moving_vertices: np.ndarray,
    triangles: np.ndarray,
    reference_size: tuple[int, int],
    shown: tuple[int, int],
) -> np.ndarray:
    """The moving image registered through the mesh, drawn at ``shown = (width, height)``.

    The moving image is reduced by the same factor first (so that the picture is not aliased)
    and resampled with :func:`core.warp.warp_image`, the warp of the full-size result.

    Returns
    -------
    ndarray of uint8, shape (h, w, 4)
        BGRA; alpha is 255 inside the mesh, 0 outside.
    """
    factor = min(shown[0] / reference_size[0], shown[1] / reference_size[1])
    moving_size = (moving.shape[1], moving.shape[0])
    moving_shown = fit(moving_size, max(1, math.ceil(max(moving_size) * factor)))
    small = to_display(moving, moving_shown)
    warped = warp_image(
        small,
        scale_points(reference_vertices, reference_size, shown),
        scale_points(moving_vertices, moving_size, moving_shown),
        triangles,
        (shown[1], shown[0]),
    )
    return warped


def checkerboard(reference: np.ndarray, registered: np.ndarray, *, tiles: int = 12
                 ) -> np.ndarray:
    """Alternating square tiles of the reference and of the registered image.

    Parameters
    ----------
    reference : ndarray of uint8, shape (h, w, 3)
        BGR reference picture.
    registered : ndarray of uint8, shape (h, w, 4)
        BGRA registered picture of the same size (black where its alpha is 0).
    tiles : int
        Tiles along the longest side; the top-left tile shows the reference.

    Returns
    -------
    ndarray of uint8, shape (h, w, 3)
    """
    h, w = reference.shape[:2]
    side = max(1, math.ceil(max(h, w) / tiles))
    ys, xs = np.ogrid[:h, :w]
    odd = ((ys // side) + (xs // side)) % 2 == 1
    shown = np.where(registered[:, :, 3:] > 0, registered[:, :, :3], 0).astype(np.uint8)
    return np.where(odd[:, :, None], shown, reference)


def difference(reference: np.ndarray, registered: np.ndarray) -> np.ndarray:
    """Absolute difference of the grey levels of the reference and the registered picture,
    times :data:`DIFFERENCE_GAIN`, in the inferno colour map (black = equal); pixels outside the
    mesh are :data:`OUTSIDE`.

    Parameters
    ----------
    reference : ndarray of uint8, shape (h, w, 3)
    registered : ndarray of uint8, shape (h, w, 4)

    Returns
    -------
    ndarray of uint8, shape (h, w, 3)
    """
    diff = cv2.absdiff(to_gray(reference), to_gray(registered[:, :, :3]))
    amplified = np.minimum(diff.astype(np.uint16) * DIFFERENCE_GAIN, 255).astype(np.uint8)
    coloured = cv2.applyColorMap(amplified, cv2.COLORMAP_INFERNO)
    coloured[registered[:, :, 3] == 0] = OUTSIDE
    return coloured


def side_by_side(panels: Sequence[np.ndarray], labels: Sequence[str], *, gap: int = 8
                 ) -> np.ndarray:
    """Pictures of equal height next to each other on white, each labelled in its top-left
    corner."""
    h = panels[0].shape[0]
    out = np.full((h, sum(p.shape[1] for p in panels) + gap * (len(panels) - 1), 3), 255,
                  np.uint8)
    x = 0
    for panel, label in zip(panels, labels, strict=True):
        out[:, x:x + panel.shape[1]] = panel
        _label(out, label, (x + 4, 4))
        x += panel.shape[1] + gap
    return out


def panel_size(size: tuple[int, int], panels: int, max_side: int = MAX_SIDE, gap: int = 8
               ) -> tuple[int, int]:
    """``(width, height)`` of each of ``panels`` pictures of an image of ``size`` set side by
    side (``gap`` pixels apart) so that the whole is at most ``max_side`` on its longest side."""
    width, height = size
    s = min(1.0, (max_side - gap * (panels - 1)) / (panels * width), max_side / height)
    return max(1, round(width * s)), max(1, round(height * s))


def _label(canvas: np.ndarray, text: str, at: tuple[int, int]) -> None:
    font, scale, thickness = cv2.FONT_HERSHEY_SIMPLEX, 0.5, 1
    (tw, th), base = cv2.getTextSize(text, font, scale, thickness)
    x, y = at
    cv2.rectangle(canvas, (x, y), (x + tw + 8, y + th + base + 6), (0, 0, 0), -1)
    cv2.putText(canvas, text, (x + 4, y + th + 3), font, scale, (255, 255, 255), thickness,
                cv2.LINE_AA)


# --- consistency -----------------------------------------------------------------------------


def score_colours(scores: np.ndarray) -> np.ndarray:
    """BGR colours of consistency scores: red at 0 and below, yellow at 0.5, green at 1 and
    above; NaN (no texture) is grey."""
    s = np.clip(np.nan_to_num(np.asarray(scores, dtype=np.float64), nan=0.0), 0.0, 1.0)
    red = np.array([40.0, 40.0, 220.0])
    yellow = np.array([40.0, 220.0, 240.0])
    green = np.array([60.0, 190.0, 30.0])
    low = red + (yellow - red) * np.minimum(s, 0.5)[:, None] * 2
    colours = np.where((s <= 0.5)[:, None], low,
                       yellow + (green - yellow) * (np.maximum(s, 0.5)[:, None] - 0.5) * 2)
    colours[~np.isfinite(np.asarray(scores, dtype=np.float64))] = OUTSIDE
    return np.round(colours).astype(np.uint8)


def consistency_map(
    reference: np.ndarray,
    vertices: np.ndarray,
    triangles: np.ndarray,
    scores: np.ndarray,
    *,
    max_side: int = MAX_SIDE,
    opacity: float = 0.55,
) -> np.ndarray:
    """Each triangle of the mesh filled with the colour of its consistency score
    (:func:`score_colours`) over the grey reference, the mesh's edges in black.

    Parameters
    ----------
    reference : ndarray
        The reference image.
    vertices : ndarray, shape (N, 2)
        Reference vertex positions, pixels.
    triangles : ndarray, shape (T, 3)
        The (final) mesh.
    scores : ndarray, shape (T,)
        Per triangle: the share of its MI lost one step away (1 = sharp peak, <= 0 = none,
        NaN = no texture), as :class:`core.quality.Quality` gives them.
    max_side : int
        Bound of the picture's longest side.
    opacity : float
        Weight of the colours over the image.

    Returns
    -------
    ndarray of uint8, shape (h, w, 3)
    """
    size = (reference.shape[1], reference.shape[0])
    shown = fit(size, max_side)
    grey = cv2.cvtColor(to_gray(to_display(reference, shown)), cv2.COLOR_GRAY2BGR)
    pts = scale_points(vertices, size, shown)
    tris = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    labels = label_image(pts[tris], (shown[1], shown[0]))
    painted = cv2.addWeighted(grey, 1 - opacity, score_colours(scores)[np.maximum(labels, 0)],
                              opacity, 0)
    out = np.where((labels >= 0)[:, :, None], painted, grey)
    fixed = _fixed(pts)
    cv2.polylines(out, [fixed[t] for t in tris], True, (0, 0, 0), 1, cv2.LINE_AA, shift=4)
    return out


# --- convergence -----------------------------------------------------------------------------


def nice_ticks(low: float, high: float, count: int = 5) -> list[float]:
    """Round tick values covering ``[low, high]`` (steps of 1, 2 or 5 times a power of ten)."""
    if not high > low:
        pad = max(abs(low) * 1e-3, 1e-6)
        low, high = low - pad, high + pad
    raw = (high - low) / max(count - 1, 1)
    power = 10 ** math.floor(math.log10(raw))
    step = next(m * power for m in (1, 2, 5, 10) if m * power >= raw)
    first = math.floor(low / step) * step
    ticks = []
    t = first
    while t < high + step * 0.999:
        ticks.append(round(t, 12))
        t += step
    return ticks


def _format(value: float, step: float) -> str:
    digits = max(0, -math.floor(math.log10(step))) if step > 0 else 0
    return f"{value:.{digits}f}"


class _Plot:
    """Layout of the convergence figure, shared by the PNG and the SVG drawing: two panels (MI
    above, NMI below) over the same x axis, the number of accepted moves."""

    def __init__(self, mi: Sequence[float], nmi: Sequence[float], width: int, height: int):
        self.width, self.height = width, height
        self.left, self.right, self.top, self.bottom = 78, 20, 36, 44
        self.gap = 34
        self.panel_h = (height - self.top - self.bottom - self.gap) / 2
        self.x_ticks = nice_ticks(0, max(len(mi) - 1, 1), 6)
        self.x_ticks = [t for t in self.x_ticks if t == int(t)] or [0.0]
        self.x_max = max(self.x_ticks[-1], 1.0)
        self.series = []
        for i, (values, name) in enumerate(((mi, "MI (bits)"), (nmi, "NMI"))):
            ticks = nice_ticks(min(values), max(values), 4)
            top = self.top + i * (self.panel_h + self.gap)
            self.series.append((list(values), name, ticks, top))

    def x(self, value: float) -> float:
        return self.left + (self.width - self.left - self.right) * value / self.x_max

    def y(self, value: float, ticks: list[float], top: float) -> float:
        lo, hi = ticks[0], ticks[-1]
        return top + self.panel_h * (1 - (value - lo) / (hi - lo))


def _plot_title(optimizer: str, cost: str, moves: int) -> str:
    return f"Global consistency after each accepted move ({optimizer}/{cost}, {moves} moves)"


def convergence_png(
    mi: Sequence[float], nmi: Sequence[float], *, optimizer: str = "", cost: str = "",
    width: int = 800, height: int = 520,
) -> np.ndarray:
    """The convergence curve as a BGR picture.

    Parameters
    ----------
    mi, nmi : sequence of float
        Global MI (bits) and NMI before the first move and after each accepted move.
    optimizer, cost : str
        Named in the title.
    width, height : int
        Picture size in pixels.

    Returns
    -------
    ndarray of uint8, shape (height, width, 3)
    """
    plot = _Plot(mi, nmi, width, height)
    img = np.full((height, width, 3), 255, np.uint8)
    font = cv2.FONT_HERSHEY_SIMPLEX
    grid, ink, line = (225, 225, 225), (40, 40, 40), (180, 100, 20)

    def text(s: str, at: tuple[float, float], anchor: str = "left", scale: float = 0.42) -> None:
        (tw, th), _ = cv2.getTextSize(s, font, scale, 1)
        x = at[0] - (tw if anchor == "right" else tw / 2 if anchor == "middle" else 0)
        cv2.putText(img, s, (round(x), round(at[1] + th / 2)), font, scale, ink, 1, cv2.LINE_AA)

    text(_plot_title(optimizer, cost, len(mi) - 1), (width / 2, 16), "middle", 0.5)
    x0, x1 = plot.x(0), plot.x(plot.x_max)
    for values, name, ticks, top in plot.series:
        step = ticks[1] - ticks[0] if len(ticks) > 1 else 1.0
        for t in ticks:
            y = round(plot.y(t, ticks, top))
            cv2.line(img, (round(x0), y), (round(x1), y), grid, 1)
            text(_format(t, step), (x0 - 6, y), "right")
        for t in plot.x_ticks:
            x = round(plot.x(t))
            cv2.line(img, (x, round(top)), (x, round(top + plot.panel_h)), grid, 1)
        cv2.rectangle(img, (round(x0), round(top)), (round(x1), round(top + plot.panel_h)), ink, 1)
        text(name, (x0 + 6, top + 10))
        pts = np.array([[plot.x(i), plot.y(v, ticks, top)] for i, v in enumerate(values)])
        fixed = _fixed(pts)
        if len(pts) > 1:
            cv2.polylines(img, [fixed], False, line, 2, cv2.LINE_AA, shift=4)
        for p in fixed[[0, -1]]:
            cv2.circle(img, tuple(int(c) for c in p), 3 * 16, line, -1, cv2.LINE_AA, shift=4)
    bottom = plot.series[-1][3] + plot.panel_h
    for t in plot.x_ticks:
        text(str(int(t)), (plot.x(t), bottom + 12), "middle")
    text("accepted moves", (width / 2, height - 12), "middle")
    return img


def convergence_svg(
    mi: Sequence[float], nmi: Sequence[float], *, optimizer: str = "", cost: str = "",
    width: int = 800, height: int = 520,
) -> str:
    """The convergence curve as an SVG document (same layout as :func:`convergence_png`)."""
    plot = _Plot(mi, nmi, width, height)
    out = [
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" '
        f'viewBox="0 0 {width} {height}" font-family="sans-serif" font-size="12">',
        f'<rect width="{width}" height="{height}" fill="#fff"/>',
        f'<text x="{width / 2}" y="20" text-anchor="middle" font-size="14">'
        f"{escape(_plot_title(optimizer, cost, len(mi) - 1))}</text>",
    ]
    x0, x1 = plot.x(0), plot.x(plot.x_max)
    for values, name, ticks, top in plot.series:
        step = ticks[1] - ticks[0] if len(ticks) > 1 else 1.0
        bottom = top + plot.panel_h
        for t in ticks:
            y = plot.y(t, ticks, top)
            out.append(f'<line x1="{x0:.1f}" y1="{y:.1f}" x2="{x1:.1f}" y2="{y:.1f}" '
                       'stroke="#e1e1e1"/>')
            out.append(f'<text x="{x0 - 6:.1f}" y="{y + 4:.1f}" text-anchor="end">'
                       f"{_format(t, step)}</text>")
        for t in plot.x_ticks:
            x = plot.x(t)
            out.append(f'<line x1="{x:.1f}" y1="{top:.1f}" x2="{x:.1f}" y2="{bottom:.1f}" '
                       'stroke="#e1e1e1"/>')
        out.append(f'<rect x="{x0:.1f}" y="{top:.1f}" width="{x1 - x0:.1f}" '
                   f'height="{plot.panel_h:.1f}" fill="none" stroke="#282828"/>')
        out.append(f'<text x="{x0 + 6:.1f}" y="{top + 15:.1f}">{escape(name)}</text>')
        pts = [(plot.x(i), plot.y(v, ticks, top)) for i, v in enumerate(values)]
        path = " ".join(f"{x:.2f},{y:.2f}" for x, y in pts)
        out.append(f'<polyline class="curve" points="{path}" fill="none" stroke="#1464b4" '
                   'stroke-width="2"/>')
        for x, y in (pts[0], pts[-1]):
            out.append(f'<circle cx="{x:.2f}" cy="{y:.2f}" r="3" fill="#1464b4"/>')
    bottom = plot.series[-1][3] + plot.panel_h
    for t in plot.x_ticks:
        out.append(f'<text x="{plot.x(t):.1f}" y="{bottom + 16:.1f}" text-anchor="middle">'
                   f"{int(t)}</text>")
    out.append(f'<text x="{width / 2}" y="{height - 8}" text-anchor="middle">accepted moves'
               "</text>")
    out.append("</svg>")
    return "\n".join(out) + "\n"
