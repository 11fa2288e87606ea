"""Georeferenced test pairs, written as real GeoTIFFs with rasterio."""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import rasterio
from rasterio.control import GroundControlPoint
from rasterio.crs import CRS
from rasterio.errors import NotGeoreferencedWarning
from rasterio.io import MemoryFile
from rasterio.transform import Affine

UTM = CRS.from_epsg(32616)
TRANSFORM = Affine(30.0, 0.0, 452475.0, 0.0, -30.0, 3408645.0)
"""A Landsat-like grid: UTM 16N, 30 m pixels."""
LANDSAT = Path(__file__).resolve().parents[3] / "shared" / "data" / "real" / "landsat8_multiband"


def scene(height: int, width: int, bands: int, dtype: type, seed: int = 3) -> np.ndarray:
    """``(bands, height, width)`` textures with different, non-monotone radiometry per band,
    12-bit-like values for 16/32-bit integers, reflectance-like values for floats."""
    rng = np.random.default_rng(seed)
    base = sum(cv2.GaussianBlur(rng.random((height, width)).astype(np.float32), (0, 0), s)
               * (s ** 0.5) for s in (1.5, 4.0, 12.0))
    base = (base - base.min()) / (base.max() - base.min())
    out = []
    for b in range(bands):
        v = base if b % 2 == 0 else 1.0 - base
        v = v ** (1.0 + 0.3 * b)
        if np.dtype(dtype).kind == "f":
            out.append((0.02 + 0.5 * v).astype(dtype))
        elif np.dtype(dtype).itemsize == 1:
            out.append((20 + 220 * v).astype(dtype))
        else:
            out.append((300 + 3500 * v + 40 * b).astype(dtype))
    return np.stack(out)


def geotiff(data: np.ndarray, *, transform: Affine | None = TRANSFORM, crs: CRS | None = UTM,
            nodata: float | None = None, gcps: list[GroundControlPoint] | None = None,
            gcp_crs: CRS | None = None, photometric: str | None = None) -> bytes:
    """A DEFLATE-compressed (Geo)TIFF of ``(bands, height, width)`` data."""
    count, height, width = data.shape
    profile = {"driver": "GTiff", "width": width, "height": height, "count": count,
               "dtype": data.dtype.name, "compress": "deflate", "tiled": True,
               "blockxsize": 64, "blockysize": 64}
    if transform is not None:
        profile.update(transform=transform, crs=crs)
    if nodata is not None:
        profile["nodata"] = nodata
    if photometric:
        profile["photometric"] = photometric
    with MemoryFile() as memory, warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)  # plain TIFFs are meant
        with memory.open(**profile) as dst:
            dst.write(data)
            if gcps:
                dst.gcps = (gcps, gcp_crs)
        return memory.read()


@dataclass(frozen=True)
class Pair:
    """A reference and a moving raster of one scene, the moving one shifted by ``shift`` pixels
    (a reference pixel ``p`` shows what moving pixel ``p - shift`` shows), both GeoTIFFs with
    the same geotransform (so the moving one is misregistered by ``shift``); grid points."""

    reference: np.ndarray  # (bands, H, W)
    moving: np.ndarray
    reference_tif: bytes
    moving_tif: bytes
    shift: tuple[int, int]
    reference_points: np.ndarray
    moving_points: np.ndarray

    def points_json(self) -> bytes:
        import json

        return json.dumps({"reference": self.reference_points.tolist(),
                           "moving": self.moving_points.tolist()}).encode()


def make_pair(height: int = 180, width: int = 240, bands: int = 4, dtype: type = np.uint16,
              shift: tuple[int, int] = (6, 4), nodata: float | None = None,
              hole: tuple[slice, slice] | None = None, seed: int = 3) -> Pair:
    """A shifted pair; ``hole`` (rows, cols of the moving image) is set to ``nodata``."""
    dx, dy = shift
    margin = 16
    full = scene(height + 2 * margin, width + 2 * margin, bands, dtype, seed)
    reference = full[:, margin:margin + height, margin:margin + width].copy()
    moving = full[:, margin + dy:margin + dy + height, margin + dx:margin + dx + width].copy()
    if hole is not None:
        moving[:, hole[0], hole[1]] = nodata
    xs, ys = np.meshgrid(np.linspace(20, width - 20, 6), np.linspace(20, height - 20, 5))
    ref_pts = np.stack([xs.ravel(), ys.ravel()], axis=1)
    return Pair(reference, moving, geotiff(reference), geotiff(moving, nodata=nodata),
                shift, ref_pts, ref_pts - np.array(shift, float))


def map_coords(pixels: np.ndarray, transform: Affine = TRANSFORM) -> np.ndarray:
    """Map coordinates of pixel positions (centre convention) with rasterio's own helper."""
    xs, ys = rasterio.transform.xy(transform, pixels[:, 1], pixels[:, 0], offset="center")
    return np.stack([np.asarray(xs, float), np.asarray(ys, float)], axis=1)
