"""Schemathesis against openapi/openapi.json, on a real server with API keys: no 5xx, and every
answer matches the documented schema (a CI-sized run; ``python -m schemathesis`` can run
longer)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest
import schemathesis
from hypothesis import HealthCheck, settings
from schemathesis.checks import not_a_server_error
from schemathesis.specs.openapi.checks import (
    content_type_conformance,
    response_schema_conformance,
    status_code_conformance,
)

from tests.service.helpers import Server

KEY = "fuzz-key-0123456789"
schema = schemathesis.openapi.from_path(Path(__file__).parents[2] / "openapi" / "openapi.json")


@pytest.fixture(scope="module")
def fuzz_server(start_server: Callable[..., Server]) -> Server:
    return start_server(PWLREG_API_KEYS=f"fuzz:{KEY}")


@schema.parametrize()
@settings(max_examples=8, deadline=None,
          suppress_health_check=list(HealthCheck))
def test_api_answers_within_its_schema(case, fuzz_server: Server) -> None:
    # A schema cannot say "a real photograph": a schema-valid upload may rightly be refused,
    # so the checks are the ones that must always hold. Headers the operation does not declare
    # are not the API's contract: schemathesis sometimes adds malformed ones (an empty
    # "content-length"), which uvicorn's HTTP parser answers with a bare 400 before the app.
    if case.headers:
        declared = {p.name.lower() for p in case.operation.headers}
        case.headers = {k: v for k, v in case.headers.items() if k.lower() in declared}
    case.call_and_validate(
        base_url=fuzz_server.url, headers={"Authorization": f"Bearer {KEY}"}, timeout=30,
        checks=[not_a_server_error, status_code_conformance, content_type_conformance,
                response_schema_conformance],
    )
