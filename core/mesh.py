"""Two isomorphic triangle meshes (reference and moving) and the edge swap.

A mesh has vertices in both images (the same index is the same conjugate point) and one list of
triangles shared by both. Every triangle is stored positively oriented in the reference image
(see :func:`core.raster.orientation`); a triangle whose moving orientation differs is a *patch
reversal*.

Edges are ``(i, j)`` tuples with ``i < j``. An edge with two adjacent triangles is internal, one
with a single triangle is on the boundary.
"""

from __future__ import annotations

from collections.abc import Iterable
from functools import cached_property
from itertools import compress
from typing import NamedTuple

import numpy as np

from pwlreg.core.raster import cross_fixed, fixed_point, quantize

Edge = tuple[int, int]

MAX_COORDINATE = 2.0**22
"""Largest vertex coordinate magnitude (pixels) for which every predicate is exact in int64."""


def orient_fixed(p: tuple[int, int], q: tuple[int, int], r: tuple[int, int]) -> int:
    """Exact orientation sign of fixed-point points (Python ints: fast for single tests)."""
    cross = (q[0] - p[0]) * (r[1] - p[1]) - (q[1] - p[1]) * (r[0] - p[0])
    return (cross > 0) - (cross < 0)


def edge_key(i: int, j: int) -> Edge:
    """Canonical ``(min, max)`` form of an edge."""
    return (i, j) if i < j else (j, i)


class Quad(NamedTuple):
    """The two triangles around an internal edge ``{i, j}``.

    ``k`` and ``l`` are the vertices opposite the edge; swapping ``{i, j}`` gives ``{k, l}``.
    ``slots`` are the indices of the two triangles in :attr:`Mesh.triangles`.
    """

    i: int
    j: int
    k: int
    l: int  # noqa: E741 - the paper's name
    slots: tuple[int, int]
    # A NamedTuple, not a dataclass: the search builds thousands of these per second.

    @property
    def boundary(self) -> tuple[Edge, Edge, Edge, Edge]:
        """The four outer edges of the quad."""
        i, j, k, l = self.i, self.j, self.k, self.l  # noqa: E741
        return (edge_key(i, k), edge_key(k, j), edge_key(j, l), edge_key(l, i))

    def swapped_triangles(self) -> tuple[tuple[int, int, int], tuple[int, int, int]]:
        """Vertex triples of the two triangles after the swap, ``{k, l, i}`` and ``{k, l, j}``."""
        return (self.k, self.l, self.i), (self.k, self.l, self.j)


class Mesh:
    """Mutable pair of isomorphic triangle meshes.

    Parameters
    ----------
    reference, moving : ndarray, shape (N, 2)
        Vertex coordinates in pixels; they are quantized (:func:`core.raster.quantize`) so that
        every orientation test is exact.
    triangles : ndarray, shape (T, 3)
        Vertex indices. Re-ordered so that each triangle is positively oriented in the reference
        image; degenerate triangles (zero reference area) are rejected with ``ValueError``.
    """

    def __init__(self, reference: np.ndarray, moving: np.ndarray, triangles: np.ndarray) -> None:
        for pts in (reference, moving):
            # Fixed-point predicates are exact in int64 only up to this magnitude.
            arr = np.asarray(pts, dtype=np.float64)
            if not np.all(np.isfinite(arr)) or np.abs(arr).max(initial=0.0) > MAX_COORDINATE:
                raise ValueError(f"vertex coordinates must be finite, at most {MAX_COORDINATE} px")
        self.reference = quantize(reference).reshape(-1, 2)
        self.moving = quantize(moving).reshape(-1, 2)
        if self.reference.shape != self.moving.shape:
            raise ValueError("reference and moving vertices must have the same shape")
        ref_xy, mov_xy = fixed_point(self.reference), fixed_point(self.moving)
        self._fixed_arrays = (ref_xy, mov_xy)
        tris = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
        if len(tris) and (tris.min() < 0 or tris.max() >= len(self.reference)):
            raise ValueError("triangle vertex index out of range")
        cross = cross_fixed(*np.moveaxis(ref_xy[tris], 1, 0))
        if not cross.all():
            a, b, c = tris[np.argmin(cross != 0)].tolist()
            raise ValueError(f"degenerate triangle {(a, b, c)} in the reference mesh")
        tris = np.where((cross > 0)[:, None], tris, tris[:, [0, 2, 1]])
        self._tris: list[tuple[int, int, int] | None] = list(zip(*tris.T.tolist(), strict=True))
        # The slots again as arrays, for the batched queries: each slot's triangle (-1 once
        # removed) and when it was added, which orders the owners of its edges in _edges. The
        # changes are applied only when a batched query runs (_sync), not swap by swap.
        self._rows = tris
        self._stamps = np.arange(len(tris))
        self._changed: list[int] = []

    # Tuples of Python ints for the single predicates (the batched ones take the arrays): made
    # when first asked for (a mesh the compiled search alone works on never needs them).
    @cached_property
    def ref_fixed(self) -> list[tuple[int, int]]:
        """Reference vertices in fixed point (:func:`core.raster.fixed_point`), as tuples."""
        return list(zip(*self._fixed_arrays[0].T.tolist(), strict=True))

    @cached_property
    def mov_fixed(self) -> list[tuple[int, int]]:
        """Moving vertices in fixed point, as tuples."""
        return list(zip(*self._fixed_arrays[1].T.tolist(), strict=True))

    @cached_property
    def _edges(self) -> dict[Edge, list[int]]:
        """Each edge's triangles (slots), in the order they were added; made when first asked
        for (a mesh the compiled search alone works on never needs it)."""
        n = len(self.reference)
        edges: dict[Edge, list[int]] = {}
        for c, slot in zip(*(a.tolist() for a in self._sides()), strict=True):
            edges.setdefault((c // n, c % n), []).append(slot)
        return edges

    # -- construction helpers ------------------------------------------------------------------
    def _oriented(self, a: int, b: int, c: int) -> tuple[int, int, int]:
        s = orient_fixed(self.ref_fixed[a], self.ref_fixed[b], self.ref_fixed[c])
        if s == 0:
            raise ValueError(f"degenerate triangle {(a, b, c)} in the reference mesh")
        return (a, b, c) if s > 0 else (a, c, b)

    def _add(self, tri: tuple[int, int, int], slot: int) -> None:
        self._tris[slot] = tri
        self._changed.append(slot)
        a, b, c = tri
        for e in (edge_key(a, b), edge_key(b, c), edge_key(c, a)):
            self._edges.setdefault(e, []).append(slot)

    def _drop(self, slot: int) -> None:
        tri = self._tris[slot]
        assert tri is not None
        a, b, c = tri
        for e in (edge_key(a, b), edge_key(b, c), edge_key(c, a)):
            owners = self._edges[e]
            owners.remove(slot)
            if not owners:
                del self._edges[e]
        self._tris[slot] = None
        self._changed.append(slot)

    # -- queries -------------------------------------------------------------------------------
    @property
    def triangles(self) -> np.ndarray:
        """Current triangles, ``(T, 3)`` int64, in slot order (removed slots skipped)."""
        return self._live()[1]

    @property
    def n_triangles(self) -> int:
        """Number of triangles."""
        return len(self._tris) - self._tris.count(None)

    def slots(self) -> list[int]:
        """Slot indices of the live triangles."""
        return list(compress(range(len(self._tris)), self._tris))

    def _sync(self) -> None:
        """Bring the slot arrays up to date with the changes made since the last batched query."""
        if not self._changed:
            return
        changed = np.array(self._changed, dtype=np.int64)
        self._changed.clear()
        # A slot holds what its last change left; the triangles added since the last query are
        # stamped after every earlier one, in the order of their changes.
        slots, from_end = np.unique(changed[::-1], return_index=True)
        self._stamps[slots] = self._stamps.max() + len(changed) - from_end
        self._rows[slots] = [self._tris[s] or (-1, -1, -1) for s in slots.tolist()]

    def _live(self) -> tuple[np.ndarray, np.ndarray]:
        """Slots of the live triangles, ``(T,)``, and their vertex triples, ``(T, 3)``, int64."""
        self._sync()
        slots = np.flatnonzero(self._rows[:, 0] >= 0)
        return slots, self._rows[slots]

    def triangle(self, slot: int) -> tuple[int, int, int]:
        """Vertex triple stored in ``slot``."""
        tri = self._tris[slot]
        if tri is None:
            raise KeyError(f"slot {slot} holds no triangle")
        return tri

    def edges(self) -> list[Edge]:
        """All edges, sorted."""
        return sorted(self._edges)

    def has_edge(self, e: Edge) -> bool:
        """Whether edge ``e`` exists."""
        return edge_key(*e) in self._edges

    def is_internal(self, e: Edge) -> bool:
        """Whether ``e`` is shared by two triangles."""
        return len(self._edges.get(edge_key(*e), ())) == 2

    def internal_edges(self) -> list[Edge]:
        """Edges shared by two triangles, sorted."""
        return sorted(e for e, s in self._edges.items() if len(s) == 2)

    def boundary_edges(self) -> list[Edge]:
        """Edges with a single triangle, sorted."""
        return sorted(e for e, s in self._edges.items() if len(s) == 1)

    def edge_triangles(self, e: Edge) -> list[int]:
        """Slots of the triangles adjacent to ``e`` (empty if it does not exist)."""
        return list(self._edges.get(edge_key(*e), ()))

    def quad(self, e: Edge) -> Quad:
        """Quad of internal edge ``e``; ``ValueError`` if ``e`` is not internal."""
        i, j = edge_key(*e)
        owners = self._edges.get((i, j), [])
        if len(owners) != 2:
            raise ValueError(f"edge {(i, j)} is not internal")
        s0, s1 = owners
        k = sum(self._tris[s0]) - i - j  # type: ignore[arg-type]
        l = sum(self._tris[s1]) - i - j  # type: ignore[arg-type]  # noqa: E741
        return Quad(i, j, k, l, (s0, s1))

    @property
    def fixed_arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """Fixed-point vertices of the reference and the moving mesh, ``(N, 2)`` int64 each."""
        return self._fixed_arrays

    def _sides(self) -> tuple[np.ndarray, np.ndarray]:
        """Each side of each live triangle as an edge code ``i * N + j`` with its slot, grouped
        by edge (codes sorted), in a group the triangles in the order they were added (that
        of _edges): two ``(3 T,)`` int64 arrays."""
        n = len(self.reference)
        slots, tris = self._live()
        second = tris[:, [1, 2, 0]]
        code = (np.minimum(tris, second) * n + np.maximum(tris, second)).ravel()
        order = np.lexsort((np.repeat(self._stamps[slots], 3), code))
        return code[order], np.repeat(slots, 3)[order]

    def edge_owners(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every edge as a code ``i * N + j`` (``N`` vertices), sorted, and its triangles.

        Returns
        -------
        codes : ndarray of int64, shape (E,)
            Sorted; :func:`numpy.searchsorted` finds an edge in it.
        owners : ndarray of int64, shape (E, 2)
            Slots of an internal edge's two triangles, in the order they were added (that of
            :meth:`quad`'s ``k`` and ``l``); of other edges the first, and -1.
        counts : ndarray of int64, shape (E,)
            Triangles of each edge (more than two where the mesh is not a manifold).
        """
        code, owner = self._sides()
        first = np.flatnonzero(np.diff(code, prepend=-1))
        counts = np.diff(first, append=len(code))
        owners = np.stack([owner[first], np.full(len(first), -1, dtype=np.int64)], axis=1)
        pair = counts == 2
        owners[pair, 1] = owner[first[pair] + 1]
        return code[first], owners, counts

    def edge_table(self) -> tuple[np.ndarray, np.ndarray]:
        """Every edge as a code ``i * N + j`` (``N`` vertices), sorted, and its apexes.

        Returns
        -------
        codes : ndarray of int64, shape (E,)
            Sorted; :func:`numpy.searchsorted` finds an edge in it.
        apexes : ndarray of int64, shape (E, 2)
            Third vertex of the edge's first and second triangle (the ``k`` and ``l`` of
            :meth:`quad`, in its order); -1 for the missing second one of a boundary edge.
        """
        n = len(self.reference)
        codes, owners, _ = self.edge_owners()
        ends = codes // n + codes % n
        apexes = np.where(owners >= 0, self._rows[owners].sum(axis=2) - ends[:, None], -1)
        return codes, apexes

    def slot_triangles(self) -> tuple[np.ndarray, np.ndarray]:
        """Triangles by slot, ``(S, 3)`` int64 with rows of -1 for empty slots, and the order
        they were added (stamps, ``(S,)``; it orders the owners of an edge): copies."""
        self._sync()
        return self._rows.copy(), self._stamps.copy()

    def take_triangles(self, rows: np.ndarray, stamps: np.ndarray) -> None:
        """Replace the triangles by those of :meth:`slot_triangles` after a compiled search
        swapped edges in them (:func:`core.kernels.search_run`), as if the swaps had been made
        here (each triangle positively oriented in the reference, new ones stamped later)."""
        self._rows = rows
        self._stamps = stamps
        self._changed.clear()
        self._tris = [None if t[0] < 0 else (t[0], t[1], t[2]) for t in rows.tolist()]
        self.__dict__.pop("_edges", None)

    def across(self, e: Edge, apex: int) -> int:
        """Vertex facing ``apex`` across internal edge ``e``, -1 if there is none.

        The apex of the triangle of ``e`` that does not hold ``apex``; -1 if ``e`` is not
        internal or if not exactly one of its two triangles holds ``apex``.
        """
        owners = self._edges.get(edge_key(*e))
        if owners is None or len(owners) != 2:
            return -1
        t0 = self._tris[owners[0]]
        t1 = self._tris[owners[1]]
        in0 = apex in t0  # type: ignore[operator]
        if in0 == (apex in t1):  # type: ignore[operator]
            return -1
        return sum(t1 if in0 else t0) - e[0] - e[1]  # type: ignore[arg-type]

    def reversed_slots(self) -> list[int]:
        """Slots of patch reversals: triangles not positively oriented in the moving mesh."""
        slots, tris = self._live()
        cross = cross_fixed(*np.moveaxis(self._fixed_arrays[1][tris], 1, 0))
        return slots[cross <= 0].tolist()

    @staticmethod
    def strictly_convex(q: Quad, fixed: list[tuple[int, int]]) -> bool:
        """Whether the quad's diagonals cross properly with vertices ``fixed`` (exact test)."""
        pi, pj, pk, pl = fixed[q.i], fixed[q.j], fixed[q.k], fixed[q.l]
        return (
            orient_fixed(pi, pj, pk) * orient_fixed(pi, pj, pl) < 0
            and orient_fixed(pk, pl, pi) * orient_fixed(pk, pl, pj) < 0
        )

    def flipped(self, tri: tuple[int, int, int]) -> bool:
        """Whether the vertex triple turns differently in the two images (a patch reversal)."""
        a, b, c = tri
        r, m = self.ref_fixed, self.mov_fixed
        return orient_fixed(r[a], r[b], r[c]) != orient_fixed(m[a], m[b], m[c])

    def swap_blocker(self, e: Edge) -> str | None:
        """Why edge ``e`` cannot be swapped, or ``None`` if it can.

        The preconditions of the paper: the edge is internal; the new edge does not exist yet;
        the quad is strictly convex in the reference mesh and in the moving mesh, and the two new
        triangles are not patch reversals.
        """
        if not self.is_internal(e):
            return "boundary edge" if self.has_edge(e) else "no such edge"
        q = self.quad(e)
        if self.has_edge((q.k, q.l)):
            return "new edge exists"
        if not (
            self.strictly_convex(q, self.ref_fixed) and self.strictly_convex(q, self.mov_fixed)
        ):
            return "quad not strictly convex"
        if any(self.flipped(t) for t in q.swapped_triangles()):
            return "swap creates a patch reversal"
        return None

    def swappable_edges(self) -> list[Edge]:
        """Internal edges meeting every swap precondition, sorted (batched :meth:`can_swap`)."""
        return [(i, j) for i, j in self.swappable_quads()[:, :2].tolist()]

    def swappable_quads(
        self,
        near: Iterable[int] | None = None,
        table: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> np.ndarray:
        """Quads ``(i, j, k, l)`` of the edges meeting every swap precondition, ``(E, 4)`` int64
        in the order of :meth:`swappable_edges` and with :meth:`quad`'s ``k, l``.

        ``near`` keeps the edges with an end among these vertices; ``table`` is the
        :meth:`edge_table`, if the caller has it.
        """
        codes, apexes = self.edge_table() if table is None else table
        n = len(self.reference)
        quads = np.column_stack([codes // n, codes % n, apexes])[apexes[:, 1] >= 0]
        if near is not None:
            ends = np.fromiter(near, dtype=np.int64)
            quads = quads[np.isin(quads[:, 0], ends) | np.isin(quads[:, 1], ends)]
        k, l = quads[:, 2], quads[:, 3]  # noqa: E741
        new = np.minimum(k, l) * n + np.maximum(k, l)
        at = np.minimum(np.searchsorted(codes, new), max(len(codes) - 1, 0))
        exists = codes[at] == new if len(codes) else np.zeros(len(quads), dtype=bool)
        return quads[~exists & self.convex_mask(quads)]

    def convex_mask(self, quads: np.ndarray) -> np.ndarray:
        """The geometric swap preconditions of quads ``(E, 4)`` rows ``(i, j, k, l)``, batched:
        strictly convex in both meshes, new triangles not reversed (all but "the new edge does
        not exist yet", which the caller tests)."""
        ok = np.ones(len(quads), dtype=bool)
        ref_new = None
        for xy in self._fixed_arrays:
            p = xy[quads]  # (E, 4, 2): i, j, k, l
            o = {}
            for name, (a, b, c) in {
                "ijk": (0, 1, 2),
                "ijl": (0, 1, 3),
                "kli": (2, 3, 0),
                "klj": (2, 3, 1),
            }.items():
                pa, pb, pc = p[:, a], p[:, b], p[:, c]
                o[name] = np.sign(
                    (pb[:, 0] - pa[:, 0]) * (pc[:, 1] - pa[:, 1])
                    - (pb[:, 1] - pa[:, 1]) * (pc[:, 0] - pa[:, 0])
                )
            ok &= (o["ijk"] * o["ijl"] < 0) & (o["kli"] * o["klj"] < 0)
            if ref_new is None:
                ref_new = (o["kli"], o["klj"])
            else:
                ok &= (o["kli"] == ref_new[0]) & (o["klj"] == ref_new[1])
        return ok

    def swappable_quad(self, e: Edge) -> Quad | None:
        """Quad of ``e`` if ``e`` meets every swap precondition, else None.

        :meth:`swap_blocker` without the reason: the search asks this thousands of times.
        """
        i, j = edge_key(*e)
        owners = self._edges.get((i, j))
        if owners is None or len(owners) != 2:
            return None
        s0, s1 = owners
        k = sum(self._tris[s0]) - i - j  # type: ignore[arg-type]
        l = sum(self._tris[s1]) - i - j  # type: ignore[arg-type]  # noqa: E741
        if (k, l) in self._edges or (l, k) in self._edges:
            return None
        flips = []
        for fixed in (self.ref_fixed, self.mov_fixed):
            (ix, iy), (jx, jy), (kx, ky), (lx, ly) = fixed[i], fixed[j], fixed[k], fixed[l]
            ijk = (jx - ix) * (ky - iy) - (jy - iy) * (kx - ix)
            ijl = (jx - ix) * (ly - iy) - (jy - iy) * (lx - ix)
            kli = (lx - kx) * (iy - ky) - (ly - ky) * (ix - kx)
            klj = (lx - kx) * (jy - ky) - (ly - ky) * (jx - kx)
            # Strictly convex: each diagonal separates the other's ends.
            if not ((ijk > 0 and ijl < 0) or (ijk < 0 and ijl > 0)):
                return None
            if not ((kli > 0 and klj < 0) or (kli < 0 and klj > 0)):
                return None
            flips.append(kli > 0)
        # The new triangles turn the same way in both images (then both do: kli, klj differ).
        if flips[0] != flips[1]:
            return None
        return Quad(i, j, k, l, (s0, s1))

    def can_swap(self, e: Edge) -> bool:
        """Whether ``e`` meets every swap precondition."""
        return self.swappable_quad(e) is not None

    # -- modifications -------------------------------------------------------------------------
    def swap(self, e: Edge, check: bool = True) -> Edge:
        """Replace internal edge ``{i, j}`` by ``{k, l}``; returns the new edge.

        With ``check`` the preconditions are verified first (``ValueError`` if not met);
        without, only topology is required (used to repair patch reversals).
        """
        if check:
            why = self.swap_blocker(e)
            if why is not None:
                raise ValueError(f"cannot swap edge {edge_key(*e)}: {why}")
        q = self.quad(e)
        s0, s1 = q.slots
        self._drop(s0)
        self._drop(s1)
        t0, t1 = q.swapped_triangles()
        self._add(self._oriented(*t0), s0)
        self._add(self._oriented(*t1), s1)
        return edge_key(q.k, q.l)

    def remove_triangle(self, slot: int) -> None:
        """Delete the triangle in ``slot`` (its slot stays empty)."""
        self._drop(slot)

    def copy(self) -> Mesh:
        """Independent copy with the same vertices and triangles (slots compacted)."""
        return Mesh(self.reference, self.moving, self.triangles)
