"""Greedy edge-swap search driven by mutual information (the paper's Algorithm 1).

Every triangle the search looks at -- current ones and the two new triangles of each candidate
swap -- is rasterized and resampled once; its joint histogram (and moments) are cached under its
vertex triple. The consistency of a quad is then a sum of two cached rows, and the global
consistency after a swap an O(M^2) update.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import numpy as np

from pwlreg.core import kernels
from pwlreg.core.mesh import Edge, Mesh, Quad
from pwlreg.core.similarity import (
    ScoringImages,
    mutual_information,
    ncc,
    triangle_statistics,
    xlogx_table,
)

Triple = tuple[int, int, int]
ProgressFn = Callable[[float], None]

#: Bounds of a quad's threshold, in units of ``epsilon`` (:func:`gain_thresholds`). Below half
#: of it, large quads across an occluding edge took noise for gains (an automatic occluder
#: scene ended 8 % worse than Delaunay with 1/5; 1 % better with 1/2).
THRESHOLD_RANGE = (0.5, 5.0)


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
    """

    initial_mi: float
    initial_nmi: float
    final_mi: float = 0.0
    final_nmi: float = 0.0
    steps: list[SwapStep] = field(default_factory=list)
    stopped_because: str = ""
    evaluations: int = 0


def _triple(t: Iterable[int]) -> Triple:
    a, b, c = sorted(t)
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

    def quad_rows(self, quads: list[Quad]) -> np.ndarray:
        """Rows ``(E, 4)`` of each quad's two current and two swapped triangles (the order of
        :func:`quad_triples`), computed first where missing."""
        if len(quads) > _NUMPY_BATCH:
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
    ``compiled`` names the same measure in the compiled search
    (:func:`core.kernels.search_run`): ``"nmi"`` or ``"ncc"``.
    """

    needs_moments: bool
    measure: Callable[[np.ndarray, np.ndarray | None, int], np.ndarray]
    compiled: str


COSTS: dict[str, Cost] = {
    "mi": Cost(False, lambda hist, moments, bins: mutual_information(hist, bins)[1], "nmi"),
    "ncc": Cost(True, lambda hist, moments, bins: ncc(moments), "ncc"),
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
        if not edges:
            return np.zeros(0)
        rows = self.cache.quad_rows([mesh.quad(e) for e in edges])
        h = self.cache.hist_rows(rows)
        # Before (current triangles) and after (swapped) side by side: one measure call.
        sides = h[:, 0::2] + h[:, 1::2]
        m = None
        if self.cost.needs_moments:
            mo = self.cache.moment_rows(rows)
            m = mo[:, 0::2] + mo[:, 1::2]
        value = self.cost.measure(sides, m, self.cache.bins)
        return value[:, 1] - value[:, 0]


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


def compiled_mesh(mesh: Mesh) -> tuple:
    """The mesh as the compiled search holds it (:func:`core.kernels.search_run`): its
    triangles by slot, the owners of its edges, its fixed-point and float vertices, the
    slots' stamps (copies the search changes; :meth:`Mesh.take_triangles` takes them back)."""
    tris, stamps = mesh.slot_triangles()
    codes, owners, counts = mesh.edge_owners()
    if len(counts) and counts.max() > 2:
        n = len(mesh.reference)
        c = int(codes[np.argmax(counts)])
        raise ValueError(f"the search needs a manifold mesh: edge {(c // n, c % n)} has "
                         f"{counts.max()} triangles")
    return (tris, kernels.owners_dict(codes, owners), *mesh.fixed_arrays, len(mesh.reference),
            mesh.reference, mesh.moving, stamps)


def greedy_search(
    mesh: Mesh,
    images: ScoringImages,
    cost: str = "mi",
    epsilon: float = 0.01,
    max_iterations: int = 100_000,
    progress: ProgressFn | None = None,
    epsilon_pixels: float = 0.0,
    lookahead: bool = False,
    progress_interval: float = 0.05,
) -> SearchResult:
    """Swap edges of ``mesh`` in place, best gain first, while the gain exceeds ``epsilon``.

    Algorithm 1 of the paper: score every edge that meets the swap preconditions; repeatedly
    swap the best one; after a swap re-score only the four outer edges of its quad (dropping
    those that no longer meet the preconditions); stop when no gain exceeds ``epsilon``. Ties
    are broken by the smaller edge, so the result is deterministic. The search runs compiled
    (:func:`core.kernels.search_run`); the mesh takes its swaps at the end.

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
        Called with a fraction in [0, 1] at the start and then at most every
        ``progress_interval`` seconds of search, after a swap; it may raise to abort the search
        (the mesh is then left as it was).
    epsilon_pixels : float
        With a positive value the threshold follows each quad's size
        (:func:`gain_thresholds`) and swaps go in order of their gain over it; 0 is the paper's
        one ``epsilon`` for every quad, best gain first.
    lookahead : bool
        When no single swap is worth taking, also try pairs: swap an edge, then one of the four
        edges of its quad, and keep both if the pentagon of the three triangles they change
        gains more than its threshold (a gain no single swap shows, e.g. a diagonal that must
        turn twice to reach a crease). The search then goes on with single swaps.
    progress_interval : float
        Seconds of search between calls of ``progress`` at the least (0: after every swap).
        Each report leaves the compiled search, whose arguments numba types anew when it is
        entered again (about 0.7 ms on a 1024x768 registration); a cancellation waits at most
        this long.
    """
    t0 = time.perf_counter()
    if cost not in COSTS:
        raise ValueError(f"unknown cost {cost!r}; expected one of {sorted(COSTS)}")
    n = len(mesh.reference)
    if n > kernels.SEARCH_MAX_VERTICES:
        raise ValueError(f"the search takes meshes of at most {kernels.SEARCH_MAX_VERTICES} "
                         f"vertices, got {n}")
    bins = images.bins
    compiled = compiled_mesh(mesh)
    # Room for every triangle of the first pass and a few swaps' worth of new ones.
    capacity = 4 * mesh.n_triangles + 256
    with_moments = COSTS[cost].needs_moments
    hist_box = kernels.search_box(np.empty((capacity, bins * bins), dtype=np.int32))
    mom_box = kernels.search_box(np.empty((capacity if with_moments else 0, 6)))
    cache = (kernels.empty_index(), hist_box, mom_box,
             # 16-bit levels whatever the images' (the same values): one compiled search for
             # 8- and 16-bit images, not two (a cold numba cache compiles each for 20 s). The
             # reference's levels are read for the moments only (NCC).
             (images.reference_bins,
              images.reference_values.astype(np.uint16, copy=False) if with_moments
              else np.zeros(1, dtype=np.uint16),
              images.moving.astype(np.uint16, copy=False)),
             (int(images.shape[1]), int(images.shape[0]), int(bins),
              float(images.moving_bin_offset), float(images.moving_bin_scale),
              float(images.reference_scale), float(images.moving_scale)),
             COSTS[cost].compiled == "ncc", xlogx_table())
    low, high = THRESHOLD_RANGE
    search = (kernels.empty_scores(), kernels.empty_scores(), kernels.empty_heap(),
              kernels.empty_set(), float(epsilon), float(epsilon_pixels), float(low),
              float(high))
    state = kernels.search_state(int(compiled[7].max(initial=-1)) + 1)
    state[kernels.STATE_REPORT] = int(progress_interval * 1e6)
    global_hist = np.zeros(bins * bins, dtype=np.int64)
    kernels.search_start(compiled, cache, search, state, global_hist)
    mi, nmi = (float(v) for v in mutual_information(global_hist, bins))
    result = SearchResult(initial_mi=mi, initial_nmi=nmi)
    if progress is not None:
        progress(0.0)
    out = kernels.search_steps()
    moved = np.zeros(n, dtype=np.uint8)
    while kernels.search_run(compiled, cache, search, state, moved, int(max_iterations),
                             bool(lookahead),
                             -1.0 if progress is None else float(progress_interval), out, t0):
        taken = int(state[kernels.STATE_TAKEN])
        progress(taken / (taken + int(state[kernels.STATE_POSITIVE])))  # type: ignore[misc]
    mesh.take_triangles(compiled[0], compiled[7])
    steps = out[0][:int(state[kernels.STATE_TAKEN])]
    if len(steps):
        table = hist_box[0]
        r = steps[:, 5:].astype(np.int64)
        change = table[r[:, 2]].astype(np.int64) + table[r[:, 3]] - table[r[:, 0]] - table[r[:, 1]]
        snapshots = global_hist + np.cumsum(change, axis=0)
        global_hist = snapshots[-1]
        step_mi, step_nmi = mutual_information(snapshots, bins)
        for k, (row, mi_k, nmi_k) in enumerate(
            zip(steps[:, :5].tolist(), step_mi.tolist(), step_nmi.tolist(), strict=True)
        ):
            e, added, move, delta, elapsed = int(row[0]), int(row[1]), row[2], row[3], row[4]
            result.steps.append(SwapStep(
                iteration=k + 1, removed=(e // n, e % n), added=(added // n, added % n),
                delta=delta, mi=mi_k, nmi=nmi_k, elapsed_s=elapsed,
                move="pair" if move else "swap"))
    result.final_mi, result.final_nmi = (float(v) for v in mutual_information(global_hist, bins))
    result.evaluations = int(state[kernels.STATE_EVALUATIONS])
    result.stopped_because = kernels.SEARCH_STOPS[int(state[kernels.STATE_STOPPED])]
    return result
