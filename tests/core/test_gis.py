"""GeoTIFF in and out, GeoJSON, QGIS .points and GCPs, on GeoTIFFs written with rasterio."""

from __future__ import annotations

import json

import numpy as np
import pytest
import rasterio
from pyproj import Transformer
from rasterio.control import GroundControlPoint
from rasterio.crs import CRS
from rasterio.enums import ColorInterp
from rasterio.io import MemoryFile
from rasterio.transform import Affine

from pwlreg.core.errors import ImageTooLargeError, InputError, UnsupportedMediaError
from pwlreg.core.imaging import fill_invalid, matching_image
from pwlreg.core.io import load_points, probe_image, read_image
from pwlreg.core.pipeline import register
from pwlreg.core.results import RESULTS, Sources, write_outputs
from tests.core.gis import LANDSAT, TRANSFORM, UTM, geotiff, make_pair, map_coords, scene

NO_FILTER = {"epipolar_filter": False}


def _write(tmp_path, pair):
    ref, mov = tmp_path / "reference.tif", tmp_path / "moving.tif"
    ref.write_bytes(pair.reference_tif)
    mov.write_bytes(pair.moving_tif)
    return ref, mov


def _run(tmp_path, pair, points=None, options=None):
    ref_path, mov_path = _write(tmp_path, pair)
    reference = read_image(ref_path, field="reference")
    moving = read_image(mov_path, field="moving")
    if points is None:
        points = (pair.reference_points, pair.moving_points)
    result = register(reference, moving, points, options or NO_FILTER)
    written = write_outputs(result, tmp_path / "out",
                            sources=Sources(reference, moving, ref_path, mov_path))
    return result, written


# --- reading --------------------------------------------------------------------------------


def test_multiband_16bit_geotiff_is_a_raster_in_file_order():
    pair = make_pair(bands=4, dtype=np.uint16)
    raster = read_image(pair.reference_tif)
    assert isinstance(raster, np.ma.MaskedArray) and raster.shape == (180, 240, 4)
    assert raster.dtype == np.uint16 and not raster.mask.any()
    np.testing.assert_array_equal(raster.data, np.moveaxis(pair.reference, 0, -1))
    assert probe_image(pair.reference_tif, max_pixels=240 * 180) == (240, 180)
    with pytest.raises(ImageTooLargeError):
        probe_image(pair.reference_tif, max_pixels=240 * 180 - 1)
    many = geotiff(np.zeros((20, 10, 10), np.uint8))  # 20 bands: samples count too
    assert probe_image(many, max_pixels=200) == (10, 10)
    with pytest.raises(ImageTooLargeError, match="20 bands"):
        probe_image(many, max_pixels=100)


def test_nodata_and_nan_are_masked_and_rgb_is_a_bgr_picture():
    data = scene(40, 50, 1, np.float32)
    data[0, :5, :7] = np.nan
    raster = read_image(geotiff(data, nodata=float("nan")))
    assert isinstance(raster, np.ma.MaskedArray) and raster.mask.sum() == 35
    ints = scene(40, 50, 2, np.uint16)
    ints[:, 10:12, 20:30] = 0
    raster = read_image(geotiff(ints, nodata=0))
    assert raster.mask[:, :, 0].sum() == 20 and (raster.mask[:, :, 0] == raster.mask[:, :, 1]).all()
    rgb = scene(40, 50, 3, np.uint8)
    picture = read_image(geotiff(rgb, photometric="RGB"))
    assert type(picture) is np.ndarray and picture.shape == (40, 50, 3)
    np.testing.assert_array_equal(picture[:, :, 0], rgb[2])  # BGR, as OpenCV decodes
    index = np.zeros((1, 20, 30), np.uint8)
    index[0, :, 15:] = 1
    with MemoryFile() as memory:
        with memory.open(driver="GTiff", width=30, height=20, count=1, dtype="uint8",
                         photometric="palette", crs=UTM, transform=TRANSFORM) as dst:
            dst.write(index)
            dst.write_colormap(1, {0: (255, 0, 0, 255), 1: (0, 0, 255, 255)})
        palette = read_image(memory.read())
    assert palette[0, 0].tolist() == [0, 0, 255] and palette[0, 20].tolist() == [255, 0, 0]


def test_truncated_or_damaged_tiff_is_refused_from_its_structure():
    tif = make_pair().reference_tif
    for damaged in (tif[: len(tif) // 2], tif[:200], b"II*\x00" + b"\x00" * 50):
        with pytest.raises(UnsupportedMediaError, match="truncated or damaged"):
            probe_image(damaged, field="moving")
    # Damaged compressed data inside the file: only decoding (the worker's) can tell.
    damaged = bytearray(tif)
    damaged[len(tif) // 3:len(tif) // 3 + 400] = bytes(b ^ 0x5A for b in damaged[
        len(tif) // 3:len(tif) // 3 + 400])
    assert probe_image(bytes(damaged)) == (240, 180)
    with pytest.raises(UnsupportedMediaError, match="could not be decoded") as err:
        read_image(bytes(damaged), field="moving")
    assert err.value.field == "moving"
    # A complex-valued TIFF is a TIFF the registration cannot use.
    with pytest.raises(InputError, match="samples of type complex64"):
        probe_image(geotiff(np.zeros((1, 8, 8), np.complex64)))


# --- what matching and scoring see ------------------------------------------------------------


def test_matching_image_rescales_rasters_and_picks_bands():
    bands = np.moveaxis(scene(60, 80, 3, np.float32), 0, -1)
    grey = matching_image(bands, "luminance")
    assert grey.dtype == np.uint8 and grey.shape == (60, 80)
    # 0.5 / 99.5 percentiles to 0 / 255: about 0.5 % of the pixels at each end.
    assert 0.002 < (grey == 0).mean() < 0.02 and 0.002 < (grey == 255).mean() < 0.02
    second = matching_image(bands, 2)
    assert np.corrcoef(second.ravel(), bands[:, :, 1].ravel())[0, 1] > 0.99
    picture = np.dstack([np.full((6, 6), v, np.uint8) for v in (10, 20, 30)])  # B, G, R
    assert matching_image(picture) is picture
    assert (matching_image(picture, "1") == 30).all()  # band 1 of a colour picture is red
    with pytest.raises(InputError) as err:
        matching_image(bands, 4, "moving")
    assert err.value.field == "options.band" and "3 band" in str(err.value)


def test_what_a_transparent_area_holds_does_not_reach_matching_or_scoring():
    rng = np.random.default_rng(3)
    colour = rng.integers(0, 65536, (40, 50, 3), dtype=np.uint16)
    alpha = np.full((40, 50), 65535, np.uint16)
    alpha[5:25, 10:30] = 0
    one = np.dstack([colour, alpha])
    other = one.copy()
    other[5:25, 10:30, :3] = rng.integers(0, 65536, (20, 20, 3), dtype=np.uint16)
    seen = matching_image(one)
    assert seen.shape == one.shape and seen.dtype == np.uint16
    np.testing.assert_array_equal(seen, matching_image(other))
    np.testing.assert_array_equal(seen[~(alpha == 0)], one[~(alpha == 0)])
    band = matching_image(one, "1")
    assert band.shape == (40, 50, 4) and (band[:, :, 3] == alpha).all()
    np.testing.assert_array_equal(band[:, :, 0], matching_image(other, "1")[:, :, 0])
    opaque = np.dstack([colour, np.full((40, 50), 1, np.uint16)])
    assert matching_image(opaque) is opaque
    with pytest.raises(InputError, match="alpha is 0 everywhere"):
        matching_image(np.dstack([colour, np.zeros((40, 50), np.uint16)]), field="moving")


def test_invalid_pixels_get_no_edge_and_a_transparent_alpha():
    data = scene(120, 160, 1, np.uint16)[0]
    invalid = np.zeros(data.shape, bool)
    invalid[30:90, 40:110] = True
    picture = matching_image(np.ma.MaskedArray(data, mask=invalid))
    assert picture.shape == (120, 160, 4) and picture.dtype == np.uint8
    np.testing.assert_array_equal(picture[:, :, 3] == 0, invalid)
    grey = picture[:, :, 0].astype(float)
    # Inside the hole the fill is smooth: far weaker gradients than the texture's.
    gy, gx = np.gradient(grey)
    gradient = np.hypot(gx, gy)
    assert np.percentile(gradient[35:85, 45:105], 99) < 0.25 * np.percentile(gradient[~invalid], 90)
    # A constant fill would step at the hole's border; the push-pull fill does not.
    values, valid = np.linspace(0, 1, 100, dtype=np.float32)[None].repeat(50, 0), None
    valid = np.ones(values.shape, bool)
    valid[:, 50:] = False
    filled = fill_invalid(values, valid)
    assert abs(filled[25, 50] - filled[25, 49]) < 0.05


# --- GeoTIFF and GeoJSON out --------------------------------------------------------------------


@pytest.mark.parametrize(("bands", "dtype"), [(4, np.uint16), (1, np.float32)])
def test_georeferenced_pair_gives_registered_tif_in_the_reference_grid(tmp_path, bands, dtype):
    nodata = 0 if dtype == np.uint16 else -9999.0
    pair = make_pair(bands=bands, dtype=dtype, nodata=nodata, hole=(slice(0, 30), slice(0, 40)))
    result, written = _run(tmp_path, pair)
    assert {"registered_geotiff", "mesh_geojson", "tiepoints_geojson"} <= set(written)
    assert RESULTS["registered_geotiff"].media_type == "image/tiff; application=geotiff"
    with rasterio.open(written["registered_geotiff"]) as ds:
        assert ds.crs == UTM and ds.transform == TRANSFORM
        assert (ds.count, ds.dtypes[0], ds.nodata) == (bands, np.dtype(dtype).name, nodata)
        assert ds.profile["tiled"] and ds.compression.name == "deflate"
        out = ds.read()
    dx, dy = pair.shift
    # Reference pixel p shows moving pixel p - shift: the registered raster is the reference
    # wherever that pixel is inside the moving image and outside its nodata hole.
    inside = np.zeros(out.shape[1:], bool)
    inside[dy + 30:, dx + 40:] = True
    inside[dy:, dx:][:30, 40:] = True
    inside[dy:, dx:][30:, :40] = True
    np.testing.assert_allclose(out[:, inside], pair.reference[:, inside], rtol=1e-5)
    assert (out[:, :dy, :] == nodata).all() and (out[:, :, :dx] == nodata).all()
    assert (out[:, dy:dy + 30, dx:dx + 40] == nodata).all()  # the moving hole stays nodata


def test_colour_png_moving_gives_an_rgb_geotiff(tmp_path):
    pair = make_pair(bands=3, dtype=np.uint8)
    ref_path = tmp_path / "reference.tif"
    ref_path.write_bytes(pair.reference_tif)
    moving = np.ascontiguousarray(np.moveaxis(pair.moving, 0, -1)[:, :, ::-1])  # BGR, as cv2
    reference = read_image(ref_path)
    result = register(reference, moving, (pair.reference_points, pair.moving_points), NO_FILTER)
    written = write_outputs(result, tmp_path / "out", sources=Sources(reference, moving, ref_path))
    with rasterio.open(written["registered_geotiff"]) as ds:
        assert ds.colorinterp[:3] == (ColorInterp.red, ColorInterp.green, ColorInterp.blue)
        out = ds.read()
    dx, dy = pair.shift
    np.testing.assert_array_equal(out[:, dy:, dx:], pair.reference[:, dy:, dx:])  # R, G, B


def test_large_registered_tif_has_overviews(tmp_path):
    pair = make_pair(height=48, width=1100, bands=1, dtype=np.uint8)
    _, written = _run(tmp_path, pair)
    with rasterio.open(written["registered_geotiff"]) as ds:
        assert ds.overviews(1) == [2] and ds.block_shapes[0] == (512, 512)


def test_moving_positions_in_a_local_grid_without_a_way_to_wgs84(tmp_path):
    # A site's local grid has no transformation to WGS 84: the points stay in its coordinates,
    # and the moving file's positions, in the same grid, were left out.
    local = CRS.from_wkt('LOCAL_CS["plant grid",LOCAL_DATUM["site",0],UNIT["metre",1],'
                         'AXIS["Easting",EAST],AXIS["Northing",NORTH]]')
    pair = make_pair()
    ref_path, mov_path = tmp_path / "reference.tif", tmp_path / "moving.tif"
    ref_path.write_bytes(geotiff(pair.reference, crs=local))
    mov_path.write_bytes(geotiff(pair.moving, crs=local))
    reference, moving = read_image(ref_path), read_image(mov_path)
    result = register(reference, moving, (pair.reference_points, pair.moving_points), NO_FILTER)
    written = write_outputs(result, tmp_path / "out",
                            sources=Sources(reference, moving, ref_path, mov_path))
    ties = json.loads(written["tiepoints_geojson"].read_text())
    assert "crs" in ties
    for feature in ties["features"]:
        mx, my = map_coords(np.array([feature["properties"]["moving_px"]]))[0]
        np.testing.assert_allclose(feature["properties"]["moving_position"], (mx, my),
                                   atol=1e-3)


def test_geojson_lines_up_with_the_raster(tmp_path):
    pair = make_pair()
    result, written = _run(tmp_path, pair)
    to_utm = Transformer.from_crs("EPSG:4326", UTM.to_wkt(), always_xy=True)
    ties = json.loads(written["tiepoints_geojson"].read_text())
    assert ties["type"] == "FeatureCollection" and "crs" not in ties  # RFC 7946: WGS 84
    assert len(ties["features"]) == len(pair.reference_points)
    for feature in ties["features"]:
        lon, lat = feature["geometry"]["coordinates"]
        x, y = to_utm.transform(lon, lat)
        row, col = rasterio.transform.rowcol(TRANSFORM, x, y)
        rx, ry = feature["properties"]["reference_px"]
        assert (row, col) == (round(ry), round(rx))  # the pixel the point came from
        np.testing.assert_allclose(
            feature["properties"]["moving_px"], np.subtract((rx, ry), pair.shift), atol=1e-3
        )
        # The moving file has the reference's geotransform: its point is `shift` pixels off.
        mx, my = map_coords(np.array([feature["properties"]["moving_px"]]))[0]
        np.testing.assert_allclose(to_utm.transform(*feature["properties"]["moving_position"]),
                                   (mx, my), atol=0.01)
    mesh = json.loads(written["mesh_geojson"].read_text())
    assert len(mesh["features"]) == len(result.final_triangles)
    to_lonlat = Transformer.from_crs(UTM.to_wkt(), "EPSG:4326", always_xy=True)
    for feature in mesh["features"]:
        ring = np.array(feature["geometry"]["coordinates"][0])
        assert ring.shape == (4, 2) and (ring[0] == ring[-1]).all()
        area = np.sum(ring[:-1, 0] * ring[1:, 1] - ring[1:, 0] * ring[:-1, 1])
        assert area > 0  # counter-clockwise
        expected = np.stack(to_lonlat.transform(
            *map_coords(np.array(feature["properties"]["reference_px"])).T), axis=1)
        got = ring[:-1]
        assert all(np.abs(got - e).sum(axis=1).min() < 1e-8 for e in expected)
        props = feature["properties"]
        assert set(props) >= {"swapped", "consistency", "extrapolated", "vertices"}
    scores = [f["properties"]["consistency"] for f in mesh["features"]]
    expected_scores = [None if not np.isfinite(s) else round(float(s), 4)
                       for s in result.quality.triangle_scores]
    assert scores == expected_scores


def test_without_georeferencing_no_geotiff_and_geojson_in_pixels(tmp_path):
    pair = make_pair()
    plain = geotiff(pair.reference, transform=None)
    ref_path = tmp_path / "reference.tif"
    ref_path.write_bytes(plain)
    reference = read_image(ref_path)
    moving = read_image(pair.moving_tif)
    result = register(reference, moving, (pair.reference_points, pair.moving_points), NO_FILTER)
    written = write_outputs(result, tmp_path / "out", sources=Sources(reference, moving, ref_path))
    assert "registered_geotiff" not in written
    doc = json.loads(written["tiepoints_geojson"].read_text())
    assert doc["crs"]["properties"]["name"] == "urn:pwlreg:crs:pixel"
    np.testing.assert_allclose([f["geometry"]["coordinates"] for f in doc["features"]],
                               pair.reference_points, atol=1e-3)


# --- control points from GIS tools ----------------------------------------------------------------


def _qgis_points(pair, crs_line: str | None, disabled_row: bool = True) -> str:
    coords = map_coords(pair.reference_points)
    if crs_line == "EPSG:4326":
        lon, lat = Transformer.from_crs(UTM.to_wkt(), "EPSG:4326", always_xy=True).transform(
            coords[:, 0], coords[:, 1])
        coords = np.stack([lon, lat], axis=1)
    lines = [f"#CRS: {CRS.from_user_input(crs_line).to_wkt()}"] if crs_line else []
    lines.append("mapX,mapY,sourceX,sourceY,enable,dX,dY,residual")
    for (mx, my), (sx, sy) in zip(coords.tolist(), pair.moving_points.tolist(), strict=True):
        lines.append(f"{mx!r},{my!r},{sx + 0.5!r},{-(sy + 0.5)!r},1,0,0,0")
    if disabled_row:
        lines.append("452600.0,3408000.0,1.0,-1.0,0,0,0,0")
    return "\n".join(lines) + "\n"


@pytest.mark.parametrize("crs_line", [None, "EPSG:32616", "EPSG:4326"])
def test_qgis_points_file_gives_the_json_points(tmp_path, crs_line):
    pair = make_pair(bands=1)
    ref_path, mov_path = _write(tmp_path, make_pair(bands=1))
    plain_moving = tmp_path / "plain.tif"
    plain_moving.write_bytes(geotiff(pair.moving, transform=None))
    ref, mov = load_points(_qgis_points(pair, crs_line).encode(), reference=ref_path,
                           moving=plain_moving)
    np.testing.assert_allclose(ref, pair.reference_points, atol=1e-6)
    np.testing.assert_allclose(mov, pair.moving_points, atol=1e-9)
    # Without a georeferenced reference, map coordinates have nowhere to go.
    with pytest.raises(InputError, match="not georeferenced") as err:
        load_points(_qgis_points(pair, None).encode(), reference=plain_moving)
    assert err.value.field == "points"


def test_gcps_of_the_moving_geotiff_give_the_same_mesh_as_json_points(tmp_path):
    pair = make_pair(bands=1)
    coords = map_coords(pair.reference_points)
    gcps = [GroundControlPoint(row=y + 0.5, col=x + 0.5, x=mx, y=my)
            for (x, y), (mx, my) in zip(pair.moving_points.tolist(), coords.tolist(), strict=True)]
    with_gcps = geotiff(pair.moving, transform=None, gcps=gcps, gcp_crs=UTM)
    ref_path, _ = _write(tmp_path, pair)
    mov_path = tmp_path / "moving_gcps.tif"
    mov_path.write_bytes(with_gcps)
    points = load_points(with_gcps, reference=ref_path, moving=mov_path)
    np.testing.assert_allclose(points[0], pair.reference_points, atol=1e-6)
    np.testing.assert_allclose(points[1], pair.moving_points, atol=1e-9)
    own = load_points(" GCPS\n", reference=ref_path, moving=mov_path)  # the word: moving's own
    np.testing.assert_array_equal(own[0], points[0])
    with pytest.raises(InputError, match="no ground control points"):
        load_points("gcps", reference=ref_path, moving=ref_path)
    moving = read_image(mov_path)
    reference = read_image(ref_path)
    from_gcps = register(reference, moving, points, NO_FILTER)
    from_json = register(reference, moving, (pair.reference_points, pair.moving_points), NO_FILTER)
    np.testing.assert_array_equal(from_gcps.final_triangles, from_json.final_triangles)
    np.testing.assert_array_equal(from_gcps.moving_vertices, from_json.moving_vertices)
    other = tmp_path / "other.tif"
    other.write_bytes(geotiff(pair.moving[:, :100, :120]))
    with pytest.raises(InputError, match="GCPs must be those of the moving image"):
        load_points(with_gcps, reference=ref_path, moving=other)
    # A reference whose pixels have no size cannot place the GCPs' map coordinates.
    flat = tmp_path / "flat.tif"
    flat.write_bytes(geotiff(pair.reference, transform=Affine(0, 0, 500000, 0, 0, 4000000)))
    with pytest.raises(InputError, match="degenerate") as err:
        load_points(with_gcps, reference=flat, moving=mov_path)
    assert err.value.field == "reference"


# --- a real multispectral scene ------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.skipif(not LANDSAT.is_dir(), reason=f"real Landsat sample absent: {LANDSAT}")
def test_landsat_pan_band_onto_a_30m_grid(tmp_path):
    """A moving GeoTIFF at another resolution: the real panchromatic band (15 m) onto its own
    2 x 2 block average on a 30 m grid (B4 against B8 would measure the producer's band-to-band
    cloud parallax, not the registration). Truth: reference x -> moving 2 x + 0.5."""
    with rasterio.open(LANDSAT / "l8_B8.tif") as ds:
        pan, pan_transform = ds.read(1), ds.transform
    h, w = pan.shape[0] // 2 * 2, pan.shape[1] // 2 * 2
    coarse = pan[:h, :w].reshape(h // 2, 2, w // 2, 2).mean(axis=(1, 3)).round().astype(np.uint16)
    ref_path = tmp_path / "pan30.tif"
    ref_path.write_bytes(geotiff(coarse[None], transform=pan_transform @ Affine.scale(2),
                                 crs=UTM))
    result = register(read_image(ref_path), read_image(LANDSAT / "l8_B8.tif"))
    measured = ~result.extrapolated
    truth = 2 * result.reference_vertices[measured] + 0.5
    error = np.hypot(*(result.moving_vertices[measured] - truth).T)
    assert measured.sum() >= 50 and np.median(error) < 0.3, np.percentile(error, [50, 90])
    written = write_outputs(result, tmp_path, sources=Sources(
        None, None, ref_path, LANDSAT / "l8_B8.tif"))
    with rasterio.open(written["registered_geotiff"]) as ds, rasterio.open(ref_path) as ref:
        assert (ds.crs, ds.transform, ds.shape, ds.dtypes) == (ref.crs, ref.transform, ref.shape,
                                                               ref.dtypes)
        registered = ds.read(1).astype(float)
        mapped = ds.read_masks(1) > 0
    # registered.tif has data where registered.png is opaque (the same mesh, the same fill
    # rule; pixel centres exactly on the mesh's outline are left out), and there it shows the
    # reference's content.
    opaque = result.registered[:, :, -1] > 0
    assert not (mapped & ~opaque).any() and (mapped == opaque).mean() > 0.99
    assert np.corrcoef(registered[mapped], coarse[mapped])[0, 1] > 0.97
