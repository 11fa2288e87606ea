"""GIS inputs and outputs over real HTTP: GeoTIFFs in (16-bit multi-band, float32, nodata),
registered.tif and GeoJSON out, QGIS .points files and GeoTIFF GCPs as points, damaged TIFFs
refused; and the command line with a .points file."""

from __future__ import annotations

import io
import json
from pathlib import Path
from typing import Any

import cv2
import httpx
import numpy as np
import pytest
import rasterio
from rasterio.control import GroundControlPoint

from tests.core.gis import TRANSFORM, UTM, geotiff, make_pair, map_coords
from tests.service.helpers import Pair, Server, assert_problem, wait_for
from tests.service.test_cli import pwlreg

GEOTIFF = "image/tiff; application=geotiff"
GEOJSON = "application/geo+json"
NO_FILTER = {"epipolar_filter": False}


def _post(client: httpx.Client, reference: bytes, moving: bytes, points: bytes | None = None,
          options: dict[str, Any] | None = None) -> httpx.Response:
    files: dict[str, Any] = {"reference": ("reference.tif", reference, "image/tiff"),
                             "moving": ("moving.tif", moving, "image/tiff")}
    if points is not None:
        files["points"] = ("points", points, "application/octet-stream")
    data = {"options": json.dumps(options)} if options is not None else None
    return client.post("/v1/jobs", files=files, data=data)


def _finished(client: httpx.Client, response: httpx.Response) -> dict[str, Any]:
    assert response.status_code == 201, response.text
    job = wait_for(client, response.json()["id"])
    assert job["status"] == "successful", job
    return job


def _links(job: dict[str, Any]) -> dict[str, tuple[str, str]]:
    return {link["href"].rsplit("/", 1)[1]: (link["href"], link["type"])
            for link in job["links"][1:]}


def _qgis_points(pair) -> bytes:
    """The pair's points as QGIS writes them for a georeferenced moving raster: its map
    coordinates on the source side (its geotransform is the reference's)."""
    lines = ["mapX,mapY,sourceX,sourceY,enable,dX,dY,residual"]
    coords = map_coords(pair.reference_points).tolist()
    for (mx, my), (sx, sy) in zip(coords, map_coords(pair.moving_points).tolist(), strict=True):
        lines.append(f"{mx!r},{my!r},{sx!r},{sy!r},1,0,0,0")
    return ("\n".join(lines) + "\n").encode()


def test_georeferenced_16bit_multiband_job_gives_geotiff_and_geojson(server: Server) -> None:
    pair = make_pair(bands=4, dtype=np.uint16, nodata=0, hole=(slice(0, 30), slice(0, 40)))
    with server.client() as client:
        job = _finished(client, _post(client, pair.reference_tif, pair.moving_tif,
                                      pair.points_json(), {**NO_FILTER, "band": 2}))
        links = _links(job)
        assert links["registered.tif"][1] == GEOTIFF
        assert links["mesh.geojson"][1] == links["tiepoints.geojson"][1] == GEOJSON
        head = client.head(links["registered.tif"][0])
        assert head.status_code == 200 and head.headers["content-type"] == GEOTIFF
        tif = client.get(links["registered.tif"][0]).content
        mesh = client.get(f"/v1/jobs/{job['id']}/mesh").json()
        geo = client.get(links["mesh.geojson"][0])
        ties = client.get(links["tiepoints.geojson"][0]).json()
    with rasterio.open(io.BytesIO(tif)) as ds:
        assert (ds.crs, ds.transform, ds.count, ds.dtypes[0], ds.nodata) == (
            UTM, TRANSFORM, 4, "uint16", 0)
        out = ds.read()
    dx, dy = pair.shift
    np.testing.assert_array_equal(out[:, 40:, 50:], pair.reference[:, 40:, 50:])
    assert (out[:, dy:dy + 30, dx:dx + 40] == 0).all()  # the moving image's nodata hole
    assert geo.headers["content-type"] == GEOJSON
    polygons = geo.json()["features"]
    assert len(polygons) == len(mesh["final_triangles"])
    assert mesh["parameters"]["band"] == "2"
    assert len(ties["features"]) == len(pair.reference_points)
    lon, lat = ties["features"][0]["geometry"]["coordinates"]
    assert -88 < lon < -87 and 30 < lat < 31  # UTM 16N near 452 km E, 3408 km N


def test_float32_pair_registers_and_a_plain_pair_has_no_geotiff(server: Server,
                                                                  pair: Pair) -> None:
    floats = make_pair(bands=1, dtype=np.float32, shift=(3, 5))
    with server.client() as client:
        job = _finished(client, _post(client, floats.reference_tif, floats.moving_tif))
        mesh = client.get(f"/v1/jobs/{job['id']}/mesh").json()
        plain = _finished(client, client.post("/v1/jobs", files={
            "reference": ("r.png", pair.reference_png), "moving": ("m.png", pair.moving_png),
            "points": ("p.json", pair.points_json)}))
    measured = ~np.array(mesh["extrapolated"])
    shifts = np.subtract(mesh["reference_vertices"], mesh["moving_vertices"])[measured]
    np.testing.assert_allclose(np.median(shifts, axis=0), floats.shift, atol=0.1)
    assert "registered.tif" in _links(job)
    assert "registered.tif" not in _links(plain) and "mesh.geojson" in _links(plain)


def test_qgis_points_and_embedded_gcps_give_the_mesh_of_json_points(server: Server) -> None:
    pair = make_pair(bands=1)
    gcps = [GroundControlPoint(row=y + 0.5, col=x + 0.5, x=mx, y=my) for (x, y), (mx, my) in
            zip(pair.moving_points.tolist(), map_coords(pair.reference_points).tolist(),
                strict=True)]
    moving_with_gcps = geotiff(pair.moving, transform=None, gcps=gcps, gcp_crs=UTM)
    with server.client() as client:
        meshes = []
        for moving, points in ((pair.moving_tif, pair.points_json()),
                               (pair.moving_tif, _qgis_points(pair)),
                               (moving_with_gcps, moving_with_gcps),
                               (moving_with_gcps, b"gcps")):  # the moving image's own GCPs
            job = _finished(client, _post(client, pair.reference_tif, moving, points, NO_FILTER))
            meshes.append(client.get(f"/v1/jobs/{job['id']}/mesh").json())
    for mesh in meshes[1:]:
        assert mesh["final_triangles"] == meshes[0]["final_triangles"]
        assert mesh["moving_vertices"] == meshes[0]["moving_vertices"]
        np.testing.assert_allclose(mesh["reference_vertices"], meshes[0]["reference_vertices"],
                                   atol=1 / 256)


def test_damaged_or_unusable_gis_inputs_are_4xx_naming_the_field(server: Server,
                                                                 pair: Pair) -> None:
    good = make_pair(bands=1)
    truncated = good.moving_tif[: len(good.moving_tif) * 2 // 3]
    complex_tif = geotiff(np.zeros((1, 40, 50), np.complex64))
    with server.client() as client:
        doc = assert_problem(_post(client, good.reference_tif, truncated), 415, field="moving")
        assert "truncated or damaged" in doc["detail"]
        doc = assert_problem(_post(client, good.reference_tif, complex_tif), 422, field="moving")
        assert "complex64" in doc["detail"]
        # A .points file gives map coordinates: a reference without georeferencing cannot
        # place them.
        response = client.post("/v1/jobs", files={
            "reference": ("r.png", pair.reference_png), "moving": ("m.tif", good.moving_tif),
            "points": ("gcp.points", _qgis_points(good))})
        doc = assert_problem(response, 422, field="points")
        assert "not georeferenced" in doc["detail"]
        response = _post(client, good.reference_tif, good.moving_tif, b"", {"band": 0})
        assert_problem(response, 422, field="options.band")


@pytest.mark.parametrize("points", ["gcp.points", "gcps"])
def test_command_line_takes_gis_points(tmp_path: Path, points: str) -> None:
    """``--points`` with a QGIS .points file, or the word gcps: the moving GeoTIFF's own."""
    pair = make_pair(bands=2)
    gcps = [GroundControlPoint(row=y + 0.5, col=x + 0.5, x=mx, y=my) for (x, y), (mx, my) in
            zip(pair.moving_points.tolist(), map_coords(pair.reference_points).tolist(),
                strict=True)]
    paths = {"reference.tif": pair.reference_tif, "gcp.points": _qgis_points(pair),
             "moving.tif": pair.moving_tif if points != "gcps" else geotiff(
                 pair.moving, gcps=gcps, gcp_crs=UTM, transform=None)}
    for name, data in paths.items():
        (tmp_path / name).write_bytes(data)
    out = tmp_path / "out"
    run = pwlreg("register", str(tmp_path / "reference.tif"), str(tmp_path / "moving.tif"),
                 "--points", points if points == "gcps" else str(tmp_path / points),
                 "--no-epipolar-filter", "--band", "luminance", "--out", str(out))
    assert run.returncode == 0, run.stderr
    mesh = json.loads((out / "mesh.json").read_text())
    np.testing.assert_allclose(mesh["matching"]["moving"], pair.moving_points, atol=1e-6)
    with rasterio.open(out / "registered.tif") as ds:
        assert ds.count == 2 and ds.crs == UTM


def test_a_raster_over_the_level_size_is_read_by_windows(start_server, tmp_path) -> None:
    """A 17 MP GeoTIFF pair (over the 16.8 MP level, and 34x the server's max_pixels, which
    only bounds images decoded whole) registers on levels: full-size registered.tif, the
    client's points as vertices."""
    height, width, shift = 3712, 4608, (7, 5)
    rng = np.random.default_rng(4)
    small = rng.random(((height + 64) // 8, (width + 64) // 8)).astype(np.float32)
    full = cv2.resize(small, ((width + 64), (height + 64)), interpolation=cv2.INTER_CUBIC)
    full = np.clip(full * 255, 0, 255).astype(np.uint8)
    reference = full[None, 32:32 + height, 32:32 + width]
    moving = full[None, 32 + shift[1]:32 + shift[1] + height, 32 + shift[0]:32 + shift[0] + width]
    xs, ys = np.meshgrid(np.linspace(40, width - 40, 9), np.linspace(40, height - 40, 7))
    ref_pts = np.stack([xs.ravel(), ys.ravel()], axis=1)
    points = json.dumps({"reference": ref_pts.tolist(),
                         "moving": (ref_pts - np.array(shift)).tolist()}).encode()
    server = start_server(PWLREG_WORKERS="1", PWLREG_MAX_UPLOAD_BYTES=str(64 << 20))
    with server.client() as client:
        job = _finished(client, _post(client, geotiff(reference), geotiff(moving), points,
                                      NO_FILTER))
        links = _links(job)
        tif = client.get(links["registered.tif"][0]).content
        mesh = client.get(f"/v1/jobs/{job['id']}/mesh").json()
        png = client.get(links["registered.png"][0]).content
    assert mesh["image_size"]["reference"] == [width, height]
    measured = ~np.array(mesh["extrapolated"])
    np.testing.assert_allclose(np.sort(np.array(mesh["reference_vertices"])[measured], axis=0),
                               np.sort(ref_pts, axis=0), atol=1 / 256)
    with rasterio.open(io.BytesIO(tif)) as ds:
        assert (ds.width, ds.height, ds.count, ds.transform) == (width, height, 1, TRANSFORM)
        out = ds.read(1)
    inside = out != 0
    assert inside.mean() > 0.9
    np.testing.assert_array_equal(out[inside], reference[0][inside])
    decoded = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)
    assert decoded.shape[:2] == (height, width)
