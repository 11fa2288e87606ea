"""End to end in a real browser: Debian's chromium, headless, driven by Playwright, against a
real server. Uploads a pair through the viewer's form, waits for the job to succeed and checks
that the overlays, the plot, the comparison and the 3D view appear, with no request leaving
127.0.0.1. Screenshots are saved in the test's tmp folder.
"""

from __future__ import annotations

import io
import json
import os
import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path
from urllib.parse import urlsplit

import cv2
import numpy as np
import pytest
from PIL import Image

from tests.core.synthetic import book_map, open_book

pytestmark = pytest.mark.slow

CHROMIUM = "/usr/bin/chromium"
# The machine notes' flags: no sandbox as root, no GPU, and none of chromium's own calls home
# (this network refuses them). WebGL runs on SwiftShader, the CPU implementation.
FLAGS = ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]
SCREENSHOTS = os.environ.get("PWLREG_SCREENSHOTS_TO")
"""A folder to copy two screenshots into (the README's pictures), when set."""


def chromium() -> str:
    """Path of Debian's chromium, installed with apt-get when absent (as .ci/run does)."""
    if not Path(CHROMIUM).exists() and shutil.which("apt-get") and os.geteuid() == 0:
        install = ["apt-get", "install", "-y", "-q", "chromium"]
        if subprocess.run(install, capture_output=True, timeout=600, check=False).returncode:
            subprocess.run(["apt-get", "update", "-q"], capture_output=True, timeout=600,
                           check=False)
            subprocess.run(install, capture_output=True, timeout=600, check=False)
    if not Path(CHROMIUM).exists():
        pytest.skip(f"no browser: {CHROMIUM} is absent and could not be installed with apt-get "
                    "(needs root and Debian's package sources)")
    return CHROMIUM


@pytest.fixture(scope="module")
def browser() -> Iterator[object]:
    sync_api = pytest.importorskip("playwright.sync_api")
    path = chromium()
    with sync_api.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=path, headless=True, args=FLAGS)
        yield browser
        browser.close()


class Offsite:
    """Route handler of a browser context: lets requests to 127.0.0.1 through, counts and
    aborts every other one."""

    def __init__(self) -> None:
        self.requests: list[str] = []

    def __call__(self, route) -> None:
        url = route.request.url
        if urlsplit(url).hostname == "127.0.0.1":
            route.continue_()
        else:
            self.requests.append(url)
            route.abort()


def book_pair(folder: Path) -> tuple[Path, Path, Path]:
    """The open book (two planes meeting at a crease) at 480 x 360, with a grid of true points:
    its affine reconstruction has a relief."""
    ref, mov = open_book((480, 360), crease=240.0, seed=5)
    xs, ys = np.meshgrid([12, 96, 180, 240, 300, 384, 466], [10, 95, 180, 265, 349])
    grid = np.stack([xs.ravel(), ys.ravel()], axis=1).astype(float)
    mx, my = book_map(grid[:, 0], grid[:, 1], 240.0)
    inside = my <= 359  # the right page is sheared down: its lowest points leave the image
    grid, mx, my = grid[inside], mx[inside], my[inside]
    paths = folder / "reference.png", folder / "moving.png", folder / "points.json"
    cv2.imwrite(str(paths[0]), ref)
    cv2.imwrite(str(paths[1]), mov)
    paths[2].write_text(json.dumps({"reference": grid.tolist(),
                                    "moving": np.stack([mx, my], axis=1).tolist()}))
    return paths


def not_blank(png: bytes) -> float:
    """Standard deviation of a screenshot's grey levels (0 for a blank picture)."""
    image = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_GRAYSCALE)
    return float(image.std())


def loaded(page, selector: str) -> None:
    page.wait_for_function(
        "s => { const i = document.querySelector(s); return i && i.complete && i.naturalWidth }",
        arg=selector, timeout=30_000)


def test_upload_through_the_form_and_see_the_results(browser, server, tmp_path):
    reference, moving, points = book_pair(tmp_path)
    offsite = Offsite()
    context = browser.new_context(viewport={"width": 1280, "height": 900})
    context.route("**/*", offsite)
    page = context.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.goto(f"{server.url}/")
    # The options are generated from /v1/options.
    page.wait_for_selector('[data-option="bins"]', state="attached")
    assert page.locator("[data-option]").count() >= 10
    page.set_input_files('input[name="reference"]', reference)
    page.set_input_files('input[name="moving"]', moving)
    page.set_input_files('input[name="points"]', points)
    page.click("summary")
    page.fill('[data-option="bins"]', "32")
    page.click("#submit-button")
    page.wait_for_selector(
        "#job-status.successful, #job-status.failed, #submit-error:not([hidden])", timeout=60_000)
    assert page.get_attribute("#job-status", "class") == "status successful", (
        page.inner_text("#submit-error") + page.inner_text("#job-error"))
    assert "points (client)" in page.inner_text("#job-message")
    for image in ("#mesh-image", "#checkerboard", "#difference", "#consistency", "#convergence",
                  "#compare-base", "#compare-top"):
        loaded(page, image)
    page.wait_for_selector('#view3d[data-ready="1"]', timeout=30_000)
    triangles = int(page.get_attribute("#view3d", "data-triangles"))
    assert triangles > 10
    # The job's options reached the service.
    job_id = page.inner_text("#job-id")
    with server.client() as client:
        job = client.get(f"/v1/jobs/{job_id}").json()
    assert job["options"]["bins"] == 32 and job["has_points"]
    # The pictures are what the service made: the mesh overlay has the reference's size.
    size = page.evaluate("() => [document.querySelector('#mesh-image').naturalWidth,"
                         " document.querySelector('#mesh-image').naturalHeight]")
    assert size == [480, 360]

    shots = {
        "mesh": page.locator("#mesh-image").screenshot(path=tmp_path / "mesh.png"),
        "compare": page.locator("#compare").screenshot(path=tmp_path / "compare.png"),
        "convergence": page.locator("#convergence").screenshot(path=tmp_path / "plot.png"),
        "view3d": page.locator("#view3d").screenshot(path=tmp_path / "view3d.png"),
    }
    spread = {name: not_blank(png) for name, png in shots.items()}
    print(f"\nscreenshots in {tmp_path}; grey-level spread {spread}")
    assert spread["view3d"] > 10  # the textured reconstruction, not the empty background
    # The other topology (the swapped quads differ) is another picture; then the blink.
    page.click('#scene-tabs button[data-scene="1"]')
    initial = cv2.imdecode(np.frombuffer(page.locator("#view3d").screenshot(), np.uint8),
                           cv2.IMREAD_GRAYSCALE)
    final = cv2.imdecode(np.frombuffer(shots["view3d"], np.uint8), cv2.IMREAD_GRAYSCALE)
    assert initial.shape == final.shape and np.count_nonzero(initial != final) > 100
    page.click("#blink")
    page.wait_for_timeout(700)
    page.click("#blink")
    page.click('.tabs[data-target="mesh-image"] button[data-result="mesh_moving"]')
    loaded(page, "#mesh-image")
    assert not errors, errors
    assert offsite.requests == []
    if SCREENSHOTS:
        page.click('.tabs[data-target="mesh-image"] button[data-result="mesh_reference"]')
        loaded(page, "#mesh-image")
        # The job's summary, the meshes and the comparison, in page coordinates.
        top = page.evaluate("""() => { const r = document.querySelector('#job')
            .getBoundingClientRect(); return {x: r.x + scrollX, y: r.y + scrollY,
            width: r.width, height: 600}; }""")
        save_small(page.screenshot(clip=top, full_page=True), Path(SCREENSHOTS) / "viewer.png")
        page.click('#scene-tabs button[data-scene="0"]')
        save_small(page.locator("#view3d").screenshot(), Path(SCREENSHOTS) / "viewer-3d.png")
    context.close()


def save_small(png: bytes, path: Path, width: int = 900) -> None:
    """A screenshot reduced to ``width`` pixels, for the README."""
    image = Image.open(io.BytesIO(png)).convert("RGB")
    small = image.resize((width, round(image.height * width / image.width)), Image.LANCZOS)
    path.parent.mkdir(parents=True, exist_ok=True)
    small.save(path, optimize=True)


def test_api_docs_load_from_the_service_alone(browser, server):
    offsite = Offsite()
    context = browser.new_context()
    context.route("**/*", offsite)
    page = context.new_page()
    page.goto(f"{server.url}/docs")
    page.wait_for_selector(".swagger-ui .info .title", timeout=30_000)
    assert "pwlreg" in page.inner_text(".swagger-ui .info .title")
    assert page.locator(".opblock").count() > 5
    page.goto(f"{server.url}/redoc")
    page.wait_for_selector("h1", timeout=30_000)
    assert "pwlreg" in page.inner_text("h1")
    assert offsite.requests == []
    context.close()


def test_the_viewer_asks_for_the_api_key(browser, start_server, pair):
    keyed = start_server(PWLREG_API_KEYS="alice:alice-key-123", PWLREG_WORKERS="1")
    with keyed.client() as client:
        created = client.post("/v1/jobs", headers={"Authorization": "Bearer alice-key-123"},
                              files={"reference": ("r.png", pair.reference_png),
                                     "moving": ("m.png", pair.moving_png),
                                     "points": ("p.json", pair.points_json)})
        assert created.status_code == 201
    context = browser.new_context()
    offsite = Offsite()
    context.route("**/*", offsite)
    page = context.new_page()
    page.goto(f"{keyed.url}/")
    page.wait_for_selector("#key-panel:not([hidden])")
    page.fill("#key-input", "wrong-key")
    page.click("#key-form button")
    page.wait_for_selector("#key-panel:not([hidden])")
    assert "refused" in page.inner_text("#key-form label")
    page.fill("#key-input", "alice-key-123")
    page.click("#key-form button")
    page.wait_for_selector(f'#jobs tr[data-job="{created.json()["id"]}"]')
    page.wait_for_selector('[data-option="bins"]', state="attached")
    assert offsite.requests == []
    context.close()
