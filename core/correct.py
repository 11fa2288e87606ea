"""Vertex correction: a measured vertex that the images contradict moves with a neighbour.

A corner where a foreground edge crosses the background (a T-junction) looks the same in both
images but belongs to neither surface: the matcher pairs it with the foreground's motion while
the point itself is background, and its neighbourhood agrees with it on one side. Insertion
cannot fix such a vertex and the swaps cannot move it. Where a vertex's displacement differs
from a neighbour's by more than :data:`SUSPECT_PX`, the triangles around it (its *star*) are
scored with the vertex moving as its neighbours do (a displacement at least :data:`SUPPORT` of
them share, within :data:`REACH` of its mean edge); when the best of these raises the star's
consistency (the swaps' cost: normalized mutual information by default) by more than
:data:`GAIN_FACTOR` times the swaps' threshold for that many pixels
(:func:`core.optimize.gain_thresholds`), and folds none of its triangles, the vertex takes it.

Judged on Middlebury's truth the move is not always right about the vertex itself: of its 22
moves there (both extents), 10 took a vertex more than 3 px off to within 3 px and 6 took one
within 3 px beyond it (4 of these beside a depth step, whose star reaches over the step and
gains by following the other surface); the mean error fell on every pair all the same.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import sparse

from pwlreg.core.optimize import COSTS, gain_thresholds
from pwlreg.core.raster import orientation
from pwlreg.core.similarity import ScoringImages, triangle_statistics

#: A vertex is tested when its displacement and a neighbour's differ by more than this (px).
#: At 1 px it tested 664 of the real facade's 1190 vertices (285 at 2 px; 39 ms against 23) for
#: Middlebury's frame figures within 0.004 px.
SUSPECT_PX = 2.0

#: Fewest neighbours whose displacements (within :data:`SUPPORT_PX`) a candidate must share:
#: with one, a single wrong neighbour moved a box's vertex 32 px off (its mean error 7.1 ->
#: 8.0 px).
SUPPORT = 2
SUPPORT_PX = 1.0

#: Longest move, as a share of the vertex's mean edge: a longer one shears its star across
#: another surface (an L-shape's vertex moved 47 px, its mean error 2.07 -> 2.35 px).
REACH = 0.5

#: A move must gain this many times the swaps' threshold for its star's pixels: it changes
#: every triangle of the star where a swap changes two. At once, a synthetic city's vertex
#: 0.65 px off moved 17.9 px for 1.3 times its threshold (its mean error 1.663 -> 1.682 px);
#: at twice, Middlebury's figures stay within 0.003 px and no synthetic case loses more than
#: 1 %.
GAIN_FACTOR = 2.0

#: The name of this move in :data:`core.moves.MOVES`.
MOVE = "correct"

#: Candidate displacements are taken once per cell of this side (px): neighbours moving
#: alike propose one candidate, not several.
DISTINCT_PX = 0.5


@dataclass(frozen=True)
class Corrections:
    """The vertices :func:`contradicted_vertices` moves.

    Attributes
    ----------
    vertices : ndarray of int, shape (K,)
        Their indices.
    moving : ndarray, shape (K, 2)
        Their new moving positions (pixels).
    before : ndarray, shape (K, 2)
        Their moving positions before.
    gains : ndarray, shape (K,)
        The gain of each vertex's star (the swaps' cost).
    tested : int
        Vertices scored: those with a candidate left after the support and reach rules.
    """

    vertices: np.ndarray
    moving: np.ndarray
    before: np.ndarray
    gains: np.ndarray
    tested: int

    def to_list(self) -> list[dict]:
        """One record per moved vertex (``mesh.json`` and ``convergence.json``)."""
        return [{"vertex": int(v), "from": [float(a) for a in b], "to": [float(a) for a in m],
                 "gain": round(float(g), 6), "move": MOVE}
                for v, b, m, g in zip(self.vertices, self.before, self.moving, self.gains,
                                      strict=True)]


def _stars(tris: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Triangles around each vertex: ``(order, start)``, the triangles of vertex ``v`` being
    ``order[start[v]:start[v + 1]]``."""
    owner = tris.ravel()
    order = np.argsort(owner, kind="stable") // 3
    start = np.concatenate([[0], np.cumsum(np.bincount(owner, minlength=n))])
    return order, start


def contradicted_vertices(
    images: ScoringImages,
    reference_vertices: np.ndarray,
    moving_vertices: np.ndarray,
    triangles: np.ndarray,
    movable: np.ndarray,
    *,
    witnesses: np.ndarray | None = None,
    epsilon: float,
    epsilon_pixels: float,
    cost: str = "mi",
    suspect: float = SUSPECT_PX,
) -> Corrections:
    """The ``movable`` vertices whose star the images score higher moving as a neighbour does.

    Parameters
    ----------
    images : ScoringImages
        The scoring images (:func:`core.similarity.prepare_images`).
    reference_vertices, moving_vertices : ndarray, shape (N, 2)
        The mesh's vertices in both images (pixels).
    triangles : ndarray of int, shape (T, 3)
        The mesh's triangles (vertex indices).
    movable : ndarray of bool, shape (N,)
        Vertices that may move (measured, not given by the client).
    witnesses : ndarray of bool, shape (N,), optional
        Vertices whose motion may be proposed or support a proposal (the measured ones);
        default every vertex.
    epsilon, epsilon_pixels : float
        The swaps' gain threshold (:func:`core.optimize.gain_thresholds`).
    cost : str, optional
        The swaps' consistency measure, an entry of :data:`core.optimize.COSTS`.
    suspect : float, optional
        Least difference (px) of displacement with a neighbour for a vertex to be tested.

    Returns
    -------
    Corrections
        In vertex order. No two of its vertices are neighbours: each was scored with its
        neighbours in place, and of two neighbours the one with the larger gain moves.
    """
    ref_v = np.asarray(reference_vertices, dtype=np.float64)
    mov_v = np.asarray(moving_vertices, dtype=np.float64)
    tris = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    n = len(ref_v)
    none = Corrections(np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), 0)
    if not len(tris):
        return none
    edges = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
    edges = np.unique(np.concatenate([edges, edges[:, ::-1]]), axis=0)
    a, b = edges.T  # sorted by a: the neighbours of v are b[around[v]:around[v + 1]]
    around = np.searchsorted(a, np.arange(n + 1))
    edge = np.bincount(a, weights=np.hypot(*(ref_v[a] - ref_v[b]).T), minlength=n)
    edge /= np.maximum(np.diff(around), 1)  # each vertex's mean edge
    disp = mov_v - ref_v
    # Only witnesses (measured vertices) propose a motion or support one: an extrapolated
    # border vertex's motion is a guess.
    seen = np.ones(n, bool) if witnesses is None else np.asarray(witnesses, bool)
    i, j = a[seen[b]], b[seen[b]]
    first = np.searchsorted(i, np.arange(n + 1))
    far = (np.hypot(*(disp[j] - disp[i]).T) > suspect) & np.asarray(movable, bool)[i]
    if not far.any():
        return none

    # Candidates: each far neighbour's displacement, one per DISTINCT_PX cell...
    cand_v, cand_d = i[far], disp[j[far]]
    cell = np.rint((cand_d - disp[cand_v]) / DISTINCT_PX).astype(np.int64)
    _, once = np.unique(np.column_stack([cand_v, cell]), axis=0, return_index=True)
    cand_v, cand_d = cand_v[once], cand_d[once]
    # ... that at least SUPPORT neighbours share (one wrong neighbour moves no vertex), within
    # REACH of the vertex's mean edge (a longer move shears its star across another surface).
    which, k = _ragged(first[cand_v], first[cand_v + 1] - first[cand_v])
    near = np.hypot(*(disp[j[k]] - cand_d[which]).T) < SUPPORT_PX
    support = np.bincount(which, weights=near, minlength=len(cand_v))
    reach = np.hypot(*(cand_d - disp[cand_v]).T) <= REACH * edge[cand_v]
    ok = (support >= SUPPORT) & reach
    cand_v, cand_m = cand_v[ok], ref_v[cand_v[ok]] + cand_d[ok]
    tested = np.unique(cand_v)
    if not len(tested):
        return none

    # Each star as it is (its triangles' histograms once), then with its vertex at each
    # candidate.
    star, start = _stars(tris, n)
    measure = COSTS[cost]
    owner, k = _ragged(start[tested], start[tested + 1] - start[tested])
    now = np.unique(star[k])
    at = np.searchsorted(now, star[k])
    hist, moments = triangle_statistics(images, ref_v[tris[now]], mov_v[tris[now]],
                                        with_moments=measure.needs_moments)
    hist_now = _group_sums(hist[at], owner, len(tested))
    base = measure.measure(hist_now, None if moments is None else _group_sums(
        moments[at], owner, len(tested)), images.bins)
    owner, k = _ragged(start[cand_v], start[cand_v + 1] - start[cand_v])
    rows = tris[star[k]]
    ref_tri, mov_tri = ref_v[rows], mov_v[rows]
    mov_tri[rows == cand_v[owner][:, None]] = cand_m[owner]  # once in each triangle
    folds = orientation(*mov_tri.transpose(1, 0, 2)) != orientation(*ref_tri.transpose(1, 0, 2))
    folded = np.bincount(owner, weights=folds, minlength=len(cand_v)) > 0
    hist, moments = triangle_statistics(images, ref_tri, mov_tri,
                                        with_moments=measure.needs_moments)
    value = measure.measure(_group_sums(hist, owner, len(cand_v)), None if moments is None
                            else _group_sums(moments, owner, len(cand_v)), images.bins)

    group = np.searchsorted(tested, cand_v)
    gain = value - base[group]
    gain[folded] = -np.inf
    threshold = gain_thresholds(hist_now.sum(axis=1).astype(np.float64), epsilon,
                                epsilon_pixels)
    best = np.full(len(tested), -np.inf)
    np.maximum.at(best, group, gain)
    chosen = (gain == best[group]) & (gain > GAIN_FACTOR * threshold[group])
    chosen[chosen] = np.concatenate([[True], np.diff(group[chosen]) > 0])  # first of ties
    verts, moves, gains = cand_v[chosen], cand_m[chosen], gain[chosen]
    # No two neighbours move: each was scored with the other in place.
    keep = np.zeros(len(verts), bool)
    blocked = np.zeros(n, bool)
    for c in np.argsort(-gains, kind="stable"):
        v = verts[c]
        if not blocked[v]:
            keep[c] = True
            blocked[v] = True
            blocked[b[around[v]:around[v + 1]]] = True
    verts = verts[keep]
    return Corrections(verts, moves[keep], mov_v[verts], gains[keep], len(tested))


def _ragged(starts: np.ndarray, sizes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The runs ``starts[g]:starts[g] + sizes[g]`` end to end: each element's run ``g`` and
    its index."""
    owner = np.repeat(np.arange(len(sizes)), sizes)
    return owner, starts[owner] + np.arange(len(owner)) - np.repeat(np.cumsum(sizes) - sizes, sizes)


def _group_sums(rows: np.ndarray, owner: np.ndarray, groups: int) -> np.ndarray:
    """Sums of the ``rows`` of each ``owner`` group (a sparse product: a third of the time
    of ``np.add.reduceat`` on these shapes)."""
    pick = sparse.csr_matrix((np.ones(len(owner), rows.dtype), (owner, np.arange(len(owner)))),
                             shape=(groups, len(owner)))
    return np.asarray(pick @ rows)
