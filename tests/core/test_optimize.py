import copy

import cv2
import numpy as np
import pytest
from scipy.spatial import Delaunay

from pwlreg.core.mesh import Mesh
from pwlreg.core.optimize import QuadScorer, TriangleCache, greedy_search
from pwlreg.core.optimizers import (
    OPTIMIZERS,
    keep_initial,
    optimize_again,
    optimize_on_level,
)
from pwlreg.core.options import RegistrationOptions
from pwlreg.core.raster import quantize
from pwlreg.core.similarity import prepare_images, reduced, to_level
from pwlreg.core.triangulation import initial_mesh
from tests.core.synthetic import book_points, open_book, texture


def _crosses(points, e, crease=100.0):
    a, b = points[e[0]], points[e[1]]
    return (a[0] - crease) * (b[0] - crease) < 0


def test_open_book_crease_edges_are_swapped():
    ref, mov = open_book()
    rp, mp = book_points()
    mesh, _ = initial_mesh(rp, mp, 25)
    before = [e for e in mesh.internal_edges() if _crosses(mesh.reference, e)]
    assert len(before) >= 2, "the test scene must start with crease-crossing diagonals"
    result = greedy_search(mesh, prepare_images(ref, mov, 16))
    assert [e for e in mesh.internal_edges() if _crosses(mesh.reference, e)] == []
    assert {s.removed for s in result.steps} == set(before)
    assert all(s.delta > 0.01 for s in result.steps)
    assert result.final_mi > result.initial_mi
    assert result.steps[-1].mi == pytest.approx(result.final_mi)
    assert result.stopped_because.startswith("no swap")


def test_planar_scene_no_swap_and_small_deltas():
    # A single plane: every triangulation registers exactly; resampling noise only.
    shape = (240, 320)
    mov = texture(shape, 4)
    A = np.array([[0.92, 0.1, 6.0], [-0.05, 0.95, 4.0]])
    ref = cv2.warpAffine(mov, A, (shape[1], shape[0]), flags=cv2.WARP_INVERSE_MAP)
    rng = np.random.default_rng(3)
    rp = rng.uniform(5, [shape[1] - 30, shape[0] - 30], size=(60, 2))
    mp = rp @ A[:, :2].T + A[:, 2]
    mesh, _ = initial_mesh(rp, mp, 25)
    images = prepare_images(ref, mov, 16)
    scorer = QuadScorer(TriangleCache(images, mesh), "mi")
    edges = [e for e in mesh.internal_edges() if mesh.can_swap(e)]
    deltas = scorer.deltas(mesh, edges)
    assert len(edges) > 50
    assert np.abs(deltas).max() < 0.01
    result = greedy_search(mesh, images)
    assert result.steps == []


def _figure6_pair(invert_right: bool):
    """Open book whose two faces change grey levels differently between the images."""
    ref_tex, mov = open_book(seed=7)
    # The crease maps onto the column x = 100 of the moving image (book_map fixes it).
    xs = np.arange(mov.shape[1])[None, :].repeat(mov.shape[0], axis=0)
    right = xs > 100
    mov2 = mov.astype(np.float64)
    mov2[~right] = 0.5 * mov2[~right] + 20  # darker, lower contrast
    if invert_right:
        mov2[right] = 255 - mov2[right]  # contrast inversion: NCC is fooled, MI is not
    else:
        mov2[right] = np.clip(1.3 * mov2[right] + 30, 0, 255)
    return ref_tex, np.round(mov2).astype(np.uint8)


@pytest.mark.parametrize("invert_right", [False, True])
def test_figure6_mi_picks_3d_compatible_diagonal(invert_right):
    ref, mov = _figure6_pair(invert_right)
    rp, mp = book_points()
    mesh, _ = initial_mesh(rp, mp, 25)
    greedy_search(mesh, prepare_images(ref, mov, 16), cost="mi")
    assert [e for e in mesh.internal_edges() if _crosses(mesh.reference, e)] == []
    if invert_right:
        # The paper's point: a non-linear radiometric change fools NCC.
        mesh, _ = initial_mesh(rp, mp, 25)
        greedy_search(mesh, prepare_images(ref, mov, 16), cost="ncc")
        assert [e for e in mesh.internal_edges() if _crosses(mesh.reference, e)] != []


def test_deterministic():
    ref, mov = open_book(seed=3)
    rp, mp = book_points()
    runs = []
    for _ in range(2):
        mesh, _ = initial_mesh(rp, mp, 25)
        res = greedy_search(mesh, prepare_images(ref, mov, 16))
        runs.append(([(s.removed, s.added, s.delta) for s in res.steps], mesh.triangles.tolist()))
    assert runs[0] == runs[1]


def test_ncc_cost_and_max_iterations():
    ref, mov = open_book()
    rp, mp = book_points()
    mesh, _ = initial_mesh(rp, mp, 25)
    res = greedy_search(mesh, prepare_images(ref, mov, 16), cost="ncc")
    assert [e for e in mesh.internal_edges() if _crosses(mesh.reference, e)] == []
    mesh, _ = initial_mesh(rp, mp, 25)
    res = greedy_search(mesh, prepare_images(ref, mov, 16), max_iterations=1)
    assert len(res.steps) == 1 and res.stopped_because == "max_iterations reached"


def test_progress_can_abort():
    ref, mov = open_book()
    rp, mp = book_points()
    mesh, _ = initial_mesh(rp, mp, 25)

    class Stop(Exception):
        pass

    def progress(f):
        raise Stop

    with pytest.raises(Stop):
        greedy_search(mesh, prepare_images(ref, mov, 16), progress=progress)


def test_progress_reports_leave_the_search_as_it_was():
    # Reported after every swap, the compiled search is left and entered again each time.
    ref, mov = open_book()
    rp, mp = book_points()
    images = prepare_images(ref, mov, 16)
    quiet, _ = initial_mesh(rp, mp, 25)
    alone = greedy_search(quiet, images, epsilon_pixels=250, lookahead=True)
    seen = []
    told, _ = initial_mesh(rp, mp, 25)
    reported = greedy_search(told, images, epsilon_pixels=250, lookahead=True,
                             progress=seen.append, progress_interval=0.0)
    assert len(alone.steps) >= 2 and len(seen) == len(alone.steps) + 1
    assert seen[0] == 0.0 and all(0.0 < f <= 1.0 for f in seen[1:])
    assert ([(s.removed, s.added, s.delta, s.nmi) for s in reported.steps]
            == [(s.removed, s.added, s.delta, s.nmi) for s in alone.steps])
    assert np.array_equal(told.triangles, quiet.triangles)
    assert reported.evaluations == alone.evaluations


def test_quad_gain_is_antisymmetric():
    rng = np.random.default_rng(0)
    ref = texture((100, 120), 1)
    pts = quantize(rng.uniform(0, [119, 99], size=(20, 2)))
    mesh = Mesh(pts, pts + 0.5, Delaunay(pts).simplices)
    scorer = QuadScorer(TriangleCache(prepare_images(ref, ref, 16), mesh), "mi")
    e = next(e for e in mesh.internal_edges() if mesh.can_swap(e))
    d = scorer.deltas(mesh, [e])[0]
    new = mesh.swap(e)
    assert scorer.deltas(mesh, [new])[0] == pytest.approx(-d, abs=1e-12)


def test_search_never_cycles():
    # A scene where improving NCC swaps cycle through the triangulations of a convex pentagon
    # (found by the quality report); with retired edges the search ends on its own.
    scenes = pytest.importorskip("bench.scenes")
    sc = scenes.make_scene(
        "city",
        7,
        size=(640, 480),
        camera="perspective",
        radiometric="nonmonotone",
        noise=2.0,
        blur=0.8,
        n_interior=40,
    )
    mesh, _ = initial_mesh(sc.points_reference, sc.points_moving, 25)
    res = greedy_search(
        mesh, prepare_images(sc.reference, sc.moving, 16), cost="ncc", max_iterations=2000
    )
    assert res.stopped_because.startswith("no swap")
    removed = [s.removed for s in res.steps]
    assert len(set(removed)) == len(removed)
    # No swap re-creates an edge an earlier swap removed.
    assert all(s.added not in removed[: s.iteration - 1] for s in res.steps)


def test_the_cost_table_and_the_option_list_agree():
    from pwlreg.core.optimize import COSTS
    from pwlreg.core.options import RegistrationOptions

    assert set(RegistrationOptions.model_fields["cost"].annotation.__args__) == set(COSTS)


def test_greedy_pyramid_runs_sharp_last_and_reports_on_the_images():
    from pwlreg.core.pipeline import register
    from tests.core.synthetic import book_points, open_book

    reference, moving = open_book(seed=2)
    rp, mp = book_points()
    plain = register(reference, moving, (rp, mp), {"optimizer": "none", "extent": "hull"})
    pyr = register(reference, moving, (rp, mp),
                   {"optimizer": "greedy-pyramid", "extent": "hull"})
    assert pyr.search.initial_mi == pytest.approx(plain.search.initial_mi)
    assert [s.iteration for s in pyr.search.steps] == list(range(1, len(pyr.search.steps) + 1))
    assert pyr.search.steps  # the crease-crossing diagonals get swapped
    assert pyr.search.final_mi > pyr.search.initial_mi


def test_gain_thresholds_follow_the_quad_size_within_bounds():
    from pwlreg.core.optimize import gain_thresholds

    n = np.array([62.5, 250.0, 500.0, 1e6, 1.0])
    t = gain_thresholds(n, 0.01, 250.0)
    assert t[1] == pytest.approx(0.01)
    assert t[0] == pytest.approx(0.02) and t[2] == pytest.approx(0.01 / np.sqrt(2))
    assert t[3] == pytest.approx(0.005) and t[4] == pytest.approx(0.05)  # the bounds
    assert np.all(gain_thresholds(n, 0.01, 0.0) == 0.01)  # the paper's fixed epsilon


def test_the_compiled_search_s_threshold_is_the_batched_one_bit_for_bit():
    from pwlreg.core.kernels import gain_threshold
    from pwlreg.core.optimize import THRESHOLD_RANGE, gain_thresholds

    rng = np.random.default_rng(0)
    pixels = np.concatenate([rng.integers(0, 200_000, 2000), [0, 1, 2, 249, 250, 251]])
    pixels = pixels.astype(np.float64)
    for epsilon, epsilon_pixels in ((0.01, 250.0), (0.013, 77.7), (0.01, 0.0)):
        batched = gain_thresholds(pixels, epsilon, epsilon_pixels).tolist()
        assert [gain_threshold(p, epsilon, epsilon_pixels, *THRESHOLD_RANGE)
                for p in pixels.tolist()] == batched


def _pentagon_nmi(images, mesh, triangles):
    idx = np.array(triangles, dtype=np.int64)
    from pwlreg.core.similarity import mutual_information, triangle_statistics

    hist, _ = triangle_statistics(images, mesh.reference[idx], mesh.moving[idx])
    return float(mutual_information(hist.sum(axis=0), images.bins)[1])


def _gable():
    """A scene whose search needs pairs of swaps: its images and points."""
    scenes = pytest.importorskip("bench.scenes")
    sc = scenes.make_scene("gable", 4, size=(640, 480), camera="affine",
                           radiometric="nonmonotone", noise=2.0, blur=0.0, n_interior=40)
    return sc, prepare_images(sc.reference, sc.moving, 16)


def test_lookahead_pairs_gain_what_they_record_over_their_pentagon():
    sc, images = _gable()
    plain, _ = initial_mesh(sc.points_reference, sc.points_moving, 25)
    mesh = plain.copy()
    single = greedy_search(plain, images, epsilon_pixels=250)
    res = greedy_search(mesh, images, epsilon_pixels=250, lookahead=True)
    pairs = [s for s in res.steps if s.move == "pair"]
    assert pairs and len(pairs) % 2 == 0, "this scene needs two swaps in a row somewhere"
    assert all(a.delta == b.delta > 0 for a, b in zip(pairs[::2], pairs[1::2], strict=True))
    assert res.final_nmi > single.final_nmi  # the pairs add consistency the single swaps missed
    # Replaying the steps on a fresh mesh, every pair raises its pentagon's NMI by its delta.
    replay, _ = initial_mesh(sc.points_reference, sc.points_moving, 25)
    steps = res.steps
    n = 0
    while n < len(steps):
        if steps[n].move != "pair":
            replay.swap(steps[n].removed)
            n += 1
            continue
        first, second = steps[n], steps[n + 1]
        q = replay.quad(first.removed)
        before = [replay.triangle(s) for s in q.slots]
        outer = [s for s in replay.edge_triangles(second.removed)
                 if set(replay.triangle(s)) - set(q[:4])]
        before.append(replay.triangle(outer[0]))
        replay.swap(first.removed)
        replay.swap(second.removed)
        pentagon = set().union(*map(set, before))
        after = [t for t in map(replay.triangle, replay.slots()) if set(t) <= pentagon]
        assert len(after) == 3
        gain = _pentagon_nmi(images, replay, after) - _pentagon_nmi(images, replay, before)
        assert gain == pytest.approx(first.delta, abs=1e-9)
        n += 2
    assert not replay.reversed_slots()


def test_the_searched_mesh_is_the_one_its_swaps_make():
    # The compiled search hands its triangles back to the Mesh at the end: they must be those
    # the recorded swaps make, each a valid swap in turn, with the same owners for every edge.
    sc, images = _gable()
    mesh, _ = initial_mesh(sc.points_reference, sc.points_moving, 25)
    replay = copy.deepcopy(mesh)  # the same slots (Mesh.copy compacts them)
    res = greedy_search(mesh, images, epsilon_pixels=250, lookahead=True)
    assert len(res.steps) > 20 and any(s.move == "pair" for s in res.steps)
    for s in res.steps:
        assert replay.swap(s.removed) == s.added
    assert mesh.slot_triangles()[0].tolist() == replay.slot_triangles()[0].tolist()
    assert mesh.edges() == replay.edges()
    assert all(sorted(mesh.edge_triangles(e)) == sorted(replay.edge_triangles(e))
               for e in mesh.edges())
    assert not mesh.reversed_slots()
    # A second search (its retired edges forgotten) goes on from either mesh alike.
    again = [greedy_search(m, images, epsilon_pixels=250, lookahead=True) for m in (mesh, replay)]
    assert again[0].steps and [(s.removed, s.added, s.delta) for s in again[0].steps] == [
        (s.removed, s.added, s.delta) for s in again[1].steps]


def _pair_moves_loop(mesh, edges, allowed):
    """pair_moves written as the loops of its docstring (the compiled one must agree)."""
    rows = []
    for e in edges:
        q = mesh.quad(e)
        if not allowed((q.k, q.l)):
            continue
        for p, p2 in ((q.i, q.j), (q.j, q.i)):
            for r, r2 in ((q.k, q.l), (q.l, q.k)):
                owners = mesh.edge_triangles((p, r))
                outer = [s for s in owners if p2 not in mesh.triangle(s)]
                if len(owners) != 2 or len(outer) != 1:
                    continue
                m = sum(mesh.triangle(outer[0])) - p - r
                if m in (r2, p2) or mesh.has_edge((r2, m)) or not allowed((r2, m)):
                    continue
                trial = mesh.copy()  # swapping back would reorder the owners of edges
                trial.swap(e, check=False)
                if trial.can_swap((p, r)):
                    rows.append((q.i, q.j, q.k, q.l, m, p, r, p2, r2))
    return rows


def _compiled_pairs(mesh, banned, near=None):
    from pwlreg.core import kernels
    from pwlreg.core.optimize import compiled_mesh

    n = len(mesh.reference)
    retired = kernels.empty_set()
    for i, j in banned:
        retired[i * n + j] = 1
    moved = np.zeros(n, dtype=np.uint8)
    moved[list(near or ())] = 1
    return kernels.pair_moves(compiled_mesh(mesh), retired, moved, near is not None)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_pair_moves_agree_with_the_loops(seed):
    rng = np.random.default_rng(seed)
    ref = quantize(rng.uniform(0, 200, size=(60, 2)))
    mesh = Mesh(ref, ref + rng.normal(0, 8, size=ref.shape), Delaunay(ref).simplices)
    for e in mesh.swappable_edges()[::7]:
        if mesh.can_swap(e):
            mesh.swap(e)
    edges = mesh.swappable_edges()
    # Edges the first swaps would create: retired, as the search retires swapped-away edges.
    banned = {(min(q.k, q.l), max(q.k, q.l)) for q in map(mesh.quad, edges[::5])}
    allowed = lambda e: (min(e), max(e)) not in banned  # noqa: E731
    pairs = _compiled_pairs(mesh, banned)
    assert len(pairs) > 20
    assert pairs.tolist() == [list(r) for r in _pair_moves_loop(mesh, edges, allowed)]
    # Only the edges with an end among some vertices (those of quads changed since a pass).
    near = {3, 17, 40}
    nearby = [e for e in edges if e[0] in near or e[1] in near]
    assert nearby
    assert _compiled_pairs(mesh, banned, near).tolist() == [
        list(r) for r in _pair_moves_loop(mesh, nearby, allowed)]
    assert _compiled_pairs(mesh, banned, set()).shape == (0, 9)
    # Something retired: fewer pairs than without.
    assert len(_compiled_pairs(mesh, set())) > len(pairs)


def _doubled_book() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The open book at twice its size: images, reference and moving points."""
    ref, mov = open_book()
    rp, mp = book_points()
    up = [cv2.resize(im, None, fx=2, fy=2, interpolation=cv2.INTER_CUBIC) for im in (ref, mov)]
    return up[0], up[1], (rp + 0.5) * 2 - 0.5, (mp + 0.5) * 2 - 0.5


def test_optimizing_on_a_reduced_level_swaps_the_crease_and_reports_on_it():
    ref, mov, rp, mp = _doubled_book()
    images = prepare_images(ref, mov, 16)
    level, scale = reduced(images, 200)
    assert scale == 0.5
    mesh, _ = initial_mesh(rp, mp, 25)
    assert [e for e in mesh.internal_edges() if _crosses(mesh.reference, e, 200.5)]
    out, result = optimize_on_level(mesh, level, scale, RegistrationOptions(), None)
    assert [e for e in out.internal_edges() if _crosses(out.reference, e, 200.5)] == []
    np.testing.assert_array_equal(out.reference, mesh.reference)
    np.testing.assert_array_equal(out.moving, mesh.moving)

    def whole(m: Mesh):  # a pass over the whole mesh on the level
        return keep_initial(Mesh(to_level(m.reference, scale), to_level(m.moving, scale),
                                 m.triangles), level, None, None)

    # Every figure is the level's.
    assert result.initial_mi == whole(mesh).initial_mi
    assert (result.final_mi, result.final_nmi) == (whole(out).final_mi, whole(out).final_nmi)
    assert result.steps[-1].mi == pytest.approx(result.final_mi)
    # At scale 1 the optimizer runs on the mesh itself.
    again, _ = initial_mesh(rp, mp, 25)
    same, direct = optimize_on_level(again, images, 1.0, RegistrationOptions(), None)
    assert same is again and direct.steps


def test_the_optimizer_runs_again_after_the_vertex_moves_within_its_budget():
    ref, mov = open_book()
    rp, mp = book_points()
    images = prepare_images(ref, mov, 16)
    mesh, _ = initial_mesh(rp, mp, 25)
    crossing = [e for e in mesh.internal_edges() if _crosses(mesh.reference, e)]
    assert len(crossing) >= 2
    one = RegistrationOptions(max_iterations=1)
    first = OPTIMIZERS["greedy"](mesh, images, one, None)
    assert len(first.steps) == 1
    # The budget is the options' in all: one more swap, numbered after the first search's.
    two = RegistrationOptions(max_iterations=2)
    out, again = optimize_again(first, mesh, images, 1.0, two, elapsed=5.0)
    assert [s.iteration for s in again.steps] == [1, 2]
    assert again.steps[0] == first.steps[0] and again.steps[1].elapsed_s >= 5.0
    out, again = optimize_again(first, mesh, images, 1.0, RegistrationOptions(), elapsed=5.0)
    assert [e for e in out.internal_edges() if _crosses(out.reference, e)] == []
    assert [s.iteration for s in again.steps] == list(range(1, len(again.steps) + 1))
    assert again.initial_mi == first.initial_mi and again.final_mi > first.final_mi
    whole = keep_initial(out, images, None, None)
    assert (again.final_mi, again.final_nmi) == (whole.final_mi, whole.final_nmi)
