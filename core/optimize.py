"""Greedy edge-swap search driven by mutual information (the paper's Algorithm 1).

Every triangle the search looks at -- current ones and the two new triangles of each candidate
swap -- is rasterized and resampled once; its joint histogram (and moments) are cached under its
vertex triple. The consistency of a quad is then a sum of two cached rows, and the global
consistency after a swap an O(M^2) update.
"""

from __future__ import annotations

import heapq
import math
import time
from collections.abc import Callable, Collection, Iterable
from dataclasses import dataclass, field

import numpy as np

from pwlreg.core.mesh import Edge, Mesh, Quad, edge_key
from pwlreg.core.similarity import (
    ScoringImages,
    mutual_information,
    ncc,
    summed_information,
    triangle_statistics,
)

Triple = tuple[int, int, int]
ProgressFn = Callable[[float], None]

#: Bounds of a quad's threshold, in units of ``epsilon`` (:func:`gain_thresholds`). Below half
#: of it, large quads across an occluding edge took noise for gains (an automatic occluder
#: scene ended 8 % worse than Delaunay with 1/5; 1 % better with 1/2).
THRESHOLD_RANGE = (0.5, 5.0)

#: Pairs of swaps scored at once by the look-ahead when the cost has no ``summed`` (their six
#: histograms each are gathered).
PAIR_BLOCK = 512


@dataclass(frozen=True)
class SwapStep:
    """One accepted swap.

    ``delta`` is the gain of the quad's consistency (NMI for cost ``mi``, NCC for ``ncc``);
    ``mi`` (bits) and ``nmi`` are the global consistency of the whole mesh after the swap;
    ``elapsed_s`` counts seconds since the search started. ``move`` is ``"swap"`` for a swap
    taken on its own gain, ``"pair"`` for either swap of two taken together (their joint gain
    over the pentagon of the three triangles they change is ``delta`` of both).
    """

    iteration: int
    removed: Edge
    added: Edge
    delta: float
    mi: float
    nmi: float
    elapsed_s: float
    move: str = "swap"


@dataclass
class SearchResult:
    """Outcome of a mesh optimization.

    Attributes
    ----------
    initial_mi, initial_nmi, final_mi, final_nmi : float
        Global MI (bits) and NMI over all pixels of the mesh (the paper's expression 8),
        before and after.
    steps : list of SwapStep
        Accepted swaps in order.
    stopped_because : str
        Why the search ended.
    evaluations : int
        Number of candidate swaps scored.
    histogram : ndarray of int64, shape (M * M,), or None
        Joint histogram of the final mesh on the scoring images, from which ``final_mi`` was
        computed; None when the optimizer does not keep it.
    """

    initial_mi: float
    initial_nmi: float
    final_mi: float = 0.0
    final_nmi: float = 0.0
    steps: list[SwapStep] = field(default_factory=list)
    stopped_because: str = ""
    evaluations: int = 0
    histogram: np.ndarray | None = field(default=None, repr=False)


def _triple(t: Iterable[int]) -> Triple:
    a, b, c = t
    # Three compares, not sorted(): the search sorts tens of thousands of triples one by one.
    if a > b:
        a, b = b, a
    if b > c:
        b, c = c, b
        if a > b:
            a, b = b, a
    return (a, b, c)


#: Batches of quads larger than this get their triples sorted by numpy, not one by one.
_NUMPY_BATCH = 32


def _sorted_triples(tris: np.ndarray) -> list[Triple]:
    """Sorted vertex triples of the rows of an int ``(T, 3)`` array, as tuples."""
    return list(map(tuple, np.sort(tris, axis=1).tolist()))


def quad_keys(quads: list[Quad]) -> list[Triple]:
    """Sorted triples of each quad's two current and two swapped triangles, flattened.

    Four per quad, in the order of :func:`quad_triples`.
    """
    if len(quads) > _NUMPY_BATCH:
        ijkl = np.array([q[:4] for q in quads], dtype=np.int64)
        return _sorted_triples(ijkl[:, [0, 1, 2, 0, 1, 3, 2, 3, 0, 2, 3, 1]].reshape(-1, 3))
    keys: list[Triple] = []
    for q in quads:
        i, j, k, l = q[:4]  # noqa: E741
        keys += (_triple((i, j, k)), _triple((i, j, l)), _triple((k, l, i)), _triple((k, l, j)))
    return keys


class TriangleCache:
    """Joint histograms (and moments) of triangles, keyed by sorted vertex triple.

    Parameters
    ----------
    images : ScoringImages
        Prepared images.
    mesh : Mesh
        Supplies the vertex coordinates (they never change).
    with_moments : bool
        Also keep the six moments needed by NCC and SSD.
    """

    def __init__(
        self, images: ScoringImages, mesh: Mesh, with_moments: bool = False, capacity: int = 64
    ) -> None:
        self.images = images
        self.reference = mesh.reference
        self.moving = mesh.moving
        self.with_moments = with_moments
        self.bins = images.bins
        # Keyed by the code (a * N + b) * N + c of the sorted triple (N vertices): ints hash
        # faster than tuples, and numpy makes them for a whole batch.
        self._n = len(mesh.reference)
        self._numpy_codes = self._n**3 < 2**62  # else int64 would overflow: Python ints
        self._rows: dict[int, int] = {}
        # int32: a triangle's counts fit, and half the memory traffic of every gather. Rows are
        # zeroed when first used (allocating zeros, then copying on growth, costs more).
        self._hist = np.empty((capacity, self.bins * self.bins), dtype=np.int32)
        self._moments = np.empty((capacity if with_moments else 0, 6), dtype=np.float64)

    def __len__(self) -> int:
        return len(self._rows)

    def _codes(self, triples: Iterable[Triple]) -> list[int]:
        n = self._n
        return [(a * n + b) * n + c for a, b, c in triples]

    def ensure(self, triples: Iterable[Triple]) -> None:
        """Compute, in one batch, the statistics of the triples not cached yet."""
        self._ensure_codes(self._codes(triples))

    def _ensure_codes(self, codes: list[int], triples: list[Triple] | None = None) -> None:
        """Compute the codes not cached yet; ``triples``, if given, are those of ``codes``."""
        known = self._rows
        if triples is not None:  # a few: no decoding
            fresh = {c: t for c, t in zip(codes, triples, strict=True) if c not in known}
            if not fresh:
                return
            missing = list(fresh)
            idx = np.array(list(fresh.values()), dtype=np.int64)
        else:
            missing = [c for c in dict.fromkeys(codes) if c not in known]
            if not missing:
                return
            idx = self._decode(missing)
        self._compute(missing, idx)

    def _decode(self, missing: list[int]) -> np.ndarray:
        n = self._n
        if self._numpy_codes:
            m = np.array(missing, dtype=np.int64)
            idx = np.stack([m // (n * n), m // n % n, m % n], axis=1)
        else:
            idx = np.array([(c // (n * n), c // n % n, c % n) for c in missing], dtype=np.int64)
        return idx

    def _compute(self, missing: list[int], idx: np.ndarray) -> None:
        """Statistics of the triangles ``idx`` (M, 3), cached under the codes ``missing``."""
        known = self._rows
        start = len(self._rows)
        need = start + len(missing)
        if need > len(self._hist):
            grow = max(need, 2 * len(self._hist))
            grown = np.empty((grow, self._hist.shape[1]), dtype=np.int32)
            grown[:start] = self._hist[:start]
            self._hist = grown
            if self.with_moments:
                grown_m = np.empty((grow, 6))
                grown_m[:start] = self._moments[:start]
                self._moments = grown_m
        # Counted straight into the cache's rows: no copy.
        hist_out = self._hist[start:need]
        hist_out[...] = 0
        moments_out = None
        if self.with_moments:
            moments_out = self._moments[start:need]
            moments_out[...] = 0.0
        triangle_statistics(
            self.images, self.reference[idx], self.moving[idx], self.with_moments,
            hist_out=hist_out, moments_out=moments_out,
        )
        known.update(zip(missing, range(start, need), strict=True))

    def _code_rows(self, codes: list[int]) -> np.ndarray:
        known = self._rows
        return np.array([known[c] for c in codes], dtype=np.int64)

    def rows(self, triples: Iterable[Triple]) -> np.ndarray:
        """Row indices of cached triples."""
        return self._code_rows(self._codes(triples))

    def lookup(self, tris: np.ndarray) -> np.ndarray:
        """Rows of the triangles ``tris`` (int, shape (..., 3), vertices in any order), their
        statistics computed first where missing. Shape ``(...)``."""
        s = np.sort(np.asarray(tris, dtype=np.int64).reshape(-1, 3), axis=1)
        n = self._n
        if not self._numpy_codes:
            codes = self._codes(s.tolist())
            self._ensure_codes(codes)
            return self._code_rows(codes).reshape(np.shape(tris)[:-1])
        # Each distinct triangle once through the dict (a batch repeats many).
        unique, inverse = np.unique((s[:, 0] * n + s[:, 1]) * n + s[:, 2], return_inverse=True)
        codes = unique.tolist()
        self._ensure_codes(codes)
        return self._code_rows(codes)[inverse].reshape(np.shape(tris)[:-1])

    def quad_rows(self, quads: list[Quad] | np.ndarray) -> np.ndarray:
        """Rows ``(E, 4)`` of each quad's two current and two swapped triangles (the order of
        :func:`quad_triples`), computed first where missing. ``quads`` may be an ``(E, 4)``
        array of ``(i, j, k, l)``."""
        if isinstance(quads, np.ndarray) or len(quads) > _NUMPY_BATCH:
            if isinstance(quads, np.ndarray):
                ijkl = quads
            else:
                ijkl = np.array([q[:4] for q in quads], dtype=np.int64).reshape(-1, 4)
            return self.lookup(ijkl[:, [0, 1, 2, 0, 1, 3, 2, 3, 0, 2, 3, 1]].reshape(-1, 4, 3))
        keys = quad_keys(quads)
        codes = self._codes(keys)
        self._ensure_codes(codes, keys)
        return self._code_rows(codes).reshape(-1, 4)

    def hist(self, triples: Iterable[Triple]) -> np.ndarray:
        """Summed joint histogram ``(M * M,)`` of cached triples."""
        return self._hist[self.rows(triples)].sum(axis=0)

    @property
    def table(self) -> np.ndarray:
        """The cached histograms, ``(rows, M * M)`` int32 (a view: valid until ``ensure``)."""
        return self._hist[:len(self._rows)]

    def hist_rows(self, rows: np.ndarray) -> np.ndarray:
        """Histograms of the given rows, ``(..., M * M)``."""
        return self._hist[rows]

    def moment_rows(self, rows: np.ndarray) -> np.ndarray:
        """Moments of the given rows, ``(..., 6)``."""
        return self._moments[rows]


def quad_triples(q: Quad, mesh: Mesh) -> tuple[Triple, Triple, Triple, Triple]:
    """Sorted triples of a quad's two current triangles and its two swapped triangles."""
    s0, s1 = q.slots
    n0, n1 = q.swapped_triangles()
    return (
        _triple(mesh.triangle(s0)),
        _triple(mesh.triangle(s1)),
        _triple(n0),
        _triple(n1),
    )


@dataclass(frozen=True)
class Cost:
    """A consistency measure of a pixel set, from its summed joint histogram (and moments).

    ``measure(hist, moments, bins)`` takes ``(..., M * M)`` histograms and ``(..., 6)`` moments
    (None unless ``needs_moments``) and returns ``(...)`` values, larger is more consistent.
    ``summed(table, rows, bins)``, if given, returns ``measure`` of the sums
    ``table[rows].sum(axis=-2)`` and their pixel counts, the same values without gathering the
    rows (the search's hot path).
    """

    needs_moments: bool
    measure: Callable[[np.ndarray, np.ndarray | None, int], np.ndarray]
    summed: Callable[[np.ndarray, np.ndarray, int], tuple[np.ndarray, np.ndarray]] | None = None


def _summed_nmi(table: np.ndarray, rows: np.ndarray, bins: int) -> tuple[np.ndarray, np.ndarray]:
    _, nmi, pixels = summed_information(table, rows, bins)
    return nmi, pixels


COSTS: dict[str, Cost] = {
    "mi": Cost(False, lambda hist, moments, bins: mutual_information(hist, bins)[1], _summed_nmi),
    "ncc": Cost(True, lambda hist, moments, bins: ncc(moments)),
}
"""Cost name (value of ``options.cost``) -> measure: NMI (the paper) or NCC."""


class QuadScorer:
    """Consistency gain of swapping internal edges, from cached triangle statistics.

    ``cost`` names an entry of :data:`COSTS`.
    """

    def __init__(self, cache: TriangleCache, cost: str) -> None:
        if cost not in COSTS:
            raise ValueError(f"unknown cost {cost!r}; expected one of {sorted(COSTS)}")
        self.cache = cache
        self.cost = COSTS[cost]

    def deltas(self, mesh: Mesh, edges: list[Edge]) -> np.ndarray:
        """Gain of each swap: consistency after minus before, same order as ``edges``."""
        return self.deltas_and_pixels(mesh, edges)[0]

    def deltas_and_pixels(self, mesh: Mesh, edges: list[Edge]) -> tuple[np.ndarray, np.ndarray]:
        """Gain of each swap and the number of reference pixels of its quad."""
        return self.quad_deltas([mesh.quad(e) for e in edges])

    def quad_deltas(self, quads: list[Quad] | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`deltas_and_pixels` of the quads themselves (the caller has them already),
        :class:`Quad` objects or an ``(E, 4)`` array of ``(i, j, k, l)``."""
        if len(quads) == 0:
            return np.zeros(0), np.zeros(0)
        rows = self.cache.quad_rows(quads)
        if self.cost.summed is not None:
            sums = rows.reshape(-1, 2, 2)  # (quad, before/after, triangle)
            value, pixels = self.cost.summed(self.cache.table, sums, self.cache.bins)
            return value[:, 1] - value[:, 0], pixels[:, 0]
        h = self.cache.hist_rows(rows)
        # Before (current triangles) and after (swapped) side by side: one measure call.
        sides = h[:, 0::2] + h[:, 1::2]
        m = None
        if self.cost.needs_moments:
            mo = self.cache.moment_rows(rows)
            m = mo[:, 0::2] + mo[:, 1::2]
        value = self.cost.measure(sides, m, self.cache.bins)
        return value[:, 1] - value[:, 0], sides[:, 0].sum(axis=1).astype(np.float64)


def gain_thresholds(pixels: np.ndarray, epsilon: float, epsilon_pixels: float) -> np.ndarray:
    """Smallest accepted gain of swaps whose quads have ``pixels`` reference pixels.

    The noise of a consistency estimate falls as one over the square root of its sample size:
    ``epsilon`` for a quad of ``epsilon_pixels`` pixels, ``epsilon * sqrt(epsilon_pixels / n)``
    for ``n`` pixels, within :data:`THRESHOLD_RANGE` times ``epsilon``. ``epsilon_pixels`` 0
    keeps the paper's one threshold for every quad.
    """
    if epsilon_pixels <= 0:
        return np.full(len(pixels), float(epsilon))
    scaled = epsilon * np.sqrt(epsilon_pixels / np.maximum(pixels, 1.0))
    low, high = THRESHOLD_RANGE
    return np.clip(scaled, low * epsilon, high * epsilon)


def gain_threshold(pixels: float, epsilon: float, epsilon_pixels: float) -> float:
    """:func:`gain_thresholds` of one quad, the same value bit for bit (the same IEEE
    operations in the same order) without numpy's per-call cost: the search asks it for a
    few quads at a time."""
    if epsilon_pixels <= 0:
        return float(epsilon)
    scaled = epsilon * math.sqrt(epsilon_pixels / max(pixels, 1.0))
    low, high = THRESHOLD_RANGE
    return min(max(scaled, low * epsilon), high * epsilon)


def pair_moves(
    mesh: Mesh,
    edges: list[Edge] | None,
    retired: Collection[Edge],
    near: Iterable[int] | None = None,
) -> np.ndarray:
    """Every valid pair of swaps starting with one of ``edges`` (each already swappable).

    ``edges`` None stands for every swappable edge of the mesh, in order, or with ``near``
    those with an end among these vertices (found in one batch with the pairs).

    Swapping ``e = (i, j)`` of quad ``(i, j; k, l)`` makes triangles ``(k, l, i)`` and
    ``(k, l, j)``; a second swap then turns one of the quad's sides ``b = (p, r)`` (``p`` in
    ``{i, j}``, ``r`` in ``{k, l}``) over the outer triangle ``(p, r, m)`` into ``(r', m)``,
    ``r'`` the other of ``k, l``. Both swaps must meet the preconditions of
    :meth:`Mesh.swap_blocker` on the mesh they apply to, and neither may create an edge of
    ``retired`` (``(i, j)`` with ``i < j``).

    Returns
    -------
    ndarray of int64, shape (P, 9)
        Rows ``(i, j, k, l, m, p, r, p', r')``, ``p'`` the other of ``i, j``. The pentagon's
        three triangles go from ``(i, j, k), (i, j, l), (p, r, m)`` to ``(k, l, p'),
        (r', m, p), (r', m, r)``.
    """
    if edges is not None and not edges:
        return np.zeros((0, 9), dtype=np.int64)
    # Vectorized over every edge and side, the retired edges as codes.
    codes, apexes = mesh.edge_table()
    n = len(mesh.reference)

    def find(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rows of the edges (a, b) in the table, and whether each exists."""
        code = np.minimum(a, b) * n + np.maximum(a, b)
        at = np.minimum(np.searchsorted(codes, code), len(codes) - 1)
        return at, codes[at] == code

    if edges is None:
        quads = mesh.swappable_quads(near, (codes, apexes))
    else:
        ij = np.array(edges, dtype=np.int64).reshape(-1, 2)
        at, _ = find(ij[:, 0], ij[:, 1])
        quads = np.column_stack([ij, apexes[at]])  # (i, j, k, l) as Mesh.quad gives them
    banned = np.array([i * n + j for i, j in retired], dtype=np.int64)

    def allowed(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return ~np.isin(np.minimum(a, b) * n + np.maximum(a, b), banned)

    i, j, k, l = quads[allowed(quads[:, 2], quads[:, 3])].T  # noqa: E741
    # The four second swaps of each, in the order p in (i, j), then r in (k, l).
    p, p2 = np.stack([i, i, j, j], axis=1), np.stack([j, j, i, i], axis=1)
    r, r2 = np.stack([k, l, k, l], axis=1), np.stack([l, k, l, k], axis=1)
    at, _ = find(p, r)
    a0, a1 = apexes[at, 0], apexes[at, 1]
    # The outer triangle over the side (p, r) is the one of its two without p2.
    m = np.where((a0 == p2) & (a1 != p2), a1, np.where((a1 == p2) & (a0 != p2), a0, -1))
    ok = (a1 >= 0) & (m >= 0) & (m != r2) & (m != p2)
    ok &= ~find(r2, np.where(ok, m, r2 + 1))[1]  # the second swap's new edge is not there yet
    wide = [np.broadcast_to(c[:, None], p.shape) for c in (i, j, k, l)]
    pairs = np.stack([*wide, m, p, r, p2, r2], axis=-1).reshape(-1, 9)[ok.ravel()]
    m, p, r, r2 = pairs[:, 4], pairs[:, 5], pairs[:, 6], pairs[:, 8]
    ok = np.ones(len(pairs), dtype=bool)
    turns = []
    for xy in mesh.fixed_arrays:
        xm, xp, xr, xr2 = xy[m], xy[p], xy[r], xy[r2]

        def orient(pa: np.ndarray, pb: np.ndarray, pc: np.ndarray) -> np.ndarray:
            return np.sign((pb[:, 0] - pa[:, 0]) * (pc[:, 1] - pa[:, 1])
                           - (pb[:, 1] - pa[:, 1]) * (pc[:, 0] - pa[:, 0]))

        new_p, new_r = orient(xr2, xm, xp), orient(xr2, xm, xr)
        # The quad (p, r; r', m) of the second swap is strictly convex...
        ok &= (orient(xp, xr, xr2) * orient(xp, xr, xm) < 0) & (new_p * new_r < 0)
        turns.append((new_p, new_r))
    # ... in both images, and its new triangles turn the same way in both (no reversal).
    ok &= (turns[0][0] == turns[1][0]) & (turns[0][1] == turns[1][1])
    pairs = pairs[ok]
    return pairs[allowed(pairs[:, 8], pairs[:, 4])]  # the second swap's new edge (r', m)


def greedy_search(
    mesh: Mesh,
    images: ScoringImages,
    cost: str = "mi",
    epsilon: float = 0.01,
    max_iterations: int = 100_000,
    progress: ProgressFn | None = None,
    epsilon_pixels: float = 0.0,
    lookahead: bool = False,
) -> SearchResult:
    """Swap edges of ``mesh`` in place, best gain first, while the gain exceeds ``epsilon``.

    Algorithm 1 of the paper: score every edge that meets the swap preconditions; repeatedly
    swap the best one; after a swap re-score only the four outer edges of its quad (dropping
    those that no longer meet the preconditions); stop when no gain exceeds ``epsilon``. Ties
    are broken by the smaller edge, so the result is deterministic.

    One addition to the paper: an edge, once swapped away, is never created again. Quad gains
    are not differences of a global potential, so improving swaps can cycle (the five
    triangulations of a convex pentagon, each swap with a positive local gain, was seen with NCC);
    with this rule every swap retires an edge for good and the search ends after at most as many
    swaps as there are vertex pairs.

    Parameters
    ----------
    mesh : Mesh
        Modified in place.
    images : ScoringImages
        Prepared images.
    cost : {"mi", "ncc"}
        Ranking measure: NMI (the paper) or NCC.
    epsilon : float
        Minimum gain of an accepted swap (NMI or NCC units).
    max_iterations : int
        Upper bound on accepted swaps.
    progress : callable, optional
        Called with a fraction in [0, 1]; it may raise to abort the search.
    epsilon_pixels : float
        With a positive value the threshold follows each quad's size
        (:func:`gain_thresholds`) and swaps go in order of their gain over it; 0 is the paper's
        one ``epsilon`` for every quad, best gain first.
    lookahead : bool
        When no single swap is worth taking, also try pairs: swap an edge, then one of the four
        edges of its quad, and keep both if the pentagon of the three triangles they change
        gains more than its threshold (a gain no single swap shows, e.g. a diagonal that must
        turn twice to reach a crease). The search then goes on with single swaps.
    """
    t0 = time.perf_counter()
    current = [_triple(mesh.triangle(s)) for s in mesh.slots()]
    first = mesh.swappable_quads()
    candidates = [(i, j) for i, j in first[:, :2].tolist()]
    # Room for every triangle of the first pass and a few swaps' worth of new ones.
    capacity = len(current) + 2 * len(candidates) + 256
    cache = TriangleCache(
        images, mesh, with_moments=COSTS[cost].needs_moments, capacity=capacity
    )
    scorer = QuadScorer(cache, cost)
    cache.ensure(current)

    def margins(quads: list[Quad] | np.ndarray) -> tuple[list[float], list[float]]:
        gains, pixels = scorer.quad_deltas(quads)
        if len(quads) > _NUMPY_BATCH:
            over = gains - gain_thresholds(pixels, epsilon, epsilon_pixels)
            return gains.tolist(), over.tolist()
        listed = gains.tolist()
        return listed, [g - gain_threshold(n, epsilon, epsilon_pixels)
                        for g, n in zip(listed, pixels.tolist(), strict=True)]

    gains, over = margins(first)
    global_hist = cache.hist(current)
    mi, nmi = (float(v) for v in mutual_information(global_hist, images.bins))
    result = SearchResult(initial_mi=mi, initial_nmi=nmi, evaluations=len(candidates))

    retired: set[Edge] = set()

    def eligible(e: Edge) -> Quad | None:
        """The quad of ``e`` if it may be swapped, else None."""
        q = mesh.swappable_quad(e)
        if q is None or edge_key(q.k, q.l) in retired:
            return None
        return q

    # Keyed by the gain over the edge's threshold; the gain itself is what a step records.
    best: dict[Edge, float] = dict(zip(candidates, over, strict=True))
    gain: dict[Edge, float] = dict(zip(candidates, gains, strict=True))
    heap = [(-d, e) for e, d in best.items()]
    heapq.heapify(heap)
    # Edges of ``best`` over their threshold, counted as they change: the progress fraction
    # read it every 16 swaps, and a pass over ``best`` cost 5 % of the search (1139 vertices).
    positive = sum(d > 0.0 for d in over)
    stopped = "no swap raises the consistency by more than epsilon"
    if progress is not None:
        progress(0.0)
    # Accepted swaps, their SwapStep made at the end: the global histogram after every step is
    # a cumulative sum of the steps' changes, and its MI and NMI one batched call.
    taken: list[tuple[Edge, Edge, float, str, float]] = []
    moves: list[np.ndarray] = []  # cache rows of each step's quad: two removed, two added

    def move_hist(q: Quad) -> None:
        """Note the global histogram's change by swapping the quad (its triangles are cached)."""
        moves.append(cache.quad_rows([q])[0])

    def record(e: Edge, added: Edge, delta: float, move: str) -> None:
        if moved is not None:
            moved.update((*e, *added))
        taken.append((e, added, delta, move, time.perf_counter() - t0))

    def rescore(edges: Iterable[Edge]) -> None:
        nonlocal positive
        ring, quads = [], []
        for b in dict.fromkeys(edges):
            if best.pop(b, 0.0) > 0.0:
                positive -= 1
            q = eligible(b)
            if q is not None:
                ring.append(b)
                quads.append(q)
        for b, g, d in zip(ring, *margins(quads), strict=True):
            best[b] = d
            positive += d > 0.0
            gain[b] = g
            heapq.heappush(heap, (-d, b))
        result.evaluations += len(ring)

    moved: set[int] | None = None  # vertices of quads changed since the last pass of pairs
    # Triangles of a pair, as columns of its row (i, j, k, l, m, p, r, p', r'): the three
    # before, (i, j, k), (i, j, l), (p, r, m), and the three after, (k, l, p'), (r', m, p),
    # (r', m, r).
    pair_triangles = np.array([[0, 1, 2], [0, 1, 3], [5, 6, 4], [2, 3, 7], [8, 4, 5], [8, 4, 6]])

    def take_pair() -> bool:
        """One pass of pair moves; True if any was taken. After the first pass over the whole
        mesh, only edges touching a quad changed since the previous pass are tried again."""
        nonlocal moved
        pairs = pair_moves(mesh, None, retired, near=moved)
        moved = set()
        if len(pairs) == 0:
            return False
        rows = cache.lookup(pairs[:, pair_triangles]).reshape(-1, 2, 3)  # before/after
        bins = cache.bins
        if scorer.cost.summed is not None:
            value, counts = scorer.cost.summed(cache.table, rows, bins)
            pair_gain = value[:, 1] - value[:, 0]
            pixels = counts[:, 0]
        else:
            pair_gain = np.empty(len(rows))
            pixels = np.empty(len(rows))
            for start in range(0, len(rows), PAIR_BLOCK):
                # Bounded memory: the six histograms of a pair are gathered.
                block = rows[start:start + PAIR_BLOCK]
                h = cache.hist_rows(block).sum(axis=2)
                m = cache.moment_rows(block).sum(axis=2) if scorer.cost.needs_moments else None
                value = scorer.cost.measure(h, m, bins)  # before and after in one call
                pair_gain[start:start + len(block)] = value[:, 1] - value[:, 0]
                pixels[start:start + len(block)] = h[:, 0].sum(axis=1)
        over_t = pair_gain - gain_thresholds(pixels, epsilon, epsilon_pixels)
        result.evaluations += len(pairs)
        touched: set[int] = set()
        any_taken = False
        for n in np.argsort(-over_t, kind="stable"):
            if over_t[n] <= 0.0 or len(taken) + 2 > max_iterations:
                break
            i, j, k, ll, m_, p, r, _, r2 = pairs[n].tolist()
            if touched & {i, j, k, ll, m_}:
                continue  # scored on a mesh that has changed around it since
            e, b = edge_key(i, j), edge_key(p, r)
            q = mesh.quad(e)
            added = mesh.swap(e, check=False)
            qb = mesh.quad(b)
            if {qb.k, qb.l} != {r2, m_} or eligible(b) is None:
                mesh.swap(added, check=False)  # the pair's second swap is not there: undo
                continue
            move_hist(q)
            retired.add(e)
            delta = float(pair_gain[n])
            record(e, added, delta, "pair")
            move_hist(qb)
            added_b = mesh.swap(b, check=False)
            retired.add(b)
            record(b, added_b, delta, "pair")
            touched.update((i, j, k, ll, m_))
            rescore([*q.boundary, *qb.boundary])
            any_taken = True
        return any_taken

    while True:
        while heap and best.get(heap[0][1]) != -heap[0][0]:
            heapq.heappop(heap)
        if not heap or -heap[0][0] <= 0.0:
            if lookahead and take_pair():
                continue
            break
        if len(taken) >= max_iterations:
            stopped = "max_iterations reached"
            break
        _, e = heapq.heappop(heap)
        del best[e]
        positive -= 1  # it was the best, over its threshold
        q = eligible(e)
        if q is None:
            # A swap elsewhere created, or retired, the edge this one would add.
            continue
        move_hist(q)
        added = mesh.swap(e, check=False)
        retired.add(e)
        record(e, added, gain[e], "swap")
        rescore(q.boundary)
        if progress is not None and len(taken) % 16 == 0:
            progress(len(taken) / (len(taken) + positive))
    if taken:
        r = np.array(moves)
        table = cache.table
        change = table[r[:, 2]].astype(np.int64) + table[r[:, 3]] - table[r[:, 0]] - table[r[:, 1]]
        snapshots = global_hist + np.cumsum(change, axis=0)
        global_hist = snapshots[-1]
        step_mi, step_nmi = mutual_information(snapshots, images.bins)
        for n, ((e, added, delta, move, elapsed), mi_n, nmi_n) in enumerate(
            zip(taken, step_mi.tolist(), step_nmi.tolist(), strict=True)
        ):
            result.steps.append(SwapStep(iteration=n + 1, removed=e, added=added, delta=delta,
                                         mi=mi_n, nmi=nmi_n, elapsed_s=elapsed, move=move))
    result.final_mi, result.final_nmi = (
        float(v) for v in mutual_information(global_hist, images.bins))
    result.histogram = global_hist
    result.stopped_because = stopped
    return result
