"""Speed of the automatic path against an earlier revision: ``python -m bench.auto_speed
[--rev REV] [--rounds N] [--repeat N]``.

Times ``register(reference, moving)`` with default options (automatic matching, guided
insertion, ``extent="frame"``) on the 1024x768 synthetic city of :func:`bench.trust.speed_section`
and, when the real data is there, the 1024x682 facade pair. Each tree runs in a fresh process
(kernels warmed up first) that reports the best of ``--repeat`` registrations per pair; the two
trees alternate ``--rounds`` times, so a drift of the shared machine's speed hits both. The old
tree is a ``git worktree`` of ``--rev`` in a temporary directory, imported through a package
shim (``pwlreg/`` with its ``core`` and ``service`` linked in), because the editable install
maps ``pwlreg`` to this checkout. Both trees register the same images, written once by this
one. The default revision is the code at the filing of issue #10, whose bound is 2 x.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from bench import realdata
from bench.scenes import make_scene

ROOT = Path(__file__).resolve().parents[1]

#: Run in each tree's process: best time per pair, as JSON on the last line.
CHILD = """
import json, sys, time
import numpy as np
from pwlreg import register
from pwlreg.core.pipeline import warm_up
warm_up()
best = {}
for path in sys.argv[2:]:
    data = np.load(path)
    times = []
    for _ in range(int(sys.argv[1])):
        t = time.perf_counter()
        register(data["reference"], data["moving"])
        times.append(time.perf_counter() - t)
    best[path] = min(times)
print(json.dumps(best))
"""


def _pairs(work: Path) -> dict[str, Path]:
    scene = make_scene("city", 3, size=(1024, 768), camera="perspective",
                       radiometric="lighting", noise=3.0, baseline=12.0)
    images = {"city 1024x768 (synthetic)": (scene.reference, scene.moving)}
    facade = realdata.default_root() / "lightglue_facade"
    if facade.is_dir():
        images["facade 1024x682 (real)"] = (realdata.read_image(facade / "DSC_0410.JPG"),
                                            realdata.read_image(facade / "DSC_0411.JPG"))
    paths = {}
    for n, (name, (ref, mov)) in enumerate(images.items()):
        paths[name] = work / f"pair{n}.npz"
        np.savez(paths[name], reference=ref, moving=mov)
    return paths


def _shim(tree: Path, work: Path, label: str) -> Path:
    """A folder whose ``pwlreg`` package is ``tree``'s."""
    shim = work / label
    (shim / "pwlreg").mkdir(parents=True)
    shutil.copy(tree / "pwlreg" / "__init__.py", shim / "pwlreg" / "__init__.py")
    for sub in ("core", "service"):
        (shim / "pwlreg" / sub).symlink_to(tree / sub)
    return shim


def _run(shim: Path, paths: dict[str, Path], repeat: int) -> dict[str, float]:
    out = subprocess.run(
        [sys.executable, "-c", CHILD, str(repeat), *map(str, paths.values())],
        cwd=shim, env={"PYTHONPATH": str(shim), "PATH": "/usr/bin:/bin"},
        capture_output=True, text=True, check=True, timeout=1800,
    )
    best = json.loads(out.stdout.strip().splitlines()[-1])
    return {name: best[str(path)] for name, path in paths.items()}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.auto_speed", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rev", default="f6c21bb^", help="git revision to compare with")
    parser.add_argument("--rounds", type=int, default=4, help="alternations of the two trees")
    parser.add_argument("--repeat", type=int, default=5, help="registrations per pair and run")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="pwlreg-auto-speed-") as tmp:
        work = Path(tmp)
        old = work / "old-tree"
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(old),
                        args.rev], check=True, capture_output=True)
        try:
            paths = _pairs(work)
            shims = {"new": _shim(ROOT, work, "new"), "old": _shim(old, work, "old")}
            ratios: dict[str, list[float]] = {name: [] for name in paths}
            print(f"register() best of {args.repeat}, seconds: this tree against {args.rev}")
            for r in range(args.rounds):
                times = {label: _run(shim, paths, args.repeat) for label, shim in shims.items()}
                for name in paths:
                    new, old_s = times["new"][name], times["old"][name]
                    ratios[name].append(new / old_s)
                    print(f"  round {r + 1}  {name:28s} {new:.3f} against {old_s:.3f}  "
                          f"{new / old_s:.2f} x", flush=True)
            for name, values in ratios.items():
                print(f"{name:28s} ratio {min(values):.2f}-{max(values):.2f} x, median "
                      f"{np.median(values):.2f} x")
        finally:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(old)],
                           check=False, capture_output=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
