import re

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import Delaunay, QhullError

from pwlreg.core.mesh import MAX_COORDINATE, Mesh, edge_key, orient_fixed
from pwlreg.core.raster import SUBPIXEL, fixed_point, label_image, orientation, quantize


def _random_mesh(seed, n=30, jitter=2.0):
    rng = np.random.default_rng(seed)
    ref = quantize(rng.uniform(0, 100, size=(n, 2)))
    mov = ref + rng.normal(0, jitter, size=ref.shape)
    tris = Delaunay(ref).simplices
    return Mesh(ref, mov, tris)


def _coverage(mesh):
    return label_image(mesh.reference[mesh.triangles], (101, 101)) >= 0


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**31), st.lists(st.integers(0, 10_000), min_size=1, max_size=40))
def test_legal_swaps_keep_a_triangulation(seed, picks):
    mesh = _random_mesh(seed)
    n_tri = mesh.n_triangles
    boundary = mesh.boundary_edges()
    coverage = _coverage(mesh)
    reversed_before = set(map(tuple, mesh.triangles[mesh.reversed_slots()].tolist()))
    for p in picks:
        legal = [e for e in mesh.internal_edges() if mesh.can_swap(e)]
        if not legal:
            break
        mesh.swap(legal[p % len(legal)])
    assert mesh.n_triangles == n_tri
    assert mesh.boundary_edges() == boundary
    np.testing.assert_array_equal(_coverage(mesh), coverage)
    # Each pixel still owned once: labels cover exactly the same region (checked above) and the
    # triangle areas add up to the hull area.
    tri = mesh.reference[mesh.triangles]
    d1, d2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    area = 0.5 * (d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0])
    assert np.all(area > 0)
    hull = Delaunay(mesh.reference).convex_hull
    assert area.sum() == pytest.approx(_hull_area(mesh.reference, hull), rel=1e-9)
    # Every internal edge has exactly two triangles, and no swap created a patch reversal.
    assert all(len(mesh.edge_triangles(e)) == 2 for e in mesh.internal_edges())
    after = set(map(tuple, mesh.triangles[mesh.reversed_slots()].tolist()))
    assert after <= reversed_before


def _hull_area(points, hull_edges):
    from scipy.spatial import ConvexHull

    return ConvexHull(points).volume


def test_swap_preconditions():
    ref = np.array([[0, 0], [10, 0], [10, 10], [0, 10]], float)
    mesh = Mesh(ref, ref + 1, [[0, 1, 2], [0, 2, 3]])
    assert mesh.internal_edges() == [(0, 2)]
    assert mesh.swap_blocker((0, 1)) == "boundary edge"
    assert mesh.swap((0, 2)) == (1, 3)
    assert mesh.swap_blocker((1, 3)) is None  # swapping back is legal
    # Non-convex quad in the reference mesh: dart shape.
    dart = np.array([[0, 0], [10, 5], [0, 10], [3, 5]], float)
    m2 = Mesh(dart, dart, [[0, 1, 3], [1, 2, 3]])
    assert m2.swap_blocker((1, 3)) == "quad not strictly convex"
    # Convex in the reference, not in the moving mesh.
    m3 = Mesh(ref, dart, [[0, 1, 2], [0, 2, 3]])
    assert m3.swap_blocker((0, 2)) == "quad not strictly convex"
    with pytest.raises(ValueError):
        m3.swap((0, 2))


def test_existing_new_edge_blocks_swap():
    # Vertex 4 at the centre: edge (0, 2) quad opposite vertices are 1 and 3 only if the mesh
    # is the two-triangle square; build a mesh where the new edge already exists.
    ref = np.array([[0, 0], [10, 0], [10, 10], [0, 10], [5, -20]], float)
    tris = [[0, 1, 2], [0, 2, 3], [0, 4, 1]]
    mesh = Mesh(ref, ref, tris)
    assert mesh.swap_blocker((0, 2)) is None
    mesh2 = Mesh(ref, ref, [[0, 1, 3], [1, 2, 3], [0, 4, 1]])
    assert mesh2.is_internal((1, 3))


def test_reversed_slots_detects_flipped_triangle():
    ref = np.array([[0, 0], [10, 0], [0, 10]], float)
    mov = np.array([[0, 0], [0, 10], [10, 0]], float)
    assert Mesh(ref, mov, [[0, 1, 2]]).reversed_slots() == [0]
    assert Mesh(ref, ref, [[0, 1, 2]]).reversed_slots() == []


@settings(max_examples=20, deadline=None)
@given(st.integers(0, 2**31))
def test_batched_swappable_edges_agree_with_can_swap(seed):
    mesh = _random_mesh(seed, n=40, jitter=6.0)
    assert mesh.swappable_edges() == [e for e in mesh.internal_edges() if mesh.can_swap(e)]


@settings(max_examples=20, deadline=None)
@given(st.integers(0, 2**31))
def test_swappable_quad_agrees_with_swap_blocker(seed):
    # The fast single test of the search says what swap_blocker says.
    mesh = _random_mesh(seed, n=40, jitter=6.0)
    rng = np.random.default_rng(seed)
    for _ in range(3):
        for e in mesh.edges():
            q = mesh.swappable_quad(e)
            assert (q is None) == (mesh.swap_blocker(e) is not None)
            if q is not None:
                assert q == mesh.quad(e)
        legal = mesh.swappable_edges()
        if legal:
            mesh.swap(legal[int(rng.integers(len(legal)))])


def test_across_gives_the_outer_apex():
    ref = np.array([[0, 0], [10, 0], [10, 10], [0, 10], [5, -20]], float)
    mesh = Mesh(ref, ref, [[0, 1, 2], [0, 2, 3], [0, 4, 1]])
    assert mesh.across((0, 1), 2) == 4
    assert mesh.across((1, 0), 4) == 2
    assert mesh.across((0, 1), 3) == -1  # 3 is on neither side
    assert mesh.across((1, 2), 0) == -1  # boundary edge
    assert mesh.across((1, 3), 0) == -1  # no such edge


def test_edge_table_matches_quads():
    mesh = _random_mesh(5, n=40, jitter=6.0)
    for e in mesh.swappable_edges()[:10]:
        mesh.swap(e)  # owner lists out of their construction order
    codes, apexes = mesh.edge_table()
    n = len(mesh.reference)
    assert codes.tolist() == [i * n + j for i, j in mesh.edges()]
    for (i, j), (a, b) in zip(mesh.edges(), apexes.tolist(), strict=True):
        if mesh.is_internal((i, j)):
            q = mesh.quad((i, j))
            assert (a, b) == (q.k, q.l)
        else:
            assert b == -1 and set(mesh.triangle(mesh.edge_triangles((i, j))[0])) == {i, j, a}


# -- construction: the vectorised Mesh.__init__ against the per-triangle one it replaced --------
def _reference_state(reference, moving, triangles):
    """The state the per-triangle construction built: ``(reference, moving, ref_fixed,
    mov_fixed, tris, edges)``, with its ``ValueError``s."""
    for pts in (reference, moving):
        arr = np.asarray(pts, dtype=np.float64)
        if not np.all(np.isfinite(arr)) or np.abs(arr).max(initial=0.0) > MAX_COORDINATE:
            raise ValueError(f"vertex coordinates must be finite, at most {MAX_COORDINATE} px")
    ref = quantize(reference).reshape(-1, 2)
    mov = quantize(moving).reshape(-1, 2)
    if ref.shape != mov.shape:
        raise ValueError("reference and moving vertices must have the same shape")
    ref_fixed = [tuple(v) for v in fixed_point(ref).tolist()]
    mov_fixed = [tuple(v) for v in fixed_point(mov).tolist()]
    tris = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    if len(tris) and (tris.min() < 0 or tris.max() >= len(ref)):
        raise ValueError("triangle vertex index out of range")
    slots, edges = [], {}
    for t in tris:
        a, b, c = int(t[0]), int(t[1]), int(t[2])
        s = orient_fixed(ref_fixed[a], ref_fixed[b], ref_fixed[c])
        if s == 0:
            raise ValueError(f"degenerate triangle {(a, b, c)} in the reference mesh")
        tri = (a, b, c) if s > 0 else (a, c, b)
        slots.append(tri)
        a, b, c = tri
        for e in (edge_key(a, b), edge_key(b, c), edge_key(c, a)):
            edges.setdefault(e, []).append(len(slots) - 1)
    return ref, mov, ref_fixed, mov_fixed, slots, edges


def _reference_edge_table(mesh):
    """:meth:`Mesh.edge_table` as it was computed from ``_edges`` and ``_tris``."""
    n = len(mesh.reference)
    table = np.array(
        [(i, j, o[0], o[1] if len(o) == 2 else -1) for (i, j), o in mesh._edges.items()],
        dtype=np.int64,
    ).reshape(-1, 4)
    table = table[np.argsort(table[:, 0] * n + table[:, 1])]
    i, j, s0, s1 = table.T
    sums = np.array([sum(t) if t is not None else 0 for t in mesh._tris] + [0], dtype=np.int64)
    apexes = sums[np.stack([s0, s1], axis=1)] - (i + j)[:, None]
    apexes[s1 < 0, 1] = -1
    return i * n + j, apexes


def _assert_queries_as_before(mesh):
    live = [(s, t) for s, t in enumerate(mesh._tris) if t is not None]
    expected = np.array([t for _, t in live], dtype=np.int64).reshape(-1, 3)
    tris = mesh.triangles
    assert tris.dtype == np.int64 and tris.shape == expected.shape
    assert np.array_equal(tris, expected)
    assert repr(mesh.slots()) == repr([s for s, _ in live])
    assert mesh.n_triangles == len(live)
    for got, want in zip(mesh.edge_table(), _reference_edge_table(mesh), strict=True):
        assert got.dtype == want.dtype and got.shape == want.shape and np.array_equal(got, want)
    sign = orientation(*np.moveaxis(mesh.moving[expected], 1, 0)) if live else []
    want = [s for (s, _), g in zip(live, sign, strict=True) if g <= 0]
    assert repr(mesh.reversed_slots()) == repr(want)


def _assert_built_as_before(reference, moving, triangles):
    """Mesh(...) gives the reference construction's state, or raises its error."""
    try:
        want = _reference_state(reference, moving, triangles)
    except ValueError as exc:
        with pytest.raises(ValueError) as got:
            Mesh(reference, moving, triangles)
        assert str(got.value) == str(exc)
        return None
    mesh = Mesh(reference, moving, triangles)
    ref, mov, ref_fixed, mov_fixed, tris, edges = want
    for got, arr in ((mesh.reference, ref), (mesh.moving, mov)):
        assert got.dtype == arr.dtype and got.shape == arr.shape and np.array_equal(got, arr)
    # repr: the same values and the same types (Python ints, tuples, lists), in the same order.
    assert repr(mesh.ref_fixed) == repr(ref_fixed) and repr(mesh.mov_fixed) == repr(mov_fixed)
    for xy, fixed in zip(mesh.fixed_arrays, (ref_fixed, mov_fixed), strict=True):
        assert xy.dtype == np.int64 and np.array_equal(xy, np.array(fixed).reshape(-1, 2))
    assert repr(mesh._tris) == repr(tris)
    # The edges are made when first asked for, in the order of their codes: the same owners,
    # in the same order, for every edge.
    assert repr(sorted(mesh._edges.items())) == repr(sorted(edges.items()))
    _assert_queries_as_before(mesh)
    return mesh


def _mixed_triangles(rng, points, extra):
    """Delaunay triangles of ``points`` shuffled, each in a random rotation and orientation, with
    ``extra`` more: repeated triangles and triangles over random vertices, so that some edges
    have one owner on each side, two on one side or three or more."""
    tris = Delaunay(points).simplices
    rows = [tris[rng.integers(len(tris), size=extra)]]
    rows.append(rng.integers(len(points), size=(extra, 3)))
    tris = np.concatenate([tris, *rows])
    fixed = fixed_point(quantize(points))
    p, q, r = (fixed[tris[:, v]] for v in range(3))
    cross = (q[:, 0] - p[:, 0]) * (r[:, 1] - p[:, 1]) - (q[:, 1] - p[:, 1]) * (r[:, 0] - p[:, 0])
    tris = tris[cross != 0]  # the degenerate ones have a test of their own
    tris = np.take_along_axis(tris, (np.arange(3) + rng.integers(3, size=(len(tris), 1))) % 3, 1)
    flip = rng.random(len(tris)) < 0.5
    tris[flip] = tris[flip][:, ::-1]
    return tris[rng.permutation(len(tris))]


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**31), st.sampled_from([0, 3, 20]), st.booleans())
def test_construction_is_the_per_triangle_one(seed, extra, on_grid):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(3, 200))
    points = rng.uniform(-500, 1500, size=(n, 2))
    if on_grid:  # many collinear triples and equal coordinates
        points = np.round(points / 100) * 100 + rng.normal(0, 1e-3, size=points.shape)
    moving = points + rng.normal(0, 20, size=points.shape)
    try:
        tris = _mixed_triangles(rng, points, extra)
    except QhullError:
        return
    _assert_built_as_before(points, moving, tris)
    # Input forms the constructor accepts: lists, float indices, a flat array.
    _assert_built_as_before(points.tolist(), moving.tolist(), tris.tolist())
    _assert_built_as_before(points, moving, tris.astype(float).ravel())


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**31))
def test_batched_queries_follow_swaps_and_removals(seed):
    # The slot arrays of the batched queries are brought up to date lazily: after any sequence
    # of swaps (checked and not), undone swaps and removals they say what _tris and _edges say.
    rng = np.random.default_rng(seed)
    points = rng.uniform(0, 100, size=(int(rng.integers(4, 60)), 2))
    try:
        tris = _mixed_triangles(rng, points, 0)
    except QhullError:
        return
    mesh = _assert_built_as_before(points, points + rng.normal(0, 6, size=points.shape), tris)
    for _ in range(int(rng.integers(1, 60))):
        action = rng.random()
        if action < 0.1 and mesh.n_triangles:
            mesh.remove_triangle(mesh.slots()[int(rng.integers(mesh.n_triangles))])
        elif action < 0.8:
            legal = mesh.swappable_edges()
            if legal:
                added = mesh.swap(legal[int(rng.integers(len(legal)))])
                if rng.random() < 0.3:
                    mesh.swap(added, check=False)
        else:
            # A topological swap, as the repair of patch reversals makes: the reference quad
            # strictly convex, the new edge absent, reversals allowed.
            for e in mesh.internal_edges():
                q = mesh.quad(e)
                if not mesh.has_edge((q.k, q.l)) and mesh.strictly_convex(q, mesh.ref_fixed):
                    mesh.swap(e, check=False)
                    break
        if rng.random() < 0.5:
            _assert_queries_as_before(mesh)
    _assert_queries_as_before(mesh)


def test_construction_errors_are_the_per_triangle_ones():
    square = np.array([[0, 0], [10, 0], [10, 10], [0, 10], [5, 5], [20, 20]], float)
    good = [[0, 1, 2], [0, 2, 3]]
    # Degenerate triangles: the first one in input order is named, in its input vertex order.
    for tris in (
        [*good, [0, 4, 2], [1, 3, 4]],
        [*good, [1, 3, 4], [0, 4, 2]],
        [[2, 0, 4], *good],
        [*good, [3, 3, 1]],
        [*good, [0, 2, 5], [5, 5, 5]],
    ):
        _assert_built_as_before(square, square, tris)
    with pytest.raises(ValueError, match=re.escape("degenerate triangle (1, 3, 4) in the ref")):
        Mesh(square, square, [*good, [1, 3, 4], [0, 4, 2]])
    # Indices out of range, checked before the orientation.
    for tris in ([*good, [0, 1, 6]], [*good, [-1, 1, 2]], [[0, 4, 2], [0, 1, 6]]):
        _assert_built_as_before(square, square, tris)
    # Coordinates the fixed-point predicates cannot take, and mismatched shapes.
    for bad in (np.nan, np.inf, -np.inf, MAX_COORDINATE + 1):
        moved = square.copy()
        moved[2, 1] = bad
        _assert_built_as_before(moved, square, good)
        _assert_built_as_before(square, moved, good)
    _assert_built_as_before(square, square[:-1], good)
    # Triangles with no area in the moving image are patch reversals.
    squashed = square.copy()
    squashed[1] = squashed[0]
    assert _assert_built_as_before(square, squashed, good).reversed_slots() == [0]
    # Edges with two owners on one side, and with four.
    mesh = _assert_built_as_before(square, square, [*good, [2, 1, 0], [3, 0, 2], [0, 1, 2]])
    assert mesh._edges[(0, 2)] == [0, 1, 2, 3, 4] and mesh._edges[(0, 1)] == [0, 2, 4]
    # Nothing to build.
    _assert_built_as_before(square, square, np.zeros((0, 3), int))
    _assert_built_as_before(np.zeros((0, 2)), np.zeros((0, 2)), [])
    _assert_built_as_before(np.zeros((0, 2)), np.zeros((0, 2)), [[0, 1, 2]])


def test_orientation_is_exact_at_the_largest_coordinates():
    # Cross products near 2**62 in fixed point: the int64 orientation still agrees with the
    # Python-int one, down to a step of 1 / SUBPIXEL and to exact collinearity. Consecutive
    # Fibonacci numbers near 2**31 (fixed point) give products a float64 rounds, whose
    # difference is +-1: F(n+1) F(n-1) - F(n)**2 = (-1)**n.
    m, step = MAX_COORDINATE, 1.0 / SUBPIXEL
    fib = [0, 1]
    while fib[-1] < 2**31:
        fib.append(fib[-1] + fib[-2])
    f46, f45, f44, f43 = fib[-2], fib[-3], fib[-4], fib[-5]
    points = np.array(
        [[-m, -m], [m, m], [m - step, m], [m, m - step], [0, 0], [m, -m], [-m, m], [step, 0]]
        + [[-m + f46 * step, -m + f45 * step], [-m + f45 * step, -m + f44 * step]]
        + [[-m + 2 * f44 * step, -m + 2 * f43 * step], [-m + f44 * step, -m + f43 * step]]
    )
    tris = [[0, 1, 2], [0, 1, 3], [0, 1, 5], [0, 5, 1], [6, 5, 7], [5, 6, 2], [1, 0, 6]]
    tris += [[0, 8, 9], [9, 8, 0]]
    mesh = _assert_built_as_before(points, points[::-1], tris)
    assert [t[0] for t in mesh._tris] == [0, 0, 0, 0, 6, 5, 1, 0, 9]
    for t in ([0, 1, 4], [6, 4, 5], [6, 5, 4], [0, 10, 11], [11, 0, 10]):
        _assert_built_as_before(points, points, [*tris, t])
    # A triangle with no area in the moving image is a patch reversal.
    moving = points.copy()
    moving[9] = moving[8]
    assert _assert_built_as_before(points, moving, tris).reversed_slots() == [7, 8]
