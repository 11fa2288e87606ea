"""Trust report: automatic registration on scenes with exact truth, and its verdict.

Run ``python -m bench.trust`` (about 6 minutes on 2 cores; ``--quick`` for a subset,
``--seeds 2,3`` for scenes the thresholds were not set on, ``--size 1280x960`` to render the
synthetic scenes at another size, ``--out DIR`` for the output folder, default
``bench/results/trust/``). Every case is registered as a
client without points would: :func:`core.pipeline.register` with default options (automatic
matching, ``extent="frame"``). It writes ``report.md`` and ``results.json``.

What it measures
----------------
* **Synthetic suite** (:mod:`bench.scenes`): the polyhedral families under lighting and
  non-monotone changes, a tiled ground seen off by a period (``checker``, ``checker_box``, with
  sensor noise 3-8 grey levels, blur up to 1 px and lighting or per-face gamma changes),
  occluders in front of a facade, wide baselines with half the scene in common
  (``overlap=0.5``), and unrelated pairs. Per case: the kept conjugate pairs and the share more
  than 3 px from the truth, the true endpoint error (EPE) of the registration over the covisible
  pixels of its mesh, its coverage and the verdict, and how far the true matches lie from the
  epipolar lines of the matcher's fundamental matrix (its 90th percentile). A failed job (no
  reliable pairs) is reported as such; for the verdict table it counts as ``unreliable``.
* **The verdict against the truth**: per verdict, the cases and the distribution of their true
  mean EPE; unrelated pairs must all be ``unreliable`` (or refused), and no case whose kept
  pairs are mostly wrong may be ``good``.
* **Middlebury** (real pairs with dense truth): coverage of the valid-truth pixels and mean
  EPE with ``extent="hull"`` and ``"frame"``, and the extrapolation models compared on the
  pixels outside the hull.
* **Strecha photographs** (3072 x 2048, calibrated cameras): verdict, pairs and the distance
  of the dense map to the true epipolar geometry, registered at full and at half resolution.
* **Hard real pairs**: Sacre-Coeur day/night and unrelated real photographs.
* **Speed**: the automatic path on a 1024x768 pair (best of 3).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from scipy.spatial import Delaunay, cKDTree

from bench import middlebury, realdata
from bench.metrics import endpoint_error, epipolar_line_error, epipolar_map_error, truth_at
from bench.scenes import make_scene, make_unrelated_pair
from pwlreg.core.errors import RegistrationError
from pwlreg.core.extent import local_affine_extrapolation
from pwlreg.core.matching import find_conjugate_points
from pwlreg.core.options import RegistrationOptions
from pwlreg.core.pipeline import register, warm_up

DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "trust"
SIZE = (640, 480)
WRONG_PX = 3.0
#: Distance of a true match from its epipolar line beyond which the insertion's search along the
#: line cannot find it (the final pass looks 2 px either side).
EPIPOLAR_OFF_PX = 2.0
VERDICTS = ("good", "doubtful", "unreliable", "refused")


@dataclass
class Case:
    """A named synthetic case and how to make its scene."""

    name: str
    group: str
    make: Any


def _size_tag(size: tuple[int, int]) -> str:
    """``-WxH`` in a case's name, empty at :data:`SIZE` (the names the measurement log
    quotes)."""
    return "" if tuple(size) == SIZE else f"-{size[0]}x{size[1]}"


def parse_size(text: str) -> tuple[int, int]:
    """``"WxH"`` -> ``(W, H)`` (command-line option)."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WxH such as 1280x960, got {text!r}") from None
    if w < 64 or h < 64:
        raise argparse.ArgumentTypeError(f"scenes need at least 64x64 pixels, got {text!r}")
    return w, h


def _scene_case(group: str, family: str, seed: int, size: tuple[int, int],
                **kw: Any) -> Case:
    tag = "-".join(f"{k[:3]}{v}" for k, v in kw.items()) + _size_tag(size)
    return Case(f"{family}-{tag}-s{seed}", group,
                lambda: make_scene(family, seed, size=size, n_interior=0, supersample=2, **kw))


def build_cases(quick: bool = False, seeds: tuple[int, ...] | None = None,
                size: tuple[int, int] = SIZE) -> list[Case]:
    """The synthetic suite (a subset with ``quick``); ``seeds`` replaces the scene seeds
    (0 and 1, 0 with ``quick``) of every family but the unrelated pairs; ``size`` (width,
    height) renders every scene, the unrelated pairs too, at another size."""
    seeds = seeds if seeds is not None else (0,) if quick else (0, 1)
    cases: list[Case] = []
    poly = ("box", "gable", "city") if quick else ("box", "prism", "gable", "lshape",
                                                   "open_book", "city")
    for fam in poly:
        for seed in seeds:
            cases.append(_scene_case("polyhedral", fam, seed, size, camera="perspective",
                                     radiometric="lighting", noise=3.0, blur=0.5,
                                     baseline=12.0))
            if not quick:
                cases.append(_scene_case("polyhedral", fam, seed, size, camera="affine",
                                         radiometric="nonmonotone", noise=2.0, blur=0.0,
                                         baseline=12.0))
                cases.append(_scene_case("polyhedral, wide", fam, seed, size, camera="perspective",
                                         radiometric="lighting", noise=3.0, blur=0.5,
                                         baseline=22.0))
    for fam in ("checker", "checker_box"):
        for seed in seeds:
            cases.append(_scene_case("repetitive", fam, seed, size, camera="perspective",
                                     radiometric="lighting", noise=3.0, blur=0.0))
            cases.append(_scene_case("repetitive", fam, seed, size, camera="perspective",
                                     radiometric="monotone", noise=8.0, blur=1.0))
    for seed in seeds:
        cases.append(_scene_case("occluders", "occluder", seed, size, camera="perspective",
                                 radiometric="lighting", noise=3.0, blur=0.5))
        if not quick:
            cases.append(_scene_case("occluders", "occluder", seed, size, camera="affine",
                                     radiometric="monotone", noise=2.0, blur=0.0))
    for fam in ("city", "occluder") if quick else ("city", "lshape", "occluder"):
        for seed in seeds:
            cases.append(_scene_case("partial overlap", fam, seed, size, camera="perspective",
                                     radiometric="lighting", noise=3.0, blur=0.5,
                                     baseline=35.0, overlap=0.5))
    for seed in range(3 if quick else 6):
        cases.append(Case(f"unrelated{_size_tag(size)}-s{seed}", "unrelated",
                          lambda seed=seed: make_unrelated_pair(seed, size=size, supersample=2)))
    return cases


def _error(moving: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Distance of each pair's moving point to its truth; infinite where the truth is unknown
    (such a pair counts as wrong)."""
    err = np.linalg.norm(moving - truth, axis=1)
    return np.where(np.isfinite(err), err, np.inf)


def run_case(case: Case) -> dict:
    """Register one synthetic case automatically and score it against its truth."""
    scene = case.make()
    row: dict[str, Any] = {"name": case.name, "group": case.group,
                           "covisible_fraction": scene.info.get("covisible_fraction")}
    unrelated = bool(scene.info.get("unrelated"))
    t = time.perf_counter()
    try:
        r = register(scene.reference, scene.moving)
    except RegistrationError as exc:
        row.update(status="refused", verdict="refused", reason=str(exc),
                   seconds=time.perf_counter() - t)
        return row
    row["seconds"] = time.perf_counter() - t
    q = r.quality.to_dict()
    row.update(status="successful", verdict=q["verdict"], reasons=q["reasons"],
               quality={k: v for k, v in q.items() if k not in ("verdict", "reasons")},
               points=len(r.points), source=r.points.source,
               dropped=r.points.rejected)
    if unrelated:
        row.update(wrong_share=1.0, epe_mean=float("nan"))
        return row
    # Matched pairs and the pairs the guided insertion added: every measured vertex counts, at
    # its position in the result (the `correct` move may have moved a matched one).
    _, at = cKDTree(r.reference_vertices).query(r.points.reference)
    same = np.hypot(*(r.reference_vertices[at] - r.points.reference).T) < 0.01
    matched = np.where(same[:, None], r.moving_vertices[at], r.points.moving)
    ref_pts = np.concatenate([r.points.reference, r.reference_vertices[r.inserted]])
    mov_pts = np.concatenate([matched, r.moving_vertices[r.inserted]])
    if r.corrections is not None and len(r.corrections.vertices):
        # Per vertex move: vertices moved, of which wrong before, wrong after (a vertex of
        # unknown truth, such as an occluded border vertex, counts as wrong both times).
        c = r.corrections
        t = truth_at(scene.truth_x, scene.truth_y, r.reference_vertices[c.vertices])
        wrong_before, wrong_after = (_error(p, t) > WRONG_PX for p in (c.before, c.moving))
        moves = np.array(c.moves)
        row["corrected"] = {str(m): [int(np.count_nonzero(moves == m)),
                                     int(np.count_nonzero(wrong_before[moves == m])),
                                     int(np.count_nonzero(wrong_after[moves == m]))]
                            for m in dict.fromkeys(c.moves)}
    err = _error(mov_pts, truth_at(scene.truth_x, scene.truth_y, ref_pts))
    row["inserted"] = int(r.inserted.sum())
    row["inserted_wrong"] = int(np.count_nonzero(err[len(r.points.reference):] > WRONG_PX))
    sources = np.array(["matched"] * len(r.points.reference)
                       + [o for o, i in zip(r.origins, r.inserted, strict=True) if i])
    row["wrong_by_source"] = {str(k): [int(np.count_nonzero(err[sources == k] > WRONG_PX)),
                                       int(np.count_nonzero(sources == k))]
                              for k in dict.fromkeys(sources)}
    row["wrong_share"] = float(np.mean(err > WRONG_PX)) if len(err) else 1.0
    row["wrong"] = int(np.count_nonzero(err > WRONG_PX))
    row["point_error_median"] = float(np.median(err)) if len(err) else float("nan")
    if r.points.epipolar is not None:
        # The insertion searches along these lines: where they miss the truth, it can only find
        # lookalikes.
        off = epipolar_line_error(r.points.epipolar.matrix, scene.truth_x, scene.truth_y,
                                  scene.covisible)
        row["epipolar_p90"] = float(np.percentile(off, 90)) if len(off) else float("nan")
    epe = endpoint_error(r.reference_vertices, r.moving_vertices, r.final_triangles,
                         scene.truth_x, scene.truth_y, scene.covisible)
    row.update(epe_mean=epe["mean"], epe_median=epe["median"], coverage=epe["coverage"])
    measured = ~r.extrapolated[r.final_triangles].any(axis=1)
    inner = endpoint_error(r.reference_vertices, r.moving_vertices, r.final_triangles[measured],
                           scene.truth_x, scene.truth_y, scene.covisible)
    row.update(epe_measured=inner["mean"], coverage_measured=inner["coverage"])
    return row


def middlebury_section() -> list[dict]:
    """Coverage and EPE of the automatic path on the Middlebury pairs, hull against frame, and
    the extrapolation models on the pixels outside the hull."""
    rows = []
    for name in middlebury.available_middlebury():
        pair = middlebury.load_middlebury(name)
        row: dict[str, Any] = {"pair": name}
        for extent in ("hull", "frame"):
            try:
                r = register(pair.reference, pair.moving, options={"extent": extent})
            except RegistrationError as exc:
                row[extent] = {"refused": str(exc)}
                continue
            epe = endpoint_error(r.reference_vertices, r.moving_vertices, r.final_triangles,
                                 pair.truth_x, pair.truth_y, pair.valid)
            row[extent] = {"coverage": epe["coverage"], "epe_mean": epe["mean"],
                           "epe_median": epe["median"], "verdict": r.quality.verdict}
        cp = find_conjugate_points(pair.reference, pair.moving, RegistrationOptions())
        h, w = pair.shape
        yy, xx = np.mgrid[0:h, 0:w]
        pix = np.column_stack([xx.ravel(), yy.ravel()]).astype(np.float64)
        out = (Delaunay(cp.reference).find_simplex(pix) < 0) & pair.valid.ravel()
        truth = np.column_stack([pair.truth_x.ravel(), pair.truth_y.ravel()])[out]
        models = {
            "local affine (12 nearest)": local_affine_extrapolation(cp.reference, cp.moving,
                                                                    pix[out]),
        }
        H, _ = cv2.findHomography(cp.reference, cp.moving, cv2.USAC_MAGSAC, 3.0)
        q = pix[out] @ H[:, :2].T + H[:, 2]
        models["global homography"] = q[:, :2] / q[:, 2:3]
        row["extrapolation"] = {
            "outside_hull_share": float(out.sum() / pair.valid.sum()),
            **{k: float(np.linalg.norm(v - truth, axis=1).mean()) for k, v in models.items()},
        }
        rows.append(row)
    return rows


HARD_PAIRS = {
    "sacre_coeur day/night": ("lightglue_sacre_coeur_daynight", "sacre_coeur1.jpg",
                              "lightglue_sacre_coeur_daynight", "sacre_coeur2.jpg"),
    "unrelated: teddy / graffiti": ("middlebury2003_teddy", "im2.ppm", "oxford_graf",
                                    "img1.ppm"),
    "unrelated: venus / castle": ("middlebury2001_venus", "im2.ppm", "strecha_castle_p19",
                                  "0002.jpg"),
    "unrelated: facade / leuven": ("lightglue_facade", "DSC_0410.JPG", "oxford_leuven",
                                   "img1.ppm"),
}


def hard_pairs_section() -> list[dict]:
    """Outcome of the automatic path on the hard and unrelated real pairs."""
    root = realdata.default_root()
    rows = []
    for label, (fa, a, fb, b) in HARD_PAIRS.items():
        if not (root / fa / a).exists() or not (root / fb / b).exists():
            continue
        ref, mov = realdata.read_image(root / fa / a), realdata.read_image(root / fb / b)
        try:
            r = register(ref, mov)
            rows.append({"pair": label, "outcome": r.quality.verdict,
                         "detail": "; ".join(r.quality.reasons) or r.summary()})
        except RegistrationError as exc:
            rows.append({"pair": label, "outcome": "refused", "detail": str(exc)})
    return rows


#: Scales the Strecha photographs (3072 x 2048) are registered at: themselves and halved,
#: both scored in the full-resolution pixels their cameras are calibrated for.
STRECHA_SCALES = (1.0, 0.5)
#: Grid step (pixels of the registered images) of the dense epipolar score.
STRECHA_STEP = 8


def strecha_section() -> list[dict]:
    """The automatic path on the Strecha photographs (3072 x 2048, calibrated cameras) at
    :data:`STRECHA_SCALES`: verdict, pairs, and the dense map's distance to the true epipolar
    geometry (:func:`bench.metrics.epipolar_map_error`)."""
    rows = []
    for name in realdata.available_pairs():
        if realdata.PAIRS[name][2] != "strecha":
            continue
        pair = realdata.load_pair(name)
        for scale in STRECHA_SCALES:
            ref, mov = pair.reference, pair.moving
            if scale != 1.0:
                ref, mov = (cv2.resize(im, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
                            for im in (ref, mov))
            row: dict[str, Any] = {"pair": name, "size": f"{ref.shape[1]}x{ref.shape[0]}"}
            t = time.perf_counter()
            try:
                r = register(ref, mov)
            except RegistrationError as exc:
                row.update(verdict="refused", reason=str(exc))
                rows.append(row)
                continue
            row["seconds"] = time.perf_counter() - t
            d, coverage = epipolar_map_error(pair.F, r.reference_vertices, r.moving_vertices,
                                             r.final_triangles, ref.shape[:2], scale=scale,
                                             step=STRECHA_STEP)
            row.update(verdict=r.quality.verdict, points=len(r.points), coverage=coverage,
                       sampson_median=float(np.median(d)), sampson_p90=float(np.percentile(d, 90)),
                       sampson_over_5=float(np.mean(d > 5.0)))
            rows.append(row)
    return rows


def speed_section(repeat: int = 3) -> list[dict]:
    """Automatic registration time on 1024x768 pairs (best of ``repeat``)."""
    rows = []
    pairs = {"city, perspective, 1024x768 (synthetic)": lambda: make_scene(
        "city", 3, size=(1024, 768), camera="perspective", radiometric="lighting", noise=3.0,
        baseline=12.0)}
    root = realdata.default_root()
    facade = root / "lightglue_facade"
    for label, make in pairs.items():
        s = make()
        rows.append(_time(label, s.reference, s.moving, repeat))
    if facade.exists():
        rows.append(_time("lightglue_facade 1024x682 (real)",
                          realdata.read_image(facade / "DSC_0410.JPG"),
                          realdata.read_image(facade / "DSC_0411.JPG"), repeat))
    return rows


def _time(label: str, ref: np.ndarray, mov: np.ndarray, repeat: int) -> dict:
    best, stages = np.inf, {}
    for _ in range(repeat):
        t = time.perf_counter()
        r = register(ref, mov)
        dt = time.perf_counter() - t
        if dt < best:
            best, stages = dt, r.timings
    return {"pair": label, "seconds": best, "stages": stages}


# --- report ------------------------------------------------------------------------------------


def _f(v: Any, digits: int = 2) -> str:
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return "-"
    return f"{v:.{digits}f}" if isinstance(v, float) else str(v)


def _median(rows: list[dict], key: str) -> str:
    values = [r[key] for r in rows if key in r and np.isfinite(r[key])]
    return _f(float(np.median(values))) if values else "-"


def summarize(rows: list[dict]) -> dict:
    """The figures the issue asks for, from the per-case rows."""
    scored = [r for r in rows if r["group"] != "unrelated" and r["status"] == "successful"]
    kept = sum(r["points"] + r.get("inserted", 0) for r in scored)
    wrong = sum(r["wrong"] for r in scored)
    table = {}
    for verdict in VERDICTS:
        sel = [r for r in rows if r["verdict"] == verdict]
        epe = [r["epe_mean"] for r in sel if np.isfinite(r.get("epe_mean", np.nan))]
        table[verdict] = {
            "cases": len(sel),
            "unrelated": sum(r["group"] == "unrelated" for r in sel),
            "mostly_wrong": sum(r.get("wrong_share", 0) > 0.5 for r in sel
                                if r["group"] != "unrelated" and r["status"] == "successful"),
            "epe_median": float(np.median(epe)) if epe else float("nan"),
            "epe_p90": float(np.percentile(epe, 90)) if epe else float("nan"),
            "epe_max": float(np.max(epe)) if epe else float("nan"),
        }
    unrelated = [r for r in rows if r["group"] == "unrelated"]
    by_source: dict[str, list[int]] = {}
    for r in scored:
        for k, (w, n) in r.get("wrong_by_source", {}).items():
            by_source.setdefault(k, [0, 0])
            by_source[k][0] += w
            by_source[k][1] += n
    by_verdict = {v: [sum(r["wrong"] for r in scored if r["verdict"] == v),
                      sum(r["points"] + r.get("inserted", 0) for r in scored
                          if r["verdict"] == v)] for v in VERDICTS}
    return {
        "cases": len(rows),
        "kept_pairs": kept,
        "wrong_pairs": wrong,
        "wrong_share": wrong / kept if kept else float("nan"),
        "inserted_pairs": sum(r.get("inserted", 0) for r in scored),
        "inserted_wrong": sum(r.get("inserted_wrong", 0) for r in scored),
        "wrong_by_source": by_source,
        "wrong_by_verdict": {v: wn for v, wn in by_verdict.items() if wn[1]},
        # Per vertex move: vertices moved, wrong before, wrong after.
        "corrected": {m: [sum(r.get("corrected", {}).get(m, [0, 0, 0])[k] for r in scored)
                          for k in range(3)]
                      for m in dict.fromkeys(m for r in scored for m in r.get("corrected", {}))},
        "mostly_wrong_called_good": sum(
            r["verdict"] == "good" and r.get("wrong_share", 0) > 0.5 for r in scored),
        "unrelated_not_unreliable": sum(r["verdict"] not in ("unreliable", "refused")
                                        for r in unrelated),
        # Cases with an epipolar geometry, and of them those whose lines miss the true matches
        # by more than EPIPOLAR_OFF_PX at the 90th percentile.
        "epipolar_off": [sum(r["epipolar_p90"] > EPIPOLAR_OFF_PX for r in scored
                             if "epipolar_p90" in r),
                         sum("epipolar_p90" in r for r in scored)],
        "verdicts": table,
    }


def write_report(rows: list[dict], summary: dict, mb: list[dict], hard: list[dict],
                 speed: list[dict], out: Path, strecha: list[dict] | None = None) -> str:
    """Markdown report."""
    lines = ["# Trust report (automatic points, default options)", ""]
    s = summary
    lines += [
        f"* {s['cases']} synthetic cases; kept pairs (matched, and inserted by the guided "
        f"insertion: {s['inserted_pairs']}, of which {s['inserted_wrong']} wrong) over all "
        f"registered cases with truth: {s['kept_pairs']}, of which {s['wrong_pairs']} more "
        f"than {WRONG_PX:.0f} px from the "
        f"truth (**{100 * s['wrong_share']:.2f} %**).",
        "* Wrong / kept pairs by what found them: " + ", ".join(
            f"{k} {w} / {n} ({100 * w / n:.2f} %)" for k, (w, n) in s["wrong_by_source"].items()
            if n) + "; by the verdict of their result: " + ", ".join(
            f"`{v}` {w} / {n} ({100 * w / n:.2f} %)" for v, (w, n) in
            s["wrong_by_verdict"].items()) + ".",
        "* Vertices moved by the vertex moves: " + (", ".join(
            f"`{m}` {n}, of which wrong before {before}, after {after}"
            for m, (n, before, after) in s["corrected"].items()) or "none") + ".",
        f"* Cases whose kept pairs are mostly wrong and called `good`: "
        f"**{s['mostly_wrong_called_good']}**.",
        f"* Unrelated pairs not `unreliable` or refused: **{s['unrelated_not_unreliable']}**.",
        f"* Epipolar geometry: in {s['epipolar_off'][0]} of {s['epipolar_off'][1]} registered "
        f"cases with one, a tenth of the covisible pixels or more have their true match more "
        f"than {EPIPOLAR_OFF_PX:.0f} px from their estimated epipolar line, along which the "
        f"insertion searches.",
        "", "## Verdict against the true mean EPE (pixels) of each case", "",
        "| verdict | cases | of which unrelated | mostly wrong pairs | EPE median | p90 | max |",
        "|---|---|---|---|---|---|---|",
    ]
    for v, t in s["verdicts"].items():
        lines.append(f"| {v} | {t['cases']} | {t['unrelated']} | {t['mostly_wrong']} | "
                     f"{_f(t['epe_median'])} | {_f(t['epe_p90'])} | {_f(t['epe_max'])} |")
    groups: dict[str, list[dict]] = {}
    for r in rows:
        groups.setdefault(r["group"], []).append(r)
    lines += ["", "## Per group", "",
              "| group | cases | pairs kept (median) | wrong pairs | EPE mean (median) | "
              "coverage (median) | verdicts |", "|---|---|---|---|---|---|---|"]
    for g, sel in groups.items():
        ok = [r for r in sel if r["status"] == "successful"]
        kept = sum(r["points"] for r in ok if g != "unrelated")
        wrong = sum(r.get("wrong", 0) for r in ok)
        verdicts = ", ".join(f"{v} {sum(r['verdict'] == v for r in sel)}" for v in VERDICTS
                             if any(r["verdict"] == v for r in sel))
        lines.append(f"| {g} | {len(sel)} | {_median(ok, 'points')} | {wrong}/{kept} | "
                     f"{_median(ok, 'epe_mean')} | {_median(ok, 'coverage')} | {verdicts} |")
    lines += ["", "## Cases", "",
              "EPE and coverage of the covisible pixels: whole mesh (frame) / measured part "
              "(triangles without an extrapolated vertex). Epipolar p90: the 90th percentile, "
              "over the covisible pixels, of the distance from their true match to their "
              "epipolar line under the matcher's fundamental matrix.", "",
              "| case | verdict | pairs | wrong | point err med | epipolar p90 | EPE mean | "
              "coverage | time s | reasons |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        reason = r.get("reason") or "; ".join(r.get("reasons", []))
        lines.append(
            f"| {r['name']} | {r['verdict']} | {r.get('points', 0)} | {r.get('wrong', '-')} | "
            f"{_f(r.get('point_error_median'))} | {_f(r.get('epipolar_p90'))} | "
            f"{_f(r.get('epe_mean'))} / "
            f"{_f(r.get('epe_measured'))} | {_f(r.get('coverage'))} / "
            f"{_f(r.get('coverage_measured'))} | {_f(r.get('seconds'))} | {reason[:160]} |")
    if mb:
        lines += ["", "## Middlebury, automatic points", "",
                  "| pair | hull: coverage / EPE | frame: coverage / EPE | verdict (frame) | "
                  "outside hull | extrapolation EPE: local affine / global homography |",
                  "|---|---|---|---|---|---|"]
        for m in mb:
            h, f, e = m.get("hull", {}), m.get("frame", {}), m["extrapolation"]
            lines.append(
                f"| {m['pair']} | {_f(h.get('coverage'))} / {_f(h.get('epe_mean'))} | "
                f"{_f(f.get('coverage'))} / {_f(f.get('epe_mean'))} | {f.get('verdict', '-')} | "
                f"{_f(e['outside_hull_share'])} | {_f(e['local affine (12 nearest)'])} / "
                f"{_f(e['global homography'])} |")
    if strecha:
        lines += ["", "## Strecha photographs, automatic points", "",
                  "Distance of the registration's map (every "
                  f"{STRECHA_STEP}th pixel it covers) to the true epipolar geometry, in pixels "
                  "of the 3072 x 2048 photographs: it measures the error across the epipolar "
                  "lines only.", "",
                  "| pair | registered at | verdict | pairs | coverage | Sampson median | p90 | "
                  "> 5 px | time s |", "|---|---|---|---|---|---|---|---|---|"]
        for m in strecha:
            lines.append(
                f"| {m['pair']} | {m['size']} | {m['verdict']} | {m.get('points', 0)} | "
                f"{_f(m.get('coverage'))} | {_f(m.get('sampson_median'))} | "
                f"{_f(m.get('sampson_p90'))} | {_f(m.get('sampson_over_5'), 3)} | "
                f"{_f(m.get('seconds'))} |")
    if hard:
        lines += ["", "## Hard and unrelated real pairs", "", "| pair | outcome | detail |",
                  "|---|---|---|"]
        lines += [f"| {h['pair']} | {h['outcome']} | {h['detail'][:200]} |" for h in hard]
    if speed:
        lines += ["", "## Speed of the automatic path (best of 3)", "",
                  "| pair | total s | matching | triangulation | optimization | rendering | "
                  "quality |", "|---|---|---|---|---|---|---|"]
        for sp in speed:
            st = sp["stages"]
            lines.append(
                f"| {sp['pair']} | {sp['seconds']:.3f} | {st.get('matching_s', 0):.3f} | "
                f"{st.get('triangulation_s', 0):.3f} | {st.get('optimization_s', 0):.3f} | "
                f"{st.get('rendering_s', 0):.3f} | {st.get('quality_s', 0):.3f} |")
    text = "\n".join(lines) + "\n"
    out.mkdir(parents=True, exist_ok=True)
    (out / "report.md").write_text(text)
    return text


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.trust", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="a subset (about a minute)")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    parser.add_argument("--no-speed", action="store_true", help="skip the speed section")
    parser.add_argument("--seeds", help="comma-separated scene seeds instead of 0,1 (scenes "
                        "the verdict's thresholds were not set on, e.g. 2,3)")
    parser.add_argument("--size", type=parse_size, default=SIZE,
                        help=f"WxH of the synthetic scenes (default {SIZE[0]}x{SIZE[1]})")
    args = parser.parse_args(argv)
    seeds = tuple(int(s) for s in args.seeds.split(",")) if args.seeds else None
    warm_up()
    t0 = time.perf_counter()
    rows = []
    for case in build_cases(args.quick, seeds, args.size):
        row = run_case(case)
        rows.append(row)
        print(f"{row['name']:45s} {row['verdict']:10s} pairs {row.get('points', 0):4d} "
              f"wrong {row.get('wrong', '-')!s:>4} EPE {_f(row.get('epe_mean'))}",
              file=sys.stderr, flush=True)
    summary = summarize(rows)
    mb = middlebury_section()
    strecha = strecha_section()
    hard = hard_pairs_section()
    speed = [] if args.no_speed else speed_section()
    text = write_report(rows, summary, mb, hard, speed, args.out, strecha)
    (args.out / "results.json").write_text(json.dumps(
        {"summary": summary, "cases": rows, "middlebury": mb, "strecha": strecha,
         "hard_pairs": hard, "speed": speed, "elapsed_s": time.perf_counter() - t0},
        indent=1, default=float))
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
