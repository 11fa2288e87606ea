"""The ``pwlreg`` command: ``register`` locally, ``submit`` to a real server, option flags
derived from the options model."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from pwlreg.core.options import RegistrationOptions
from pwlreg.core.results import RESULTS
from pwlreg.service.cli import build_parser, options_from_args
from tests.service.helpers import REPO, Pair, Server, free_port, make_pair

# Every declared result but the GeoTIFF, which needs a georeferenced reference.
RESULT_FILES = {fmt.filename for fmt in RESULTS.values()} - {"registered.tif"}


def pwlreg(*args: str, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.run([sys.executable, "-m", "pwlreg.service.cli", *args], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=timeout, check=False)


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory, pair: Pair) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("cli-inputs")
    paths = {
        "reference": root / "reference.png",
        "moving": root / "moving.png",
        "points": root / "points.json",
        "points_csv": root / "points.csv",
        "not_image": root / "notes.txt",
    }
    paths["reference"].write_bytes(pair.reference_png)
    paths["moving"].write_bytes(pair.moving_png)
    paths["points"].write_bytes(pair.points_json)
    paths["points_csv"].write_bytes(pair.points_csv())
    paths["not_image"].write_text("hello")
    return paths


def test_register_writes_every_result(files: dict[str, Path], tmp_path: Path) -> None:
    out = tmp_path / "out"
    run = pwlreg("register", str(files["reference"]), str(files["moving"]), "--points",
                 str(files["points_csv"]), "--out", str(out), "--bins", "20", "--cost", "ncc")
    assert run.returncode == 0, run.stderr
    assert {p.name for p in out.iterdir()} == RESULT_FILES
    lines = run.stdout.strip().splitlines()
    assert len(lines) == 1 and "triangles" in lines[0]
    mesh = json.loads((out / "mesh.json").read_text())
    assert mesh["parameters"]["bins"] == 20 and mesh["parameters"]["cost"] == "ncc"


@pytest.mark.parametrize(
    ("args", "expected"),
    [
        (["{reference}", "{missing}"], "No such file"),
        (["{reference}", "{not_image}"], "moving"),
        (["{reference}", "{moving}", "--bins", "1"], "options.bins"),
        (["{reference}", "{moving}", "--points", "{not_image}"], "points"),
    ],
)
def test_register_bad_input_exits_non_zero_without_traceback(
    files: dict[str, Path], tmp_path: Path, args: list[str], expected: str
) -> None:
    names = {k: str(v) for k, v in files.items()} | {"missing": str(tmp_path / "nope.png")}
    run = pwlreg("register", *[a.format(**names) for a in args], "--out", str(tmp_path / "o"))
    assert run.returncode == 2, (run.stdout, run.stderr)
    assert "Traceback" not in run.stderr
    assert run.stderr.startswith("pwlreg register: error:") and expected in run.stderr


def test_submit_uploads_follows_and_downloads(
    server: Server, files: dict[str, Path], tmp_path: Path
) -> None:
    out = tmp_path / "results"
    run = pwlreg("submit", str(files["reference"]), str(files["moving"]), "--points",
                 str(files["points"]), "--url", server.url, "--out", str(out), "--bins", "24",
                 "--poll-interval", "0.1")
    assert run.returncode == 0, run.stderr
    assert {p.name for p in out.iterdir()} == RESULT_FILES
    assert (out / "registered.png").read_bytes()[:4] == b"\x89PNG"
    mesh = json.loads((out / "mesh.json").read_text())
    assert mesh["parameters"]["bins"] == 24
    assert "job " in run.stderr  # the job URL is shown
    assert "triangles" in run.stdout


def test_submit_reports_a_failed_job_and_an_unreachable_server(
    server: Server, files: dict[str, Path], tmp_path: Path, pair: Pair
) -> None:
    two = tmp_path / "two.json"
    two.write_text(json.dumps({"reference": pair.reference_points[:2].tolist(),
                               "moving": pair.moving_points[:2].tolist()}))
    run = pwlreg("submit", str(files["reference"]), str(files["moving"]), "--points", str(two),
                 "--url", server.url, "--out", str(tmp_path / "o"), "-q")
    assert run.returncode == 1 and "422" in run.stderr and "points" in run.stderr  # refused

    unrelated = tmp_path / "unrelated.png"  # nothing to match: the job fails
    unrelated.write_bytes(make_pair(seed=99).moving_png)
    run = pwlreg("submit", str(files["reference"]), str(unrelated), "--url", server.url,
                 "--out", str(tmp_path / "o"), "-q")
    assert run.returncode == 1 and "failed" in run.stderr and "Traceback" not in run.stderr

    run = pwlreg("submit", str(files["reference"]), str(files["not_image"]), "--url", server.url,
                 "--out", str(tmp_path / "o"), "-q")
    assert run.returncode == 1 and "415" in run.stderr and "moving" in run.stderr

    run = pwlreg("submit", str(files["reference"]), str(files["moving"]), "--url",
                 f"http://127.0.0.1:{free_port()}", "--out", str(tmp_path / "o"), "-q")
    assert run.returncode == 1 and "cannot reach" in run.stderr and "Traceback" not in run.stderr


def test_option_flags_are_derived_from_the_options_model() -> None:
    parser = build_parser()
    for command in ("register", "submit"):
        args = parser.parse_args([command, "r.png", "m.png", "--out", "o"])
        assert options_from_args(args) == {}  # nothing given, core's defaults apply
        flags = {a.dest for a in parser._subparsers._group_actions[0].choices[command]._actions}
        assert set(RegistrationOptions.model_fields) <= flags
    args = parser.parse_args(["register", "r", "m", "--out", "o", "--cost", "ncc",
                              "--no-epipolar-filter", "--min-triangle-area", "12.5",
                              "--optimizer", "morris-kanade"])
    assert options_from_args(args) == {"cost": "ncc", "epipolar_filter": False,
                                       "min_triangle_area": 12.5, "optimizer": "morris-kanade"}
    with pytest.raises(SystemExit):
        parser.parse_args(["register", "r", "m", "--out", "o", "--cost", "entropy"])
