"""The sharpening's fit against OpenCV's: ``python -m bench.sharpen [--seeds 6] [--repeat 3]``.

Registers the trust suite's scenes of ``--seeds`` (without points, default options) and records
every call of :func:`core.refine.sharpened` (the pairs, their local maps, the grey levels).
Then, per method, moves the recorded pairs by :func:`core.refine.sharpened` with the method's
fits in place of :func:`core.kernels.window_fits` (so the same bounds: at most
:data:`core.refine.SHARP_MOVE`, correlation :data:`core.refine.SHARP_CORRELATION`, the
epipolar threshold) and reports the error of the right pairs (within 3 px of their truth) as
matched and as moved, and the time of all the calls (best of ``--repeat``), with its ratio to
the compiled fit:

* ``compiled``: :func:`core.kernels.window_fits`, the product's;
* ``opencv 10`` and ``opencv 50``: ``cv2.findTransformECC`` (``MOTION_AFFINE``) on each pair's
  window, started from the same map, at most 10 iterations down to a rise of 1e-3, and at most
  50 down to 1e-5.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import cv2
import numpy as np

from bench import trust
from bench.metrics import truth_at
from pwlreg.core import refine
from pwlreg.core.epipolar import EpipolarModel
from pwlreg.core.errors import InputError
from pwlreg.core.pipeline import register
from pwlreg.core.refine import Levels

Call = tuple[Levels, np.ndarray, np.ndarray, np.ndarray, EpipolarModel | None]


def recorded(seeds: tuple[int, ...]) -> list[tuple[Call, np.ndarray]]:
    """Each recorded call of :func:`core.refine.sharpened`, with the true moving positions of its
    pairs (NaN where the truth has none)."""
    calls: list[tuple[Call, np.ndarray]] = []
    product = refine.sharpened
    seen: list[Call] = []

    def spy(image_levels, reference, moving, linear, *, model):  # type: ignore[no-untyped-def]
        seen.append((image_levels, reference.copy(), moving.copy(), linear.copy(), model))
        return product(image_levels, reference, moving, linear, model=model)

    for case in trust.build_cases(seeds=seeds):
        if case.group in ("unrelated", "partial overlap"):
            continue
        scene = case.make()
        seen.clear()
        refine.sharpened = spy
        try:
            register(scene.reference, scene.moving)
        except InputError:  # too few reliable pairs: nothing sharpened
            pass
        finally:
            refine.sharpened = product
        for call in seen:
            calls.append((call, truth_at(scene.truth_x, scene.truth_y, call[1])))
    return calls


def opencv_fits(iterations: int, epsilon: float) -> Callable[..., None]:
    """A stand-in for :func:`core.kernels.window_fits` (same arguments and outputs) that fits
    each window with ``cv2.findTransformECC`` (``MOTION_AFFINE``), at most ``iterations``
    iterations down to a rise of ``epsilon``."""
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, iterations, epsilon)

    def fits(reference: np.ndarray, moving: np.ndarray, points: np.ndarray, maps: np.ndarray,
             half: int, _iterations: int, _tolerance: float, centres: np.ndarray,
             scores: np.ndarray) -> None:
        lh, lw = moving.shape
        for k in range(len(points)):
            linear, start = maps[k, :, :2], maps[k, :, 2]
            centres[k], scores[k] = start, -2.0
            # A crop with room to move: OpenCV takes the gradients of its whole input image.
            reach = int(np.ceil(half * np.abs(linear).sum(axis=1).max())) + 6
            c = np.rint(start).astype(np.int64)
            if c[0] < reach or c[1] < reach or c[0] + reach >= lw or c[1] + reach >= lh:
                continue
            corner = c - reach
            crop = moving[corner[1]:c[1] + reach + 1, corner[0]:c[0] + reach + 1]
            window = cv2.getRectSubPix(reference, (2 * half + 1, 2 * half + 1),
                                       tuple(points[k]))
            shift = start - corner - linear @ [half, half]
            warp = np.hstack([linear, shift[:, None]]).astype(np.float32)
            try:
                score, warp = cv2.findTransformECC(window, crop, warp, cv2.MOTION_AFFINE,
                                                   criteria, None, 1)
            except cv2.error:  # a flat window, or the fit diverged
                scores[k] = -1.0
                continue
            centres[k] = warp[:, :2] @ [half, half] + warp[:, 2] + corner
            scores[k] = score

    return fits


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="6", help="comma-separated scene seeds")
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args(argv)
    calls = recorded(tuple(int(s) for s in args.seeds.split(",")))
    # The same bounds on every fit (refine.sharpened), each method's fits in place of the
    # compiled ones.
    methods: dict[str, Callable[..., None]] = {
        "compiled": refine.window_fits,
        "opencv 10": opencv_fits(10, 1e-3),
        "opencv 50": opencv_fits(50, 1e-5),
    }
    right = [np.isfinite(e) & (e < 3) for e in
             (np.hypot(*(call[2] - truth).T) for call, truth in calls)]
    pairs = sum(int(r.sum()) for r in right)
    print(f"{len(calls)} calls, {sum(len(c[1]) for c, _ in calls)} pairs, {pairs} right "
          f"(within 3 px of their truth)")
    rows = {"as matched": (np.concatenate([np.hypot(*(c[2] - t).T)[r]
                                           for (c, t), r in zip(calls, right, strict=True)]),
                           None)}
    compiled_fits = refine.window_fits
    for name, fits in methods.items():
        best = np.inf
        refine.window_fits = fits
        try:
            for _ in range(args.repeat):
                start = time.perf_counter()
                out = [refine.sharpened(levels, ref, mov, lin, model=model)
                       for (levels, ref, mov, lin, model), _ in calls]
                best = min(best, time.perf_counter() - start)
        finally:
            refine.window_fits = compiled_fits
        errors = np.concatenate([np.hypot(*(o - t).T)[r]
                                 for o, (_, t), r in zip(out, calls, right, strict=True)])
        rows[name] = (errors, best)
    compiled = rows["compiled"][1]
    print("right pairs' error px: median / mean / 90th / 99th percentile; time of all calls")
    for name, (errors, seconds) in rows.items():
        q = np.percentile(errors, [50, 90, 99])
        timing = "" if seconds is None else f"  {seconds:.3f} s  {seconds / compiled:.2f} x"
        print(f"  {name:11s} {q[0]:.3f} / {errors.mean():.3f} / {q[1]:.3f} / {q[2]:.3f}{timing}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
