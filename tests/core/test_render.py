"""The pictures and 3D files of a result: sizes, and the mesh drawn where it is."""

from __future__ import annotations

import io
import json
import xml.etree.ElementTree as ET
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
import trimesh

from pwlreg.core import figures, render
from pwlreg.core.io import read_image
from pwlreg.core.pipeline import register
from pwlreg.core.results import RESULTS, Sources, write_outputs
from tests.core.synthetic import book_points, open_book, texture

NEW = ("mesh_reference", "mesh_moving", "checkerboard", "difference", "consistency",
       "convergence_png", "convergence_svg", "preview_reference", "preview_registered",
       "preview_registered_initial", "reconstruction_ply", "reconstruction_initial_ply",
       "reconstruction_glb")


@pytest.fixture(scope="module")
def book(tmp_path_factory):
    """The open-book pair registered from its points (the swaps fix the crease), with every
    result written."""
    ref, mov = open_book()
    rp, mp = book_points()
    result = register(ref, mov, (rp, mp), {"epipolar_filter": False})
    assert len(result.search.steps) >= 2
    out = tmp_path_factory.mktemp("figures")
    paths = write_outputs(result, out, sources=Sources(ref, mov))
    return result, ref, mov, paths


def near(picture: np.ndarray, point: np.ndarray, colour: tuple[int, int, int],
         tolerance: int = 40) -> bool:
    """Whether a pixel within one pixel of ``point`` has (about) ``colour`` (BGR)."""
    x, y = np.round(point).astype(int)
    h, w = picture.shape[:2]
    patch = picture[max(y - 1, 0):min(y + 2, h), max(x - 1, 0):min(x + 2, w), :3].astype(int)
    return bool((np.abs(patch - colour).max(axis=2) <= tolerance).any())


def edge_hits(picture, vertices, edge, colour) -> float:
    """Share of the points along the middle half of an edge, and 5 pixels or more from its ends
    (where the vertices' marks are drawn and neighbouring edges meet), near a pixel of
    ``colour``."""
    a, b = vertices[edge[0]], vertices[edge[1]]
    margin = max(0.25, 5 / np.linalg.norm(b - a))
    ts = np.linspace(margin, 1 - margin, 13)
    return float(np.mean([near(picture, a + t * (b - a), colour) for t in ts]))


def area(triangle: np.ndarray) -> float:
    (x0, y0), (x1, y1), (x2, y2) = triangle
    return abs((x1 - x0) * (y2 - y0) - (y1 - y0) * (x2 - x0)) / 2


def test_every_result_is_written_and_linked(book):
    result, ref, mov, paths = book
    assert set(NEW) <= set(RESULTS)
    for name in NEW:
        assert paths[name].is_file() and paths[name].stat().st_size > 0, name


@pytest.mark.parametrize("name, vertices", [("mesh_reference", "reference_vertices"),
                                            ("mesh_moving", "moving_vertices")])
def test_mesh_overlays_show_both_meshes_where_they_are(book, name, vertices):
    result, ref, mov, paths = book
    picture = read_image(paths[name])
    image = ref if name == "mesh_reference" else mov
    assert picture.shape == image.shape[:2] + (3,)  # small images keep their size
    pts = getattr(result, vertices)
    before = render.edges(result.initial_triangles)
    after = render.edges(result.final_triangles)
    kept, removed, added = before & after, before - after, after - before
    assert removed and added
    # Extrapolated border vertices may lie outside the moving image: edges inside the image.
    h, w = image.shape[:2]
    seen = {i for i, (x, y) in enumerate(pts) if -0.5 <= x <= w - 0.5 and -0.5 <= y <= h - 0.5}
    kept, removed, added = ({e for e in group if set(e) <= seen} for group in (kept, removed,
                                                                               added))
    # Kept and added edges are never crossed by an edge drawn later; the swapped-away ones
    # may be crossed by the edges that replaced them.
    assert all(edge_hits(picture, pts, e, render.KEPT) == 1.0 for e in kept)
    assert all(edge_hits(picture, pts, e, render.ADDED) == 1.0 for e in added)
    assert all(edge_hits(picture, pts, e, render.REMOVED) >= 0.6 for e in removed)
    # ... and the colours are only there: not inside the biggest triangle of both meshes.
    both = {tuple(sorted(t)) for t in result.initial_triangles.tolist()} & {
        tuple(sorted(t)) for t in result.final_triangles.tolist()}
    tri = list(max(both, key=lambda t: area(pts[list(t)])))
    centre = pts[tri].mean(axis=0)
    for colour in (render.KEPT, render.ADDED, render.REMOVED):
        assert not near(picture, centre, colour, tolerance=20)


def test_checkerboard_and_difference_compare_initial_and_final_mesh(book):
    result, ref, mov, paths = book
    h, w = ref.shape
    board = read_image(paths["checkerboard"])
    diff = read_image(paths["difference"])
    assert board.shape == diff.shape == (h, 2 * w + 8, 3)
    preview = read_image(paths["preview_registered"])
    assert preview.shape == (h, w, 4)
    # The final panel's tiles (below its label): reference and registered alternate.
    right = board[:, w + 8:]
    side = int(np.ceil(max(h, w) / 12))
    rows = slice(2 * side, 3 * side)
    assert np.array_equal(right[rows, :side], cv2.cvtColor(ref, cv2.COLOR_GRAY2BGR)[rows, :side])
    assert np.array_equal(right[rows, side:2 * side], preview[rows, side:2 * side, :3])
    # The swaps fix the diagonals across the crease: the final difference is darker.
    inside = preview[:, :, 3] > 0
    grey_left = cv2.cvtColor(diff[:, :w], cv2.COLOR_BGR2GRAY)[inside].mean()
    grey_right = cv2.cvtColor(diff[:, w + 8:], cv2.COLOR_BGR2GRAY)[inside].mean()
    print(f"\nmean difference picture grey level: initial mesh {grey_left:.1f}, final "
          f"{grey_right:.1f}")
    assert grey_right < 0.8 * grey_left


def test_consistency_map_colours_each_triangle_by_its_score(book):
    result, ref, mov, paths = book
    picture = read_image(paths["consistency"])
    assert picture.shape == ref.shape + (3,)
    scores = result.quality.triangle_scores
    colours = render.score_colours(scores)
    pts = result.reference_vertices
    checked = 0
    for t, tri in enumerate(result.final_triangles):
        centre = np.round(pts[tri].mean(axis=0)).astype(int)
        if area(pts[tri]) < 200:
            continue
        grey = float(ref[centre[1], centre[0]])
        expected = np.round(0.45 * grey + 0.55 * colours[t].astype(float))
        assert np.abs(picture[centre[1], centre[0]].astype(float) - expected).max() <= 1
        checked += 1
    assert checked >= 5
    assert np.array_equal(render.score_colours(np.array([0.0, 1.0, np.nan])),
                          [[40, 40, 220], [30, 190, 60][::-1], render.OUTSIDE])


def test_convergence_plot_png_and_svg_carry_every_accepted_move(book):
    result, ref, mov, paths = book
    mi = [result.search.initial_mi] + [s.mi for s in result.search.steps]
    png = read_image(paths["convergence_png"])
    assert png.shape == (520, 800, 3)
    plot = render._Plot(mi, mi, 800, 520)
    _, _, ticks, top = plot.series[0]
    for i in (0, len(mi) - 1):  # the first and last points are drawn as dots on the curve
        assert near(png, np.array([plot.x(i), plot.y(mi[i], ticks, top)]), (180, 100, 20), 10)
    svg = ET.fromstring(paths["convergence_svg"].read_text())
    curves = [e for e in svg.iter("{http://www.w3.org/2000/svg}polyline")]
    assert len(curves) == 2
    assert all(len(c.get("points").split()) == len(mi) for c in curves)


def test_three_d_results_parse(book):
    result, ref, mov, paths = book
    ply = trimesh.load(paths["reconstruction_ply"], process=False)
    assert len(ply.vertices) == len(result.reference_vertices)
    assert np.array_equal(ply.faces, result.final_triangles)
    assert np.allclose(ply.vertices[:, :2], result.reference_vertices, atol=2.0)
    initial = trimesh.load(paths["reconstruction_initial_ply"], process=False)
    assert np.array_equal(initial.faces, result.initial_triangles)
    data = paths["reconstruction_glb"].read_bytes()
    doc = json.loads(data[20:20 + int.from_bytes(data[12:16], "little")])
    assert [s["name"] for s in doc["scenes"]] == ["final", "initial"]
    scene = trimesh.load(io.BytesIO(data), file_type="glb", process=False)
    final = scene.geometry["final"]
    assert np.array_equal(final.faces, result.final_triangles)
    assert np.allclose(final.vertices * [1, -1, -1], ply.vertices, atol=1e-3)
    tex = np.asarray(final.visual.material.baseColorTexture)
    assert tex.shape[:2] == ref.shape


def test_results_without_the_images_are_the_ones_that_need_none(book, tmp_path):
    result = book[0]
    written = write_outputs(result, tmp_path)
    assert {"convergence_png", "convergence_svg", "reconstruction_glb"} <= set(written)
    assert not {"mesh_reference", "checkerboard", "preview_reference"} & set(written)


def test_large_images_are_drawn_at_a_bounded_size():
    big = texture((1200, 3000), 3, sigma=4.0)
    pts = np.array([[10.0, 10.0], [2990, 20], [1500, 1190], [20, 1180], [2980, 1185]])
    tris = np.array([[0, 1, 2], [0, 2, 3], [1, 4, 2]])
    overlay = render.mesh_overlay(big, pts, tris, tris)
    assert overlay.shape == (640, 1600, 3)
    assert edge_hits(overlay, render.scale_points(pts, (3000, 1200), (1600, 640)), (0, 2),
                     render.KEPT) == 1.0
    shown = render.panel_size((3000, 1200), 2)
    assert 2 * shown[0] + 8 <= render.MAX_SIDE and shown == (796, 318)
    warped = render.registered_preview(big, pts, pts, tris, (3000, 1200), shown)
    assert warped.shape == (318, 796, 4)
    reference = render.to_display(big, shown)
    same = warped[:, :, 3] > 0
    assert np.abs(warped[:, :, :3][same].astype(int) - reference[same]).mean() < 2
    outside = warped.copy()
    outside[:, :100, 3] = 0
    assert (render.difference(reference, outside)[:, :100] == render.OUTSIDE).all()
    assert render.fit((800, 3200)) == (400, 1600)
    assert render.to_display(np.full((4, 4), 1023, np.uint16)).max() == 255


def test_reconstruction_falls_back_to_every_vertex_when_the_measured_ones_are_on_a_line():
    measured = np.array([[10.0, 10.0], [20, 20], [30, 30], [40, 40]])
    border = np.array([[-0.5, -0.5], [99.5, -0.5], [99.5, 79.5], [-0.5, 79.5]])
    ref = np.concatenate([measured, border])
    result = SimpleNamespace(reference_vertices=ref, moving_vertices=ref * 1.1 + 3,
                             extrapolated=np.array([False] * 4 + [True] * 4))
    assert figures.can_reconstruct(result, Sources())
    rec = figures.reconstruction(result)
    assert rec.points.shape == (8, 3) and rec.residual < 1e-9
    result.reference_vertices = measured
    result.moving_vertices = measured
    assert not figures.can_reconstruct(result, Sources())


def test_vertices_only_one_mesh_uses_are_ringed():
    image = np.full((101, 101), 90, np.uint8)
    pts = np.array([[0.0, 0], [100, 0], [100, 100], [0, 100], [50, 50], [40, 60]])
    fan = lambda c: np.array([[0, 1, c], [1, 2, c], [2, 3, c], [3, 0, c]])  # noqa: E731
    picture = render.mesh_overlay(image, pts, fan(4), fan(5), extrapolated=np.zeros(6, bool))
    assert near(picture, pts[4] + [6, 0], render.VERTEX_REMOVED)
    assert near(picture, pts[5] + [6, 0], render.VERTEX_ADDED)
    assert not near(picture, pts[4] + [6, 0], render.VERTEX_ADDED)
    assert near(picture, pts[4], render.VERTEX) and near(picture, pts[5], render.VERTEX)
