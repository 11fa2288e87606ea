import json
import os
import subprocess
import sys

import cv2
import numpy as np
import pytest

from pwlreg.core.errors import InputError
from pwlreg.core.io import read_image
from pwlreg.core.mesh import Mesh
from pwlreg.core.optimizers import keep_initial
from pwlreg.core.pipeline import STAGES, register
from pwlreg.core.quality import SCORING_SIDE
from pwlreg.core.results import write_outputs
from pwlreg.core.similarity import prepare_images, reduced, to_level
from tests.core.synthetic import book_points, open_book, texture


def test_register_with_points_writes_the_file_contract(tmp_path):
    ref, mov = open_book()
    rp, mp = book_points()
    seen = []
    result = register(
        ref, mov, (rp, mp), {"epipolar_filter": False}, progress=lambda s, f: seen.append(s)
    )
    assert [s for i, s in enumerate(seen) if i == 0 or seen[i - 1] != s] == list(STAGES)
    assert len(result.search.steps) >= 2
    paths = write_outputs(result, tmp_path)
    mesh = json.loads(paths["mesh"].read_text())
    for key in (
        "reference_vertices",
        "moving_vertices",
        "initial_triangles",
        "final_triangles",
        "swaps",
        "parameters",
        "matching",
    ):
        assert key in mesh
    assert mesh["swaps"][0].keys() >= {"removed", "added", "delta"}
    assert mesh["parameters"]["cost"] == "mi"
    conv = json.loads(paths["convergence"].read_text())
    assert conv["initial"].keys() >= {"mi", "nmi"} and conv["final"]["mi"] > conv["initial"]["mi"]
    assert conv["iterations"][0].keys() >= {
        "iteration",
        "removed",
        "added",
        "delta",
        "mi",
        "nmi",
        "elapsed_s",
    }
    assert conv["stopped_because"]
    png = read_image(paths["registered"])
    assert png.shape == (ref.shape[0], ref.shape[1], 4)
    # The registered image matches the reference where the mesh is correct (after the swaps).
    alpha = png[..., 3] > 0
    err = np.abs(png[..., 0].astype(int) - ref.astype(int))[alpha]
    assert np.median(err) <= 2
    assert "swaps" in result.summary()


def test_register_finds_points_automatically():
    shape = (240, 320)
    mov = texture(shape, 11, sigma=1.5)
    A = np.array([[0.97, 0.05, 4.0], [-0.04, 0.99, 3.0]])
    ref = cv2.warpAffine(mov, A, (shape[1], shape[0]), flags=cv2.WARP_INVERSE_MAP)
    result = register(ref, mov, options={"max_points": 200})
    assert result.points.source in ("lk", "sift")
    assert len(result.reference_vertices) >= 50
    pred = result.reference_vertices @ A[:, :2].T + A[:, 2]
    assert np.median(np.linalg.norm(pred - result.moving_vertices, axis=1)) < 0.5


def test_invalid_options_and_points_are_input_errors():
    ref, mov = open_book()
    rp, mp = book_points()
    with pytest.raises(InputError) as err:
        register(ref, mov, (rp, mp), {"bins": 1})
    assert err.value.field == "options.bins"
    with pytest.raises(InputError) as err:
        register(ref, mov, (rp, mp), {"no_such_option": 1})
    assert err.value.field == "options.no_such_option"
    with pytest.raises(InputError):
        register(ref, mov, (rp, mp[:-1]), {"epipolar_filter": False})
    with pytest.raises(InputError, match=r"\(N, 2\)"):  # (x, y, weight) rows are not points
        register(ref, mov, (np.c_[rp, rp[:, :1]], np.c_[mp, mp[:, :1]]), {"epipolar_filter": False})
    for bad in ("abc", 5, [("bins", 3)]):
        with pytest.raises(InputError) as err:
            register(ref, mov, (rp, mp), bad)
        assert err.value.field == "options"
    with pytest.raises(InputError, match="samples of"):  # float32 is a raster, int64 nothing
        register(ref.astype(np.int64), mov, (rp, mp))


def test_optimizer_none_keeps_delaunay():
    ref, mov = open_book()
    rp, mp = book_points()
    result = register(ref, mov, (rp, mp), {"optimizer": "none", "epipolar_filter": False})
    assert result.search.steps == []
    np.testing.assert_array_equal(result.initial_triangles, result.final_triangles)
    assert result.search.initial_mi == result.search.final_mi > 0


def test_warm_up_compiles_the_automatic_paths_kernels() -> None:
    # In a fresh process, as a worker calls it: afterwards no kernel of either path is left to
    # compile (or to load from numba's cache) in the first job.
    # The process's long-lived objects are then out of the collector's reach.
    code = (
        "import gc\n"
        "from pwlreg.core import kernels\n"
        "from pwlreg.core.pipeline import warm_up\n"
        "warm_up()\n"
        "names = ['strip_correlation', 'template_peaks', 'spaced', 'triangle_histograms',\n"
        "         'group_histograms', 'fill_spans', 'warp', 'search_start',\n"
        "         'search_run', 'containing', 'trimmed_affine_fits', 'affine_fits']\n"
        "print(' '.join(n for n in names if not getattr(kernels, n).signatures))\n"
        "print(gc.get_freeze_count())\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=600, check=True)
    missing, frozen = out.stdout.split("\n")[:2]
    assert missing.strip() == "", f"not compiled by warm_up: {missing}"
    assert int(frozen) > 10_000


def test_after_the_warm_up_no_input_type_compiles_a_kernel() -> None:
    # A kernel compiled at a job's first use is written into numba's cache outside the
    # warm-up's lock (core.compilation): an 8-bit image against a 16-bit one compiled the
    # joint histograms, a read-only array (np.frombuffer) three kernels.
    code = (
        "import numpy as np\n"
        "from numba.core.registry import CPUDispatcher\n"
        "from pwlreg.core import kernels, tiled\n"
        "from pwlreg.core.pipeline import register, warm_up\n"
        "from tests.core.synthetic import texture\n"
        "warm_up()\n"
        "def signatures():\n"
        "    return {(m.__name__, n): len(f.signatures) for m in (kernels, tiled)\n"
        "            for n, f in vars(m).items() if isinstance(f, CPUDispatcher)}\n"
        "before = signatures()\n"
        "ref = texture((200, 260), 3)\n"
        "mov = np.roll(ref, (2, 3), axis=(0, 1))\n"
        "frozen = np.frombuffer(mov.tobytes(), np.uint8).reshape(mov.shape)\n"
        "for r, m in ((ref, mov.astype(np.uint16) * 257), (ref.astype(np.uint16) * 257, mov),\n"
        "             (ref, frozen)):\n"
        "    register(r, m)\n"
        "after = signatures()\n"
        "print(' '.join(f'{k[1]}' for k in after if after[k] != before.get(k)))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=600, check=True, cwd=os.path.dirname(os.path.dirname(
                             os.path.dirname(os.path.abspath(__file__)))))
    assert out.stdout.strip() == "", f"compiled after the warm-up: {out.stdout}"


def test_threaded_kernels_wait_passively_unless_told_otherwise() -> None:
    # OpenMP reads the policy when numba starts its threads, after the kernels' import.
    code = (
        "import os\n"
        "from pwlreg.core import kernels\n"
        "kernels.set_threads(2)\n"
        "print(os.environ['OMP_WAIT_POLICY'])\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    for given, expected in ((None, "passive"), ("active", "active")):
        run_env = env if given is None else {**env, "OMP_WAIT_POLICY": given}
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                             timeout=120, check=True, env=run_env)
        assert out.stdout.strip() == expected


def test_without_points_the_swaps_and_their_figures_are_the_reduced_images():
    # 1280 x 960: the automatic path ranks its swaps, before and after the vertex moves, on the
    # images halved to the verdict's scale, and reports the MI of its final mesh there.
    reference, moving = open_book(size=(1280, 960), crease=640.0, seed=3)
    r = register(reference, moving, options={"extent": "hull"})
    assert r.points.source != "client" and r.corrections is not None
    level, scale = reduced(prepare_images(reference, moving, 16), SCORING_SIDE)
    assert scale == 0.5
    final = Mesh(to_level(r.reference_vertices, scale), to_level(r.moving_vertices, scale),
                 r.final_triangles)
    whole = keep_initial(final, level, None, None)
    full = keep_initial(Mesh(r.reference_vertices, r.moving_vertices, r.final_triangles),
                        prepare_images(reference, moving, 16), None, None)
    assert (r.search.final_mi, r.search.final_nmi) == (whole.final_mi, whole.final_nmi)
    assert abs(r.search.final_mi - full.final_mi) > 0.01  # 0.04 bits
    steps = r.search.steps
    assert [s.iteration for s in steps] == list(range(1, len(steps) + 1))
    assert all(b.elapsed_s >= a.elapsed_s for a, b in zip(steps, steps[1:], strict=False))


@pytest.mark.parametrize("turn", [cv2.ROTATE_180, cv2.ROTATE_90_CLOCKWISE])
def test_vertices_found_on_the_reduced_images_keep_their_place_under_a_rotation(turn: int) -> None:
    # A photo and the same photo turned (another heading), larger than the images the
    # insertion and the verdict read: the vertices inserted there were half a pixel of the
    # level off on both sides, which a rotation does not cancel (0.8 to 1.2 px).
    ref = texture((600, 1100), 4, sigma=3.0)
    mov = cv2.rotate(ref, turn)
    h, w = ref.shape
    result = register(ref, mov)
    assert result.quality.verdict == "good"
    x, y = result.reference_vertices.T
    truth = (np.column_stack([w - 1 - x, h - 1 - y]) if turn == cv2.ROTATE_180
             else np.column_stack([h - 1 - y, x]))
    measured = ~np.asarray(result.extrapolated, bool)
    error = np.hypot(*(result.moving_vertices - truth)[measured].T)
    assert measured.sum() > 50
    assert np.median(error) < 0.1 and error.mean() < 0.25, (np.median(error), error.mean())


def _with_a_hole(scene: np.ndarray, shift: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """The moving view of ``scene`` (shifted by ``shift``) and its top-left quarter's content
    seen elsewhere: what a stale or pasted area under alpha 0 holds."""
    h, w = scene.shape
    moved = cv2.warpAffine(scene, np.float32([[1, 0, shift[0]], [0, 1, shift[1]]]), (w, h),
                           borderMode=cv2.BORDER_REFLECT)
    stale = cv2.warpAffine(scene, np.float32([[1, 0, 30], [0, 1, 25]]), (w, h),
                           borderMode=cv2.BORDER_REFLECT)
    hole = np.zeros((h, w), bool)
    hole[: h // 2, : w // 2] = True
    moved[hole] = stale[hole]
    return moved, hole


def test_what_lies_under_alpha_zero_is_not_matched():
    # A moving image whose transparent quarter holds another part of the scene: it was matched
    # and scored like the rest (vertices 36 px off there, the verdict good).
    ref = texture((480, 640), 8, sigma=3.0)
    shift = (4.3, -2.6)
    grey, hole = _with_a_hole(ref, shift)
    moving = np.dstack([grey, grey, grey, np.where(hole, 0, 255).astype(np.uint8)])
    result = register(ref, moving, options={"extent": "hull"})
    measured = ~np.asarray(result.extrapolated, bool)
    error = np.hypot(*(result.moving_vertices - result.reference_vertices - shift)[measured].T)
    assert error.max() < 1.0, error.max()
    x, y = result.moving_vertices[measured].T
    assert not np.any((x < 320 - 8) & (y < 240 - 8))


def test_no_pair_is_inserted_along_the_edge_of_the_data():
    # Along the edge of a nodata area the residual flow jumps as across a depth step: the
    # insertion matched points there 50-80 px off (seen on photographs, verdict good).
    ref = texture((480, 640), 9, sigma=3.0)
    shift = (4.3, -2.6)
    grey, hole = _with_a_hole(ref, shift)
    moving = np.ma.MaskedArray(grey.astype(np.float32) / 255, mask=hole)
    result = register(ref, moving, options={"extent": "hull"})
    error = np.hypot(*(result.moving_vertices - result.reference_vertices - shift).T)
    inserted = result.inserted
    assert inserted.sum() > 20
    assert error[inserted].max() < 1.0, error[inserted].max()


@pytest.mark.parametrize("shape", [(200, 1600), (1600, 200)])
def test_a_strip_is_judged_on_a_level_wide_enough(shape):
    # Halved until its longer side was 400 px, a 1600 x 200 strip left 50 px across: too few
    # of its triangles held the pixels to be judged, and an exact result was unreliable.
    ref = texture(shape, 10, sigma=2.0)
    h, w = shape
    moving = cv2.warpAffine(ref, np.float32([[1, 0, 3.2], [0, 1, -1.7]]), (w, h),
                            borderMode=cv2.BORDER_REFLECT)
    result = register(ref, moving, options={"extent": "hull"})
    assert result.quality.verdict == "good", result.quality.reasons
    error = np.hypot(*(result.moving_vertices - result.reference_vertices - (3.2, -1.7)).T)
    assert np.median(error) < 0.1


def on_the_ground(family, seed, baseline=12.0):
    """A scene of the trust suite's polyhedral group: ``family`` standing on textured ground."""
    from bench.scenes import make_scene

    return make_scene(family, seed, size=(640, 480), n_interior=0, supersample=2,
                      camera="perspective", radiometric="lighting", noise=3.0, blur=0.5,
                      baseline=baseline)


def against_delaunay(scene):
    """The default registration of ``scene`` (extent hull), its mean endpoint error and that
    of Delaunay's mesh over the matched pairs."""
    from bench.metrics import endpoint_error

    def epe(result):
        return endpoint_error(result.reference_vertices, result.moving_vertices,
                              result.final_triangles, scene.truth_x, scene.truth_y,
                              scene.covisible)["mean"]

    result = register(scene.reference, scene.moving, options={"extent": "hull"})
    plain = register(scene.reference, scene.moving,
                     options={"extent": "hull", "optimizer": "none", "insert_vertices": "never"})
    return result, epe(result), epe(plain)


def test_no_pair_is_searched_along_lines_that_the_pairs_do_not_determine():
    # The matcher's pairs of this gable all lie on the ground, and SIFT's pairs off it fix no
    # epipole: the model is the plane's, whose lines pass through the ground's pairs in a
    # direction of its own. Searched along such lines (a box's, 38 px from the true matches of
    # its front, median), 16 of 37 inserted pairs were 8-106 px off, a mesh 9.7 % worse than
    # Delaunay's: the insertion keeps to the plane.
    from bench.metrics import truth_at

    scene = on_the_ground("gable", 102, baseline=22.0)
    result = register(scene.reference, scene.moving, options={"extent": "hull"})
    assert result.points.epipolar.plane is not None
    assert result.inserted.any()
    truth = truth_at(scene.truth_x, scene.truth_y, result.reference_vertices)
    error = np.hypot(*(result.moving_vertices - truth).T)
    known = np.isfinite(error)
    assert known[result.inserted].all()
    assert not np.any(error[known & result.inserted] > 3.0), error[result.inserted]


def test_sift_s_pairs_off_the_plane_open_the_surfaces_above_it_to_the_insertion():
    # That box: SIFT's pairs off the ground fix the epipole (core.epipolar.parallax_fundamental
    # without a fixed pair), and the insertion finds pairs on its faces along the lines.
    result, epe, delaunay = against_delaunay(on_the_ground("box", 73))
    assert result.points.epipolar.plane is None and result.points.epipolar.parallax >= 8
    assert epe < 0.25 * delaunay  # 4.5 px against 43.1 (the plane's lines: 43.5)


def test_sift_s_pairs_overrule_wrong_pairs_off_the_plane():
    # A prism whose only tracked pairs off the ground are wrong: their epipole kept the
    # insertion off its faces (16.5 px, Delaunay 16.6); SIFT's pairs fix another.
    result, epe, delaunay = against_delaunay(on_the_ground("prism", 113))
    assert result.points.epipolar.parallax >= 8
    assert epe < 0.7 * delaunay  # 8.7 px against 16.6


def test_the_right_one_of_two_pairs_off_the_plane_fixes_the_lines():
    # A prism's two tracked pairs off its face: one right, one 17 px off. The lines through
    # both led the insertion to 22 lookalikes of 28 (4.10 px against Delaunay's 2.61).
    result, epe, delaunay = against_delaunay(on_the_ground("prism", 132))
    assert result.points.epipolar.parallax >= 6
    assert epe < 0.8 * delaunay  # 1.53 px against 2.61


def test_a_map_no_epipolar_geometry_explains_is_not_called_good():
    # A smooth non-rigid map (lens distortion, a surface that bends): the epipolar filter
    # rejected 56 % of the pairs the uniqueness check confirmed (real rigid pairs: at most
    # 1.5 %), the insertion searched along its wrong lines, and the verdict was good.
    h, w, amp = 480, 640, 6.0
    ref = texture((h, w), 21, sigma=2.5)

    def true_map(x, y):
        return (x + amp * np.sin(2 * np.pi * y / 190.0) + 0.02 * (x - w / 2) + 8,
                y + 0.8 * amp * np.sin(2 * np.pi * x / 170.0 + 1.0) - 0.015 * (y - h / 2))

    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    px, py = xs.copy(), ys.copy()
    for _ in range(60):  # the inverse map, by fixed-point iteration
        fx, fy = true_map(px, py)
        px, py = px + (xs - fx), py + (ys - fy)
    moving = cv2.remap(ref, px.astype(np.float32), py.astype(np.float32), cv2.INTER_LINEAR)
    result = register(ref, moving, options={"extent": "hull"})
    assert result.quality.figures["epipolar_rejected_share"] > 0.4
    assert result.quality.verdict != "good"
    assert any("epipolar geometry rejects" in r for r in result.quality.reasons)
    assert result.points.lines is None
    tx, ty = true_map(*result.reference_vertices[result.inserted].T)
    error = np.hypot(*(result.moving_vertices[result.inserted] - np.stack([tx, ty], 1)).T)
    assert error.max() < 1.5, error.max()


def test_a_client_pair_the_filter_could_not_check_makes_the_result_doubtful(tmp_path):
    # A flat scene's 40 true points and one outlier on the line the robust fit chose through
    # the plane: it passed, its triangles were 100 px off and the verdict good. Nothing tells
    # it from a true point on a roof: it is kept, and the verdict says so.
    from pwlreg.core.epipolar import epipolar_lines, line_direction
    from pwlreg.core.matching import find_conjugate_points
    from pwlreg.core.options import RegistrationOptions

    ref = texture((480, 640), 23, sigma=2.5)
    H = np.array([[0.95, 0.05, 12.0], [-0.04, 0.97, 9.0], [5e-5, 2e-5, 1.0]])
    moving = cv2.warpPerspective(ref, H, (640, 480), flags=cv2.INTER_CUBIC,
                                 borderMode=cv2.BORDER_REFLECT)
    rng = np.random.default_rng(4)
    points = rng.uniform([40, 40], [600, 440], (41, 2))
    q = np.c_[points, np.ones(41)] @ H.T
    true = q[:, :2] / q[:, 2:]
    clean = register(ref, moving, (points[1:], true[1:]), {"extent": "hull"})
    assert clean.quality.verdict == "good", clean.quality.reasons
    model = find_conjugate_points(ref, moving, RegistrationOptions(),
                                  (points[1:], true[1:])).epipolar
    wrong = true.copy()
    wrong[0] += 100 * line_direction(epipolar_lines(model.matrix, points[:1]))[0]
    result = register(ref, moving, (points, wrong), {"extent": "hull"})
    assert len(result.points) == 41
    assert result.quality.figures["unverified_pairs"] == 1
    assert result.quality.verdict == "doubtful"
    assert any("could not be checked" in r for r in result.quality.reasons)
    # Which one: tiepoints.geojson says it of each kept pair.
    written = write_outputs(result, tmp_path)
    features = json.loads(written["tiepoints_geojson"].read_text())["features"]
    flagged = [f["properties"]["reference_px"] for f in features
               if f["properties"].get("unverified")]
    np.testing.assert_allclose(flagged, points[:1], atol=1e-3)
    assert sum("unverified" in f["properties"] for f in features) == 41
