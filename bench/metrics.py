"""Quality measures of a piecewise-linear registration against a known truth.

The measures, all pure functions of numpy arrays:

* **Endpoint error** (pixels): where the mesh sends each reference pixel, against where the
  pixel truly goes in the moving image (:func:`endpoint_error`, :func:`endpoint_error_map`).
* **Mesh correctness** (the paper's, section 5): the share of internal edges (edges shared by two
  triangles) that are *3-D compatible*, i.e. lie on one scene plane
  (:func:`mesh_correctness`, :func:`edge_compatibility`).
* **Global mutual information** (bits) of the reference and registered images inside a mask
  (:func:`global_mi`), the paper's expression (8), for reporting.
* **Epipolar line error** (:func:`epipolar_line_error`): how far each pixel's true match lies
  from its epipolar line under an estimated fundamental matrix, which the insertion searches
  along; and its converse against a true fundamental matrix (:func:`epipolar_map_error`): the
  Sampson distance of the registration's dense map, the score of a camera-only truth.
* **Disparity correctness** (:func:`disparity_correctness`): a proxy of mesh correctness for
  rectified stereo pairs with a dense disparity but no plane labels (Middlebury): an edge lies on
  one plane only if the disparity is linear along it.

Conventions: pixel coordinates have x to the right, y down, (0, 0) at the centre of the top-left
pixel; a pixel ``(x, y)`` is the array element ``[y, x]``. Vertices are ``(N, 2)`` arrays of
``(x, y)``; triangles are ``(T, 3)`` vertex indices (any orientation). The piecewise map is
evaluated with :func:`core.warp.piecewise_map`, so a pixel belongs to a triangle by the fill rule
of :mod:`core.raster`, exactly as in registration.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from pwlreg.core.epipolar import epipolar_lines, sampson_distance
from pwlreg.core.scaled import up
from pwlreg.core.similarity import mutual_information
from pwlreg.core.warp import piecewise_map

__all__ = [
    "TRIANGLE_CLASSES",
    "EdgeCompatibility",
    "disparity_correctness",
    "disparity_steps",
    "disparity_edge_compatibility",
    "edge_compatibility",
    "endpoint_error",
    "endpoint_error_map",
    "epipolar_line_error",
    "error_by_triangle",
    "error_summary",
    "global_mi",
    "mesh_correctness",
    "mesh_edges",
]


# --------------------------------------------------------------------------------------------
# Endpoint error
# --------------------------------------------------------------------------------------------


def endpoint_error_map(
    reference_vertices: np.ndarray,
    moving_vertices: np.ndarray,
    triangles: np.ndarray,
    truth_x: np.ndarray,
    truth_y: np.ndarray,
    valid: np.ndarray | None = None,
) -> np.ndarray:
    """Per-pixel endpoint error of a piecewise-linear map.

    Parameters
    ----------
    reference_vertices, moving_vertices : ndarray, shape (N, 2)
        Mesh vertices in the reference and moving images (pixels).
    triangles : ndarray of int, shape (T, 3)
        Vertex indices of the triangles (shared by both meshes).
    truth_x, truth_y : ndarray of float, shape (H, W)
        True position in the moving image of each reference pixel (pixels); NaN where unknown.
    valid : ndarray of bool, shape (H, W), optional
        Pixels to score (e.g. covisible ones). Default: every pixel with a finite truth.

    Returns
    -------
    ndarray of float64, shape (H, W)
        Euclidean distance (pixels) between the mapped position and the true one; NaN outside
        the mesh, where the truth is unknown or where ``valid`` is False.
    """
    truth_x = np.asarray(truth_x, dtype=np.float64)
    truth_y = np.asarray(truth_y, dtype=np.float64)
    if truth_x.shape != truth_y.shape or truth_x.ndim != 2:
        raise ValueError("truth_x and truth_y must be (H, W) arrays of the same shape")
    map_x, map_y, label = piecewise_map(
        np.asarray(reference_vertices, dtype=np.float64),
        np.asarray(moving_vertices, dtype=np.float64),
        np.asarray(triangles, dtype=np.int64).reshape(-1, 3),
        truth_x.shape,
    )
    err = np.hypot(map_x - truth_x, map_y - truth_y)
    keep = (label >= 0) & np.isfinite(err)
    if valid is not None:
        keep &= np.asarray(valid, dtype=bool)
    err[~keep] = np.nan
    return err


def truth_at(
    truth_x: np.ndarray, truth_y: np.ndarray, points: np.ndarray, *, reach: int = 2
) -> np.ndarray:
    """True moving positions ``(N, 2)`` of reference ``points``: bilinear in the truth maps,
    else (a point on a silhouette, whose neighbouring pixel centres see the background) the
    value of the nearest pixel within ``reach`` pixels that sees the scene; NaN if none does."""
    p = np.asarray(points, np.float32).reshape(-1, 2)
    out = np.column_stack([
        cv2.remap(np.asarray(m, np.float32), p[:, 0], p[:, 1], cv2.INTER_LINEAR,
                  borderMode=cv2.BORDER_REPLICATE).ravel()
        for m in (truth_x, truth_y)
    ]).astype(np.float64)
    h, w = truth_x.shape
    for i in np.flatnonzero(~np.all(np.isfinite(out), axis=1)):
        x, y = p[i]
        best = np.inf
        for iy in range(int(np.floor(y)) - reach, int(np.ceil(y)) + reach + 1):
            for ix in range(int(np.floor(x)) - reach, int(np.ceil(x)) + reach + 1):
                if 0 <= ix < w and 0 <= iy < h and np.isfinite(truth_x[iy, ix]):
                    d = (ix - x) ** 2 + (iy - y) ** 2
                    if d < best:
                        best = d
                        out[i] = truth_x[iy, ix], truth_y[iy, ix]
    return out


def error_summary(errors: np.ndarray) -> dict[str, float]:
    """Mean, median, 90th percentile, maximum and RMS of the finite entries of ``errors``.

    Returns a dict with keys ``mean``, ``median``, ``p90``, ``max``, ``rms`` (same unit as the
    input) and ``n`` (number of finite entries); statistics are NaN when ``n == 0``.
    """
    e = np.asarray(errors, dtype=np.float64)
    e = e[np.isfinite(e)]
    if e.size == 0:
        nan = float("nan")
        return {"mean": nan, "median": nan, "p90": nan, "max": nan, "rms": nan, "n": 0}
    return {
        "mean": float(e.mean()),
        "median": float(np.median(e)),
        "p90": float(np.percentile(e, 90)),
        "max": float(e.max()),
        "rms": float(np.sqrt(np.mean(e * e))),
        "n": int(e.size),
    }


def endpoint_error(
    reference_vertices: np.ndarray,
    moving_vertices: np.ndarray,
    triangles: np.ndarray,
    truth_x: np.ndarray,
    truth_y: np.ndarray,
    valid: np.ndarray | None = None,
) -> dict[str, float]:
    """Endpoint error statistics (pixels) of a piecewise-linear registration.

    The map of each reference pixel inside the mesh (the affine map of its triangle, see
    :func:`core.warp.piecewise_map`) is compared with its true position in the moving image,
    over the pixels that are inside the mesh and ``valid``.

    Parameters
    ----------
    reference_vertices, moving_vertices, triangles, truth_x, truth_y, valid
        As in :func:`endpoint_error_map`. Pass ``scene.covisible`` (synthetic scenes) or the
        pair's ``valid`` mask (Middlebury) as ``valid``.

    Returns
    -------
    dict
        ``mean``, ``median``, ``p90``, ``max``, ``rms`` in pixels; ``n`` the number of scored
        pixels; ``coverage`` the share of valid pixels (finite truth and ``valid``) that lie
        inside the mesh and were scored.
    """
    err = endpoint_error_map(
        reference_vertices, moving_vertices, triangles, truth_x, truth_y, valid
    )
    stats: dict[str, float] = error_summary(err)
    scorable = np.isfinite(np.asarray(truth_x)) & np.isfinite(np.asarray(truth_y))
    if valid is not None:
        scorable &= np.asarray(valid, dtype=bool)
    total = int(scorable.sum())
    stats["coverage"] = stats["n"] / total if total else float("nan")
    return stats


def epipolar_line_error(
    fundamental: np.ndarray,
    truth_x: np.ndarray,
    truth_y: np.ndarray,
    valid: np.ndarray | None = None,
    *,
    step: int = 4,
) -> np.ndarray:
    """Distance (pixels) of each reference pixel's true match to its epipolar line.

    Parameters
    ----------
    fundamental : ndarray, shape (3, 3)
        ``x_mov^T F x_ref = 0`` in pixels (:attr:`core.epipolar.EpipolarModel.matrix`).
    truth_x, truth_y, valid
        As in :func:`endpoint_error_map`.
    step : int
        Every ``step``-th pixel in x and y is scored.

    Returns
    -------
    ndarray of float64, shape (K,)
        One distance per scored pixel with a finite truth (and ``valid``).
    """
    tx = np.asarray(truth_x, dtype=np.float64)[::step, ::step]
    ty = np.asarray(truth_y, dtype=np.float64)[::step, ::step]
    keep = np.isfinite(tx) & np.isfinite(ty)
    if valid is not None:
        keep &= np.asarray(valid, dtype=bool)[::step, ::step]
    ys, xs = np.nonzero(keep)
    lines = epipolar_lines(np.asarray(fundamental, dtype=np.float64),
                           np.column_stack([xs * step, ys * step]).astype(np.float64))
    return np.abs(lines[:, 0] * tx[keep] + lines[:, 1] * ty[keep] + lines[:, 2])


def epipolar_map_error(
    F: np.ndarray,
    reference_vertices: np.ndarray,
    moving_vertices: np.ndarray,
    triangles: np.ndarray,
    shape: tuple[int, int],
    *,
    scale: float = 1.0,
    step: int = 8,
) -> tuple[np.ndarray, float]:
    """Sampson distance to the true fundamental matrix ``F`` of a registration's dense map.

    The map of a mesh registered on images reduced by ``scale`` with an area average
    (:func:`cv2.resize`, ``INTER_AREA``; its reference grid of ``shape``) is read at every
    ``step``-th pixel it covers; both positions are taken back to the full-resolution pixels
    ``F`` is for. A camera-only truth measures the error across the
    epipolar lines, not along them: a lower bound of the endpoint error.

    Returns
    -------
    distances : ndarray
        Per grid pixel covered, the Sampson distance in full-resolution pixels.
    coverage : float
        Share of the grid the mesh covers.
    """
    map_x, map_y, label = piecewise_map(reference_vertices, moving_vertices, triangles, shape)
    ys, xs = np.mgrid[0:shape[0]:step, 0:shape[1]:step]
    covered = label[ys, xs] >= 0
    ref = up(np.column_stack([xs[covered], ys[covered]]), 1.0 / scale)
    mov = up(np.column_stack([map_x[ys, xs][covered], map_y[ys, xs][covered]]), 1.0 / scale)
    return sampson_distance(F, ref, mov), float(covered.mean())


TRIANGLE_CLASSES = ("extrapolated", "step", "vertex off", "clean")
"""The classes of :func:`error_by_triangle`, in the order a triangle is given its class."""


def disparity_steps(disparity: np.ndarray, *, jump: float = 1.0) -> np.ndarray:
    """Pixels where a disparity map jumps by more than ``jump`` pixels to its right or lower
    neighbour (a depth step); NaN (unknown) never makes a step. Boolean ``(H, W)``."""
    d = np.asarray(disparity, dtype=np.float64)
    steps = np.zeros(d.shape, bool)
    with np.errstate(invalid="ignore"):
        steps[:, :-1] |= np.abs(np.diff(d, axis=1)) > jump
        steps[:-1, :] |= np.abs(np.diff(d, axis=0)) > jump
    return steps


def error_by_triangle(
    reference_vertices: np.ndarray,
    moving_vertices: np.ndarray,
    triangles: np.ndarray,
    truth_x: np.ndarray,
    truth_y: np.ndarray,
    valid: np.ndarray,
    *,
    steps: np.ndarray,
    extrapolated: np.ndarray,
    others: dict[str, np.ndarray] | None = None,
    vertex_tolerance: float = 1.0,
) -> dict[str, dict[str, float]]:
    """Where the endpoint error of a mesh lives: per class of triangle, its pixels and error.

    Each triangle takes the first class of :data:`TRIANGLE_CLASSES` that fits it:
    ``extrapolated`` (a vertex whose moving position was extrapolated, not measured), ``step``
    (it holds a pixel of ``steps``: a planar map cannot follow a depth step inside it),
    ``vertex off`` (a vertex more than ``vertex_tolerance`` pixels from the truth at its nearest
    pixel) and ``clean`` (none of these: what is left is the planar approximation and the
    vertices' small errors).

    Parameters
    ----------
    reference_vertices, moving_vertices, triangles, truth_x, truth_y, valid
        As in :func:`endpoint_error_map`; ``valid`` is required.
    steps : ndarray of bool, shape (H, W)
        Depth steps (e.g. :func:`disparity_steps`).
    extrapolated : ndarray of bool, shape (N,)
        Per vertex, whether its moving position was extrapolated.
    others : dict of str to ndarray, optional
        Per-pixel endpoint error maps of other methods (e.g. a dense optical flow), averaged
        over the same pixels.
    vertex_tolerance : float
        Pixels.

    Returns
    -------
    dict
        Class -> ``share`` (of the scored pixels), ``mean`` (mesh EPE over its pixels) and
        ``contribution`` (its part of the overall mean: ``share * mean``); for each of
        ``others``, ``<name> mean`` and ``<name> contribution`` over the same pixels.
    """
    ref = np.asarray(reference_vertices, dtype=np.float64)
    mov = np.asarray(moving_vertices, dtype=np.float64)
    tris = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    truth_x = np.asarray(truth_x, dtype=np.float64)
    truth_y = np.asarray(truth_y, dtype=np.float64)
    map_x, map_y, label = piecewise_map(ref, mov, tris, truth_x.shape)
    err = np.hypot(map_x - truth_x, map_y - truth_y)
    scored = (label >= 0) & np.isfinite(err) & np.asarray(valid, dtype=bool)
    h, w = truth_x.shape
    col = np.clip(np.rint(ref[:, 0]).astype(np.int64), 0, w - 1)
    row = np.clip(np.rint(ref[:, 1]).astype(np.int64), 0, h - 1)
    off = np.hypot(truth_x[row, col] - mov[:, 0], truth_y[row, col] - mov[:, 1])
    off = np.isfinite(off) & (off > vertex_tolerance)
    holds_step = np.bincount(label[(label >= 0) & np.asarray(steps, bool)],
                             minlength=len(tris)) > 0
    # The first class that fits: the last column (clean) always does.
    fits = np.column_stack([np.asarray(extrapolated, bool)[tris].any(axis=1), holds_step,
                            off[tris].any(axis=1), np.ones(len(tris), bool)])
    pixel_kind = np.argmax(fits, axis=1)[label[scored]]
    total = int(scored.sum())
    values = {("" if name == "mesh" else f"{name} "): np.asarray(e, dtype=np.float64)[scored]
              for name, e in {"mesh": err, **(others or {})}.items()}
    out: dict[str, dict[str, float]] = {}
    for k, name in enumerate(TRIANGLE_CLASSES):
        mask = pixel_kind == k
        n = int(mask.sum())
        cell = {"share": n / total if total else float("nan")}
        for prefix, v in values.items():
            cell[f"{prefix}mean"] = float(v[mask].mean()) if n else float("nan")
            cell[f"{prefix}contribution"] = float(v[mask].sum()) / total if total else float("nan")
        out[name] = cell
    return out


# --------------------------------------------------------------------------------------------
# Mesh correctness
# --------------------------------------------------------------------------------------------


def mesh_edges(triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unique edges of a triangle mesh and how many triangles share each.

    Parameters
    ----------
    triangles : ndarray of int, shape (T, 3)

    Returns
    -------
    edges : ndarray of int64, shape (E, 2)
        Vertex pairs ``(i, j)`` with ``i < j``, sorted lexicographically.
    count : ndarray of int64, shape (E,)
        Number of triangles having the edge: 2 for an internal edge, 1 for a boundary edge
        (more than 2 means the input is not a manifold mesh).
    """
    tris = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    pairs = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
    pairs.sort(axis=1)
    if len(pairs) == 0:
        return np.zeros((0, 2), dtype=np.int64), np.zeros(0, dtype=np.int64)
    edges, count = np.unique(pairs, axis=0, return_counts=True)
    return edges, count.astype(np.int64)


@dataclass(frozen=True, eq=False)
class EdgeCompatibility:
    """Per-edge result of :func:`edge_compatibility`.

    Attributes
    ----------
    edges : ndarray of int64, shape (E, 2)
        The edges tested (vertex indices).
    compatible : ndarray of bool, shape (E,)
        The edge lies on one scene plane (3-D compatible).
    plane : ndarray of int64, shape (E,)
        The plane covering most of the edge's samples (among the planes containing both
        vertices, when vertex planes are given); -1 if none.
    agreement : ndarray of float64, shape (E,)
        Share of the edge's samples covered by that plane, in [0, 1].
    samples : ndarray of int64, shape (E,)
        Number of samples taken along the edge.
    """

    edges: np.ndarray
    compatible: np.ndarray
    plane: np.ndarray
    agreement: np.ndarray
    samples: np.ndarray


def _disk(radius: float) -> np.ndarray:
    r = int(np.floor(radius))
    yy, xx = np.mgrid[-r : r + 1, -r : r + 1]
    return (xx * xx + yy * yy <= radius * radius + 1e-9).astype(np.uint8)


def edge_compatibility(
    reference_vertices: np.ndarray,
    edges: np.ndarray,
    plane_map: np.ndarray,
    vertex_planes: np.ndarray | None = None,
    margin: float = 2.0,
    radius: float = 1.5,
    step: float = 0.5,
    agreement: float = 0.98,
) -> EdgeCompatibility:
    """Decide for each edge whether it lies on one scene plane (is 3-D compatible).

    The segment between the edge's reference vertices is sampled every ``step`` pixels,
    leaving out ``margin`` pixels at each end (mesh vertices sit on creases and corners, and
    carry localisation noise; the margin shrinks to a quarter of the length for short edges, so
    every edge keeps at least its midpoint). A plane *covers* a sample when a pixel of that plane
    lies within ``radius`` pixels of it (nearest-pixel lookup after dilating each plane's mask
    by a disk of that radius), which lets an edge running along a crease or an occluding contour
    belong to the plane on either side. The edge is compatible when one plane covers at least
    ``agreement`` of its samples; background (plane id < 0) and samples outside the image are
    covered by no plane.

    The image alone cannot tell where a vertex lies in depth: a vertex on an occluding contour
    (a box's top corner seen against the ground) has the background plane next to it, and an
    edge from it across the background would pass the sample test although its 3-D segment
    runs through the air. ``vertex_planes`` closes that gap: when given, the covering plane
    must also contain both end vertices in 3-D (for synthetic scenes, from
    :meth:`bench.scenes.Scene.vertex_planes`).

    Parameters
    ----------
    reference_vertices : ndarray, shape (N, 2)
        Vertex positions in the reference image (pixels).
    edges : ndarray of int, shape (E, 2)
        Vertex index pairs.
    plane_map : ndarray of int, shape (H, W)
        Plane id of the surface seen at each reference pixel; < 0 for none (background,
        unknown). For a synthetic scene, ``scene.face``.
    vertex_planes : ndarray of bool, shape (N, P), optional
        ``vertex_planes[i, p]``: vertex ``i`` lies on plane ``p`` in 3-D (P greater than every
        plane id of ``plane_map``). Default: no constraint (image test only).
    margin : float
        Pixels left out at each end of the segment.
    radius : float
        Tolerance (pixels) of the plane lookup.
    step : float
        Sampling step along the segment (pixels).
    agreement : float
        Minimum share of samples covered by one plane, in (0, 1].

    Returns
    -------
    EdgeCompatibility
    """
    if not 0 < agreement <= 1:
        raise ValueError("agreement must be in (0, 1]")
    if step <= 0 or margin < 0 or radius < 0:
        raise ValueError("step must be > 0, margin and radius >= 0")
    verts = np.asarray(reference_vertices, dtype=np.float64).reshape(-1, 2)
    edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    planes = np.asarray(plane_map)
    height, width = planes.shape
    n_edges = len(edges)
    if n_edges == 0:
        z = np.zeros(0)
        return EdgeCompatibility(edges, z.astype(bool), z.astype(np.int64), z, z.astype(np.int64))

    p, q = verts[edges[:, 0]], verts[edges[:, 1]]
    length = np.hypot(*(q - p).T)
    m = np.minimum(margin, 0.25 * length)
    span = length - 2 * m
    counts = np.maximum(np.ceil(span / step).astype(np.int64) + 1, 1)
    edge_of = np.repeat(np.arange(n_edges), counts)
    start = np.cumsum(counts) - counts
    k = np.arange(counts.sum()) - np.repeat(start, counts)
    denom = np.maximum(counts - 1, 1)
    s = m[edge_of] + span[edge_of] * np.where(counts[edge_of] > 1, k / denom[edge_of], 0.5)
    with np.errstate(invalid="ignore", divide="ignore"):
        t = np.where(length[edge_of] > 0, s / length[edge_of], 0.5)
    xy = p[edge_of] + t[:, None] * (q - p)[edge_of]
    col = np.rint(xy[:, 0]).astype(np.int64)
    row = np.rint(xy[:, 1]).astype(np.int64)
    inside = (col >= 0) & (col < width) & (row >= 0) & (row < height)
    col, row = np.clip(col, 0, width - 1), np.clip(row, 0, height - 1)

    ids = np.unique(planes[planes >= 0])
    kernel = _disk(radius)
    covered = np.zeros((len(edge_of), max(len(ids), 1)), dtype=bool)
    for c, pid in enumerate(ids):
        mask = (planes == pid).astype(np.uint8)
        if radius > 0:
            mask = cv2.dilate(mask, kernel)
        covered[:, c] = mask[row, col].astype(bool) & inside
    per_edge = np.add.reduceat(covered.astype(np.int64), start, axis=0)  # (E, P)
    if vertex_planes is not None and len(ids):
        vp = np.asarray(vertex_planes, dtype=bool)
        if vp.ndim != 2 or vp.shape[0] != len(verts) or vp.shape[1] <= ids.max():
            raise ValueError("vertex_planes must be (N vertices, P > max plane id) booleans")
        allowed = vp[edges[:, 0]][:, ids] & vp[edges[:, 1]][:, ids]
        per_edge = np.where(allowed, per_edge, 0)
    best = per_edge.argmax(axis=1)
    best_count = per_edge[np.arange(n_edges), best]
    share = best_count / counts
    plane = np.where(best_count > 0, ids[best] if len(ids) else -1, -1).astype(np.int64)
    compatible = share >= agreement - 1e-12
    return EdgeCompatibility(
        edges=edges, compatible=compatible, plane=plane, agreement=share, samples=counts
    )


def mesh_correctness(
    reference_vertices: np.ndarray,
    triangles: np.ndarray,
    plane_map: np.ndarray,
    vertex_planes: np.ndarray | None = None,
    margin: float = 2.0,
    radius: float = 1.5,
    step: float = 0.5,
    agreement: float = 0.98,
) -> dict[str, float]:
    """The paper's mesh correctness: share of internal edges that are 3-D compatible.

    An internal edge is shared by two triangles; a boundary edge by one. Compatibility is
    decided by :func:`edge_compatibility` (an edge is compatible when it lies on one scene
    plane), whose tolerance parameters are passed through. Boundary edges are counted
    separately, as the paper leaves them out.

    Parameters
    ----------
    reference_vertices : ndarray, shape (N, 2)
        Vertices in the reference image (pixels).
    triangles : ndarray of int, shape (T, 3)
    plane_map : ndarray of int, shape (H, W)
        Plane id at each reference pixel, < 0 for none (``scene.face``).
    vertex_planes : ndarray of bool, shape (N, P), optional
        Planes each vertex lies on in 3-D (``scene.vertex_planes(reference_vertices)``).
        Strongly recommended for scenes with occlusions: without it an edge leaving an
        occluding-contour vertex across the background counts as compatible.
    margin, radius, step, agreement
        See :func:`edge_compatibility`.

    Returns
    -------
    dict
        ``correctness`` (compatible internal / internal, NaN without internal edges),
        ``internal_edges``, ``compatible_internal``, ``incompatible_internal``,
        ``boundary_edges``, ``compatible_boundary``, ``boundary_correctness``.
    """
    edges, count = mesh_edges(triangles)
    result = edge_compatibility(
        reference_vertices, edges, plane_map, vertex_planes=vertex_planes, margin=margin,
        radius=radius, step=step, agreement=agreement,
    )
    internal = count == 2
    boundary = count == 1
    n_int = int(internal.sum())
    n_bnd = int(boundary.sum())
    ok_int = int((result.compatible & internal).sum())
    ok_bnd = int((result.compatible & boundary).sum())
    return {
        "correctness": ok_int / n_int if n_int else float("nan"),
        "internal_edges": n_int,
        "compatible_internal": ok_int,
        "incompatible_internal": n_int - ok_int,
        "boundary_edges": n_bnd,
        "compatible_boundary": ok_bnd,
        "boundary_correctness": ok_bnd / n_bnd if n_bnd else float("nan"),
    }


def _edge_samples(
    verts: np.ndarray, edges: np.ndarray, margin: float, step: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Points along each edge as in :func:`edge_compatibility`.

    Returns ``(xy, t, edge_of, counts)``: sample positions (pixels), their parameter in [0, 1]
    along the edge, the edge of each sample and the number of samples per edge.
    """
    p, q = verts[edges[:, 0]], verts[edges[:, 1]]
    length = np.hypot(*(q - p).T)
    m = np.minimum(margin, 0.25 * length)
    span = length - 2 * m
    counts = np.maximum(np.ceil(span / step).astype(np.int64) + 1, 1)
    edge_of = np.repeat(np.arange(len(edges)), counts)
    start = np.cumsum(counts) - counts
    k = np.arange(counts.sum()) - np.repeat(start, counts)
    denom = np.maximum(counts - 1, 1)
    s = m[edge_of] + span[edge_of] * np.where(counts[edge_of] > 1, k / denom[edge_of], 0.5)
    with np.errstate(invalid="ignore", divide="ignore"):
        t = np.where(length[edge_of] > 0, s / length[edge_of], 0.5)
    xy = p[edge_of] + t[:, None] * (q - p)[edge_of]
    return xy, t, edge_of, counts


def disparity_edge_compatibility(
    reference_vertices: np.ndarray,
    vertex_disparity: np.ndarray,
    edges: np.ndarray,
    disparity: np.ndarray,
    tolerance: float = 1.0,
    margin: float = 2.0,
    step: float = 0.5,
    agreement: float = 0.98,
    min_known: float = 0.5,
) -> tuple[np.ndarray, np.ndarray]:
    """Decide from a dense disparity whether each edge lies on one scene plane.

    In a rectified stereo pair the disparity of a scene plane is an affine function of the
    reference pixel, hence linear along any segment on it. An edge is compatible when, at
    ``agreement`` of its samples with a known disparity (nearest pixel), the true disparity is
    within ``tolerance`` pixels of the linear interpolation of its two vertices' disparities.
    This is a necessary condition of 3-D compatibility; curved surfaces pass it when the edge is
    short or flat enough (the tolerance), and an edge along the intersection of two planes
    passes it (it lies on both).

    Parameters
    ----------
    reference_vertices : ndarray, shape (N, 2)
        Vertices in the reference image (pixels).
    vertex_disparity : ndarray, shape (N,)
        Disparity (pixels) of each vertex as the mesh has it: ``x_reference - x_moving``.
    edges : ndarray of int, shape (E, 2)
    disparity : ndarray, shape (H, W)
        True reference disparity in pixels, NaN where unknown.
    tolerance : float
        Largest deviation from linearity (pixels).
    margin, step : float
        Sampling, as in :func:`edge_compatibility` (pixels).
    agreement : float
        Minimum share of known samples within the tolerance.
    min_known : float
        Edges with a smaller share of samples of known disparity are undetermined.

    Returns
    -------
    compatible : ndarray of bool, shape (E,)
    determined : ndarray of bool, shape (E,)
        False for edges with too few samples of known disparity (their ``compatible`` is
        False and should be ignored).
    """
    verts = np.asarray(reference_vertices, dtype=np.float64).reshape(-1, 2)
    vd = np.asarray(vertex_disparity, dtype=np.float64).reshape(-1)
    edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    disp = np.asarray(disparity, dtype=np.float64)
    if len(edges) == 0:
        z = np.zeros(0, dtype=bool)
        return z, z
    height, width = disp.shape
    xy, t, edge_of, counts = _edge_samples(verts, edges, margin, step)
    col = np.clip(np.rint(xy[:, 0]).astype(np.int64), 0, width - 1)
    row = np.clip(np.rint(xy[:, 1]).astype(np.int64), 0, height - 1)
    d = disp[row, col]
    expected = (1 - t) * vd[edges[edge_of, 0]] + t * vd[edges[edge_of, 1]]
    known = np.isfinite(d)
    good = known & (np.abs(np.where(known, d, 0.0) - expected) <= tolerance)
    start = np.cumsum(counts) - counts
    n_known = np.add.reduceat(known.astype(np.int64), start)
    n_good = np.add.reduceat(good.astype(np.int64), start)
    determined = n_known >= min_known * counts
    with np.errstate(invalid="ignore", divide="ignore"):
        share = np.where(n_known > 0, n_good / np.maximum(n_known, 1), 0.0)
    compatible = determined & (share >= agreement - 1e-12)
    return compatible, determined


def disparity_correctness(
    reference_vertices: np.ndarray,
    moving_vertices: np.ndarray,
    triangles: np.ndarray,
    disparity: np.ndarray,
    tolerance: float = 1.0,
) -> dict[str, float]:
    """Mesh correctness of a rectified stereo registration, from its dense disparity.

    The share of internal edges that pass :func:`disparity_edge_compatibility`, among the
    internal edges whose disparity is known along at least half of their length. A proxy of
    :func:`mesh_correctness` for pairs without plane labels (Middlebury).

    Parameters
    ----------
    reference_vertices, moving_vertices : ndarray, shape (N, 2)
        Mesh vertices (pixels); a vertex's disparity is ``x_reference - x_moving``.
    triangles : ndarray of int, shape (T, 3)
    disparity : ndarray, shape (H, W)
        True reference disparity (pixels), NaN where unknown.
    tolerance : float
        Largest deviation from linearity along an edge (pixels).

    Returns
    -------
    dict
        ``correctness`` (compatible / determined internal edges, NaN if none),
        ``internal_edges``, ``determined_internal``, ``compatible_internal``,
        ``incompatible_internal``.
    """
    ref = np.asarray(reference_vertices, dtype=np.float64).reshape(-1, 2)
    mov = np.asarray(moving_vertices, dtype=np.float64).reshape(-1, 2)
    edges, count = mesh_edges(triangles)
    internal = edges[count == 2]
    ok, determined = disparity_edge_compatibility(
        ref, ref[:, 0] - mov[:, 0], internal, disparity, tolerance=tolerance
    )
    n_det = int(determined.sum())
    n_ok = int(ok.sum())
    return {
        "correctness": n_ok / n_det if n_det else float("nan"),
        "internal_edges": len(internal),
        "determined_internal": n_det,
        "compatible_internal": n_ok,
        "incompatible_internal": n_det - n_ok,
    }


# --------------------------------------------------------------------------------------------
# Global mutual information
# --------------------------------------------------------------------------------------------


def _bin(image: np.ndarray, bins: int) -> np.ndarray:
    """Bin ``floor(g * M / (G + 1))`` of each grey level (G = 255 for uint8 and float input)."""
    a = np.asarray(image)
    if a.dtype == np.uint8 or a.dtype == np.uint16:
        levels = int(np.iinfo(a.dtype).max) + 1
        return (a.astype(np.int64) * bins) // levels
    v = np.nan_to_num(a.astype(np.float64), nan=0.0)
    return np.clip(np.floor(v * bins / 256.0), 0, bins - 1).astype(np.int64)


def global_mi(
    reference_gray: np.ndarray,
    registered_gray: np.ndarray,
    mask: np.ndarray | None = None,
    bins: int = 16,
) -> float:
    """Mutual information (bits) between the reference and the registered image.

    ``MI = H(A) + H(B) - H(A, B)`` from the joint histogram of the pixels in ``mask``, with
    ``bins`` grey-level bins per image (the paper's M = 16); the formula is
    :func:`core.similarity.mutual_information`'s. A grey level ``g`` of a uint8 (uint16) image
    falls in bin ``floor(g * M / 256)`` (``/ 65536``); float images are taken on the 0-255
    scale. This is the paper's global registration consistency (its expression (8)), for
    reporting; it is not normalised.

    Parameters
    ----------
    reference_gray, registered_gray : ndarray, shape (H, W)
        Grey images of the same shape (uint8, uint16 or float on 0-255).
    mask : ndarray of bool, shape (H, W), optional
        Pixels to use (e.g. inside the mesh and mapped inside the moving image). Default: all
        pixels where the registered image is finite.
    bins : int
        Bins per image (>= 2).

    Returns
    -------
    float
        MI in bits; 0 for an empty mask.
    """
    a = np.asarray(reference_gray)
    b = np.asarray(registered_gray)
    if a.shape != b.shape or a.ndim != 2:
        raise ValueError("reference_gray and registered_gray must be (H, W) of the same shape")
    if bins < 2:
        raise ValueError("bins must be >= 2")
    keep = np.ones(a.shape, dtype=bool) if mask is None else np.asarray(mask, dtype=bool).copy()
    if np.issubdtype(b.dtype, np.floating):
        keep &= np.isfinite(b)
    if np.issubdtype(a.dtype, np.floating):
        keep &= np.isfinite(a)
    if not keep.any():
        return 0.0
    key = _bin(a[keep], bins) * bins + _bin(b[keep], bins)
    hist = np.bincount(key, minlength=bins * bins)
    mi, _ = mutual_information(hist, bins)
    return float(mi)
