"""The moves a registration makes on its mesh, one table: :data:`MOVES`.

Three kinds. *Insertions* run while the mesh is built, on the automatic path (or with
``insert_vertices="always"``): each finds new conjugate pairs from the images guided by the
current mesh (:class:`core.refine.Guide`), and the mesh is built again over the old and the new
pairs. *Swaps* are the optimizer's changes of the triangulation (:mod:`core.optimize`), recorded
step by step with their gain. *Vertex* moves change a vertex's moving position after the
swaps, on the same path as the insertions (:mod:`core.correct`): a measured vertex the images
contradict, an extrapolated border vertex searched for along its epipolar line, every vertex
aligned, a vertex that none of these placed taken out; each recorded with its gain; the swaps
then run once more. Every move's name and reason go into ``mesh.json`` and
``convergence.json``, and every mesh vertex says which move (or the matcher) put it there.
Adding an insertion source is one entry here.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from pwlreg.core.align import REACH as ALIGN_REACH
from pwlreg.core.correct import (
    ALIGN_MOVE,
    BORDER_MARGIN,
    BORDER_MOVE,
    GAIN_FACTOR,
    REACH,
    REMOVE_MOVE,
    SUPPORT,
    SUPPORT_PX,
    SUSPECT_PX,
)
from pwlreg.core.correct import MOVE as CORRECT
from pwlreg.core.epipolar import EpipolarModel
from pwlreg.core.refine import (
    EPI_ALONE_AMBIGUITY,
    EPI_REACH,
    STEP_OFFSET,
    STEP_WINDOW,
    Guide,
    Insertion,
    epipolar_pairs,
    guided_pairs,
    step_points,
)
from pwlreg.core.similarity import ScoringImages


@dataclass(frozen=True)
class Search:
    """What an insertion source is given besides the mesh.

    Attributes
    ----------
    images : ScoringImages
        Full-resolution scoring images (mutual-information tests).
    epipolar : EpipolarModel or None
        The matcher's epipolar geometry, None when it was not estimated.
    measured : int
        Measured vertices so far (sets the spacing of new pairs).
    budget : int
        Most new pairs this source may return.
    added : (ndarray, ndarray)
        Pairs the sources before it found in this round (reference, moving).
    epsilon, epsilon_pixels : float
        The swaps' gain threshold (:func:`core.optimize.gain_thresholds`).
    round : int
        The insertion round (0 the first).
    """

    images: ScoringImages
    epipolar: EpipolarModel | None
    measured: int
    budget: int
    added: tuple[np.ndarray, np.ndarray]
    epsilon: float
    epsilon_pixels: float
    round: int


Finder = Callable[[Guide, Search], "Insertion | None"]


@dataclass(frozen=True)
class Move:
    """One kind of move.

    Attributes
    ----------
    kind : {"insertion", "swap", "vertex"}
        When it runs: while the mesh is built, in the optimizer's search, or after it.
    reason : str
        Why such a move is made, as ``mesh.json`` and ``convergence.json`` give it.
    find : callable or None
        For insertions: ``find(guide, search) -> Insertion`` (None when the source cannot run
        on this pair).
    own_budget : float or None
        For insertions: None to draw on the budget the sources share
        (:func:`core.pipeline.insertion_budget`), or a budget of its own over all rounds, as a
        share of the matched pairs.
    runs : callable or None
        For insertions: ``runs(search)``, whether it searches in this round on this pair
        (:attr:`Search.round`, :attr:`Search.epipolar`); None: every round.
    """

    kind: str
    reason: str
    find: Finder | None = None
    own_budget: float | None = None
    runs: Callable[[Search], bool] | None = None


def _flow(mesh: Guide, search: Search) -> Insertion:
    return guided_pairs(mesh, search.images, measured=search.measured, budget=search.budget,
                        epsilon=search.epsilon, epsilon_pixels=search.epsilon_pixels)


def _along_lines(
    candidates: Callable[[Guide], tuple[np.ndarray, np.ndarray]] | None,
) -> Finder:
    """A finder of pairs matched along the epipolar lines (:func:`core.refine.epipolar_pairs`):
    of the reference corners, or of the points (and their patches' offsets) ``candidates(mesh)``
    gives."""

    def find(mesh: Guide, search: Search) -> Insertion | None:
        if search.epipolar is None:
            return None
        return epipolar_pairs(
            mesh, search.images, search.epipolar, added=search.added, measured=search.measured,
            budget=search.budget, epsilon=search.epsilon, epsilon_pixels=search.epsilon_pixels,
            candidates=None if candidates is None else candidates(mesh),
        )

    return find


MOVES: dict[str, Move] = {
    "flow": Move(
        "insertion",
        "a reference corner where the residual optical flow of the registered image is "
        "consistent forward and backward and unique; corrections above 1.5 px also raised the "
        "mutual information of the triangle they split; in the second round, on the mesh the "
        "epipolar move has corrected (in every round without an epipolar geometry)",
        _flow,
        # The epipolar search corrects the first mesh; the flow reads the corrected one.
        runs=lambda search: search.round > 0 or search.epipolar is None,
    ),
    "epipolar": Move(
        "insertion",
        f"a reference corner matched along its epipolar line, over {EPI_REACH} px of the level "
        "either side of the mesh's prediction or the span of its neighbours' displacements if "
        "wider: "
        "correlated, peaked, without a rival peak, confirmed both ways, "
        "not contradicted by its neighbours (where none stands near enough to judge it and "
        f"none moves like it, with no rival peak reaching {EPI_ALONE_AMBIGUITY:g} of the best); "
        "corrections above "
        "1.5 px also raised the mutual information of the triangle they split",
        _along_lines(None),
    ),
    "step": Move(
        "insertion",
        f"a reference point {STEP_OFFSET:g} px of the level beside a jump of the residual "
        "optical flow (a depth step inside a triangle), matched along its epipolar line as the "
        f"epipolar move's corners are, by a patch centred {STEP_WINDOW:g} px farther from the "
        "jump (on the point's side of the step), in the second round (it reads the flow the "
        "flow move measures); it has a budget of its own, half the matched pairs, since a "
        "step needs vertices on both sides however dense the mesh is elsewhere",
        _along_lines(step_points),
        own_budget=0.5,
        runs=lambda search: search.round == 1,
    ),
    CORRECT: Move(
        "vertex",
        f"a measured vertex (not the client's) whose displacement differs from a neighbour's "
        f"by more than {SUSPECT_PX:g} px moved as at least {SUPPORT} of its neighbours do "
        f"(within {SUPPORT_PX:g} px), by at most {REACH:g} of its mean edge, when that raised "
        f"the consistency (the swaps' cost) of its triangles by more than {GAIN_FACTOR:g} times "
        "the swaps' threshold and folded none of them, only measured neighbours proposing a "
        "motion; no two neighbours move in one pass (a corner where a "
        "foreground edge crosses the background is matched with the foreground's motion)",
    ),
    BORDER_MOVE: Move(
        "vertex",
        "an extrapolated vertex on the frame's border moved along its epipolar line, within "
        "the segment its position and its extrapolations (the nearest pairs' local affine "
        f"map, the pairs' homography) span, extended by its length and {BORDER_MARGIN:g} px "
        "at both ends, "
        "when that raised the consistency of its triangles as the correct move must (the "
        "images scored at the verdict's scale); no two neighbours move in one pass (a surface "
        "that shows only along the border, such as a floor nearer than the pairs above it, "
        "is missed by both extrapolations)",
    ),
    ALIGN_MOVE: Move(
        "vertex",
        "every vertex not given by the client moved together, after the other moves, so that "
        "the reference mapped through the mesh matches the moving image over all the "
        "triangles' pixels (locally normalized images, a gain and bias per triangle, robust "
        f"weights, coarse to fine), by at most {ALIGN_REACH:g} px; kept where the consistency "
        "(the swaps' cost) of its triangles, all aligned, did not fall below theirs before "
        "and no triangle folds (the matcher and the insertion place each vertex by a patch "
        "around it alone)",
    ),
    REMOVE_MOVE: Move(
        "vertex",
        "a measured inner vertex (not the client's) taken out of the mesh after the other "
        "vertex moves, its star triangulated again by the best of the fans from its corners "
        "that fold in neither image, when that raised the consistency (the swaps' cost) of "
        "the star by more than the correct move must; no two neighbours in one pass (a "
        "T-junction matches no surface wherever it goes; a right vertex whose triangles reach "
        "over a depth step maps the other surface wrong); it stays in the vertex list, which "
        "the initial mesh shares, in no final triangle",
    ),
    "swap": Move(
        "swap",
        "the consistency (cost) of the quad rose by more than its threshold",
    ),
    "pair": Move(
        "swap",
        "two swaps in a row: the consistency of the three triangles they change rose by more "
        "than its threshold where neither swap alone did",
    ),
}
"""Move name -> :class:`Move`; insertion sources run in this order."""

def inserted_mask(origins: list[str]) -> np.ndarray:
    """Per vertex, whether an insertion move of :data:`MOVES` found it (``origins`` as
    :attr:`core.pipeline.RegistrationResult.origins`)."""
    return np.array([MOVES.get(o) is not None and MOVES[o].kind == "insertion"
                     for o in origins], bool)


def insertions() -> list[tuple[str, Move]]:
    """The insertion sources, in their order."""
    return [(name, m) for name, m in MOVES.items() if m.kind == "insertion"]


def move_counts(
    origins: list[str], steps: list, *, moved: list[dict] | None = None
) -> list[dict]:
    """Per move of :data:`MOVES` that was made: its name, kind, count and reason.

    ``origins`` are the mesh vertices' origins (a move's name, or ``client``, ``matched``,
    ``frame``), ``steps`` the optimizer's accepted steps and ``moved`` the vertex moves'
    records (each with a ``move`` name).
    """
    made = [*origins, *(s.move for s in steps), *(m["move"] for m in moved or [])]
    return [
        {"move": name, "kind": m.kind, "count": made.count(name), "reason": m.reason}
        for name, m in MOVES.items() if name in made
    ]
