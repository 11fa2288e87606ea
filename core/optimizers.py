"""The mesh optimizers, one table: ``options.optimizer`` names an entry of :data:`OPTIMIZERS`.

Every optimizer takes the initial mesh (modified in place by its moves), the prepared images,
the options and a progress callback, and returns a :class:`core.optimize.SearchResult`. Adding
one is an entry here and its name in ``RegistrationOptions.optimizer`` (a test holds the two
lists equal). On the path with vertex moves the pipeline runs the options' optimizer on the
verdict's reduced images (:func:`optimize_on_level`) and again after the moves
(:func:`optimize_again`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from pwlreg.core.baselines import morris_kanade_search, nakatuji_search
from pwlreg.core.mesh import Mesh
from pwlreg.core.optimize import ProgressFn, SearchResult, greedy_search
from pwlreg.core.similarity import (
    ScoringImages,
    mutual_information,
    smoothed,
    to_level,
    triangle_statistics,
)

if TYPE_CHECKING:
    from pwlreg.core.options import RegistrationOptions

Optimizer = Callable[
    [Mesh, ScoringImages, "RegistrationOptions", "ProgressFn | None"], SearchResult
]


def keep_initial(
    mesh: Mesh, images: ScoringImages, options: RegistrationOptions, progress: ProgressFn | None
) -> SearchResult:
    """No optimization: the initial mesh, with its global MI (bits) and NMI (one pass over its
    pixels)."""
    # Each triangle's vertices in increasing order, as the compiled search counts them: the map
    # of a triangle's pixels, computed from another corner, can round a sample across a bin's
    # edge (a sliver of a halved image, 3e-5 bits after 361 swaps).
    tris = np.sort(mesh.triangles, axis=1)
    hist, _ = triangle_statistics(images, mesh.reference[tris], mesh.moving[tris])
    mi, nmi = (float(v) for v in mutual_information(hist.sum(axis=0), images.bins))
    return SearchResult(initial_mi=mi, initial_nmi=nmi, final_mi=mi, final_nmi=nmi,
                        stopped_because="optimizer none")


def optimize_on_level(
    mesh: Mesh,
    level: ScoringImages,
    scale: float,
    options: RegistrationOptions,
    progress: ProgressFn | None,
) -> tuple[Mesh, SearchResult]:
    """The options' optimizer on ``level``, the images reduced by ``scale`` from the mesh's
    pixels (:func:`core.similarity.reduced`): the mesh with the triangles it chose (``mesh``
    itself, changed in place, at scale 1), and its result, whose figures are ``level``'s."""
    optimizer = OPTIMIZERS[options.optimizer]
    if scale == 1.0:
        return mesh, optimizer(mesh, level, options, progress)
    scaled = Mesh(to_level(mesh.reference, scale), to_level(mesh.moving, scale), mesh.triangles)
    result = optimizer(scaled, level, options, progress)
    return Mesh(mesh.reference, mesh.moving, scaled.triangles), result


def optimize_again(
    search: SearchResult,
    mesh: Mesh,
    level: ScoringImages,
    scale: float,
    options: RegistrationOptions,
    *,
    elapsed: float,
) -> tuple[Mesh, SearchResult]:
    """After the vertex moves (:mod:`core.correct`), the optimizer once more over ``mesh``
    (:func:`optimize_on_level`): the mesh, and ``search`` with its steps after the first
    search's (``elapsed`` seconds added to theirs, the time since that search began), within
    the options' ``max_iterations`` in all.

    The first search ranked the diagonals by vertices the moves then changed (Middlebury's
    frame 0.494 / 0.325 / 0.924 / 1.105 px before this second search, 0.481 / 0.319 / 0.888
    / 1.066 after).
    """
    budget = max(options.max_iterations - len(search.steps), 0)
    mesh, again = optimize_on_level(
        mesh, level, scale, options.model_copy(update={"max_iterations": budget}), None)
    first = len(search.steps)
    steps = [replace(s, iteration=first + k + 1, elapsed_s=s.elapsed_s + elapsed)
             for k, s in enumerate(again.steps)]
    return mesh, replace(search, steps=search.steps + steps, final_mi=again.final_mi,
                         final_nmi=again.final_nmi,
                         evaluations=search.evaluations + again.evaluations,
                         stopped_because=again.stopped_because)


def greedy(
    mesh: Mesh, images: ScoringImages, options: RegistrationOptions, progress: ProgressFn | None
) -> SearchResult:
    """The paper's Algorithm 1 (:func:`core.optimize.greedy_search`) with the options' cost."""
    return greedy_search(
        mesh, images, cost=options.cost, epsilon=options.epsilon,
        max_iterations=options.max_iterations, progress=progress,
        epsilon_pixels=options.epsilon_pixels, lookahead=options.lookahead,
    )


#: Blur (pixels) of the successive passes of :func:`greedy_pyramid`; the last is the images.
PYRAMID_SIGMAS = (3.0, 1.0, 0.0)


def greedy_pyramid(
    mesh: Mesh, images: ScoringImages, options: RegistrationOptions, progress: ProgressFn | None
) -> SearchResult:
    """The greedy search on blurred images first, then on sharper ones (:data:`PYRAMID_SIGMAS`).

    Mutual information saturates once a quad is misregistered by more than the scale of its
    texture; on blurred images it still tells the better diagonal, and the sharp pass then
    decides the rest. Each pass retires its own swapped edges only. The swaps' ``mi``/``nmi``
    are measured on the images of their pass; the initial and final figures on the images.
    """
    start = keep_initial(mesh, images, options, None)
    steps: list = []
    result = start
    for i, sigma in enumerate(PYRAMID_SIGMAS):
        level = images if sigma == 0 else smoothed(images, sigma)

        def report(f: float, i: int = i) -> None:
            progress((i + f) / len(PYRAMID_SIGMAS))  # type: ignore[misc]

        result = greedy_search(
            mesh, level, cost=options.cost, epsilon=options.epsilon,
            max_iterations=max(options.max_iterations - len(steps), 0),
            progress=None if progress is None else report,
            epsilon_pixels=options.epsilon_pixels, lookahead=options.lookahead,
        )
        steps += [replace(s, iteration=len(steps) + k + 1) for k, s in enumerate(result.steps)]
    result.initial_mi, result.initial_nmi = start.initial_mi, start.initial_nmi
    result.steps = steps
    return result


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
    "greedy-pyramid": greedy_pyramid,
    "morris-kanade": morris_kanade,
    "nakatuji": nakatuji,
}
"""Optimizer name (value of ``options.optimizer``) -> function."""
