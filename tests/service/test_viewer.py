"""The viewer's page, its files and the API docs, over real HTTP: everything a page loads comes
from the service itself (no CDN, no outside font)."""

from __future__ import annotations

import re
from html.parser import HTMLParser
from urllib.parse import urljoin, urlsplit

from pwlreg.service.api.viewer import STATIC_DIR

BROWSER = {"Accept": "text/html,application/xhtml+xml,application/xml;q=0.9,*/*;q=0.8"}


class Assets(HTMLParser):
    """The URLs a page loads: scripts, style sheets, icons, images, import-map entries."""

    def __init__(self) -> None:
        super().__init__()
        self.urls: list[str] = []
        self._importmap = False

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        a = dict(attrs)
        if tag == "script" and a.get("src"):
            self.urls.append(a["src"])
        self._importmap = tag == "script" and a.get("type") == "importmap"
        if tag == "link" and a.get("href"):
            self.urls.append(a["href"])
        if tag == "img" and a.get("src"):
            self.urls.append(a["src"])

    def handle_data(self, data: str) -> None:
        if self._importmap:
            self.urls += re.findall(r'"(\./[^"]+\.js)"', data)


def assets(html: str) -> list[str]:
    parser = Assets()
    parser.feed(html)
    return parser.urls


def test_browsers_get_the_viewer_and_json_clients_the_landing_page(server):
    with server.client() as client:
        page = client.get("/", headers=BROWSER)
        assert page.status_code == 200
        assert page.headers["content-type"].startswith("text/html")
        assert '<form id="submit-form"' in page.text
        landing = client.get("/", headers={"Accept": "application/json"})
        assert landing.status_code == 200 and landing.json()["links"]


def test_every_file_the_pages_load_is_served_by_the_service(server):
    with server.client() as client:
        for path in ("/", "/docs", "/redoc"):
            html = client.get(path, headers=BROWSER).text
            urls = assets(html)
            assert urls, path
            for url in urls:
                absolute = urljoin(f"{server.url}{path}", url)
                assert urlsplit(absolute).netloc == urlsplit(server.url).netloc, (path, url)
                answer = client.get(absolute)
                assert answer.status_code == 200, (path, url)
        # The scripts' own imports resolve too (three.js and its add-ons, the viewer's modules).
        for module in ("static/app.js", "static/view3d.js",
                       "static/vendor/three/addons/loaders/GLTFLoader.js"):
            source = client.get(f"/{module}").text
            for imported in re.findall(r"""from\s+["'](\.{1,2}/[^"']+)["']""", source):
                assert client.get(urljoin(f"/{module}", imported)).status_code == 200, imported
        swagger = client.get("/docs").text
        assert '"validatorUrl": null' in swagger  # no call to validator.swagger.io
        assert "fonts.googleapis" not in client.get("/redoc").text


def test_no_page_of_ours_refers_to_another_host():
    for path in STATIC_DIR.glob("*"):
        if path.is_file():
            text = path.read_text()
            assert not re.search(r"""(src|href)=["']?(https?:)?//""", text), path
            assert "@import" not in text and "url(http" not in text, path


def test_vendored_files_come_with_their_licences():
    vendor = STATIC_DIR / "vendor"
    for package, licence in (("three", "LICENSE"), ("swagger-ui", "LICENSE"),
                             ("redoc", "LICENSE")):
        assert (vendor / package / licence).read_text().strip(), package
    versions = (vendor / "README.md").read_text()
    for package in ("three", "swagger-ui-dist", "redoc"):
        assert package in versions
