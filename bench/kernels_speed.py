"""Speed of the automatic path's correlation kernels: ``python -m bench.kernels_speed [--rev REV]
[--pair NAME] [--repeat N] [--threads N]``.

Registers one pair (default the facade, ``lightglue_facade``; ``city`` is the synthetic
1024x768 perspective city scene) once, recording the arguments of every call of
:func:`core.reliability.uniqueness` (the matcher's and the insertion's) and of
:func:`core.kernels.strip_correlation` (the insertion's epipolar search). Then times, best of
``--repeat`` runs:

1. ``uniqueness`` over the recorded calls;
2. ``strip_correlation`` over the recorded calls (the kernel alone);
3. the whole ``register()`` of the pair.

With ``--rev``, each is timed side by side (alternating runs, one process) with the same
functions of that git revision: its ``core/reliability.py`` and ``core/kernels.py`` are read
with ``git show`` and loaded as modules (numba's cache off, so they compile here), and for the
registration its ``uniqueness`` and ``strip_correlation`` are patched into the current pipeline
(a revision without ``strip_correlation``, before 2026-11-26, has only its ``uniqueness``
compared). The outputs are compared: causes of every pair, correlations bit for bit, final
vertices.
"""

from __future__ import annotations

import argparse
import importlib.util
import subprocess
import sys
import tempfile
import time
import types
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

import pwlreg
from bench.realdata import PAIRS, default_root, read_image
from pwlreg.core import kernels, matching, refine, reliability

ROOT = Path(__file__).resolve().parents[1]


def load_revision(rev: str, folder: Path) -> tuple[types.ModuleType, types.ModuleType]:
    """``core/kernels.py`` and ``core/reliability.py`` of git revision ``rev`` as modules, the
    second importing the first (not the current kernels)."""
    modules = []
    for name in ("kernels", "reliability"):
        text = subprocess.run(["git", "show", f"{rev}:core/{name}.py"], cwd=ROOT, check=True,
                              capture_output=True, text=True).stdout
        # numba cannot cache functions of a module loaded from a file outside the package.
        text = text.replace("cache=True", "cache=False")
        text = text.replace("from pwlreg.core.kernels import", "from _bench_rev_kernels import")
        path = folder / f"_bench_rev_{name}.py"
        path.write_text(text)
        spec = importlib.util.spec_from_file_location(f"_bench_rev_{name}", path)
        assert spec is not None and spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        sys.modules[spec.name] = module
        spec.loader.exec_module(module)
        modules.append(module)
    return modules[0], modules[1]


def load_images(pair: str) -> tuple[np.ndarray, np.ndarray]:
    """The pair's reference and moving images."""
    if pair == "city":
        from bench.scenes import make_scene

        scene = make_scene("city", 3, size=(1024, 768), camera="perspective",
                           radiometric="lighting", noise=3.0, baseline=12.0)
        return scene.reference, scene.moving
    ref_file, mov_file, _ = PAIRS[pair]
    folder = default_root() / pair
    return read_image(folder / ref_file), read_image(folder / mov_file)


def record_calls(reference: np.ndarray, moving: np.ndarray) -> tuple[list, list]:
    """Arguments of the uniqueness and strip_correlation calls of one registration."""
    checks: list[tuple] = []
    lines: list[tuple] = []
    check, line = reliability.uniqueness, refine.strip_correlation

    def recorded_check(*args: Any) -> Any:
        checks.append(tuple(np.array(a) if isinstance(a, np.ndarray) else a for a in args))
        return check(*args)

    def recorded_line(*args: Any) -> Any:
        lines.append(tuple(np.array(a) for a in args))
        return line(*args)

    with patched(recorded_check, recorded_line):
        pwlreg.register(reference, moving)
    return checks, lines


class patched:
    """Context: ``uniqueness`` and ``strip_correlation`` replaced where the pipeline calls them."""

    def __init__(self, check: Callable, line: Callable) -> None:
        self.new = (check, check, line)
        self.slots = ((matching, "uniqueness"), (refine, "uniqueness"),
                      (refine, "strip_correlation"))

    def __enter__(self) -> None:
        self.old = [getattr(module, name) for module, name in self.slots]
        for (module, name), value in zip(self.slots, self.new, strict=True):
            setattr(module, name, value)

    def __exit__(self, *exc: object) -> None:
        for (module, name), value in zip(self.slots, self.old, strict=True):
            setattr(module, name, value)


def best_times(sides: dict[str, Callable[[], Any]], repeat: int) -> dict[str, float]:
    """Best wall time of each side, the sides alternating run by run (after one warm-up)."""
    for run in sides.values():
        run()
    times: dict[str, list[float]] = {name: [] for name in sides}
    for _ in range(repeat):
        for name, run in sides.items():
            start = time.perf_counter()
            run()
            times[name].append(time.perf_counter() - start)
    return {name: min(t) for name, t in times.items()}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rev", help="git revision to compare with (e.g. HEAD~1)")
    parser.add_argument("--pair", default="lightglue_facade", help="a real pair or 'city'")
    parser.add_argument("--repeat", type=int, default=7, help="timed runs per side")
    parser.add_argument("--threads", type=int, help="numba threads (default: numba's)")
    args = parser.parse_args(argv)
    if args.threads:
        kernels.set_threads(args.threads)
    reference, moving = load_images(args.pair)
    checks, lines = record_calls(reference, moving)
    pairs = sum(len(c[2]) for c in checks)
    terms = sum(int(c[6].sum()) * len(c[7]) * c[1][0].size for c in lines)
    print(f"{args.pair}: {len(checks)} uniqueness calls ({pairs} pairs), {len(lines)} "
          f"strip_correlation calls ({terms / 1e6:.1f} M correlation terms)")

    sides_check = {"now": reliability.uniqueness}
    sides_line = {"now": kernels.strip_correlation}
    with tempfile.TemporaryDirectory() as folder:
        if args.rev:
            old_kernels, old_reliability = load_revision(args.rev, Path(folder))
            sides_check = {args.rev: old_reliability.uniqueness, **sides_check}
            if hasattr(old_kernels, "strip_correlation"):
                sides_line = {args.rev: old_kernels.strip_correlation, **sides_line}

        causes = {name: [f(*c).cause for c in checks] for name, f in sides_check.items()}
        timed = best_times({name: (lambda f=f: [f(*c) for c in checks])
                            for name, f in sides_check.items()}, args.repeat)
        report("uniqueness", timed, same_causes(causes))

        outputs = {}
        for name, f in sides_line.items():
            outputs[name] = []
            for c in lines:
                out = np.full_like(c[8], np.nan)
                f(*c[:8], out)
                outputs[name].append(out)
        timed = best_times({name: (lambda f=f: [f(*c) for c in lines])
                            for name, f in sides_line.items()}, args.repeat)
        report("strip_correlation", timed, same_correlations(outputs, lines))

        results: dict[str, Any] = {}

        def registration(name: str) -> Callable[[], None]:
            def run() -> None:
                with patched(sides_check[name], sides_line.get(name, kernels.strip_correlation)):
                    results[name] = pwlreg.register(reference, moving)
            return run

        timed = best_times({name: registration(name) for name in sides_check},
                           max(1, args.repeat // 2))
        report("register", timed, same_vertices(results))
    return 0


def same_causes(causes: dict[str, list]) -> str:
    first, *others = causes.values()
    differ = sum(int(np.sum(a != b)) for other in others for a, b in zip(first, other,
                                                                          strict=True))
    return "" if not others else ("causes identical" if not differ
                                  else f"{differ} pairs of different cause")


def same_correlations(outputs: dict[str, list], lines: list) -> str:
    first, *others = outputs.values()
    if not others:
        return ""
    worst = 0.0
    for a, b, c in zip(first, others[0], lines, strict=True):
        written = np.arange(a.shape[1])[None, :] < c[6][:, None]
        worst = max(worst, float(np.max(np.abs(a[written] - b[written]), initial=0.0)))
    return "bit for bit identical" if worst == 0 else f"largest difference {worst:.3g}"


def same_vertices(results: dict[str, Any]) -> str:
    first, *others = results.values()
    if not others:
        return f"{len(first.reference_vertices)} vertices"
    other = others[0]
    same = (np.array_equal(first.reference_vertices, other.reference_vertices)
            and np.array_equal(first.moving_vertices, other.moving_vertices)
            and np.array_equal(first.final_triangles, other.final_triangles))
    return (f"{len(other.reference_vertices)} vertices, "
            + ("identical" if same else "DIFFERENT"))


def report(what: str, timed: dict[str, float], note: str) -> None:
    sides = ", ".join(f"{name} {t * 1e3:.1f} ms" for name, t in timed.items())
    print(f"  {what}: {sides} (best of runs){'; ' + note if note else ''}")


if __name__ == "__main__":
    sys.exit(main())
