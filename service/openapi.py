"""The OpenAPI document of the service, exported to ``openapi/openapi.json``.

Run ``python -m pwlreg.service.openapi`` after changing the API; a test fails while the file is
out of date.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from pwlreg.service.app import create_app
from pwlreg.service.settings import Settings

OPENAPI_PATH = Path(__file__).resolve().parents[1] / "openapi" / "openapi.json"
"""Where the exported document lives in the repository."""


def openapi_document() -> dict[str, Any]:
    """The OpenAPI document generated from the application (nothing is started)."""
    return create_app(Settings(_env_file=None)).openapi()  # type: ignore[call-arg]


def render(doc: dict[str, Any]) -> str:
    """The document as stable, reviewable JSON text."""
    return json.dumps(doc, indent=2, ensure_ascii=False) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    """Write the document to the given path (default: ``openapi/openapi.json``)."""
    args = list(sys.argv[1:] if argv is None else argv)
    path = Path(args[0]) if args else OPENAPI_PATH
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(render(openapi_document()))
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
