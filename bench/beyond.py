"""Optimizers against the ceiling of edge swaps (a search told the true error), issue 10.

Run ``python -m bench.beyond [--quick] [--configs a,b] [--cases synthetic,middlebury]``. For
every case of :func:`bench.quality.build_cases` (synthetic polyhedral scenes with noisy true
points, Middlebury pairs with 150 true points and with automatic points) it registers the pair
with each configuration of :data:`CONFIGS` on the paper's mesh (``extent=hull``), runs
:func:`bench.ceiling.ceiling_search` from the same initial mesh, and prints per case the mean
endpoint error (pixels) of Delaunay, every configuration and the ceiling, then per group the
median share of the achievable gain each configuration realises and how many cases it leaves
worse than Delaunay.
"""

from __future__ import annotations

import argparse
import json
import time

import cv2
import numpy as np

from bench import middlebury, quality, trust
from bench.ceiling import ceiling_search, realised_share
from bench.metrics import (
    disparity_steps,
    endpoint_error,
    endpoint_error_map,
    error_by_triangle,
    truth_at,
)
from bench.quality import Case, CaseData, build_cases
from pwlreg.core.errors import InputError
from pwlreg.core.pipeline import register, warm_up

PAPER = {"optimizer": "greedy", "epsilon_pixels": 0, "lookahead": False, "bins": 16,
         "insert_vertices": "never"}
"""The paper's method (Algorithm 1 with one epsilon, 16 bins, no insertion)."""

CONFIGS: dict[str, dict] = {
    "paper": PAPER,
    "sized eps": {**PAPER, "epsilon_pixels": 250},
    "pyramid": {**PAPER, "epsilon_pixels": 250, "optimizer": "greedy-pyramid"},
    "lookahead": {**PAPER, "epsilon_pixels": 250, "lookahead": True},
    "bins32": {**PAPER, "epsilon_pixels": 250, "bins": 32},
    "swaps only": {"insert_vertices": "never"},
    "default": {},
}
"""Report name -> options of each configuration (the rest default)."""


def _trust_case(case: trust.Case) -> Case:
    """A case of the trust suite (scenes built for the automatic matcher), without points."""

    def load() -> CaseData:
        scene = case.make()
        return CaseData(reference=scene.reference, moving=scene.moving, points=None,
                        truth_x=scene.truth_x, truth_y=scene.truth_y, valid=scene.covisible,
                        correctness=None, compatibility=None)

    return Case(case.name, "synthetic", case.group, {}, load)


#: Distance (pixels) from its truth beyond which an inserted pair counts as wrong.
WRONG_PX = 3.0


def wrong_inserted(
    reference: np.ndarray,
    moving: np.ndarray,
    inserted: np.ndarray,
    truth_x: np.ndarray,
    truth_y: np.ndarray,
) -> tuple[int, int]:
    """How many of the ``inserted`` pairs lie more than :data:`WRONG_PX` from their truth
    (:func:`bench.metrics.truth_at`), of those whose truth is known.

    A scene worse than Delaunay is worse either through such pairs or through right ones that
    change how the triangles beside a surface without vertices interpolate: the count says
    which.
    """
    inserted = np.asarray(inserted, bool)
    if not inserted.any():
        return 0, 0
    truth = truth_at(truth_x, truth_y, np.asarray(reference)[inserted])
    err = np.hypot(*(np.asarray(moving, np.float64)[inserted] - truth).T)
    known = np.isfinite(err)
    return int(np.count_nonzero(err[known] > WRONG_PX)), int(np.count_nonzero(known))


def run(cases, configs: dict[str, dict], automatic: bool = False) -> list[dict]:
    rows = []
    for case in cases:
        t0 = time.perf_counter()
        data = case.load()
        kind = f"{case.kind} auto" if automatic else case.kind
        row = {"name": case.name, "kind": kind, "group": case.group, "params": case.params,
               "epe": {}, "time": {}}
        base = None
        # Delaunay over the pairs as matched (or given): no insertion, no swaps.
        plain = {"optimizer": "none", "insert_vertices": "never"}
        for label, opts in {"delaunay": plain, **configs}.items():
            given = {} if automatic else {"epipolar_filter": False}
            try:
                r = register(data.reference, data.moving, data.points,
                             {**opts, **given, "extent": "hull"})
            except InputError as exc:  # too few reliable automatic pairs: nothing to compare
                print(f"{case.name}: {label}: {exc}")
                break
            base = base or r
            row["epe"][label] = endpoint_error(r.reference_vertices, r.moving_vertices,
                                               r.final_triangles, data.truth_x, data.truth_y,
                                               data.valid)["mean"]
            row["time"][label] = r.timings["optimization_s"]
        else:
            ceiling = ceiling_search(base.reference_vertices, base.moving_vertices,
                                     base.final_triangles, data.truth_x, data.truth_y,
                                     data.valid)
            row["epe"]["ceiling"] = endpoint_error(
                base.reference_vertices, base.moving_vertices, ceiling, data.truth_x,
                data.truth_y, data.valid)["mean"]
            if automatic:
                # A dense optical flow over the pixels the last configuration's mesh covers.
                covered = np.isfinite(endpoint_error_map(
                    r.reference_vertices, r.moving_vertices, r.final_triangles, data.truth_x,
                    data.truth_y, data.valid))
                fx, fy = dense_flow(data.reference, data.moving)
                row["epe"]["DIS"] = float(np.mean(np.hypot(fx - data.truth_x,
                                                           fy - data.truth_y)[covered]))
                row["wrong inserted"] = wrong_inserted(r.reference_vertices, r.moving_vertices,
                                                       r.inserted, data.truth_x, data.truth_y)
        if "ceiling" not in row["epe"]:
            continue
        row["case_s"] = time.perf_counter() - t0
        rows.append(row)
        cells = " ".join(f"{k}={v:.3f}" for k, v in row["epe"].items())
        if "wrong inserted" in row:
            cells += " wrong inserted {}/{}".format(*row["wrong inserted"])
        print(f"{case.name:40s} {cells}  ({row['case_s']:.0f} s)", flush=True)
    return rows


def summary(rows: list[dict], configs: dict[str, dict]) -> None:
    groups = {
        "synthetic": [r for r in rows if r["kind"] == "synthetic" and "plane" not in r["name"]],
        "synthetic automatic (trust suite)": [r for r in rows if r["kind"] == "synthetic auto"],
        "middlebury truth": [r for r in rows if r["kind"] == "middlebury" and "truth" in r["name"]],
        "middlebury auto": [r for r in rows if r["kind"] == "middlebury" and "auto" in r["name"]],
    }
    for title, group in groups.items():
        if not group:
            continue
        print(f"\n{title} ({len(group)} cases): median share of the achievable gain / EPE "
              f"reduction vs Delaunay, mean and median / cases worse than Delaunay (> 2 % worse) "
              "/ median optimization s")
        ceil_red = np.mean([1 - r["epe"]["ceiling"] / r["epe"]["delaunay"] for r in group])
        print(f"  ceiling: mean reduction {100 * ceil_red:.1f} %")
        for label in configs:
            shares = [realised_share(r["epe"]["delaunay"], r["epe"][label], r["epe"]["ceiling"])
                      for r in group]
            reductions = [1 - r["epe"][label] / r["epe"]["delaunay"] for r in group]
            worse = sum(r["epe"][label] > r["epe"]["delaunay"] for r in group)
            much = [r["name"] + (" ({}/{} inserted wrong)".format(*r["wrong inserted"])
                                 if "wrong inserted" in r and label == list(configs)[-1] else "")
                    for r in group if r["epe"][label] > 1.02 * r["epe"]["delaunay"]]
            t = np.median([r["time"][label] for r in group])
            print(f"  {label:12s} share {np.nanmedian(shares):.2f}  reduction mean "
                  f"{100 * np.mean(reductions):5.1f} % median {100 * np.median(reductions):5.1f} %"
                  f"  worse {worse} ({len(much)})  {t:.2f} s" + (f"  > 2 % worse: {', '.join(much)}"
                                                                if much else ""))
        if all("DIS" in r["epe"] for r in group):
            _dense_flow_summary(group, list(configs)[-1])
        if title == "synthetic":
            _condition_summary(group, configs)


def _condition_summary(group: list[dict], configs: dict[str, dict]) -> None:
    """Median share and cases worse than Delaunay per imaging condition of
    :data:`bench.quality.CONDITIONS` (the issue asks for the non-monotone and noisy ones)."""
    print("  by condition (camera, radiometric change, sensor noise grey levels, blur px): "
          "median share / cases worse than Delaunay")
    for camera, radiometric, noise, blur in quality.CONDITIONS:
        condition = {"camera": camera, "radiometric": radiometric, "noise": noise, "blur": blur}
        rows = [r for r in group
                if all(r["params"].get(k) == v for k, v in condition.items())]
        if not rows:
            continue
        cells = []
        for label in configs:
            shares = [realised_share(r["epe"]["delaunay"], r["epe"][label], r["epe"]["ceiling"])
                      for r in rows]
            worse = sum(r["epe"][label] > r["epe"]["delaunay"] for r in rows)
            cells.append(f"{label} {np.nanmedian(shares):.2f} / {worse}")
        print(f"    {camera[:3]} {radiometric:11s} noise {noise:g} blur {blur:g} "
              f"({len(rows)} cases): " + ", ".join(cells))


def _dense_flow_summary(group: list[dict], label: str) -> None:
    """DIS against ``label`` over the pixels its meshes cover, narrow and wide baselines
    apart: where a raw dense flow stands against the mesh."""
    print(f"  DIS (OpenCV, medium preset) over the pixels the {label!r} meshes cover, median / "
          f"mean EPE px, DIS against {label!r}:")
    # The trust suite's wide-baseline scenes are a group of their own.
    wide = {"wide baseline": [r for r in group if "wide" in r["group"]],
            "narrow baseline": [r for r in group if "wide" not in r["group"]]}
    for part, rows in {"all": group, **wide}.items():
        if not rows:
            continue
        dis = np.array([r["epe"]["DIS"] for r in rows])
        mesh = np.array([r["epe"][label] for r in rows])
        print(f"    {part:16s} {len(rows):3d} cases: {np.median(dis):7.2f} / {np.mean(dis):7.2f} "
              f"against {np.median(mesh):6.2f} / {np.mean(mesh):6.2f}; DIS lower in "
              f"{int((dis < mesh).sum())}")


def _arosics_best(pair: str, mask: str) -> float | None:
    """Best mean EPE of the peer measurement (../shared/peers/arosics/results.json) over
    ``mask``: ``"nonocc"`` (the pixels this benchmark scores: known, not occluded by the
    left-right check at 1 px) or ``"all"`` (every pixel of known disparity), if any."""
    path = middlebury.real_data_root().parent.parent / "peers" / "arosics" / "results.json"
    if not path.is_file():
        return None
    runs = json.loads(path.read_text())["pairs"].get(pair, {}).get("runs", [])
    values = [r["dense_tps"][mask]["mean_epe"] for r in runs
              if r.get("dense_tps") and r["dense_tps"][mask]["mean_epe"] is not None]
    return min(values) if values else None


def dense_flow(reference: np.ndarray, moving: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV DIS optical flow (medium preset) from the reference to the moving image: the
    moving position of every reference pixel."""
    grey = [im if im.ndim == 2 else cv2.cvtColor(im, cv2.COLOR_BGR2GRAY)
            for im in (reference, moving)]
    flow = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM).calc(*grey, None)
    h, w = grey[0].shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    return xx + flow[..., 0], yy + flow[..., 1]


def frame_section(configs: dict[str, dict]) -> None:
    """Middlebury, automatic points, the whole frame: pwlreg against AROSICS and DIS, and where
    the first configuration's frame error lives against DIS's
    (:func:`bench.metrics.error_by_triangle`).

    Each method is scored over the same pixels: those of known disparity not occluded in the
    moving view (``nonocc``, what the rest of this benchmark scores) and, on a second line,
    every pixel of known disparity mapped inside the moving image (``all``, the mask of the
    figures the issue quotes for AROSICS; occluded pixels have no counterpart to find, every
    method interpolates over them)."""
    print("\nMiddlebury, automatic points: mean EPE px over the valid pixels the mesh covers "
          "(coverage of the valid pixels) / time s, for extent=hull and frame")
    where = []
    for name in middlebury.available_middlebury():
        pair = middlebury.load_middlebury(name)
        cells, cells_all = [], []
        frame = None
        for label, opts in configs.items():
            for extent in ("hull", "frame"):
                t0 = time.perf_counter()
                r = register(pair.reference, pair.moving, options={**opts, "extent": extent})
                t = time.perf_counter() - t0
                if extent == "frame" and frame is None:
                    frame = r
                e, e_all = (endpoint_error(r.reference_vertices, r.moving_vertices,
                                           r.final_triangles, pair.truth_x, pair.truth_y, mask)
                            for mask in (pair.valid, pair.mapped))
                cells.append(f"{label} {extent} {e['mean']:.3f} ({100 * e['coverage']:.0f} %) "
                             f"{t:.2f} s")
                cells_all.append(f"{label} {extent} {e_all['mean']:.3f} "
                                 f"({100 * e_all['coverage']:.0f} %)")
        t0 = time.perf_counter()
        fx, fy = dense_flow(pair.reference, pair.moving)
        t = time.perf_counter() - t0
        dis = np.hypot(fx - pair.truth_x, fy - pair.truth_y)
        cells.append(f"DIS {np.nanmean(dis[pair.valid]):.3f} {t:.3f} s")
        cells_all.append(f"DIS {np.nanmean(dis[pair.mapped]):.3f}")
        for mask, row in (("nonocc", cells), ("all", cells_all)):
            peer = _arosics_best(name, mask)
            row.append("AROSICS (peer file) " + ("-" if peer is None else f"{peer:.3f}"))
        print(f"  {name:26s} nonocc: " + " | ".join(cells), flush=True)
        print(f"  {'':26s} all:    " + " | ".join(cells_all), flush=True)
        classes = error_by_triangle(
            frame.reference_vertices, frame.moving_vertices, frame.final_triangles,
            pair.truth_x, pair.truth_y, pair.valid, steps=disparity_steps(pair.disparity),
            extrapolated=frame.triangulation.extrapolated, others={"DIS": dis})
        where.append(f"  {name:26s} " + " | ".join(
            f"{k} {100 * c['share']:.0f} %: {c['mean']:.2f} / {c['DIS mean']:.2f} "
            f"({c['contribution']:.3f} / {c['DIS contribution']:.3f})"
            for k, c in classes.items()))
    print(f"\nWhere the frame error of '{next(iter(configs))}' lives (nonocc), by triangle "
          "(pixels of the class, mean EPE px mesh / DIS over them, their part of the overall "
          "mean); a step is a disparity jump over 1 px, a vertex off is more than 1 px from "
          "the truth")
    print("\n".join(where))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="one case per family")
    parser.add_argument("--configs", help="comma-separated subset of CONFIGS")
    parser.add_argument("--kinds", default="synthetic,middlebury",
                        help="case kinds to run (synthetic, middlebury)")
    parser.add_argument("--middlebury-points", type=int, default=quality.MIDDLEBURY_POINTS,
                        help="true points drawn on each Middlebury pair (the issue quotes 100)")
    parser.add_argument("--frame", action="store_true",
                        help="only the Middlebury whole-frame comparison with AROSICS and DIS")
    parser.add_argument("--automatic", action="store_true",
                        help="synthetic cases without points (the automatic matcher)")
    parser.add_argument("--seeds", help="with --automatic: comma-separated scene seeds "
                        "(default 0,1, the scenes the insertion was developed on); else "
                        "comma-separated draws of the synthetic scenes with points (default 0, "
                        "the suite's own; see bench.quality.build_cases)")
    parser.add_argument("--size", type=trust.parse_size, default=trust.SIZE,
                        help="with --automatic: WxH of the scenes (default "
                        f"{trust.SIZE[0]}x{trust.SIZE[1]})")
    args = parser.parse_args(argv)
    configs = CONFIGS if not args.configs else {k: CONFIGS[k] for k in args.configs.split(",")}
    kinds = set(args.kinds.split(","))
    warm_up()
    quality.MIDDLEBURY_POINTS = args.middlebury_points
    if args.frame:
        frame_section(configs)
        return 0
    if args.automatic:
        seeds = tuple(int(v) for v in args.seeds.split(",")) if args.seeds else None
        cases = [_trust_case(c) for c in trust.build_cases(quick=args.quick, seeds=seeds,
                                                             size=args.size)
                 if c.group not in ("unrelated", "partial overlap")]
    else:
        draws = tuple(int(v) for v in args.seeds.split(",")) if args.seeds else (0,)
        cases = [c for c in build_cases(quick=args.quick, draws=draws) if c.kind in kinds]
    rows = run(cases, configs, automatic=args.automatic)
    summary(rows, configs)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
