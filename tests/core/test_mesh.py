import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import Delaunay

from pwlreg.core.mesh import Mesh
from pwlreg.core.raster import label_image, quantize


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
