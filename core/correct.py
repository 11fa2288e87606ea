"""Vertex moves after the swaps: a measured vertex that the images contradict moves with a
neighbour (:func:`contradicted_vertices`, the move ``correct``); an extrapolated border vertex
is searched for along its epipolar line (:func:`border_search`, the move ``border``); after
the alignment (:func:`aligned_vertices`, ``align``), a vertex whose star the images score
higher without it leaves the mesh (:func:`removed_vertices`, ``remove``). They score a vertex
by its star and accept a candidate by the same rule.

A corner where a foreground edge crosses the background (a T-junction) looks the same in both
images but belongs to neither surface: the matcher pairs it with the foreground's motion while
the point itself is background, and its neighbourhood agrees with it on one side. Insertion
cannot fix such a vertex and the swaps cannot move it. Where a vertex's displacement differs
from a neighbour's by more than :data:`SUSPECT_PX`, the triangles around it (its *star*) are
scored with the vertex moving as its neighbours do (a displacement at least :data:`SUPPORT` of
them share, within :data:`REACH` of its mean edge); when the best of these raises the star's
consistency (the swaps' cost: normalized mutual information by default) by more than
:data:`GAIN_FACTOR` times the swaps' threshold for that many pixels
(:func:`core.optimize.gain_thresholds`), and folds none of its triangles, the vertex takes it;
no two neighbours move in one pass.

Judged on Middlebury's truth the move is not always right about the vertex itself: of its 22
moves there (both extents), 10 took a vertex more than 3 px off to within 3 px and 6 took one
within 3 px beyond it (4 of these beside a depth step, whose star reaches over the step and
gains by following the other surface); the mean error fell on every pair all the same.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import sparse

from pwlreg.core.epipolar import epipolar_lines, line_direction, line_foot, on_level
from pwlreg.core.optimize import COSTS, Cost, gain_thresholds
from pwlreg.core.raster import orientation
from pwlreg.core.similarity import (
    ScoringImages,
    from_level,
    group_statistics,
    to_level,
    triangle_statistics,
)

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

#: The border search (:func:`border_search`): the segment of the epipolar line its
#: extrapolations span is searched over three times its length and BORDER_MARGIN px more at
#: both ends; in BORDER_COARSE steps either side of its middle first (4: teddy's frame 1.157
#: px against 1.146); BORDER_PASSES passes (3: 1.145).
#: Searched over half the vertex's mean edge whatever the extrapolations, Middlebury teddy's
#: frame came to 1.136 px instead of 1.145, but on the planar Oxford pairs right vertices
#: moved 2-15 px (Leuven's frame 0.522 -> 0.586 px against its homography).
BORDER_MARGIN = 2.0
BORDER_COARSE = 6
BORDER_PASSES = 2

#: The names of the moves in :data:`core.moves.MOVES`.
MOVE = "correct"
BORDER_MOVE = "border"
ALIGN_MOVE = "align"
REMOVE_MOVE = "remove"

#: Candidate displacements are taken once per cell of this side (px): neighbours moving
#: alike propose one candidate, not several.
DISTINCT_PX = 0.5


@dataclass(frozen=True)
class Corrections:
    """The vertices a vertex move (:func:`contradicted_vertices`, :func:`border_search`) moves.

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
        Vertices scored: those with a candidate left after the move's rules (for the border
        search, a candidate inside the moving image).
    moves : tuple of str
        The move of each (its name in :data:`core.moves.MOVES`).
    """

    vertices: np.ndarray
    moving: np.ndarray
    before: np.ndarray
    gains: np.ndarray
    tested: int
    moves: tuple[str, ...]

    @classmethod
    def none(cls) -> Corrections:
        """No vertex moved."""
        return cls(np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), 0, ())

    def __add__(self, other: Corrections) -> Corrections:
        """Both moves' vertices (each moved by one of them), in vertex order."""
        order = np.argsort(np.concatenate([self.vertices, other.vertices]), kind="stable")
        moves = self.moves + other.moves
        return Corrections(
            *(np.concatenate([a, b])[order] for a, b in (
                (self.vertices, other.vertices), (self.moving, other.moving),
                (self.before, other.before), (self.gains, other.gains))),
            self.tested + other.tested, tuple(moves[i] for i in order))

    def to_list(self) -> list[dict]:
        """One record per moved vertex (``mesh.json`` and ``convergence.json``)."""
        return [{"vertex": int(v), "from": [float(a) for a in b], "to": [float(a) for a in m],
                 "gain": round(float(g), 6), "move": name}
                for v, b, m, g, name in zip(self.vertices, self.before, self.moving, self.gains,
                                            self.moves, strict=True)]


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
    none = Corrections.none()
    if not len(tris):
        return none
    a, b, around, edge = _neighbours(ref_v, tris)
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

    gain, threshold = _star_gains(images, ref_v, mov_v, tris, cand_v, cand_m,
                                  stars=_stars(tris, n), cost=cost, epsilon=epsilon,
                                  epsilon_pixels=epsilon_pixels)
    chosen = _best(cand_v, gain) & (gain > threshold)
    verts, moves, gains = cand_v[chosen], cand_m[chosen], gain[chosen]
    keep = _independent(verts, gains, (b, around), n)
    verts = verts[keep]
    return Corrections(verts, moves[keep], mov_v[verts], gains[keep], len(tested),
                       (MOVE,) * len(verts))


def aligned_vertices(
    images: ScoringImages,
    reference_vertices: np.ndarray,
    moving_vertices: np.ndarray,
    aligned: np.ndarray,
    triangles: np.ndarray,
    *,
    cost: str = "mi",
    scale: float = 1.0,
) -> Corrections:
    """The vertices that keep the position the photometric alignment gave them
    (:func:`core.align.align_vertices`, the move ``align``).

    The alignment fits one gain and bias per triangle, which a tone curve or a surface the
    triangle does not follow bends; the swaps' cost scores by the joint histogram. Each moved
    vertex's star (its triangles) is scored with every vertex where the alignment put it and
    with every vertex where it was: where the star's consistency falls, the vertex goes back.
    No gain over the swaps' threshold is asked (asking half or all of the correct move's
    threshold lost a third to a half of Middlebury's gain). Vertices of a triangle the kept
    moves fold go back too, until none folds. On the synthetic scenes of seeds 0-1 without
    points, aligning every vertex without this made six scenes more than 2 % worse than
    Delaunay; with it, none that was not already.

    Parameters
    ----------
    images : ScoringImages
        The scoring images (:func:`core.similarity.prepare_images`).
    reference_vertices, moving_vertices : ndarray, shape (N, 2)
        The mesh's vertices before the alignment (pixels).
    aligned : ndarray, shape (N, 2)
        The moving positions the alignment proposes.
    triangles : ndarray of int, shape (T, 3)
        The mesh's triangles.
    cost : str, optional
        The swaps' consistency measure, an entry of :data:`core.optimize.COSTS`.
    scale : float, optional
        ``images`` are reduced by it (:func:`core.similarity.reduced`); the vertices are in
        pixels of the full images.

    Returns
    -------
    Corrections
        In vertex order, each with the gain of its star.
    """
    ref_v = np.asarray(reference_vertices, dtype=np.float64)
    before = np.asarray(moving_vertices, dtype=np.float64)
    after = np.asarray(aligned, dtype=np.float64).copy()
    tris = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    moved = np.flatnonzero((after != before).any(axis=1))
    if not len(moved) or not len(tris):
        return Corrections.none()
    # Each triangle scored once before and once after; a vertex's star sums its triangles'
    # histograms (scoring each star with its vertex put back took 17 ms on a 1024 x 768 city,
    # this 5 ms).
    measure = COSTS[cost]
    star, start = _stars(tris, len(ref_v))
    owner, k = _ragged(start[moved], start[moved + 1] - start[moved])
    value = []
    for mov in (before, after):
        hist, moments = triangle_statistics(images, to_level(ref_v[tris], scale),
                                            to_level(mov[tris], scale),
                                            with_moments=measure.needs_moments)
        value.append(measure.measure(
            _group_sums(hist, owner, len(moved), star[k]),
            None if moments is None else _group_sums(moments, owner, len(moved), star[k]),
            images.bins))
    gain = value[1] - value[0]
    after[moved[gain < 0.0]] = before[moved[gain < 0.0]]
    ref_orient = orientation(*ref_v[tris].transpose(1, 0, 2))
    while True:
        folded = orientation(*after[tris].transpose(1, 0, 2)) != ref_orient
        reset = np.unique(tris[folded])
        reset = reset[(after[reset] != before[reset]).any(axis=1)]
        if not len(reset):
            break
        after[reset] = before[reset]
    kept = moved[(after[moved] != before[moved]).any(axis=1)]
    return Corrections(kept, after[kept], before[kept], gain[np.searchsorted(moved, kept)],
                       len(moved), (ALIGN_MOVE,) * len(kept))


def removed_vertices(
    images: ScoringImages,
    reference_vertices: np.ndarray,
    moving_vertices: np.ndarray,
    triangles: np.ndarray,
    removable: np.ndarray,
    *,
    epsilon: float,
    epsilon_pixels: float,
    cost: str = "mi",
    scale: float = 1.0,
) -> tuple[Corrections, np.ndarray]:
    """The ``removable`` inner vertices whose star the images score higher without them (the
    move ``remove``), and the triangles without them.

    The images judge a vertex's triangles, not its position: a T-junction matches no surface
    wherever it goes, and a right vertex whose triangles reach over a depth step maps the other
    surface wrong (of the 59 vertices removed on the trust suite's seeds 0-1, 57 were within
    3 px of their truth; their errors still fell).
    Each inner vertex's star (a polygon around it) is scored as it is and triangulated without
    the vertex by each fan from one of the polygon's corners that folds in neither image; when
    the best of these raises the star's consistency (the swaps' cost) by more than
    :data:`GAIN_FACTOR` times the swaps' threshold for its pixels, the vertex leaves the mesh
    (it stays in the vertex list, in no triangle) and the fan takes its place; no two
    neighbours in one pass. The star's pixels stay the same, so the mesh's extent does not
    change.

    Parameters
    ----------
    images : ScoringImages
        The scoring images, reduced by ``scale`` (:func:`core.similarity.reduced`).
    reference_vertices, moving_vertices : ndarray, shape (N, 2)
        The mesh's vertices in both images (pixels of the full images).
    triangles : ndarray of int, shape (T, 3)
        The mesh's triangles, positively oriented in the reference.
    removable : ndarray of bool, shape (N,)
        Vertices that may leave (measured, not given by the client); on the mesh's boundary
        none does.
    epsilon, epsilon_pixels : float
        The swaps' gain threshold (:func:`core.optimize.gain_thresholds`).
    cost : str, optional
        The swaps' consistency measure, an entry of :data:`core.optimize.COSTS`.
    scale : float, optional
        Scale of ``images`` against the pixels of the vertices.

    Returns
    -------
    removed : Corrections
        In vertex order, each with the gain of its star (its position stays: ``moving`` is
        ``before``).
    triangles : ndarray of int, shape (T', 3)
        The mesh's triangles without the removed vertices' stars, with their fans.
    """
    ref_v, mov_v = to_level(reference_vertices, scale), to_level(moving_vertices, scale)
    tris = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    n = len(ref_v)
    none = Corrections.none(), tris
    if not len(tris):
        return none
    _, b, around, _ = _neighbours(ref_v, tris)
    star, start = _stars(tris, n)
    degree = np.diff(start)
    # Inner: as many triangles as neighbours (a closed fan).
    cand = np.flatnonzero(np.asarray(removable, bool) & (degree >= 3)
                          & (degree == np.diff(around)))
    if not len(cand):
        return none
    k = degree[cand]
    measure = COSTS[cost]
    fan_tris, fan_of, fan_apex = _fans(_polygons(tris, cand, k, n), k)
    fan_id = fan_of * k.max() + fan_apex
    ref_t, mov_t = ref_v[fan_tris], mov_v[fan_tris]
    folds = ((orientation(*ref_t.transpose(1, 0, 2)) <= 0)
             | (orientation(*mov_t.transpose(1, 0, 2)) <= 0))
    fans, fan = np.unique(fan_id, return_inverse=True)
    valid = np.bincount(fan, weights=folds, minlength=len(fans)) == 0
    if not valid.any():
        return none
    # Each star as it is, then each of its fans that folds nowhere.
    base, pixels = _star_values(images, ref_v, mov_v, tris, cand, (star, start), measure)
    kept = valid[fan]
    fans = fans[valid]
    group = np.searchsorted(fans, fan_id[kept])
    value = _group_values(images, ref_t[kept], mov_t[kept], group, len(fans), measure)
    which = fans // k.max()
    gain = value - base[which]
    threshold = GAIN_FACTOR * gain_thresholds(pixels, epsilon, epsilon_pixels)
    chosen = _best(which, gain) & (gain > threshold[which])
    keep = _independent(cand[which[chosen]], gain[chosen], (b, around), n)
    verts, gains, best = cand[which[chosen]][keep], gain[chosen][keep], fans[chosen][keep]
    drop = np.zeros(len(tris), bool)
    drop[star[_ragged(start[verts], degree[verts])[1]]] = True
    out = np.concatenate([tris[~drop], fan_tris[np.isin(fan_id, best)]])
    at = np.asarray(moving_vertices, dtype=np.float64)[verts]
    return Corrections(verts, at, at.copy(), gains, len(cand), (REMOVE_MOVE,) * len(verts)), out


def _polygons(tris: np.ndarray, inner: np.ndarray, degree: np.ndarray, n: int) -> np.ndarray:
    """The polygon around each ``inner`` vertex (its neighbours in order, ``degree[i]`` of
    them, the rest of its row 0): in a positive triangle ``(v, a, b)`` it runs ``a -> b``."""
    keys = tris.ravel() * n + tris[:, [1, 2, 0]].ravel()
    order = np.argsort(keys)
    keys, then = keys[order], tris[:, [2, 0, 1]].ravel()[order]
    poly = np.zeros((len(inner), degree.max()), np.int64)
    poly[:, 0] = tris[:, [1, 2, 0]].ravel()[order][np.searchsorted(keys, inner * n)]
    for j in range(1, degree.max()):
        at = np.minimum(np.searchsorted(keys, inner * n + poly[:, j - 1]), len(keys) - 1)
        poly[:, j] = np.where(j < degree, then[at], 0)
    return poly


def _fans(poly: np.ndarray, degree: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every fan triangulation of each polygon (``degree[i]`` corners of row ``i``), one per
    corner (its apex): the triangles ``(T, 3)``, each one's polygon and apex."""
    tris, owner, apexes = [], [], []
    for size in np.unique(degree):
        rows = np.flatnonzero(degree == size)
        apex, step = np.divmod(np.arange(size * (size - 2)), size - 2)
        pattern = np.column_stack([apex, (apex + step + 1) % size, (apex + step + 2) % size])
        tris.append(poly[rows][:, pattern].reshape(-1, 3))
        owner.append(np.repeat(rows, size * (size - 2)))
        apexes.append(np.tile(apex, len(rows)))
    return tuple(np.concatenate(a) for a in (tris, owner, apexes))  # type: ignore[return-value]


def _star_gains(
    images: ScoringImages,
    ref_v: np.ndarray,
    mov_v: np.ndarray,
    tris: np.ndarray,
    cand_v: np.ndarray,
    cand_m: np.ndarray,
    *,
    stars: tuple[np.ndarray, np.ndarray],
    cost: str,
    epsilon: float,
    epsilon_pixels: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Per candidate (vertex ``cand_v`` at ``cand_m``), the gain of its vertex's star
    (``stars`` as :func:`_stars` gives them) in the swaps' cost (-inf where a triangle folds)
    and :data:`GAIN_FACTOR` times the swaps' threshold for the star's pixels."""
    tested = np.unique(cand_v)
    measure = COSTS[cost]
    base, pixels = _star_values(images, ref_v, mov_v, tris, tested, stars, measure)
    # Then each star with its vertex at each candidate.
    star, start = stars
    owner, k = _ragged(start[cand_v], start[cand_v + 1] - start[cand_v])
    rows = tris[star[k]]
    ref_tri, mov_tri = ref_v[rows], mov_v[rows]
    mov_tri[rows == cand_v[owner][:, None]] = cand_m[owner]  # once in each triangle
    folds = orientation(*mov_tri.transpose(1, 0, 2)) != orientation(*ref_tri.transpose(1, 0, 2))
    folded = np.bincount(owner, weights=folds, minlength=len(cand_v)) > 0
    value = _group_values(images, ref_tri, mov_tri, owner, len(cand_v), measure)
    group = np.searchsorted(tested, cand_v)
    gain = np.where(folded, -np.inf, value - base[group])
    threshold = GAIN_FACTOR * gain_thresholds(pixels, epsilon, epsilon_pixels)
    return gain, threshold[group]


def _star_values(
    images: ScoringImages,
    ref_v: np.ndarray,
    mov_v: np.ndarray,
    tris: np.ndarray,
    verts: np.ndarray,
    stars: tuple[np.ndarray, np.ndarray],
    measure: Cost,
) -> tuple[np.ndarray, np.ndarray]:
    """Each of the ``verts``' star as it is (``stars`` as :func:`_stars` gives them): its
    consistency in ``measure`` and its pixels, each triangle's histogram counted once."""
    star, start = stars
    owner, k = _ragged(start[verts], start[verts + 1] - start[verts])
    now, at = np.unique(star[k], return_inverse=True)
    hist, moments = triangle_statistics(images, ref_v[tris[now]], mov_v[tris[now]],
                                        with_moments=measure.needs_moments)
    summed = _group_sums(hist, owner, len(verts), at)
    value = measure.measure(summed, None if moments is None else _group_sums(
        moments, owner, len(verts), at), images.bins)
    return value, summed.sum(axis=1).astype(np.float64)


def _group_values(
    images: ScoringImages,
    ref_tri: np.ndarray,
    mov_tri: np.ndarray,
    owner: np.ndarray,
    groups: int,
    measure: Cost,
) -> np.ndarray:
    """The consistency in ``measure`` of each group of triangles ``(ref_tri, mov_tri)``, each
    triangle's group its ``owner``."""
    hist, moments = group_statistics(images, ref_tri, mov_tri, owner, groups,
                                     with_moments=measure.needs_moments)
    return measure.measure(hist, moments, images.bins)


def _best(cand_v: np.ndarray, gain: np.ndarray) -> np.ndarray:
    """Whether each candidate is its vertex's best (``cand_v`` sorted; the first of ties)."""
    tested, group = np.unique(cand_v, return_inverse=True)
    best = np.full(len(tested), -np.inf)
    np.maximum.at(best, group, gain)
    chosen = gain == best[group]
    chosen[chosen] = np.concatenate([[True], np.diff(group[chosen]) > 0])
    return chosen


def _independent(
    verts: np.ndarray, gains: np.ndarray, neighbours: tuple[np.ndarray, np.ndarray], n: int
) -> np.ndarray:
    """Which of the ``verts`` move: the largest gains first, none beside one that moves (each
    was scored with its neighbours in place)."""
    b, around = neighbours
    keep = np.zeros(len(verts), bool)
    blocked = np.zeros(n, bool)
    for c in np.argsort(-gains, kind="stable"):
        v = verts[c]
        if not blocked[v]:
            keep[c] = True
            blocked[v] = True
            blocked[b[around[v]:around[v + 1]]] = True
    return keep


def _neighbours(
    ref_v: np.ndarray, tris: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Every directed edge ``(a, b)``, sorted by ``a`` (the neighbours of ``v`` are
    ``b[around[v]:around[v + 1]]``), and each vertex's mean edge length."""
    n = len(ref_v)
    edges = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
    # One integer per directed edge: unique on them is a flat sort, not a sort of rows.
    a, b = np.divmod(np.unique(np.concatenate([edges[:, 0] * n + edges[:, 1],
                                               edges[:, 1] * n + edges[:, 0]])), n)
    around = np.searchsorted(a, np.arange(n + 1))
    edge = np.bincount(a, weights=np.hypot(*(ref_v[a] - ref_v[b]).T), minlength=n)
    return a, b, around, edge / np.maximum(np.diff(around), 1)


def border_search(
    images: ScoringImages,
    reference_vertices: np.ndarray,
    moving_vertices: np.ndarray,
    triangles: np.ndarray,
    border: np.ndarray,
    extrapolated: np.ndarray,
    fundamental: np.ndarray,
    *,
    epsilon: float,
    epsilon_pixels: float,
    cost: str = "mi",
    scale: float = 1.0,
) -> Corrections:
    """The ``border`` vertices (extrapolated) searched for along their epipolar lines.

    Extrapolated from the nearest pairs, a border vertex misses a surface that shows only along
    the frame's side (Middlebury teddy's floor, 15 px nearer than the pairs above it), where
    the pairs' global homography may be nearer the truth, or neither. Each one is scored as
    :func:`contradicted_vertices` scores a vertex (its star's consistency, the same threshold,
    no fold, no two neighbours in one pass) at candidates on the epipolar line of its
    reference position, over the segment its position and its extrapolations span (their
    feet on the line), extended by its own length and :data:`BORDER_MARGIN` pixels at both
    ends: :data:`BORDER_COARSE` steps either side of its middle, then every pixel of the level
    around the best of them. A later pass (of :data:`BORDER_PASSES`) searches again the
    vertices beside one that moved (among them those it held back).

    Parameters
    ----------
    images : ScoringImages
        The scoring images, reduced by ``scale`` (:func:`core.similarity.reduced`).
    border : ndarray of bool, shape (N,)
        The vertices searched for.
    extrapolated : ndarray, shape (C, K, 2)
        The extrapolations of the ``K`` border vertices (:func:`core.extent.extrapolations`).
    fundamental : ndarray, shape (3, 3)
        ``x_mov^T F x_ref = 0`` in pixels of the full images.
    scale : float
        Scale of ``images`` against the pixels of the vertices.

    The other parameters are those of :func:`contradicted_vertices`.

    Returns
    -------
    Corrections
        In vertex order, each vertex once: its position before the first pass and after the
        last (pixels of the full images), its gains summed.
    """
    none = Corrections.none()
    ref_v, mov_v = to_level(reference_vertices, scale), to_level(moving_vertices, scale)
    tris = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    n = len(ref_v)
    idx = np.flatnonzero(border)
    if not len(idx) or not len(tris):
        return none
    line = epipolar_lines(on_level(fundamental, scale), ref_v[idx])
    ok = np.isfinite(line).all(axis=1)
    idx, line = idx[ok], line[ok]
    if not len(idx):
        return none
    direction = line_direction(line)
    # Positions on each line: origin + t * direction, the origin the foot of the vertex.
    origin = line_foot(line, mov_v[idx])
    along = np.einsum("ckj,kj->ck", to_level(extrapolated, scale)[:, ok] - origin, direction)
    low = np.minimum(np.nanmin(along, axis=0), 0.0)
    high = np.maximum(np.nanmax(along, axis=0), 0.0)
    extend = (high - low) + BORDER_MARGIN * scale
    low, high = low - extend, high + extend
    # Beyond the moving image the scoring samples replicate its border: a vertex moved there
    # is scored on made-up pixels.
    mh, mw = images.moving.shape[:2]
    _, b, around, _ = _neighbours(ref_v, tris)
    stars = _stars(tris, n)
    before = mov_v.copy()
    gains = np.zeros(n)

    def scored(which: np.ndarray, t: np.ndarray):
        # Clipped to the segment, steps repeat at its ends: each position once, in vertex order.
        t = np.clip(t, low[which], high[which])
        order = np.lexsort((t, which))
        which, t = which[order], t[order]
        once = np.ones(len(t), bool)
        once[1:] = (np.diff(which) != 0) | (np.diff(t) > 1e-9)
        cand = origin[which] + t[:, None] * direction[which]
        inside = once & np.all((cand >= -0.5) & (cand <= [mw - 0.5, mh - 0.5]), axis=1)
        which, t, cand = which[inside], t[inside], cand[inside]
        gain, threshold = _star_gains(images, ref_v, mov_v, tris, idx[which], cand,
                                      stars=stars, cost=cost, epsilon=epsilon,
                                      epsilon_pixels=epsilon_pixels)
        tested[which] = True
        return which, t, cand, gain, threshold

    tested = np.zeros(len(idx), bool)
    searched = np.arange(len(idx))
    for _ in range(BORDER_PASSES):
        if not len(searched):
            break
        # Coarse: BORDER_COARSE steps either side of the segment's middle...
        mid = 0.5 * (low[searched] + high[searched])
        step = np.maximum((high[searched] - mid) / BORDER_COARSE, 1.0)
        which, k = _ragged(np.zeros(len(searched), np.int64),
                           np.full(len(searched), 2 * BORDER_COARSE + 1))
        w1, t1, c1, g1, h1 = scored(searched[which],
                                    mid[which] + (k - BORDER_COARSE) * step[which])
        best = _best(w1, g1)
        # ... then every other pixel of the level between the best step's neighbours.
        width = np.ceil(step[np.searchsorted(searched, w1[best])]).astype(np.int64) - 1
        which, k = _ragged(np.zeros(len(width), np.int64), 2 * width + 1)
        fine = k != width[which]
        which, k = which[fine], k[fine]
        w2, _, c2, g2, h2 = scored(w1[best][which], t1[best][which] + k - width[which])
        w, cand, gain, threshold = (np.concatenate(p) for p in (
            (w1, w2), (c1, c2), (g1, g2), (h1, h2)))
        order = np.argsort(w, kind="stable")
        w, cand, gain, threshold = w[order], cand[order], gain[order], threshold[order]
        chosen = _best(w, gain) & (gain > threshold)
        verts, moves, gain = idx[w[chosen]], cand[chosen], gain[chosen]
        keep = _independent(verts, gain, (b, around), n)
        if not keep.any():
            break
        mov_v[verts[keep]] = moves[keep]
        gains[verts[keep]] += gain[keep]
        # Again: those beside one that moved (among them those it held back).
        again = np.zeros(n, bool)
        for m in verts[keep]:
            again[b[around[m]:around[m + 1]]] = True
        searched = np.flatnonzero(again[idx])
    moved = np.flatnonzero(np.any(mov_v != before, axis=1))
    return Corrections(moved, from_level(mov_v[moved], scale), from_level(before[moved], scale),
                       gains[moved],
                       int(tested.sum()), (BORDER_MOVE,) * len(moved))


def _ragged(starts: np.ndarray, sizes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The runs ``starts[g]:starts[g] + sizes[g]`` end to end: each element's run ``g`` and
    its index."""
    owner = np.repeat(np.arange(len(sizes)), sizes)
    return owner, starts[owner] + np.arange(len(owner)) - np.repeat(np.cumsum(sizes) - sizes, sizes)


def _group_sums(
    rows: np.ndarray, owner: np.ndarray, groups: int, index: np.ndarray | None = None
) -> np.ndarray:
    """Sums of the rows ``rows[index[i]]`` (``index`` by default ``0, 1, ...``) of each
    ``owner[i]`` group, in the order of ``i`` (a sparse product: a third of the time of
    ``np.add.reduceat`` on these shapes, and no gathered copy of the rows)."""
    index = np.arange(len(owner)) if index is None else index
    pick = sparse.csr_matrix((np.ones(len(owner), rows.dtype), (owner, index)),
                             shape=(groups, len(rows)))
    return np.asarray(pick @ rows)
