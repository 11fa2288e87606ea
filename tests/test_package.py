"""pwlreg as a library: one top-level package in the distribution, and the in-process API."""

import json
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import cv2
import numpy as np
import pytest

import pwlreg
from tests.core.synthetic import book_points, open_book

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_the_wheel_installs_one_top_level_package(tmp_path: Path) -> None:
    source = tmp_path / "src"  # a copy, so that the build leaves nothing in the repository
    source.mkdir()
    for part in ("pyproject.toml", "README.md"):
        shutil.copy(REPO / part, source / part)
    for part in ("pwlreg", "core", "service"):
        shutil.copytree(REPO / part, source / part, ignore=shutil.ignore_patterns("__pycache__"))
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(tmp_path),
                    str(source)], check=True, cwd=tmp_path)
    (wheel,) = tmp_path.glob("pwlreg-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    tops = {name.split("/")[0] for name in names if not name.split("/")[0].endswith(".dist-info")}
    assert tops == {"pwlreg"}, tops
    for module in ("pwlreg/__init__.py", "pwlreg/core/pipeline.py", "pwlreg/service/app.py",
                   "pwlreg/service/api/jobs.py"):
        assert module in names
    entry = next(n for n in names if n.endswith("entry_points.txt"))
    assert "pwlreg = pwlreg.service.cli:main" in zipfile.ZipFile(wheel).read(entry).decode()


def test_register_takes_paths_points_files_and_keyword_options(tmp_path: Path) -> None:
    ref, mov = open_book()
    rp, mp = book_points()
    cv2.imwrite(str(tmp_path / "ref.png"), ref)
    cv2.imwrite(str(tmp_path / "mov.png"), mov)
    (tmp_path / "points.json").write_text(json.dumps({"reference": rp.tolist(),
                                                      "moving": mp.tolist()}))
    from_files = pwlreg.register(tmp_path / "ref.png", str(tmp_path / "mov.png"),
                                 tmp_path / "points.json", epipolar_filter=False)
    from_arrays = pwlreg.register(ref, mov, (rp, mp), options={"epipolar_filter": False})
    assert from_files.options.epipolar_filter is False
    np.testing.assert_array_equal(from_files.final_triangles, from_arrays.final_triangles)
    paths = pwlreg.write_outputs(from_files, tmp_path / "out")
    assert json.loads(paths["mesh"].read_text())["final_triangles"]


def test_register_reports_bad_options_and_inputs() -> None:
    ref, mov = open_book()
    with pytest.raises(pwlreg.InputError):
        pwlreg.register(ref, mov, optimizer="no-such-optimizer")
    with pytest.raises(pwlreg.InputError):
        pwlreg.register(b"not an image", mov)
    with pytest.raises(pwlreg.InputError, match="2-D"):
        pwlreg.register(ref[0], mov)
    with pytest.raises(pwlreg.InputError, match="got list"):
        pwlreg.register(ref.tolist(), mov)
    with pytest.raises(pwlreg.InputError, match="mapping"):
        pwlreg.register(ref, mov, options="bins=32")
    # As the service refuses them in a points file: not dropped silently.
    rp, mp = book_points()
    rp[3, 1] = np.nan
    with pytest.raises(pwlreg.InputError, match="non-finite"):
        pwlreg.register(ref, mov, (rp, mp))


def test_register_takes_the_moving_geotiffs_own_gcps(tmp_path: Path) -> None:
    from rasterio.control import GroundControlPoint

    from tests.core.gis import UTM, geotiff, make_pair, map_coords

    pair = make_pair(bands=1)
    gcps = [GroundControlPoint(row=y + 0.5, col=x + 0.5, x=mx, y=my)
            for (x, y), (mx, my) in zip(pair.moving_points.tolist(),
                                        map_coords(pair.reference_points).tolist(), strict=True)]
    (tmp_path / "ref.tif").write_bytes(geotiff(pair.reference))
    (tmp_path / "mov.tif").write_bytes(geotiff(pair.moving, transform=None, gcps=gcps,
                                               gcp_crs=UTM))
    options = {"epipolar_filter": False, "insert_vertices": "never"}
    from_gcps = pwlreg.register(tmp_path / "ref.tif", tmp_path / "mov.tif", "gcps", **options)
    from_arrays = pwlreg.register(tmp_path / "ref.tif", tmp_path / "mov.tif",
                                  (pair.reference_points, pair.moving_points), **options)
    np.testing.assert_array_equal(from_gcps.final_triangles, from_arrays.final_triangles)
