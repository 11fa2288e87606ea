"""Speed report: ``python -m bench.speed [--quick] [--out DIR]``.

Prints, side by side in one process:

1. On a 1024x768 pair with 500 points: the whole optimizing stage (scoring images prepared,
   default optimizer run on a ready initial mesh); a floor of 4 full-image
   passes of one remap plus one joint histogram; the same greedy search computed naively
   (every gain from fresh warps of its quad, no reuse); the registered-image warp against
   scikit-image's ``PiecewiseAffineTransform`` + ``warp``; writing the registered image as PNG
   with ``core.io.encode_png`` against OpenCV's and Pillow's PNG writers (time and size).
2. A scaling table over image size (0.5, 2, 8, 32 megapixels at 1000 points) and point count
   (100 to 5000 points at 2 megapixels), with a log-log plot.
3. Peak memory (max RSS of a fresh process) of a whole registration of a 32-megapixel pair with
   3000 points.

The pairs are "folded" textures: the reference image is the moving texture seen through a
piecewise-affine map with several creases, so the search has real swaps to make.
"""

from __future__ import annotations

import argparse
import io
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
from PIL import Image

from pwlreg.core import kernels
from pwlreg.core.io import encode_png
from pwlreg.core.mesh import Mesh
from pwlreg.core.optimize import quad_triples
from pwlreg.core.optimizers import OPTIMIZERS
from pwlreg.core.options import RegistrationOptions
from pwlreg.core.pipeline import register
from pwlreg.core.similarity import mutual_information, prepare_images, triangle_statistics
from pwlreg.core.triangulation import initial_mesh
from pwlreg.core.warp import warp_image


def folded_pair(
    width: int, height: int, n_points: int, seed: int = 0
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Reference, moving (uint8 grey) and ``n_points`` exact conjugate points.

    The truth is continuous and piecewise affine in x: five vertical creases, each strip with
    its own horizontal compression and vertical shear, like a folded screen.
    """
    rng = np.random.default_rng(seed)
    small = rng.random((max(height // 4, 8), max(width // 4, 8))).astype(np.float32)
    tex = cv2.resize(small, (width, height), interpolation=cv2.INTER_CUBIC)
    tex = cv2.GaussianBlur(tex, (0, 0), 1.0)
    tex = (tex - tex.min()) / (tex.max() - tex.min())
    moving = np.round(tex * 255).astype(np.uint8)
    creases = np.linspace(0, width - 1, 7)[1:-1]
    slopes_x = rng.uniform(0.75, 1.0, len(creases) + 1)
    slopes_y = rng.uniform(-0.12, 0.12, len(creases) + 1)

    def truth(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        mx = np.zeros_like(x, dtype=np.float64)
        my = np.array(y, dtype=np.float64)
        knots = np.concatenate([[0.0], creases, [np.inf]])
        for s in range(len(knots) - 1):
            seg = np.clip(x - knots[s], 0, (knots[s + 1] - knots[s]))
            mx += slopes_x[s] * seg
            my += slopes_y[s] * seg
        return mx, my

    ys, xs = np.mgrid[0:height, 0:width].astype(np.float32)
    mx, my = truth(xs, ys)
    reference = cv2.remap(
        moving,
        mx.astype(np.float32),
        my.astype(np.float32),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REFLECT,
    )
    pts = rng.uniform([0, 0], [width - 1, height - 1], size=(n_points - 4, 2))
    pts = np.vstack([pts, [[0, 0], [width - 1, 0], [0, height - 1], [width - 1, height - 1]]])
    tx, ty = truth(pts[:, 0], pts[:, 1])
    return reference, moving, pts, np.stack([tx, ty], axis=1)


def _best_of(fn, repeat: int) -> float:  # type: ignore[no-untyped-def]
    best = np.inf
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best


def floor_passes(
    reference: np.ndarray, moving: np.ndarray, passes: int = 4, bins: int = 16
) -> None:
    """``passes`` full-image passes of one bilinear remap plus one joint histogram."""
    h, w = reference.shape[:2]
    mx, my = np.meshgrid(
        np.arange(w, dtype=np.float32) * 0.98 + 1.0, np.arange(h, dtype=np.float32) * 0.98 + 1.0
    )
    movf = moving.astype(np.float32) / 255.0
    ref_bins = (reference.astype(np.intp) * bins) >> 8
    for _ in range(passes):
        v = cv2.remap(movf, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        key = ref_bins * bins + (v * (bins * 255 / 256)).astype(np.intp)
        np.bincount(key.ravel(), minlength=bins * bins)


def naive_greedy(
    mesh: Mesh,
    images,
    epsilon: float = 0.01,
    max_passes: int | None = None,  # type: ignore[no-untyped-def]
) -> tuple[int, int, float]:
    """The same greedy search without reuse: each pass warps every candidate quad afresh
    (both diagonals), then swaps the best edge. Returns (swaps, passes run, seconds/pass)."""
    swaps = passes = 0
    t0 = time.perf_counter()
    while max_passes is None or passes < max_passes:
        passes += 1
        best, best_edge = epsilon, None
        for e in mesh.internal_edges():
            if not mesh.can_swap(e):
                continue
            old0, old1, new0, new1 = quad_triples(mesh.quad(e), mesh)
            idx = np.array([old0, old1, new0, new1])
            h, _ = triangle_statistics(images, mesh.reference[idx], mesh.moving[idx])
            before = mutual_information(h[0] + h[1], images.bins)[1]
            after = mutual_information(h[2] + h[3], images.bins)[1]
            if after - before > best:
                best, best_edge = after - before, e
        if best_edge is None:
            break
        mesh.swap(best_edge)
        swaps += 1
    return swaps, passes, (time.perf_counter() - t0) / passes


def side_by_side(repeat: int, naive_passes: int) -> dict:
    """Section 1: the 1024x768 / 500-point figures."""
    ref, mov, rp, mp = folded_pair(1024, 768, 500)
    out: dict = {"pair": "1024x768 folded texture, 500 points"}

    # The optimizing stage of register(): preparing the scoring images and the search. The
    # initial mesh (built the same way each time, the search changes it) is made untimed.
    meshes = [initial_mesh(rp, mp, 25.0)[0] for _ in range(repeat)]

    options = RegistrationOptions()  # the default optimizer and its settings

    def optimize() -> None:
        out["search"] = OPTIMIZERS[options.optimizer](
            meshes.pop(), prepare_images(ref, mov, options.bins), options, None)

    t_opt = _best_of(optimize, repeat)
    t_floor = _best_of(lambda: floor_passes(ref, mov), repeat)
    search = out.pop("search")
    out.update(
        optimization_s=t_opt,
        swaps=len(search.steps),
        evaluations=search.evaluations,
        floor_4_passes_s=t_floor,
        optimization_over_floor=t_opt / t_floor,
    )
    mesh, _ = initial_mesh(rp, mp, 25.0)
    _, passes, per_pass = naive_greedy(mesh, prepare_images(ref, mov, 16), max_passes=naive_passes)
    naive_total = per_pass * (len(search.steps) + 1)
    out.update(
        naive_seconds_per_pass=per_pass,
        naive_passes_measured=passes,
        naive_total_s_extrapolated=naive_total,
        naive_over_optimization=naive_total / t_opt,
    )
    mesh, _ = initial_mesh(rp, mp, 25.0)
    tris = mesh.triangles
    t_warp = _best_of(lambda: warp_image(mov, mesh.reference, mesh.moving, tris, ref.shape), repeat)
    try:
        from skimage.transform import PiecewiseAffineTransform, warp

        def sk() -> None:
            tform = PiecewiseAffineTransform.from_estimate(mesh.reference, mesh.moving)
            warp(mov, tform, output_shape=ref.shape, order=1, preserve_range=True)

        t_sk = _best_of(sk, 1)
        out.update(warp_s=t_warp, skimage_warp_s=t_sk, warp_speedup=t_sk / t_warp)
    except ImportError:
        out.update(warp_s=t_warp, skimage_warp_s=None, warp_speedup=None)

    # Writing registered.png: core.io.encode_png against the libraries' PNG writers (OpenCV
    # writes no grey+alpha, so it gets the BGRA expansion encode_png used to make).
    registered = warp_image(mov, mesh.reference, mesh.moving, tris, ref.shape)
    bgra = np.dstack([registered[:, :, 0]] * 3 + [registered[:, :, 1]])

    def pillow() -> bytes:
        buffer = io.BytesIO()
        Image.fromarray(registered, "LA").save(buffer, "PNG", compress_level=1)
        return buffer.getvalue()

    writers = {
        "encode_png": lambda: encode_png(registered),
        "encode_png_2_threads": lambda: encode_png(registered, threads=2),
        "opencv_bgra": lambda: cv2.imencode(".png", bgra)[1].tobytes(),
        "pillow_la_level_1": pillow,
    }
    out["png"] = {
        name: {"s": _best_of(write, repeat), "bytes": len(write())}
        for name, write in writers.items()
    }
    return out


def _run_once(megapixels: float, n_points: int) -> dict:
    width = int(round(np.sqrt(megapixels * 1e6 * 4 / 3)))
    height = int(round(width * 3 / 4))
    ref, mov, rp, mp = folded_pair(width, height, n_points, seed=1)
    t = time.perf_counter()
    result = register(ref, mov, (rp, mp), {"epipolar_filter": False})
    total = time.perf_counter() - t
    return {
        "megapixels": width * height / 1e6,
        "size": f"{width}x{height}",
        "points": n_points,
        "triangles": len(result.final_triangles),
        "swaps": len(result.search.steps),
        "optimization_s": result.timings["optimization_s"],
        "rendering_s": result.timings["rendering_s"],
        "total_s": total,
    }


def scaling(sizes: list[float], points: list[int], base_mp: float, base_points: int) -> list[dict]:
    """Section 2: optimization time over image size and point count."""
    rows = [_run_once(mp, base_points) | {"sweep": "size"} for mp in sizes]
    rows += [_run_once(base_mp, n) | {"sweep": "points"} for n in points]
    return rows


def peak_memory(megapixels: float, n_points: int) -> dict:
    """Section 3: peak resident memory (``VmHWM``, Linux) of a fresh process that reads the pair
    from PNG files, registers it and writes the three results (what ``pwlreg register`` does).

    ``ru_maxrss`` would not do: Linux carries it across ``exec`` from the forking parent."""
    width = int(round(np.sqrt(megapixels * 1e6 * 4 / 3)))
    height = int(round(width * 3 / 4))
    ref, mov, rp, mp = folded_pair(width, height, n_points, seed=2)
    with tempfile.TemporaryDirectory() as tmp:
        cv2.imwrite(f"{tmp}/ref.png", ref)
        cv2.imwrite(f"{tmp}/mov.png", mov)
        Path(f"{tmp}/points.json").write_text(
            json.dumps({"reference": rp.tolist(), "moving": mp.tolist()})
        )
        del ref, mov
        code = (
            "import json, time\n"
            "from pwlreg.core.io import load_points, read_image\n"
            "from pwlreg.core.results import write_outputs\n"
            "from pwlreg.core.pipeline import register\n"
            "t = time.perf_counter()\n"
            f"ref = read_image('{tmp}/ref.png'); mov = read_image('{tmp}/mov.png')\n"
            f"pts = load_points(open('{tmp}/points.json', 'rb').read())\n"
            "r = register(ref, mov, pts, {'epipolar_filter': False})\n"
            f"write_outputs(r, '{tmp}/out')\n"
            "print(json.dumps({'total_s': time.perf_counter() - t, "
            "'optimization_s': r.timings['optimization_s'], 'swaps': len(r.search.steps), "
            "'max_rss_mb': int(next(l.split()[1] for l in open('/proc/self/status') "
            "if l.startswith('VmHWM'))) / 1024}))\n"
        )
        done = subprocess.run(
            [sys.executable, "-c", code],
            capture_output=True,
            text=True,
            check=True,
            cwd=Path(__file__).resolve().parents[1],
        )
    return json.loads(done.stdout.strip().splitlines()[-1]) | {"size": f"{width}x{height}"}


def _plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, sweep, key, label in (
        (axes[0], "size", "megapixels", "image size (megapixels)"),
        (axes[1], "points", "points", "points"),
    ):
        sel = [r for r in rows if r["sweep"] == sweep]
        x = np.array([r[key] for r in sel], float)
        for col in ("optimization_s", "total_s"):
            ax.loglog(x, [r[col] for r in sel], "o-", label=col)
        ref_line = np.array([sel[0]["optimization_s"] * xi / x[0] for xi in x])
        ax.loglog(x, ref_line, "k--", lw=0.8, label="linear")
        ax.set_xlabel(label)
        ax.set_ylabel("seconds")
        ax.legend()
        ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small sizes, a minute or so")
    parser.add_argument("--out", default="bench/results/speed", help="output folder")
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    # One thread for OpenCV (the floor's remap) and for the threaded kernels alike: the ratio
    # compares work, not how many cores each side takes.
    cv2.setNumThreads(1)
    kernels.set_threads(1)

    report: dict = {}
    s = side_by_side(repeat=3, naive_passes=1 if args.quick else 2)
    report["side_by_side"] = s
    print(f"== {s['pair']}")
    print(
        f"optimization (prepare + greedy search):{s['optimization_s'] * 1e3:8.1f} ms "
        f"({s['swaps']} swaps, {s['evaluations']} gains scored)"
    )
    print(
        f"floor (4 x remap + joint histogram): {s['floor_4_passes_s'] * 1e3:8.1f} ms  "
        f"-> optimization = {s['optimization_over_floor']:.2f} x floor (target <= 5)"
    )
    print(
        f"naive search: {s['naive_seconds_per_pass']:.2f} s per pass x {s['swaps'] + 1} passes "
        f"= {s['naive_total_s_extrapolated']:.1f} s (measured {s['naive_passes_measured']} "
        f"pass(es), extrapolated) -> {s['naive_over_optimization']:.0f} x slower"
    )
    if s["skimage_warp_s"] is not None:
        print(
            f"warp: {s['warp_s'] * 1e3:.1f} ms vs scikit-image {s['skimage_warp_s'] * 1e3:.0f} ms"
            f" -> {s['warp_speedup']:.0f} x faster (target >= 100)"
        )

    png = s["png"]
    base = png["opencv_bgra"]
    for name, r in png.items():
        print(
            f"registered.png {name:<21s} {r['s'] * 1e3:6.1f} ms {r['bytes'] / 1024:7.0f} KiB"
            f"  ({base['s'] / r['s']:.1f} x faster, {base['bytes'] / r['bytes']:.1f} x smaller "
            "than OpenCV)"
        )

    if args.quick:
        sizes, points, base_mp, base_pts = [0.5, 2.0], [100, 500, 1000], 0.5, 500
    else:
        sizes, points = [0.5, 2.0, 8.0, 32.0], [100, 300, 1000, 3000, 5000]
        base_mp, base_pts = 2.0, 1000
    rows = scaling(sizes, points, base_mp, base_pts)
    report["scaling"] = rows
    print("\n== scaling (register() with points given, epipolar filter off)")
    print(
        f"{'sweep':7s} {'size':>11s} {'MP':>6s} {'points':>6s} {'tris':>6s} {'swaps':>5s} "
        f"{'optim s':>8s} {'render s':>8s} {'total s':>8s}"
    )
    for r in rows:
        print(
            f"{r['sweep']:7s} {r['size']:>11s} {r['megapixels']:6.2f} {r['points']:6d} "
            f"{r['triangles']:6d} {r['swaps']:5d} {r['optimization_s']:8.3f} "
            f"{r['rendering_s']:8.3f} {r['total_s']:8.3f}"
        )
    _plot(rows, out / "scaling.png")

    mem_mp, mem_pts = (2.0, 1000) if args.quick else (32.0, 3000)
    mem = peak_memory(mem_mp, mem_pts)
    report["peak_memory"] = mem
    print(
        f"\n== peak memory: {mem['size']} pair, {mem_pts} points: max RSS "
        f"{mem['max_rss_mb']:.0f} MB (target < 2048 MB), total {mem['total_s']:.1f} s"
    )
    (out / "speed.json").write_text(json.dumps(report, indent=1))
    print(f"\nwrote {out / 'speed.json'} and {out / 'scaling.png'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
