"""The ceiling of edge swaps: a greedy swap search that is told the true error of every swap.

An optimizer that only swaps edges cannot do better on a case than the mesh this search finds
(up to the greedy order): each step takes the swap that lowers the summed true endpoint error
of its quad the most, under the same preconditions as :func:`core.optimize.greedy_search`
(strictly convex quad in both images, no patch reversal, no edge created twice). The
*achievable gain* of a case is then the error of the initial mesh minus the ceiling's, and an
optimizer's *realised share* is its own error reduction over that gain.
"""

from __future__ import annotations

import heapq

import numpy as np

from pwlreg.core.mesh import Edge, Mesh, edge_key
from pwlreg.core.raster import affine_maps, expand, rasterize

Triple = tuple[int, int, int]


class TruthError:
    """Summed endpoint error (pixels) of single triangles against a dense truth, cached.

    Pixels without truth or outside ``valid`` count nothing, so a quad's error before and
    after a swap is summed over the same pixels.
    """

    def __init__(self, mesh: Mesh, truth_x: np.ndarray, truth_y: np.ndarray,
                 valid: np.ndarray | None = None) -> None:
        self.mesh = mesh
        self.tx = np.asarray(truth_x, dtype=np.float64)
        self.ty = np.asarray(truth_y, dtype=np.float64)
        ok = np.isfinite(self.tx) & np.isfinite(self.ty)
        self.ok = ok if valid is None else ok & np.asarray(valid, dtype=bool)
        self.cache: dict[Triple, float] = {}

    def ensure(self, triples: list[Triple]) -> None:
        todo = sorted({t for t in triples if t not in self.cache})
        if not todo:
            return
        idx = np.array(todo, dtype=np.int64)
        ref = self.mesh.reference[idx]
        mov = self.mesh.moving[idx]
        spans = rasterize(ref, self.tx.shape)
        run, x, y = expand(spans)
        tri = spans.triangle[run]
        maps = affine_maps(ref, mov)[tri]
        mx = maps[:, 0, 0] * x + maps[:, 0, 1] * y + maps[:, 0, 2]
        my = maps[:, 1, 0] * x + maps[:, 1, 1] * y + maps[:, 1, 2]
        keep = self.ok[y, x]
        err = np.where(keep, np.hypot(mx - np.where(keep, self.tx[y, x], 0.0),
                                      my - np.where(keep, self.ty[y, x], 0.0)), 0.0)
        sums = np.bincount(tri, weights=err, minlength=len(todo))
        for t, s in zip(todo, sums.tolist(), strict=True):
            self.cache[t] = s

    def __call__(self, t: Triple) -> float:
        return self.cache[t]


def _triple(t: tuple[int, int, int]) -> Triple:
    a, b, c = sorted(t)
    return (a, b, c)


def ceiling_search(
    reference_vertices: np.ndarray,
    moving_vertices: np.ndarray,
    triangles: np.ndarray,
    truth_x: np.ndarray,
    truth_y: np.ndarray,
    valid: np.ndarray | None = None,
    *,
    min_gain: float = 1e-6,
) -> np.ndarray:
    """Greedy edge swaps ranked by the true error they remove; returns the final triangles.

    Parameters
    ----------
    reference_vertices, moving_vertices : ndarray, shape (N, 2)
        Mesh vertices (pixels).
    triangles : ndarray, shape (T, 3)
        The initial mesh (vertex indices).
    truth_x, truth_y : ndarray, shape (H, W)
        True moving position of each reference pixel; NaN unknown.
    valid : ndarray of bool, optional
        Pixels that count.
    min_gain : float
        Smallest accepted gain, in pixels of summed error (guards against float ties).

    Returns
    -------
    ndarray, shape (T, 3)
    """
    mesh = Mesh(reference_vertices, moving_vertices, triangles)
    error = TruthError(mesh, truth_x, truth_y, valid)
    retired: set[Edge] = set()

    def quad_triples(e: Edge) -> tuple[Triple, Triple, Triple, Triple]:
        q = mesh.quad(e)
        s0, s1 = q.slots
        n0, n1 = q.swapped_triangles()
        return (_triple(mesh.triangle(s0)), _triple(mesh.triangle(s1)), _triple(n0),
                _triple(n1))

    def gains(edges: list[Edge]) -> list[float]:
        quads = [quad_triples(e) for e in edges]
        error.ensure([t for q in quads for t in q])
        return [error(a) + error(b) - error(c) - error(d) for a, b, c, d in quads]

    def eligible(e: Edge) -> bool:
        if not mesh.can_swap(e):
            return False
        q = mesh.quad(e)
        return edge_key(q.k, q.l) not in retired

    candidates = mesh.swappable_edges()
    best = dict(zip(candidates, gains(candidates), strict=True))
    heap = [(-g, e) for e, g in best.items()]
    heapq.heapify(heap)
    while True:
        while heap and best.get(heap[0][1]) != -heap[0][0]:
            heapq.heappop(heap)
        if not heap or -heap[0][0] <= min_gain:
            break
        _, e = heapq.heappop(heap)
        del best[e]
        if not eligible(e):
            continue
        q = mesh.quad(e)
        mesh.swap(e, check=False)
        retired.add(e)
        for b in q.boundary:
            best.pop(b, None)
        ring = [b for b in q.boundary if eligible(b)]
        for b, g in zip(ring, gains(ring), strict=True):
            best[b] = g
            heapq.heappush(heap, (-g, b))
    return mesh.triangles


def realised_share(initial: float, achieved: float, ceiling: float) -> float:
    """Share of the achievable error reduction an optimizer realised (NaN if none possible).

    ``initial``, ``achieved`` and ``ceiling`` are mean endpoint errors (pixels) of the initial
    mesh, the optimizer's mesh and the ceiling's mesh over the same pixels.
    """
    gain = initial - ceiling
    if not np.isfinite(gain) or gain <= 1e-9:
        return float("nan")
    return float((initial - achieved) / gain)
