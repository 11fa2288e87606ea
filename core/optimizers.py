"""The mesh optimizers, one table: ``options.optimizer`` names an entry of :data:`OPTIMIZERS`.

Every optimizer takes the initial mesh (modified in place by its moves), the prepared images,
the options and a progress callback, and returns a :class:`core.optimize.SearchResult`. Adding
one is an entry here and its name in ``RegistrationOptions.optimizer`` (a test holds the two
lists equal).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

from core.baselines import morris_kanade_search, nakatuji_search
from core.mesh import Mesh
from core.optimize import ProgressFn, SearchResult, greedy_search
from core.similarity import ScoringImages, mutual_information, triangle_statistics

if TYPE_CHECKING:
    from core.options import RegistrationOptions

Optimizer = Callable[
    [Mesh, ScoringImages, "RegistrationOptions", "ProgressFn | None"], SearchResult
]


def keep_initial(
    mesh: Mesh, images: ScoringImages, options: RegistrationOptions, progress: ProgressFn | None
) -> SearchResult:
    """No optimization: the initial mesh, with its global MI (bits) and NMI."""
    tris = mesh.triangles
    hist, _ = triangle_statistics(images, mesh.reference[tris], mesh.moving[tris])
    mi, nmi = (float(v) for v in mutual_information(hist.sum(axis=0), images.bins))
    return SearchResult(
        initial_mi=mi, initial_nmi=nmi, final_mi=mi, final_nmi=nmi, stopped_because="optimizer none"
    )


def greedy(
    mesh: Mesh, images: ScoringImages, options: RegistrationOptions, progress: ProgressFn | None
) -> SearchResult:
    """The paper's Algorithm 1 (:func:`core.optimize.greedy_search`) with the options' cost."""
    return greedy_search(
        mesh, images, cost=options.cost, epsilon=options.epsilon,
        max_iterations=options.max_iterations, progress=progress,
    )


def morris_kanade(
    mesh: Mesh, images: ScoringImages, options: RegistrationOptions, progress: ProgressFn | None
) -> SearchResult:
    """Greedy descent of the global SSD (:func:`core.baselines.morris_kanade_search`)."""
    return morris_kanade_search(
        mesh, images, max_iterations=options.max_iterations, progress=progress
    )


def nakatuji(
    mesh: Mesh, images: ScoringImages, options: RegistrationOptions, progress: ProgressFn | None
) -> SearchResult:
    """Random search with a template inconsistency (:func:`core.baselines.nakatuji_search`)."""
    return nakatuji_search(
        mesh, images, seed=options.seed, max_iterations=options.max_iterations,
        progress=progress,
    )


OPTIMIZERS: dict[str, Optimizer] = {
    "none": keep_initial,
    "greedy": greedy,
    "morris-kanade": morris_kanade,
    "nakatuji": nakatuji,
}
"""Optimizer name (value of ``options.optimizer``) -> function."""
