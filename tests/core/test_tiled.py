"""Large rasters: the tiled warp, TIFFs read by windows, PNGs written in strips, and the
registration on reduced levels (core/scaled.py), against their whole-image counterparts."""

from __future__ import annotations

import io
import json

import cv2
import numpy as np
import pytest
import rasterio
from PIL import Image
from scipy.spatial import Delaunay

from pwlreg.core.formats.geotiff import RasterFile, open_image, read_tiff
from pwlreg.core.formats.png import PngWriter
from pwlreg.core.imaging import file_bands, matching_image
from pwlreg.core.io import encode_png, read_image
from pwlreg.core.results import Sources, write_outputs
from pwlreg.core.scaled import ScaledResult, level_factor, register
from pwlreg.core.tiled import ArrayBands, warp_tiles
from pwlreg.core.warp import warp_image
from tests.core.gis import LANDSAT, geotiff, make_pair, scene

NO_FILTER = {"epipolar_filter": False}


def _mesh(width: int, height: int, seed: int = 1):
    """A mesh over the frame with a smooth, non-affine motion (each triangle its own map)."""
    rng = np.random.default_rng(seed)
    inner = rng.uniform([5, 5], [width - 6, height - 6], size=(60, 2))
    corners = np.array([[0, 0], [width - 1, 0], [0, height - 1], [width - 1, height - 1]], float)
    ref = np.concatenate([corners, inner])
    mov = ref + np.stack([3 * np.sin(ref[:, 1] / 40), 2 * np.cos(ref[:, 0] / 55)], axis=1) + 1.5
    return ref, mov, Delaunay(ref).simplices


def _assemble(tiles, shape, count, dtype, nodata=0):
    out = np.full((*shape, count), nodata, dtype)
    inside = np.zeros(shape, bool)
    for t in tiles:
        h, w = t.inside.shape
        out[t.y0:t.y0 + h, t.x0:t.x0 + w] = t.bands
        inside[t.y0:t.y0 + h, t.x0:t.x0 + w] = t.inside
    return out, inside


@pytest.mark.parametrize("channels", [1, 3])
def test_tiled_warp_is_the_whole_image_warp(channels):
    height, width = 300, 420
    image = np.moveaxis(scene(height, width, channels, np.uint8), 0, -1)
    image = image[:, :, 0] if channels == 1 else np.ascontiguousarray(image)
    ref, mov, tris = _mesh(width, height)
    whole = warp_image(image, ref, mov, tris, (height, width))
    tiles = warp_tiles(ArrayBands(image), ref, mov, tris, (height, width), tile=64)
    bands, inside = _assemble(tiles, (height, width), channels, np.uint8)
    np.testing.assert_array_equal(inside, whole[:, :, -1] == 255)
    assert inside.mean() > 0.8  # the motion pushes a border out of the moving image
    picture = bands if channels == 1 else bands[:, :, ::-1]  # file order -> BGR
    diff = np.abs(picture.astype(int) - whole[:, :, :-1].astype(int))[inside]
    assert diff.max() <= 1  # the same bilinear weights, rounded alike within one level


def test_tiled_warp_marks_invalid_moving_pixels_and_keeps_the_sample_type():
    height, width = 200, 260
    data = scene(height, width, 2, np.float32)
    data[:, 80:100, 100:140] = np.nan
    raster = np.ma.MaskedArray(np.moveaxis(data, 0, -1), mask=np.zeros((height, width, 2), bool))
    ref = np.array([[0, 0], [width - 1, 0], [0, height - 1], [width - 1, height - 1]], float)
    tris = Delaunay(ref).simplices
    tiles = warp_tiles(ArrayBands(raster), ref, ref, tris, (height, width), tile=96,
                       nodata=-9999)
    bands, inside = _assemble(tiles, (height, width), 2, np.float32, -9999)
    assert bands.dtype == np.float32
    hole = np.zeros((height, width), bool)
    hole[80:100, 100:140] = True
    assert not inside[hole].any() and inside[~hole].all()  # the identity: nothing else lost
    np.testing.assert_array_equal(bands[inside], np.moveaxis(data, 0, -1)[inside])
    assert (bands[~inside] == -9999).all()


def test_raster_file_reads_windows_and_levels_as_read_tiff(tmp_path):
    pair = make_pair(height=200, width=300, bands=3, dtype=np.uint16, nodata=0,
                     hole=(slice(40, 70), slice(50, 120)))
    path = tmp_path / "moving.tif"
    path.write_bytes(pair.moving_tif)
    whole = read_tiff(path, "moving")
    bands, valid = file_bands(whole)
    with RasterFile(path) as source:
        assert (source.height, source.width, source.count) == (200, 300, 3)
        part, part_valid = source.read(30, 20, 170, 90)
        np.testing.assert_array_equal(part, bands[20:90, 30:170])
        np.testing.assert_array_equal(part_valid, valid[20:90, 30:170])
        level = source.level(3)
    expected = ArrayBands(whole).level(3)
    assert level.shape == expected.shape == (66, 100, 3)
    np.testing.assert_array_equal(np.ma.getmaskarray(level), np.ma.getmaskarray(expected))
    np.testing.assert_array_equal(level.data, expected.data)
    block = bands[:3, 3:6, 1].astype(float).mean()  # level pixel (0, 1) of band 2
    assert abs(int(level.data[0, 1, 1]) - block) <= 0.5


def test_open_image_reads_large_tiffs_by_windows_and_decodes_the_rest(tmp_path):
    path = tmp_path / "a.tif"
    path.write_bytes(geotiff(scene(64, 80, 1, np.uint8)))
    assert isinstance(open_image(path), np.ndarray)
    with open_image(path, level_pixels=1000) as source:
        assert isinstance(source, RasterFile) and source.width == 80
    from pwlreg.core.errors import ImageTooLargeError

    with pytest.raises(ImageTooLargeError):  # its own limit: the decoded one does not apply
        open_image(path, level_pixels=1000, max_raster_pixels=1000)
    with open_image(path, level_pixels=1000, max_pixels=10) as source:
        assert source.height == 64


@pytest.mark.parametrize(("channels", "dtype"), [(1, np.uint8), (2, np.uint8), (4, np.uint16)])
def test_png_written_in_strips_decodes_to_the_image(channels, dtype):
    rng = np.random.default_rng(channels)
    image = rng.integers(0, np.iinfo(dtype).max, size=(123, 77, channels), dtype=dtype)
    out = io.BytesIO()
    with PngWriter(out, 77, 123, channels, dtype, threads=2) as png:
        for start in range(0, 123, 50):  # strips of uneven height
            png.write(image[start:start + 50])
    decoded = cv2.imdecode(np.frombuffer(out.getvalue(), np.uint8), cv2.IMREAD_UNCHANGED)
    if channels == 2:  # OpenCV cannot read grey+alpha back as such: Pillow can
        decoded = np.asarray(Image.open(io.BytesIO(out.getvalue())))
    np.testing.assert_array_equal(decoded.reshape(image.shape), image)
    whole = encode_png(image, threads=1)
    assert Image.open(io.BytesIO(whole)).tobytes() == Image.open(out).tobytes()


def test_png_writer_refuses_a_missing_or_extra_row():
    out = io.BytesIO()
    png = PngWriter(out, 4, 3, 1, np.uint8)
    png.write(np.zeros((2, 4), np.uint8))
    with pytest.raises(ValueError, match="more than"):
        png.write(np.zeros((2, 4), np.uint8))
    with pytest.raises(ValueError, match="2 of the PNG's 3 rows"):
        png.close()


# --- registration on levels ---------------------------------------------------------------------


def test_level_factor_is_whole_and_leaves_at_most_the_limit():
    assert level_factor(100, 100, 10_000) == 1
    for height, width in ((20000, 20000), (4473, 5591), (1001, 999)):
        factor = level_factor(height, width, 1 << 18)
        assert (height // factor) * (width // factor) <= 1 << 18
        assert height * width / (factor - 1) ** 2 > 1 << 18


def _similar_pair(height=900, width=1200):
    """A textured raster and the same texture through a known affine map (3 degrees, 4 %
    larger, shifted): returns the images and the true map reference -> moving."""
    texture = np.moveaxis(scene(height, width, 1, np.uint8, seed=5), 0, -1)[:, :, 0]
    angle, scale = np.deg2rad(3.0), 1.04
    forward = np.array([[scale * np.cos(angle), -scale * np.sin(angle), 14.0],
                        [scale * np.sin(angle), scale * np.cos(angle), -9.0]])
    moving = cv2.warpAffine(texture, forward, (width, height), flags=cv2.INTER_CUBIC,
                            borderMode=cv2.BORDER_REFLECT)  # moving(forward(p)) = texture(p)
    return texture, moving, forward


def _error(result, forward):
    measured = ~np.asarray(result.extrapolated, bool)
    ref = result.reference_vertices[measured]
    truth = ref @ forward[:, :2].T + forward[:, 2]
    inside = ((truth > 20) & (truth < np.array([1180, 880]))).all(axis=1)
    return np.linalg.norm(result.moving_vertices[measured] - truth, axis=1)[inside]


def test_levels_keep_the_clients_points_exactly():
    reference, moving, forward = _similar_pair()
    rng = np.random.default_rng(2)
    ref_pts = rng.uniform([30, 30], [1100, 800], size=(150, 2))
    mov_pts = ref_pts @ forward[:, :2].T + forward[:, 2]
    mov_pts[:3] += 5000  # outside the moving image: dropped, and listed where the client put them
    result = register(reference, moving, (ref_pts, mov_pts), NO_FILTER, level_pixels=1 << 17)
    dropped = result.points.dropped
    np.testing.assert_allclose(dropped.reference, ref_pts[:3], atol=1e-9)
    np.testing.assert_allclose(dropped.moving, mov_pts[:3], atol=1e-9)
    ref_pts, mov_pts = ref_pts[3:], mov_pts[3:]
    assert isinstance(result, ScaledResult) and result.scales[0, 0] == 3
    assert result.reference_size == (1200, 900)
    measured = ~np.asarray(result.extrapolated, bool)
    assert measured.sum() >= 140
    # Each measured vertex is a client pair, to the 1/256-pixel grid of every mesh.
    distance = np.abs(result.reference_vertices[measured][:, None] - ref_pts[None]).max(axis=2)
    pair = distance.argmin(axis=1)
    assert distance.min(axis=1).max() <= 1 / 512
    np.testing.assert_allclose(result.moving_vertices[measured], mov_pts[pair], atol=1 / 512)
    assert result.options.min_triangle_area == 25.0  # the client's value, not the level's


def test_levels_keep_the_pair_the_pipeline_kept_of_two_on_one_point():
    # Of two client pairs on one reference point the pipeline keeps the first; the vertex
    # took the moving position of either (the second, 20 px off, in the probe).
    reference, moving, forward = _similar_pair()
    rng = np.random.default_rng(3)
    ref_pts = rng.uniform([30, 30], [1100, 800], size=(60, 2))
    mov_pts = ref_pts @ forward[:, :2].T + forward[:, 2]
    given = (np.vstack([ref_pts, ref_pts[:1]]), np.vstack([mov_pts, mov_pts[:1] + [20, 0]]))
    result = register(reference, moving, given, NO_FILTER, level_pixels=1 << 17)
    assert isinstance(result, ScaledResult) and result.points.rejected["duplicate"] == 1
    first = np.abs(result.reference_vertices - ref_pts[0]).max(axis=1).argmin()
    np.testing.assert_allclose(result.moving_vertices[first], mov_pts[0], atol=1 / 512)


def test_levels_take_the_band_option_once():
    reference, moving, _ = _similar_pair()
    colour = [np.dstack([image // 2, image, image // 3]) for image in (reference, moving)]
    result = register(*colour, None, {"band": "2"}, level_pixels=1 << 17)
    assert isinstance(result, ScaledResult) and result.quality.verdict == "good"
    assert result.options.band == "2"


def test_a_result_on_levels_writes_without_the_sources(tmp_path):
    # The documented call, write_outputs(result, dir), had no moving image to resample for a
    # result registered from arrays (or decoded files) on levels.
    reference, moving, _ = _similar_pair()
    result = register(reference, moving, None, {}, level_pixels=1 << 17)
    paths = write_outputs(result, tmp_path)
    registered = read_image(paths["registered"])
    assert registered.shape[:2] == reference.shape[:2]


def test_array_windows_say_where_data_is_missing_and_only_there():
    # A window of valid pixels only reads as such (None), as a file's does: a mask there kept
    # the whole image from its refinement at full resolution.
    data = np.arange(40 * 50, dtype=np.float32).reshape(40, 50)
    mask = np.zeros(data.shape, bool)
    mask[:10, :10] = True
    source = ArrayBands(np.ma.MaskedArray(data, mask=mask))
    assert source.read(20, 20, 40, 40)[1] is None
    assert not source.read(0, 0, 20, 20)[1].all()
    # A picture's alpha 0 is missing data too.
    picture = np.dstack([np.full((40, 50), 9, np.uint8)] * 3 + [np.where(mask, 0, 255)
                                                                .astype(np.uint8)])
    np.testing.assert_array_equal(ArrayBands(picture).read(0, 0, 20, 20)[1], ~mask[:20, :20])
    assert ArrayBands(picture).read(20, 20, 40, 40)[1] is None


def test_levels_refine_automatic_pairs_at_full_resolution():
    reference, moving, forward = _similar_pair()
    result = register(reference, moving, None, {}, level_pixels=1 << 17)
    level = register(cv2.resize(reference, (400, 300), interpolation=cv2.INTER_AREA),
                     cv2.resize(moving, (400, 300), interpolation=cv2.INTER_AREA), None, {})
    errors = _error(result, forward)
    assert len(errors) >= 30 and result.refined["refined"] >= 0.8 * len(errors)
    # The level alone places a pair to a fraction of its pixels (measured: a median 0.044 px
    # at full resolution on this smooth texture, where the refinement gives 0.014).
    level_errors = np.linalg.norm(
        (level.moving_vertices + 0.5) * 3 - 0.5
        - (((level.reference_vertices + 0.5) * 3 - 0.5) @ forward[:, :2].T + forward[:, 2]),
        axis=1)[~np.asarray(level.extrapolated, bool)]
    assert np.median(errors) < min(0.03, 0.6 * np.median(level_errors))


def test_large_georeferenced_raster_end_to_end(tmp_path):
    """A 4-band 16-bit GeoTIFF pair with a nodata hole registered on levels from its files:
    registered.tif in the reference grid at full size, registered.png streamed, figures."""
    pair = make_pair(height=360, width=480, bands=4, dtype=np.uint16, nodata=0,
                     hole=(slice(100, 140), slice(200, 260)))
    ref_path, mov_path = tmp_path / "reference.tif", tmp_path / "moving.tif"
    ref_path.write_bytes(pair.reference_tif)
    mov_path.write_bytes(pair.moving_tif)
    points = (pair.reference_points, pair.moving_points)
    with open_image(ref_path, level_pixels=1 << 14) as reference, \
            open_image(mov_path, level_pixels=1 << 14) as moving:
        result = register(reference, moving, points, NO_FILTER, level_pixels=1 << 14)
    assert isinstance(result, ScaledResult) and result.reference_level.shape[:2] == (90, 120)
    written = write_outputs(result, tmp_path / "out", sources=Sources(
        reference_path=ref_path, moving_path=mov_path))
    assert {"registered", "registered_geotiff", "mesh_reference", "checkerboard"} <= set(written)
    with rasterio.open(written["registered_geotiff"]) as tif:
        assert (tif.width, tif.height, tif.count, tif.dtypes[0]) == (480, 360, 4, "uint16")
        data = tif.read()
        assert tif.nodata == 0 and tif.transform == rasterio.open(ref_path).transform
    # The pair is a pure shift: inside the mesh the registered bands are the reference's.
    inside = (data != 0).all(axis=0)
    assert inside.mean() > 0.7
    np.testing.assert_array_equal(data[:, inside], pair.reference[:, inside])
    png = np.asarray(Image.open(written["registered"]))
    assert png.shape == (360, 480, 2)  # the 8-bit luminance picture and alpha
    np.testing.assert_array_equal(png[:, :, 1] == 255, inside)
    mesh = json.loads((tmp_path / "out" / "mesh.json").read_text())
    assert mesh["image_size"]["reference"] == [480, 360]
    assert mesh["levels"] == {"factors": [4, 4], "refined": None}  # the client's points


def test_matching_image_of_a_level_is_the_level_of_the_picture():
    """The level's picture is made like the full image's: same recipe, close values."""
    raster = np.ma.MaskedArray(np.moveaxis(scene(300, 400, 3, np.uint16), 0, -1),
                               mask=np.ma.nomask)
    full = matching_image(raster).astype(float)
    level = matching_image(ArrayBands(raster).level(2)).astype(float)
    reduced = cv2.resize(full, (200, 150), interpolation=cv2.INTER_AREA)
    assert np.abs(level - reduced).mean() < 3  # grey levels, of 255


@pytest.mark.skipif(not (LANDSAT / "l8_B8.tif").exists(),
                    reason=f"real data not found: {LANDSAT} (../shared/data/real)")
def test_levels_on_real_landsat_pan_band_refine_below_the_level_error(monkeypatch):
    """Landsat 8's panchromatic band and the same band through a known affine map (2 degrees,
    3 % scale): registered on levels 3 times smaller, the refined pairs are more exact than
    the level's (measured: median 0.021 px against 0.060 px; 0.028 px at full resolution)."""
    reference = read_image(LANDSAT / "l8_B8.tif")
    height, width = reference.shape
    angle = np.deg2rad(2.0)
    forward = np.array([[1.03 * np.cos(angle), -1.03 * np.sin(angle), 12.3],
                        [1.03 * np.sin(angle), 1.03 * np.cos(angle), -7.6]])
    moving = cv2.warpAffine(reference, forward, (width, height), flags=cv2.INTER_CUBIC,
                            borderMode=cv2.BORDER_REFLECT)

    def errors(result):
        measured = ~np.asarray(result.extrapolated, bool)
        truth = result.reference_vertices[measured] @ forward[:, :2].T + forward[:, 2]
        inside = ((truth > 10) & (truth < np.array([width - 10, height - 10]))).all(axis=1)
        return np.linalg.norm(result.moving_vertices[measured] - truth, axis=1)[inside]

    refined = register(reference, moving, None, {}, level_pixels=1 << 18)
    assert refined.scales[0, 0] == 3 and len(errors(refined)) > 200
    assert refined.refined["refined"] > 0.9 * len(errors(refined))
    monkeypatch.setattr("pwlreg.core.scaled.refine_pairs",
                        lambda r, m, rv, mv, measured, **k: (mv, {}))
    level = register(reference, moving, None, {}, level_pixels=1 << 18)
    assert np.median(errors(refined)) < min(0.04, 0.6 * np.median(errors(level)))
