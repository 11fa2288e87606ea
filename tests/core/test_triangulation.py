import numpy as np
import pytest

from pwlreg.core.errors import InputError, NotEnoughPointsError
from pwlreg.core.mesh import Mesh
from pwlreg.core.raster import triangle_areas
from pwlreg.core.triangulation import deduplicate, initial_mesh, repair_patch_reversals


def test_duplicates_removed_in_either_image():
    ref = np.array([[0, 0], [10, 0], [0, 10], [0, 0], [5, 5]], float)
    mov = np.array([[0, 0], [10, 0], [0, 10], [3, 3], [10, 0]], float)
    r, m, dropped = deduplicate(ref, mov)
    assert dropped == 2 and len(r) == 3


def test_small_triangles_discarded():
    ref = np.array([[0, 0], [100, 0], [0, 100], [100, 100], [50, 0.2]], float)
    mesh, report = initial_mesh(ref, ref, min_triangle_area=25)
    assert report.small_triangles_removed >= 1
    areas = []
    for a, b, c in mesh.triangles:
        d1, d2 = ref[b] - ref[a], ref[c] - ref[a]
        areas.append(abs(d1[0] * d2[1] - d1[1] * d2[0]) / 2)
    assert min(areas) >= 25


def _area(points: np.ndarray, triangles: np.ndarray) -> float:
    return float(triangle_areas(points[triangles]).sum())


def test_optional_pair_left_out_instead_of_a_triangle():
    # A pair 0.3 px inside the square's edge makes a sliver with that edge: removing the sliver
    # opens a hole in the mesh; leaving the (optional) pair out does not.
    g = np.array([25.0, 50.0, 75.0])
    inner = np.stack(np.meshgrid(g, g), axis=-1).reshape(-1, 2) + [[3.0, 1.0]]
    ref = np.concatenate([[[0, 0], [100, 0], [0, 100], [100, 100]], inner, [[50, 0.3]]])
    optional = np.zeros(len(ref), bool)
    optional[-1] = True
    holed, report = initial_mesh(ref, ref, 25)
    assert report.small_triangles_removed >= 1
    assert _area(holed.reference, holed.triangles) < 100 * 100 - 1
    whole, report = initial_mesh(ref, ref, 25, optional=optional)
    assert report.small_triangles_removed == 0 and report.optional_dropped == 1
    assert len(whole.reference) == len(ref) - 1
    assert not np.any(np.all(np.isclose(whole.reference, [50, 0.3]), axis=1))
    assert _area(whole.reference, whole.triangles) == pytest.approx(100 * 100)
    # A small triangle of given pairs only is still removed: they are not to be dropped.
    sliver = np.concatenate([ref[:-1], [[50, 0.2]]])
    _, report = initial_mesh(sliver, sliver, 25, optional=np.zeros(len(sliver), bool))
    assert report.small_triangles_removed >= 1 and report.optional_dropped == 0


def test_collinear_and_too_few_points_are_clear_errors():
    with pytest.raises(InputError, match="collinear"):
        initial_mesh(
            np.array([[0, 0], [1, 1], [2, 2], [3, 3]], float),
            np.array([[0, 0], [1, 1], [2, 2], [3, 3]], float),
            0,
        )
    with pytest.raises(NotEnoughPointsError, match="at least 3"):
        initial_mesh(np.array([[0, 0], [1, 1]], float), np.array([[0, 0], [1, 1]], float), 0)


@pytest.mark.parametrize("flip", [(-1, 1), (1, -1), "transpose"])
def test_a_mirror_image_is_named_not_blamed_on_the_points(flip):
    # A raster whose rows run the other way (a south-up grid), or points given as (row,
    # column) in one image, reverse every triangle: the repair removed them all and the error
    # asked for better points.
    ref = np.random.default_rng(0).uniform(0, 500, (40, 2))
    mov = ref[:, ::-1].copy() if flip == "transpose" else ref * flip + 600
    with pytest.raises(InputError, match="triangles are reversed") as info:
        initial_mesh(ref, mov, 0)
    assert info.value.field == "moving"
    assert "mirror image" in str(info.value)


def test_reversal_on_boundary_removes_triangle():
    ref = np.array([[0, 0], [10, 0], [0, 10], [10, 10]], float)
    mov = ref.copy()
    mov[3] = [-5, -5]  # vertex 3 jumps across: triangle (1, 3, 2) flips
    mesh = Mesh(ref, mov, [[0, 1, 2], [1, 3, 2]])
    actions, left = repair_patch_reversals(mesh)
    assert left == 0 and mesh.reversed_slots() == []
    assert actions[0]["action"] == "remove"


def test_interior_reversal_repaired_by_swap():
    # A fan around the centre vertex 4; in the moving image vertex 4 crosses edge (0, 1)
    # towards vertex 5, which flips the interior triangle (0, 1, 4) only.
    ref = np.array([[0, 0], [20, 0], [20, 20], [0, 20], [10, 8], [10, -10]], float)
    tris = [[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4], [0, 5, 1]]
    mov = ref.copy()
    mov[4] = [10, -3]
    mesh = Mesh(ref, mov, tris)
    assert len(mesh.reversed_slots()) >= 1
    actions, left = repair_patch_reversals(mesh)
    assert left == 0 and mesh.reversed_slots() == []
    assert actions == [{"action": "swap", "removed": [0, 1], "added": [4, 5]}]
    assert mesh.n_triangles == 5
