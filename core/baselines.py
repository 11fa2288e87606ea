"""The two mesh optimizers the paper compares against (its Table 1), as selectable optimizers.

Both change only the connectivity of the mesh by edge swaps that meet the paper's
preconditions (:meth:`core.mesh.Mesh.can_swap`: internal edge, new edge absent, quad strictly
convex in both images, no patch reversal), and both return a :class:`core.optimize.SearchResult`
whose steps carry the global MI (bits) and NMI of the whole mesh after each accepted swap, so the
convergence record is the same for every optimizer. Neither uses ``options.cost`` or
``options.epsilon`` (NMI/NCC units); each has its own criterion, below.

``morris-kanade`` -- Morris & Kanade, "Image-Consistent Surface Triangulation", CVPR 2000
    Greedy edge swaps driven by a global cost: the sum of squared differences (SSD) between the
    reference image and the registered moving image over every pixel of the mesh, grey levels
    scaled to [0, 1]. At each step *every* edge meeting the preconditions is evaluated by the
    change its swap makes to the global SSD, and the swap with the largest decrease is taken
    (ties: smaller edge). The search stops when the largest decrease is at most
    :data:`MK_RELATIVE_DECREASE` times the current global SSD (the role of the paper's epsilon,
    here a relative decrease of the global cost), or at ``max_iterations``.

    How the global SSD change is computed: the SSD is a sum over pixels and, by the fill rule of
    :mod:`core.raster`, a swap leaves the set of mesh pixels unchanged and re-maps only the
    pixels of its quad, so ``SSD_global(after) - SSD_global(before)`` equals the change of the
    quad's SSD exactly (up to floating-point rounding; the test suite checks it against a full
    re-rendering of the mesh). Each triangle's moments (:data:`core.similarity.MOMENTS`) are
    computed once and cached (:class:`core.optimize.TriangleCache`), so the decision is the one a
    full re-rendering would give, without re-rendering. What remains of the original's global
    character is that every candidate is re-evaluated after every swap (O(edges) per step, not
    Algorithm 1's four boundary edges). The prohibitive run times the paper reports for many
    edges presumably came from recomputing the global cost per candidate by re-rendering, which
    this implementation does not do: its times are not comparable with the paper's.

``nakatuji`` -- Nakatuji, Sugaya & Kanatani, "Mesh Optimization using an Inconsistency
Detection Template", ICCV 2005
    Random search with a local, template-based inconsistency measure. For an internal edge
    ``{i, j}`` with opposite vertices ``k`` and ``l``, the two triangles of its quad are mapped,
    in each image and by their own affine maps, onto the two halves of a fixed-size square
    template of :data:`TEMPLATE_SIZE` x :data:`TEMPLATE_SIZE` samples whose diagonal is the
    edge (``i`` and ``j`` on opposite corners, ``k`` and ``l`` on the other two). The two
    template images (reference and moving luminance, bilinear samples) are correlated; the
    *inconsistency* of the configuration is ``1 - NCC`` in [0, 2] (0 when the two images agree
    up to a gain and an offset). An edge is swapped when the swapped
    configuration (diagonal ``{k, l}``) is strictly less inconsistent, with no threshold.
    The search visits the edges in a random order (``numpy.random.default_rng(options.seed)``,
    a fresh permutation of the current internal edges at each pass) and stops after a whole pass
    without a swap (every edge then tested on the final mesh), after ``max_iterations``
    accepted swaps, or after :data:`NAKATUJI_MAX_PASSES` passes.

Deviations from the original papers (neither paper is available to this project; the
descriptions above follow sections 2 and 5 of Arévalo & González, JMIV 2010, and what is
generally known of each method)
    * Both: the meshes are 2-D conjugate meshes in the two images (the paper's setting), not
      3-D meshes projected into calibrated views; the "texture" of a triangle is the moving image
      mapped through its affine map, so image consistency is measured between the reference and
      the registered moving image only (two views).
    * Both: the swap preconditions are this project's (exact, in both images), which also forbid
      swaps creating patch reversals.
    * Morris-Kanade: the global SSD change is computed from cached per-triangle moments
      (identical decisions, see above) instead of re-rendering; the stopping rule is a relative
      decrease of the global SSD (:data:`MK_RELATIVE_DECREASE`); plain greedy descent to a
      local minimum, nothing to escape it.
    * Nakatuji: the exact template shape, size and correlation of the original are not known
      here; this implementation maps each quad onto a 32 x 32 square (the edge as its
      diagonal), correlates the two images' template patches by NCC, and takes ``1 - NCC``
      as the inconsistency. The random search draws edges as random permutations (passes)
      rather than independent draws, so that it terminates when a full pass changes nothing;
      inconsistencies are cached per quad configuration (a configuration is scored once).
      No threshold (a swap needs a strictly lower inconsistency). Anything else the original
      did beyond the edge swaps (e.g. a treatment of occluding edges) is not implemented.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import cv2
import numpy as np

from pwlreg.core.mesh import Edge, Mesh, edge_key
from pwlreg.core.optimize import SearchResult, SwapStep, TriangleCache, quad_triples
from pwlreg.core.similarity import ScoringImages, mutual_information, ssd

ProgressFn = Callable[[float], None]

MK_RELATIVE_DECREASE = 1e-4
"""Morris-Kanade stops when the best swap lowers the global SSD by at most this fraction of it.

A convergence tolerance of the global cost (0.01 %), not a noise filter. Measured on the
synthetic scenes (``python -m bench.quality --mk-threshold``, 0.3 px point noise): swaps between
two 3-D compatible diagonals change the global SSD by -1.9 % to +1.9 % (1st-99th percentile)
without radiometric change and by -0.12 % to +0.10 % with a lighting change, because vertex noise
makes the triangulations of a plane differ, while swaps repairing an incompatible edge lower it by
a median 1.3 % (0.3 % with lighting), a tenth of them by less than 0.11 % (with lighting a tenth
do not lower it at all). A threshold above the planar spread would block most repairs, so the
search descends until no swap improves the global cost noticeably.
"""

TEMPLATE_SIZE = 32
"""Side (samples) of the square template of the Nakatuji-Sugaya-Kanatani baseline."""

NAKATUJI_MAX_PASSES = 50
"""Upper bound on the random passes over the edges (bounds the run time)."""

_QUAD_CHUNK = 4096


# --------------------------------------------------------------------------------------------
# Shared bookkeeping: global MI after each swap
# --------------------------------------------------------------------------------------------


class _GlobalRecord:
    """Global joint histogram (and moments) of the current mesh, updated swap by swap."""

    def __init__(self, cache: TriangleCache, mesh: Mesh) -> None:
        self.cache = cache
        current = [tuple(sorted(mesh.triangle(s))) for s in mesh.slots()]
        cache.ensure(current)
        rows = cache.rows(current)
        self.hist = cache.hist_rows(rows).sum(axis=0)
        self.moments = cache.moment_rows(rows).sum(axis=0) if cache.with_moments else None

    def mi(self) -> tuple[float, float]:
        mi, nmi = mutual_information(self.hist, self.cache.bins)
        return float(mi), float(nmi)

    def swap(self, mesh: Mesh, e: Edge) -> Edge:
        """Swap ``e`` (preconditions already checked) and update the global statistics."""
        old0, old1, new0, new1 = quad_triples(mesh.quad(e), mesh)
        self.cache.ensure((new0, new1))
        added = mesh.swap(e, check=False)
        old = self.cache.rows((old0, old1))
        new = self.cache.rows((new0, new1))
        self.hist = self.hist - self.cache.hist_rows(old).sum(0) + self.cache.hist_rows(new).sum(0)
        if self.moments is not None:
            self.moments = (
                self.moments
                - self.cache.moment_rows(old).sum(0)
                + self.cache.moment_rows(new).sum(0)
            )
        return added


# --------------------------------------------------------------------------------------------
# Morris & Kanade: greedy descent of the global SSD
# --------------------------------------------------------------------------------------------


def ssd_swap_changes(mesh: Mesh, cache: TriangleCache, edges: list[Edge]) -> np.ndarray:
    """Change of the global SSD if each edge were swapped (negative = better).

    Parameters
    ----------
    mesh : Mesh
    cache : TriangleCache
        Built with ``with_moments=True``.
    edges : list of Edge
        Internal edges.

    Returns
    -------
    ndarray of float64, shape (len(edges),)
        ``SSD(after) - SSD(before)`` in squared grey levels scaled to [0, 1] (summed over
        pixels). Equal to the change of the whole mesh's SSD: only the quad's pixels change.
    """
    if not edges:
        return np.zeros(0)
    quads = [quad_triples(mesh.quad(e), mesh) for e in edges]
    cache.ensure(t for q in quads for t in q)
    rows = cache.rows(t for q in quads for t in q).reshape(-1, 4)
    per_triangle = ssd(cache.moment_rows(rows))  # (E, 4): SSD is additive over triangles
    return (per_triangle[:, 2] + per_triangle[:, 3]) - (per_triangle[:, 0] + per_triangle[:, 1])


def morris_kanade_search(
    mesh: Mesh,
    images: ScoringImages,
    relative_decrease: float = MK_RELATIVE_DECREASE,
    max_iterations: int = 100_000,
    progress: ProgressFn | None = None,
) -> SearchResult:
    """Greedy edge swaps that minimize the SSD of the whole registered image (Morris & Kanade).

    At each step every edge meeting the swap preconditions is evaluated by the change of the
    global SSD (reference against registered moving image over all mesh pixels, grey levels
    in [0, 1]) and the swap with the largest decrease is applied; the search stops when that
    decrease is at most ``relative_decrease`` times the current global SSD.

    Parameters
    ----------
    mesh : Mesh
        Modified in place.
    images : ScoringImages
        Prepared images.
    relative_decrease : float
        Stopping threshold, a fraction of the current global SSD (dimensionless).
    max_iterations : int
        Upper bound on accepted swaps.
    progress : callable, optional
        Called with a fraction in [0, 1] after every step; it may raise to abort.

    Returns
    -------
    SearchResult
        ``SwapStep.delta`` is the decrease of the global SSD (squared [0, 1] grey levels summed
        over pixels, positive); ``mi``/``nmi`` the global MI (bits) and NMI after the swap.
    """
    t0 = time.perf_counter()
    cache = TriangleCache(images, mesh, with_moments=True)
    record = _GlobalRecord(cache, mesh)
    mi, nmi = record.mi()
    result = SearchResult(initial_mi=mi, initial_nmi=nmi)
    stopped = "no swap lowers the global SSD by more than the relative threshold"
    if progress is not None:
        progress(0.0)
    while True:
        candidates = [e for e in mesh.internal_edges() if mesh.can_swap(e)]
        if not candidates:
            stopped = "no edge can be swapped"
            break
        changes = ssd_swap_changes(mesh, cache, candidates)
        result.evaluations += len(candidates)
        total = float(ssd(record.moments))
        limit = -relative_decrease * total
        best = int(np.argmin(changes))  # first minimum: candidates are sorted, ties -> smaller
        if not changes[best] < limit:
            break
        if len(result.steps) >= max_iterations:
            stopped = "max_iterations reached"
            break
        e = candidates[best]
        added = record.swap(mesh, e)
        mi, nmi = record.mi()
        result.steps.append(
            SwapStep(
                iteration=len(result.steps) + 1,
                removed=e,
                added=added,
                delta=float(-changes[best]),
                mi=mi,
                nmi=nmi,
                elapsed_s=time.perf_counter() - t0,
            )
        )
        if progress is not None:
            remaining = int(np.count_nonzero(changes < limit)) - 1
            progress(len(result.steps) / (len(result.steps) + max(remaining, 0) + 1))
    result.final_mi, result.final_nmi = mi, nmi
    result.stopped_because = stopped
    return result


# --------------------------------------------------------------------------------------------
# Nakatuji, Sugaya & Kanatani: random search with a template-based inconsistency
# --------------------------------------------------------------------------------------------


def _template_grid(size: int) -> tuple[np.ndarray, np.ndarray]:
    """Barycentric weights of the template samples in its two triangles.

    The template is the unit square with corners ``a = (0, 0)``, ``b = (1, 1)`` (the diagonal,
    the edge), ``c = (1, 0)`` and ``d = (0, 1)``; samples sit at the centres of a
    ``size x size`` grid. Samples with ``u >= v`` belong to triangle ``(a, b, c)``, the others
    to ``(a, b, d)`` (on the diagonal both maps agree).

    Returns
    -------
    first : ndarray of bool, shape (size * size,)
        Sample lies in triangle ``(a, b, c)``.
    weights : ndarray of float64, shape (size * size, 3)
        Weights of ``(a, b, c)`` or of ``(a, b, d)``, whichever holds the sample.
    """
    t = (np.arange(size) + 0.5) / size
    u, v = np.meshgrid(t, t)
    u, v = u.ravel(), v.ravel()
    first = u >= v
    # In (a, b, c): p = a + s (b - a) + r (c - a) with b - a = (1, 1), c - a = (1, 0).
    # In (a, b, d): d - a = (0, 1).
    s = np.where(first, v, u)
    r = np.where(first, u - v, v - u)
    weights = np.stack([1.0 - s - r, s, r], axis=1)
    return first, weights


class TemplateScorer:
    """Template inconsistency of quad configurations (Nakatuji et al.), images prepared once.

    Parameters
    ----------
    images : ScoringImages
        Prepared images; their luminance is resampled as float32 (NCC ignores the scale).
    mesh : Mesh
        Supplies the vertex coordinates (they never change).
    size : int
        Template side in samples.
    """

    def __init__(self, images: ScoringImages, mesh: Mesh, size: int = TEMPLATE_SIZE) -> None:
        self.reference = np.asarray(images.reference_values, dtype=np.float32).reshape(images.shape)
        self.moving = np.asarray(images.moving, dtype=np.float32)
        self.vertices = (mesh.reference, mesh.moving)
        self.first, self.weights = _template_grid(size)

    def inconsistency(self, configurations: list[tuple[int, int, int, int]]) -> np.ndarray:
        """``1 - NCC`` of the two images' template patches of each configuration.

        Parameters
        ----------
        configurations : list of (i, j, k, l)
            Quads triangulated by the diagonal ``{i, j}`` into ``(i, j, k)`` and ``(i, j, l)``.

        Returns
        -------
        ndarray of float64, shape (len(configurations),)
            In [0, 2]; 1 when either patch is flat (no variance).
        """
        quads = np.asarray(configurations, dtype=np.int64).reshape(-1, 4)
        out = np.empty(len(quads))
        w = self.weights
        for lo in range(0, len(quads), _QUAD_CHUNK):
            chunk = quads[lo : lo + _QUAD_CHUNK]
            # Vertices of the triangle holding each sample: (i, j, k) or (i, j, l).
            third = np.where(self.first[None, :], chunk[:, 2:3], chunk[:, 3:4])  # (Q, S)
            patches = []
            for verts, image in zip(self.vertices, (self.reference, self.moving), strict=True):
                a = verts[chunk[:, 0]][:, None, :]
                b = verts[chunk[:, 1]][:, None, :]
                c = verts[third]
                xy = w[None, :, 0:1] * a + w[None, :, 1:2] * b + w[None, :, 2:3] * c
                # One row of samples per quad: both sides stay below remap's 32767 limit.
                values = cv2.remap(
                    image,
                    np.ascontiguousarray(xy[:, :, 0], dtype=np.float32),
                    np.ascontiguousarray(xy[:, :, 1], dtype=np.float32),
                    cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REPLICATE,
                )
                patches.append(values.astype(np.float64))
            pa, pb = patches
            pa = pa - pa.mean(axis=1, keepdims=True)
            pb = pb - pb.mean(axis=1, keepdims=True)
            num = (pa * pb).sum(axis=1)
            den = np.sqrt((pa * pa).sum(axis=1) * (pb * pb).sum(axis=1))
            corr = np.where(den > 1e-12, num / np.where(den > 1e-12, den, 1.0), 0.0)
            out[lo : lo + len(chunk)] = 1.0 - corr
        return out


def quad_inconsistency(
    images: ScoringImages,
    mesh: Mesh,
    configurations: list[tuple[int, int, int, int]],
    size: int = TEMPLATE_SIZE,
) -> np.ndarray:
    """Template inconsistency ``1 - NCC`` of quad configurations (Nakatuji et al.).

    Parameters
    ----------
    images : ScoringImages
        Prepared images.
    mesh : Mesh
        Supplies the vertex coordinates.
    configurations : list of (i, j, k, l)
        Quads triangulated by the diagonal ``{i, j}`` into ``(i, j, k)`` and ``(i, j, l)``.
    size : int
        Template side in samples.

    Returns
    -------
    ndarray of float64, shape (len(configurations),)
        ``1 - NCC`` of the reference and moving template patches, in [0, 2]; 1 when either
        patch is flat (no variance). See :class:`TemplateScorer` to score many batches.
    """
    if not configurations:
        return np.zeros(0)
    return TemplateScorer(images, mesh, size).inconsistency(configurations)


def _configuration(i: int, j: int, k: int, m: int) -> tuple[int, int, int, int]:
    """Canonical key of a quad triangulated by diagonal ``{i, j}`` (other corners ``k, m``)."""
    i, j = edge_key(i, j)
    k, m = edge_key(k, m)
    return (i, j, k, m)


def nakatuji_search(
    mesh: Mesh,
    images: ScoringImages,
    seed: int = 0,
    template_size: int = TEMPLATE_SIZE,
    max_passes: int = NAKATUJI_MAX_PASSES,
    max_iterations: int = 100_000,
    progress: ProgressFn | None = None,
) -> SearchResult:
    """Random edge-swap search with the template inconsistency (Nakatuji, Sugaya & Kanatani).

    Edges are visited in random order, pass after pass; an edge meeting the swap preconditions
    is swapped when its swapped quad is strictly less inconsistent
    (:func:`quad_inconsistency`). The search ends after a pass without a swap.

    Parameters
    ----------
    mesh : Mesh
        Modified in place.
    images : ScoringImages
        Prepared images.
    seed : int
        Seed of the random order; the same inputs and seed give the same result.
    template_size : int
        Template side in samples.
    max_passes : int
        Upper bound on the passes over the edges.
    max_iterations : int
        Upper bound on accepted swaps.
    progress : callable, optional
        Called with a fraction in [0, 1] every 32 tested edges; it may raise to abort.

    Returns
    -------
    SearchResult
        ``SwapStep.delta`` is the decrease of the inconsistency ``1 - NCC`` (dimensionless);
        ``mi``/``nmi`` the global MI (bits) and NMI after the swap; ``evaluations`` counts the
        tested edges.
    """
    t0 = time.perf_counter()
    rng = np.random.default_rng(seed)
    record = _GlobalRecord(TriangleCache(images, mesh), mesh)
    mi, nmi = record.mi()
    result = SearchResult(initial_mi=mi, initial_nmi=nmi)
    scorer = TemplateScorer(images, mesh, template_size)
    scores: dict[tuple[int, int, int, int], float] = {}

    def score(keys: list[tuple[int, int, int, int]]) -> list[float]:
        missing = [c for c in dict.fromkeys(keys) if c not in scores]
        if missing:
            values = scorer.inconsistency(missing)
            scores.update(zip(missing, values.tolist(), strict=True))
        return [scores[c] for c in keys]

    stopped = f"max_passes ({max_passes}) reached"
    if progress is not None:
        progress(0.0)
    done = False
    for pass_index in range(max_passes):
        order = mesh.internal_edges()
        perm = rng.permutation(len(order))
        swapped = False
        for position, idx in enumerate(perm.tolist()):
            e = order[idx]
            if not mesh.can_swap(e):
                continue
            q = mesh.quad(e)
            before, after = score(
                [_configuration(q.i, q.j, q.k, q.l), _configuration(q.k, q.l, q.i, q.j)]
            )
            result.evaluations += 1
            if progress is not None and result.evaluations % 32 == 0:
                x = pass_index + position / len(order)
                progress(x / (x + 1.0))
            if not after < before:
                continue
            if len(result.steps) >= max_iterations:
                stopped = "max_iterations reached"
                done = True
                break
            added = record.swap(mesh, e)
            swapped = True
            mi, nmi = record.mi()
            result.steps.append(
                SwapStep(
                    iteration=len(result.steps) + 1,
                    removed=e,
                    added=added,
                    delta=before - after,
                    mi=mi,
                    nmi=nmi,
                    elapsed_s=time.perf_counter() - t0,
                )
            )
        if done:
            break
        if not swapped:
            stopped = "a whole random pass over the edges found no less inconsistent swap"
            break
    result.final_mi, result.final_nmi = mi, nmi
    result.stopped_because = stopped
    return result
