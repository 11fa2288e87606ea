"""Pages for people: the web viewer (the HTML of ``/``) and the API documentation (Swagger UI at
``/docs``, ReDoc at ``/redoc``), all served from the package's own files under ``/static``.

The viewer is static HTML and JavaScript (no build step); it talks to the API like any client,
with the API key the user gives it when keys are configured. Nothing is loaded from another host:
Swagger UI, ReDoc and three.js are vendored under ``static/vendor/`` with their licences.
"""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter, Request
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html
from fastapi.responses import FileResponse, HTMLResponse
from fastapi.staticfiles import StaticFiles

STATIC_DIR = Path(__file__).resolve().parents[1] / "static"
"""The viewer's files and the vendored scripts (package data of ``pwlreg.service``)."""
STATIC_URL = "/static"

CONTENT_SECURITY_POLICY = (
    "default-src 'self'; script-src 'self' 'unsafe-inline' blob:; "
    "style-src 'self' 'unsafe-inline'; img-src 'self' data: blob:; font-src 'self' data:; "
    "connect-src 'self' blob: data:; worker-src 'self' blob:; frame-ancestors 'self'"
)
"""Of every page: the browser itself refuses to load anything from another host (ReDoc's bundle,
for one, shows its logo from cdn.redoc.ly; the policy keeps that request from leaving, and the
logo is not shown). Inline scripts: the import map and the docs' start-up scripts."""

router = APIRouter(include_in_schema=False)


def _root(request: Request) -> str:
    return request.scope.get("root_path", "").rstrip("/")


def static_files() -> StaticFiles:
    """The ASGI app serving :data:`STATIC_DIR`, mounted at :data:`STATIC_URL`."""
    return StaticFiles(directory=STATIC_DIR)


def index_page(request: Request) -> FileResponse:
    """The viewer's page: the HTML answer of ``/`` (the JSON landing page is another router's;
    it calls this for browsers)."""
    return FileResponse(STATIC_DIR / "index.html", media_type="text/html",
                        headers={"Cache-Control": "no-cache",
                                 "Content-Security-Policy": CONTENT_SECURITY_POLICY})


def _with_policy(page: HTMLResponse) -> HTMLResponse:
    page.headers["Content-Security-Policy"] = CONTENT_SECURITY_POLICY
    return page


@router.get("/docs")
def swagger_ui(request: Request) -> HTMLResponse:
    root = _root(request)
    vendor = f"{root}{STATIC_URL}/vendor/swagger-ui"
    return _with_policy(get_swagger_ui_html(
        openapi_url=f"{root}/openapi.json",
        title="pwlreg - API",
        swagger_js_url=f"{vendor}/swagger-ui-bundle.js",
        swagger_css_url=f"{vendor}/swagger-ui.css",
        swagger_favicon_url=f"{vendor}/favicon-32x32.png",
        # No call to the public validator (validator.swagger.io) from the page.
        swagger_ui_parameters={"validatorUrl": None},
    ))


@router.get("/redoc")
def redoc(request: Request) -> HTMLResponse:
    root = _root(request)
    return _with_policy(get_redoc_html(
        openapi_url=f"{root}/openapi.json",
        title="pwlreg - API",
        redoc_js_url=f"{root}{STATIC_URL}/vendor/redoc/redoc.standalone.js",
        redoc_favicon_url=f"{root}{STATIC_URL}/vendor/swagger-ui/favicon-32x32.png",
        with_google_fonts=False,
    ))
