"""Benchmark of automatic conjugate points on the real pairs.

Run ``python -m bench.matching`` (options: ``--help``). For every real pair it prints the matcher
used, the pairs kept, the median and 90th-percentile error of the kept pairs against the ground
truth and the time of :func:`core.matching.find_conjugate_points` (images already decoded).

Errors (pixels): Sampson distance to the true fundamental matrix (Strecha), transfer error
through the true homography (Oxford), distance to the true disparity match (Middlebury, pairs
with unknown disparity ignored); ``-`` when the pair has no ground truth. OpenCV runs on one
thread (``cv2.setNumThreads(1)``) unless ``--threads`` says otherwise.
"""

from __future__ import annotations

import argparse
import sys
import time

import cv2
import numpy as np

from bench import realdata
from pwlreg.core.errors import NotEnoughPointsError
from pwlreg.core.matching import find_conjugate_points
from pwlreg.core.options import RegistrationOptions


def run_pair(pair: realdata.RealPair, options: RegistrationOptions, repeat: int = 1) -> dict:
    """Match one pair; returns a row of the table (counts, errors in pixels, best time in s)."""
    best = float("inf")
    result = None
    error: str | None = None
    for _ in range(repeat):
        t0 = time.perf_counter()
        try:
            result = find_conjugate_points(pair.reference, pair.moving, options)
        except NotEnoughPointsError as exc:
            error = str(exc)
        best = min(best, time.perf_counter() - t0)
    row: dict = {"pair": pair.name, "time_s": best, "size": pair.reference.shape[1::-1]}
    if result is None:
        row.update(source="-", kept=0, measure="-", median=np.nan, p90=np.nan, error=error)
        return row
    row.update(source=result.source, kept=len(result), counts=result.counts)
    truth = realdata.truth_error(pair, result.reference, result.moving)
    if truth is None:
        row.update(measure="-", median=np.nan, p90=np.nan)
    else:
        err, measure = truth
        err = err[np.isfinite(err)]
        row.update(
            measure=measure,
            median=float(np.median(err)) if len(err) else np.nan,
            p90=float(np.percentile(err, 90)) if len(err) else np.nan,
            over3=float(np.mean(err > 3.0)) if len(err) else np.nan,
        )
    return row


def _fmt(v: float) -> str:
    return "-" if not np.isfinite(v) else f"{v:.3f}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m bench.matching", description=__doc__.split("\n")[0]
    )
    parser.add_argument("--pairs", nargs="*", help="pair folder names (default: all present)")
    parser.add_argument("--matcher", choices=["lk", "sift", "auto"], default=None)
    parser.add_argument("--model", choices=["affine", "projective"], default=None)
    parser.add_argument("--threshold", type=float, default=None, help="epipolar threshold, px")
    parser.add_argument("--max-points", type=int, default=None)
    parser.add_argument("--no-filter", action="store_true", help="switch the epipolar filter off")
    parser.add_argument("--repeat", type=int, default=1, help="runs per pair; best time kept")
    parser.add_argument("--threads", type=int, default=1, help="OpenCV threads (default 1)")
    parser.add_argument("--root", default=None, help="real-data folder (default: see realdata)")
    args = parser.parse_args(argv)

    cv2.setNumThreads(args.threads)
    root = realdata.default_root() if args.root is None else args.root
    names = args.pairs or realdata.available_pairs(root)
    if not names:
        print(f"no real pairs found under {root} (set {realdata.ENV_VAR})", file=sys.stderr)
        return 1
    overrides: dict = {}
    if args.matcher:
        overrides["matcher"] = args.matcher
    if args.model:
        overrides["epipolar_model"] = args.model
    if args.threshold:
        overrides["epipolar_threshold"] = args.threshold
    if args.max_points:
        overrides["max_points"] = args.max_points
    if args.no_filter:
        overrides["epipolar_filter"] = False
    options = RegistrationOptions(**overrides)
    print(
        f"options: matcher={options.matcher} epipolar_model={options.epipolar_model} "
        f"filter={options.epipolar_filter} threshold={options.epipolar_threshold} px "
        f"max_points={options.max_points} min_distance={options.min_distance} px "
        f"threads={args.threads}"
    )
    header = (
        f"{'pair':32s} {'size':>10s} {'matcher':>7s} {'kept':>5s} {'measure':>9s} "
        f"{'median':>7s} {'p90':>7s} {'>3px':>6s} {'time_s':>7s}"
    )
    print(header)
    print("-" * len(header))
    for name in names:
        pair = realdata.load_pair(name, root)
        row = run_pair(pair, options, args.repeat)
        size = f"{row['size'][0]}x{row['size'][1]}"
        over3 = row.get("over3", np.nan)
        print(
            f"{name:32s} {size:>10s} {row['source']:>7s} {row['kept']:5d} {row['measure']:>9s} "
            f"{_fmt(row['median']):>7s} {_fmt(row['p90']):>7s} "
            f"{'-' if not np.isfinite(over3) else f'{100 * over3:.1f}%':>6s} "
            f"{row['time_s']:7.2f}"
        )
        if "error" in row and row["error"]:
            print(f"    {row['error']}")
        elif "counts" in row:
            print("    counts: " + ", ".join(f"{k}={v}" for k, v in row["counts"].items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
