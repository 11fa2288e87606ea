"""Initial mesh: Delaunay triangulation, small-triangle removal and patch-reversal repair."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import Delaunay, QhullError

from pwlreg.core.errors import InputError, NotEnoughPointsError
from pwlreg.core.mesh import Edge, Mesh, edge_key
from pwlreg.core.raster import first_occurrences, quantize, triangle_areas


@dataclass
class TriangulationReport:
    """What building the initial mesh did.

    Attributes
    ----------
    duplicates_removed : int
        Point pairs dropped because their reference or moving position (quantized to
        1/256 px) repeated an earlier pair's.
    small_triangles_removed : int
        Delaunay triangles with reference area below ``min_triangle_area`` (px^2).
    optional_dropped : int
        Optional pairs left out because a triangle of theirs was that small.
    repairs : list of dict
        Patch-reversal repairs in order: ``{"action": "swap", "removed": [i, j], "added":
        [k, l]}`` or ``{"action": "remove", "triangle": [a, b, c], "reason": ...}``.
    unrepaired : int
        Patch reversals left when the repair budget ran out (0 in practice).
    extrapolated : ndarray of bool, shape (N,)
        Per mesh vertex: its moving position was extrapolated, not measured.
    """

    duplicates_removed: int = 0
    small_triangles_removed: int = 0
    optional_dropped: int = 0
    repairs: list[dict] = field(default_factory=list)
    unrepaired: int = 0
    extrapolated: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))

    def to_dict(self) -> dict:
        """JSON-able form."""
        return {
            "duplicates_removed": self.duplicates_removed,
            "small_triangles_removed": self.small_triangles_removed,
            "optional_pairs_dropped": self.optional_dropped,
            "patch_reversal_repairs": self.repairs,
            "unrepaired_patch_reversals": self.unrepaired,
            "extrapolated_vertices": int(np.count_nonzero(self.extrapolated)),
        }


def deduplicate(reference: np.ndarray, moving: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Drop pairs whose quantized reference or moving point repeats an earlier pair's.

    Returns the kept reference points, moving points (quantized, original order) and the
    number dropped.
    """
    ref, mov, keep = _deduplicate(reference, moving)
    return ref, mov, int((~keep).sum())


def _deduplicate(
    reference: np.ndarray, moving: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    ref = quantize(reference).reshape(-1, 2)
    mov = quantize(moving).reshape(-1, 2)
    keep = np.zeros(len(ref), dtype=bool)
    keep[np.intersect1d(first_occurrences(ref), first_occurrences(mov))] = True
    return ref[keep], mov[keep], keep


def delaunay_triangles(points: np.ndarray) -> np.ndarray:
    """Delaunay triangles ``(T, 3)`` of 2-D points; ``InputError`` if they span no area."""
    if len(points) < 3:
        raise NotEnoughPointsError(len(points), 3, "removing duplicate points")
    try:
        return Delaunay(points).simplices.astype(np.int64)
    except QhullError as exc:
        raise InputError(
            f"the {len(points)} reference points are collinear or degenerate: no triangle "
            "can be built",
            "points",
        ) from exc


def repair_patch_reversals(mesh: Mesh, max_actions: int | None = None) -> tuple[list[dict], int]:
    """Remove patch reversals in place, as the paper does.

    A reversed triangle with a boundary edge is removed. Otherwise the edge it shares with
    the neighbour it overlaps in the moving image is swapped: among its edges whose swap keeps
    the reference mesh valid (strictly convex reference quad, new edge absent), the one leaving
    the fewest reversed triangles; if no swap lowers the number of reversals, the triangle is
    removed. Every action lowers the number of reversals or of triangles, so the loop ends.

    Returns the list of actions and the number of reversals left (only if ``max_actions``
    ran out).
    """
    budget = max_actions if max_actions is not None else 4 * mesh.n_triangles + 16
    actions: list[dict] = []

    def remove(slot: int, reason: str) -> None:
        actions.append(
            {"action": "remove", "triangle": list(mesh.triangle(slot)), "reason": reason}
        )
        mesh.remove_triangle(slot)

    while budget > 0:
        reversed_slots = mesh.reversed_slots()
        if not reversed_slots:
            return actions, 0
        budget -= 1
        slot = reversed_slots[0]
        a, b, c = mesh.triangle(slot)
        sides = [edge_key(a, b), edge_key(b, c), edge_key(c, a)]
        if any(not mesh.is_internal(e) for e in sides):
            remove(slot, "patch reversal on the boundary")
            continue
        best: tuple[int, Edge] | None = None
        for e in sides:
            q = mesh.quad(e)
            # The swap must keep the reference mesh a valid triangulation.
            if mesh.has_edge((q.k, q.l)) or not mesh.strictly_convex(q, mesh.ref_fixed):
                continue
            before = sum(mesh.flipped(mesh.triangle(s)) for s in q.slots)
            after = sum(mesh.flipped(t) for t in q.swapped_triangles())
            if after < before and (best is None or after < best[0]):
                best = (after, e)
        if best is None:
            remove(slot, "no swap removes the reversal")
            continue
        added = mesh.swap(best[1], check=False)
        actions.append({"action": "swap", "removed": list(best[1]), "added": list(added)})
    return actions, len(mesh.reversed_slots())


#: Share of the triangles reversed in the moving image over which the map is a reflection: a
#: mirror image reverses all of them, pairs at random (unrelated images) about half.
MIRRORED_SHARE = 0.9


def _refuse_a_mirror(mesh: Mesh) -> None:
    """Refuse pairs that map most triangles reversed: a reflection, which no mesh can follow
    (the repair would remove every triangle, and the message blamed the points)."""
    reversed_ = len(mesh.reversed_slots())
    if mesh.n_triangles and reversed_ > MIRRORED_SHARE * mesh.n_triangles:
        raise InputError(
            f"{reversed_} of {mesh.n_triangles} triangles are reversed in the moving image: it "
            "is a mirror image of the reference (flipped, or a raster whose rows or columns run "
            "the other way), or the points of one image are given as (row, column); flip it or "
            "swap the points' coordinates",
            "moving",
        )


def initial_mesh(
    reference_points: np.ndarray,
    moving_points: np.ndarray,
    min_triangle_area: float,
    extrapolated: np.ndarray | None = None,
    *,
    optional: np.ndarray | None = None,
) -> tuple[Mesh, TriangulationReport]:
    """Build the mesh the search starts from.

    Delaunay triangulation of the reference points (duplicates removed), the same triangles on
    the moving points, triangles with reference area below ``min_triangle_area`` (px^2)
    discarded, then patch reversals repaired (:func:`repair_patch_reversals`).
    ``extrapolated`` flags the pairs whose moving position was not measured; the report carries
    the flags of the vertices kept. ``optional`` flags pairs that may be left out instead of a
    triangle: a small triangle with one of them loses the last of its optional vertices and
    the points are triangulated again, so that pairs added near others never open a hole.
    """
    ref, mov, kept = _deduplicate(reference_points, moving_points)
    flags = np.zeros(len(kept), bool) if extrapolated is None else np.asarray(extrapolated, bool)
    flags = flags[kept]
    spare = (np.zeros(len(ref), bool) if optional is None
             else np.asarray(optional, bool)[kept])
    dropped = 0
    while True:
        tris = delaunay_triangles(ref)
        areas = triangle_areas(ref[tris])
        keep = (areas >= min_triangle_area) & (areas > 0)
        own = spare[tris] & ~keep[:, None]
        rows = np.flatnonzero(own.any(axis=1))
        if not len(rows):
            break
        drop = np.unique(np.where(own[rows], tris[rows], -1).max(axis=1))
        left = np.ones(len(ref), bool)
        left[drop] = False
        ref, mov, flags, spare = ref[left], mov[left], flags[left], spare[left]
        dropped += len(drop)
    report = TriangulationReport(
        duplicates_removed=int((~kept).sum()), extrapolated=flags,
        optional_dropped=dropped,
    )
    report.small_triangles_removed = int((~keep).sum())
    mesh = Mesh(ref, mov, tris[keep])
    _refuse_a_mirror(mesh)
    report.repairs, report.unrepaired = repair_patch_reversals(mesh)
    if mesh.n_triangles == 0:
        raise InputError(
            "no triangle is left after removing small triangles and patch reversals; send more "
            "or better spread points, or lower min_triangle_area",
            "points",
        )
    return mesh, report
