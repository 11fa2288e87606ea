"""Speed of the automatic path against an earlier revision: ``python -m bench.auto_speed
[--rev REV] [--rounds N] [--repeat N]``.

Times ``register(reference, moving)`` with default options (automatic matching, guided
insertion, ``extent="frame"``) on the 1024x768 synthetic city of :func:`bench.trust.speed_section`
and, when the real data is there, the 1024x682 facade pair. Each tree runs in a process of its
own (kernels warmed up and each pair registered once first, the kernels loaded from numba's
cache that a first process of the tree wrote), and the two processes take turns
registration by registration (which goes first alternates), so that the ratio of each
adjacent pair of registrations sees the same state of the shared machine: its speed drifts by
20-30 % over seconds, which blocks of whole runs took as a difference between the trees. The
report gives, per pair, the median of those ratios and their spread, and the ratio of the two
trees' best times; then the median ratio of their CPU times (all threads), the work each does,
which a second core busy with other work changes less than the wall time. The old tree is a
``git worktree`` of ``--rev`` in a temporary directory, imported through a package shim
(``pwlreg/`` with its ``core`` and ``service`` linked in), because the editable install maps
``pwlreg`` to this checkout. Both trees register the same
images, written once by this one. The default revision is the code at the filing of issue
#10, whose bound is 2 x.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from bench import realdata
from bench.scenes import make_scene

ROOT = Path(__file__).resolve().parents[1]

#: Run in each tree's process: loads the pairs, warms up, then registers the pair whose index
#: it reads on each line of its input and answers with the seconds it took, wall and CPU (all
#: the process's threads).
CHILD = """
import sys, time
import numpy as np
from pwlreg import register
from pwlreg.core.pipeline import warm_up
warm_up()
pairs = [np.load(path) for path in sys.argv[1:]]
pairs = [(p["reference"], p["moving"]) for p in pairs]
for ref, mov in pairs:
    register(ref, mov)
print("ready", flush=True)
for line in sys.stdin:
    ref, mov = pairs[int(line)]
    t, c = time.perf_counter(), time.process_time()
    register(ref, mov)
    print(time.perf_counter() - t, time.process_time() - c, flush=True)
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


class _Tree:
    """A child process of one tree that registers a pair when asked."""

    def __init__(self, shim: Path, paths: list[Path]) -> None:
        self.process = subprocess.Popen(
            [sys.executable, "-c", CHILD, *map(str, paths)], cwd=shim,
            env={"PYTHONPATH": str(shim), "PATH": "/usr/bin:/bin"},
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        if self.process.stdout.readline().strip() != "ready":
            raise RuntimeError(f"the tree in {shim} did not start")

    def time(self, pair: int) -> tuple[float, float]:
        """Wall and CPU seconds of one registration of the pair ``pair``."""
        self.process.stdin.write(f"{pair}\n")
        self.process.stdin.flush()
        wall, cpu = self.process.stdout.readline().split()
        return float(wall), float(cpu)

    def close(self) -> None:
        self.process.stdin.close()
        self.process.wait(timeout=60)


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
            names = list(paths)
            shims = {"new": _shim(ROOT, work, "new"), "old": _shim(old, work, "old")}
            # A first process per tree compiles its kernels into numba's cache and the timed
            # one loads them, as a service does after its first start: code compiled in the
            # process itself ran 6-9 % slower (the same tree timed against itself, one cache
            # warm and one cold, 0.91-0.93 x).
            for shim in shims.values():
                _Tree(shim, list(paths.values())).close()
            trees = {label: _Tree(shim, list(paths.values())) for label, shim in shims.items()}
            times = {(name, label): [] for name in names for label in trees}
            ratios: dict[str, list[float]] = {name: [] for name in names}
            work: dict[str, list[float]] = {name: [] for name in names}
            print(f"register(), {args.rounds} x {args.repeat} turns per pair, seconds: this "
                  f"tree against {args.rev}")
            try:
                for r in range(args.rounds):
                    for k, name in enumerate(names):
                        for j in range(args.repeat):
                            order = ("new", "old") if (r + j) % 2 == 0 else ("old", "new")
                            took = {label: trees[label].time(k) for label in order}
                            for label, (t, _) in took.items():
                                times[(name, label)].append(t)
                            ratios[name].append(took["new"][0] / took["old"][0])
                            work[name].append(took["new"][1] / took["old"][1])
                        print(f"  round {r + 1}  {name:28s} median "
                              f"{np.median(times[(name, 'new')][-args.repeat:]):.3f} against "
                              f"{np.median(times[(name, 'old')][-args.repeat:]):.3f}  "
                              f"{np.median(ratios[name][-args.repeat:]):.2f} x", flush=True)
            finally:
                for tree in trees.values():
                    tree.close()
            for name, values in ratios.items():
                best = min(times[(name, "new")]) / min(times[(name, "old")])
                q1, q3 = np.percentile(values, [25, 75])
                print(f"{name:28s} ratio median {np.median(values):.2f} x (quartiles "
                      f"{q1:.2f}-{q3:.2f}, {len(values)} turns), best times "
                      f"{min(times[(name, 'new')]):.3f} / {min(times[(name, 'old')]):.3f} s: "
                      f"{best:.2f} x")
                print(f"{'':28s} CPU time ratio median {np.median(work[name]):.2f} x (quartiles "
                      f"{np.percentile(work[name], 25):.2f}-{np.percentile(work[name], 75):.2f})")
        finally:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(old)],
                           check=False, capture_output=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
