"""Baseline optimizers (Morris-Kanade, Nakatuji-Sugaya-Kanatani) through the pipeline."""

import numpy as np
import pytest

from bench.scenes import make_scene
from pwlreg.core.baselines import (
    morris_kanade_search,
    quad_inconsistency,
    ssd_swap_changes,
)
from pwlreg.core.mesh import Mesh
from pwlreg.core.optimize import TriangleCache
from pwlreg.core.optimizers import OPTIMIZERS
from pwlreg.core.options import RegistrationOptions
from pwlreg.core.pipeline import register
from pwlreg.core.raster import label_image
from pwlreg.core.similarity import prepare_images, ssd, triangle_statistics
from pwlreg.core.triangulation import initial_mesh
from tests.core.synthetic import book_points, open_book

BASELINES = ("morris-kanade", "nakatuji")


@pytest.fixture(scope="module")
def scene():
    return make_scene("open_book", 2, size=(320, 240), supersample=2)


def _register(scene, optimizer, **options):
    return register(
        scene.reference,
        scene.moving,
        (scene.points_reference, scene.points_moving),
        {"optimizer": optimizer, "epipolar_filter": False, **options},
    )


def _global_ssd(images, mesh_like_ref, mesh_like_mov, triangles):
    _, moments = triangle_statistics(
        images, mesh_like_ref[triangles], mesh_like_mov[triangles], with_moments=True
    )
    return float(ssd(moments.sum(axis=0)))


@pytest.mark.parametrize("optimizer", BASELINES)
def test_baseline_keeps_a_valid_triangulation(scene, optimizer):
    result = _register(scene, optimizer)
    ref, mov = result.reference_vertices, result.moving_vertices
    before = Mesh(ref, mov, result.initial_triangles)
    after = Mesh(ref, mov, result.final_triangles)
    assert len(result.search.steps) > 0
    assert after.n_triangles == before.n_triangles
    assert after.boundary_edges() == before.boundary_edges()
    assert after.reversed_slots() == []
    shape = scene.shape
    np.testing.assert_array_equal(
        label_image(ref[result.final_triangles], shape) >= 0,
        label_image(ref[result.initial_triangles], shape) >= 0,
    )
    # The convergence record: global MI after every accepted swap, time non-decreasing.
    steps = result.search.steps
    assert [s.iteration for s in steps] == list(range(1, len(steps) + 1))
    assert steps[-1].mi == pytest.approx(result.search.final_mi)
    assert all(b.elapsed_s >= a.elapsed_s for a, b in zip(steps, steps[1:], strict=False))
    assert all(s.delta > 0 for s in steps)


@pytest.mark.parametrize("optimizer", BASELINES)
def test_baseline_is_deterministic(scene, optimizer):
    runs = [_register(scene, optimizer, seed=5) for _ in range(2)]
    assert runs[0].final_triangles.tolist() == runs[1].final_triangles.tolist()
    assert [(s.removed, s.added) for s in runs[0].search.steps] == [
        (s.removed, s.added) for s in runs[1].search.steps
    ]


def test_morris_kanade_lowers_the_global_ssd(scene):
    result = _register(scene, "morris-kanade")
    images = prepare_images(scene.reference, scene.moving, 16)
    ref, mov = result.reference_vertices, result.moving_vertices
    before = _global_ssd(images, ref, mov, result.initial_triangles)
    after = _global_ssd(images, ref, mov, result.final_triangles)
    assert after < before
    assert sum(s.delta for s in result.search.steps) == pytest.approx(before - after, rel=1e-6)


def test_morris_kanade_decision_equals_full_recomputation():
    # The cached quad change is the change of the SSD of the whole re-rendered mesh.
    ref_img, mov_img = open_book(seed=4)
    rp, mp = book_points()
    mesh, _ = initial_mesh(rp, mp, 25)
    images = prepare_images(ref_img, mov_img, 16)
    cache = TriangleCache(images, mesh, with_moments=True)
    edges = [e for e in mesh.internal_edges() if mesh.can_swap(e)]
    fast = ssd_swap_changes(mesh, cache, edges)
    base = _global_ssd(images, mesh.reference, mesh.moving, mesh.triangles)
    full = []
    for e in edges:
        m = mesh.copy()
        m.swap(e)
        full.append(_global_ssd(images, m.reference, m.moving, m.triangles) - base)
    np.testing.assert_allclose(fast, full, rtol=1e-9, atol=1e-9 * base)
    assert int(np.argmin(fast)) == int(np.argmin(full))


def test_morris_kanade_respects_max_iterations_and_progress(scene):
    result = _register(scene, "morris-kanade", max_iterations=1)
    assert len(result.search.steps) == 1
    assert result.search.stopped_because == "max_iterations reached"

    class Stop(Exception):
        pass

    def progress(fraction):
        raise Stop

    mesh, _ = initial_mesh(scene.points_reference, scene.points_moving, 25)
    with pytest.raises(Stop):
        morris_kanade_search(
            mesh, prepare_images(scene.reference, scene.moving, 16), progress=progress
        )


def test_nakatuji_max_iterations_and_cancel(scene):
    result = _register(scene, "nakatuji", max_iterations=2)
    assert len(result.search.steps) == 2
    assert result.search.stopped_because == "max_iterations reached"
    seen = []

    def progress(fraction):
        seen.append(fraction)
        if len(seen) > 1:
            raise KeyboardInterrupt

    mesh, _ = initial_mesh(scene.points_reference, scene.points_moving, 25)
    images = prepare_images(scene.reference, scene.moving, 16)
    with pytest.raises(KeyboardInterrupt):
        OPTIMIZERS["nakatuji"](mesh, images, RegistrationOptions(), progress)
    assert all(0.0 <= f <= 1.0 for f in seen)


def test_template_detects_the_crease_crossing_diagonal():
    # Exact two-plane map, no noise: the diagonal along one plane is consistent, the one
    # crossing the crease is not.
    ref_img, mov_img = open_book(seed=1)
    rp, mp = book_points()
    mesh, _ = initial_mesh(rp, mp, 25)
    images = prepare_images(ref_img, mov_img, 16)
    crossing = [
        e
        for e in mesh.internal_edges()
        if (mesh.reference[e[0], 0] - 100) * (mesh.reference[e[1], 0] - 100) < 0
        and mesh.can_swap(e)
    ]
    assert crossing
    for e in crossing:
        q = mesh.quad(e)
        configurations = [(q.i, q.j, q.k, q.l), (q.k, q.l, q.i, q.j)]
        now, swapped = quad_inconsistency(images, mesh, configurations)
        assert swapped < now
        assert swapped < 0.05


def test_the_optimizer_table_and_the_option_list_agree():
    allowed = RegistrationOptions.model_fields["optimizer"].annotation.__args__
    assert set(allowed) == set(OPTIMIZERS)
