"""Large rasters: time and peak memory of a whole registration (the ``pwlreg register`` CLI in
a child process) on synthetic GeoTIFF pairs of 25, 100 and 400 megapixels, 8-bit grey and
4-band 16-bit, with 3000 given points; and the tiled warp beside one ``cv2.remap`` pass.

The pairs are written block by block (they never exist whole in memory): the reference is a
multi-octave value noise (edges, texture at 4 to 256 px), georeferenced in UTM; the moving
image is the same texture seen through a known smooth map (a similarity with a mild
perspective term), so every given point is exact and the registered image's error is known.

Run ``python -m bench.large`` (all sizes, about 15 min on 2 cores) or ``--sizes 25 --kinds
grey`` for one row; ``--warp`` times only the warp against ``cv2.remap``. Files go to
``--work`` (default: a temporary folder, removed afterwards; 400 MP takes about 1.5 GB of
disk per pair).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
import warnings
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import rasterio
from rasterio.errors import NotGeoreferencedWarning
from rasterio.transform import from_origin
from rasterio.windows import Window

BLOCK = 1024
POINTS = 3000
OCTAVES = (4, 16, 64, 256)
"""Cell sizes (pixels) of the noise octaves."""


class Texture:
    """A deterministic value noise that can be sampled anywhere (one grid per octave)."""

    def __init__(self, width: int, height: int, seed: int = 7) -> None:
        rng = np.random.default_rng(seed)
        self.grids = [
            (cell, rng.random((height // cell + 3, width // cell + 3), dtype=np.float32))
            for cell in OCTAVES
        ]

    def sample(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Values in [0, 1] at float32 positions ``x``, ``y`` (any shape)."""
        out = np.zeros(x.shape, np.float32)
        total = 0.0
        for i, (cell, grid) in enumerate(self.grids):
            weight = 0.6 ** (len(self.grids) - 1 - i)  # coarse octaves dominate
            gx = (x / cell + 1.0).astype(np.float32)
            gy = (y / cell + 1.0).astype(np.float32)
            out += weight * cv2.remap(grid, gx, gy, cv2.INTER_CUBIC,
                                      borderMode=cv2.BORDER_REFLECT)
            total += weight
        return np.clip(out / total, 0.0, 1.0)


class Motion:
    """The true map from reference to moving pixels: a similarity (0.8 degree, 2 % scale) with
    a weak perspective term, and its inverse by fixed-point iteration."""

    def __init__(self, width: int, height: int) -> None:
        a, s = np.deg2rad(0.8), 1.02
        self.m = np.array([[s * np.cos(a), -s * np.sin(a), 0.011 * width],
                           [s * np.sin(a), s * np.cos(a), -0.007 * height]])
        self.p = np.array([2e-2 / width, -1.5e-2 / height])
        self.centre = np.array([width / 2, height / 2])

    def forward(self, xy: np.ndarray) -> np.ndarray:
        q = xy - self.centre
        w = 1.0 + q @ self.p
        return (q @ self.m[:, :2].T) / w[:, None] + self.centre + self.m[:, 2]

    def inverse(self, xy: np.ndarray) -> np.ndarray:
        guess = xy.copy()
        for _ in range(8):
            guess = guess - (self.forward(guess) - xy)
        return guess


def write_pair(folder: Path, megapixels: int, kind: str) -> tuple[Path, Path, Path, Motion]:
    """Write reference.tif, moving.tif and points.json; ``kind`` is ``grey`` (uint8, 1 band)
    or ``multi`` (uint16, 4 bands: the texture under four different radiometric curves).
    Files a previous run left in ``folder`` are used again (the pair is deterministic)."""
    side = int(round(np.sqrt(megapixels * 1e6 / 1.25)))
    width, height = int(side * 1.25) // 16 * 16, side // 16 * 16
    motion = Motion(width, height)
    paths = folder / "reference.tif", folder / "moving.tif"
    if all(p.exists() for p in (*paths, folder / "points.json")):
        return paths[0], paths[1], folder / "points.json", motion
    warnings.simplefilter("ignore", NotGeoreferencedWarning)  # the moving file has no grid
    texture = Texture(width, height)
    count, dtype = (1, "uint8") if kind == "grey" else (4, "uint16")
    profile = {"driver": "GTiff", "width": width, "height": height, "count": count,
               "dtype": dtype, "tiled": True, "blockxsize": 512, "blockysize": 512,
               "compress": "deflate", "zlevel": 1, "predictor": 2, "bigtiff": "yes"}
    for path, moving in zip(paths, (False, True), strict=True):
        extra = {"crs": "EPSG:32633", "transform": from_origin(500000, 5200000, 0.5, 0.5)}
        with rasterio.open(path, "w", **profile, **({} if moving else extra)) as dst:
            for y0 in range(0, height, BLOCK):
                for x0 in range(0, width, BLOCK):
                    w, h = min(BLOCK, width - x0), min(BLOCK, height - y0)
                    gx, gy = np.meshgrid(np.arange(x0, x0 + w, dtype=np.float64),
                                         np.arange(y0, y0 + h, dtype=np.float64))
                    xy = np.stack([gx.ravel(), gy.ravel()], axis=1)
                    if moving:
                        xy = motion.inverse(xy)
                    v = texture.sample(xy[:, 0].reshape(h, w).astype(np.float32),
                                       xy[:, 1].reshape(h, w).astype(np.float32))
                    dst.write(_bands(v, kind, moving), window=Window(x0, y0, w, h))
    rng = np.random.default_rng(11)
    ref = rng.uniform([0, 0], [width - 1, height - 1], size=(POINTS, 2))
    mov = motion.forward(ref)
    keep = (mov >= 0).all(axis=1) & (mov[:, 0] <= width - 1) & (mov[:, 1] <= height - 1)
    points = folder / "points.json"
    points.write_text(json.dumps({"reference": ref[keep].tolist(),
                                  "moving": mov[keep].tolist()}))
    return paths[0], paths[1], points, motion


def _bands(v: np.ndarray, kind: str, moving: bool) -> np.ndarray:
    if kind == "grey":
        return np.round(v * 255)[None].astype(np.uint8)
    gain = 0.9 if moving else 1.0  # a different exposure on the moving image
    curves = (v, v ** 0.7, 1.0 - v, np.sqrt(v))
    return np.stack([np.round(c * gain * 60000) for c in curves]).astype(np.uint16)


def run_cli(reference: Path, moving: Path, points: Path | None, out: Path
            ) -> tuple[float, float, str]:
    """Seconds and peak resident memory (MB) of ``pwlreg register`` in a child process (the
    child's own peak, from ``wait4``)."""
    out.mkdir(parents=True, exist_ok=True)
    with (out / "stdout.txt").open("w+") as stdout, (out / "stderr.txt").open("w+") as stderr:
        start = time.perf_counter()
        child = subprocess.Popen(
            [sys.executable, "-m", "pwlreg.service.cli", "register", str(reference),
             str(moving), *(["--points", str(points)] if points else []), "--out", str(out),
             "--quiet"],
            stdout=stdout, stderr=stderr,
        )
        _, status, usage = os.wait4(child.pid, 0)
        child.returncode = os.waitstatus_to_exitcode(status)
        seconds = time.perf_counter() - start
        stdout.seek(0)
        stderr.seek(0)
        if child.returncode:
            raise RuntimeError(f"pwlreg register failed: {stderr.read().strip()[-2000:]}")
        return seconds, usage.ru_maxrss / 1024, stdout.read().strip().splitlines()[-1]


def mesh_error(out: Path, motion: Motion) -> tuple[float, float]:
    """Median and largest distance (px) between the result's moving vertices and the true map
    of their reference vertices, over the measured vertices."""
    doc = json.loads((out / "mesh.json").read_text())
    ref = np.asarray(doc["reference_vertices"], np.float64)
    mov = np.asarray(doc["moving_vertices"], np.float64)
    measured = ~np.asarray(doc.get("extrapolated", [False] * len(ref)), bool)
    error = np.linalg.norm(mov[measured] - motion.forward(ref[measured]), axis=1)
    return float(np.median(error)), float(error.max())


def time_warp(reference: Path, moving: Path, points: Path, repeats: int = 7) -> None:
    """The tiled warp of a whole registered raster, read by windows from the file and from the
    image in memory, against one ``cv2.remap`` of the same output with a precomputed map (the
    moving image and the map in memory)."""
    from scipy.spatial import Delaunay

    from pwlreg.core.formats.geotiff import RasterFile
    from pwlreg.core.tiled import ArrayBands, warp_tiles
    from pwlreg.core.warp import piecewise_map

    doc = json.loads(points.read_text())
    ref, mov = np.asarray(doc["reference"]), np.asarray(doc["moving"])
    tris = Delaunay(ref).simplices
    threads = os.cpu_count() or 1  # as many as OpenCV's remap uses
    with RasterFile(moving, threads=threads) as source:
        image, _ = source.read(0, 0, source.width, source.height)
        shape = (source.height, source.width)
        map_x, map_y, _ = piecewise_map(ref, mov, tris, shape)
        map_x = np.nan_to_num(map_x, nan=-1.0).astype(np.float32)
        map_y = np.nan_to_num(map_y, nan=-1.0).astype(np.float32)
        runs = {
            "tiled, file": lambda: all(True for _ in warp_tiles(
                source, ref, mov, tris, shape, threads=threads)),
            "tiled, memory": lambda: all(True for _ in warp_tiles(
                ArrayBands(image), ref, mov, tris, shape, threads=threads)),
            "one cv2.remap": lambda: cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR),
        }
        best = {name: min(_timed(f) for _ in range(repeats)) for name, f in runs.items()}
    floor = best["one cv2.remap"]
    print(f"  warp {shape[1]}x{shape[0]}x{image.shape[2]} {image.dtype}: " + ", ".join(
        f"{name} {t:.2f} s ({t / floor:.2f}x)" for name, t in best.items()) + " (target <= 2x)")


def _timed(f: Callable[[], object]) -> float:
    start = time.perf_counter()
    f()
    return time.perf_counter() - start


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[25, 100, 400],
                        help="megapixels")
    parser.add_argument("--kinds", nargs="+", default=["grey", "multi"],
                        choices=["grey", "multi"])
    parser.add_argument("--work", type=Path, help="keep the files here")
    parser.add_argument("--warp", action="store_true", help="only time the warp")
    parser.add_argument("--automatic", action="store_true",
                        help="register without the points (automatic matching)")
    args = parser.parse_args(argv)
    print(f"load average {os.getloadavg()[0]:.2f}, {os.cpu_count()} cores")
    with tempfile.TemporaryDirectory() as tmp:
        work = args.work or Path(tmp)
        for kind in args.kinds:
            for size in args.sizes:
                folder = work / f"{kind}-{size}"
                folder.mkdir(parents=True, exist_ok=True)
                start = time.perf_counter()
                reference, moving, points, motion = write_pair(folder, size, kind)
                made = time.perf_counter() - start
                if args.warp:
                    time_warp(reference, moving, points)
                    continue
                seconds, peak, summary = run_cli(reference, moving,
                                                 None if args.automatic else points,
                                                 folder / "out")
                median, largest = mesh_error(folder / "out", motion)
                print(f"{kind:5} {size:4d} MP: {seconds:6.1f} s, peak {peak:6.0f} MB, vertex "
                      f"error median {median:.3f} / max {largest:.3f} px (pair written in "
                      f"{made:.0f} s)")
                print(f"  {summary}")
                if not args.work:
                    for f in folder.rglob("*"):
                        if f.is_file():
                            f.unlink()


if __name__ == "__main__":
    main()
