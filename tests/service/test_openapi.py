"""The exported OpenAPI document is current and documents every model."""

from __future__ import annotations

import json

from pwlreg.service.openapi import OPENAPI_PATH, openapi_document


def test_openapi_file_is_up_to_date() -> None:
    assert OPENAPI_PATH.is_file(), (
        "openapi/openapi.json is missing: run python -m pwlreg.service.openapi")
    exported = json.loads(OPENAPI_PATH.read_text())
    assert exported == openapi_document(), (
        "openapi/openapi.json is out of date: run python -m pwlreg.service.openapi"
    )


def test_every_model_has_a_description_and_examples() -> None:
    schemas = openapi_document()["components"]["schemas"]
    assert {"StatusInfo", "JobList", "ProblemDetails", "Link", "OptionInfo", "Options"} <= set(
        schemas
    )
    for name, schema in schemas.items():
        assert schema.get("description"), f"{name} has no description"
        if schema.get("type") == "object":
            assert schema.get("examples"), f"{name} has no examples"
            for prop, spec in schema.get("properties", {}).items():
                assert spec.get("description"), f"{name}.{prop} has no description"


def test_errors_are_documented_as_problem_documents() -> None:
    doc = openapi_document()
    for path, operations in doc["paths"].items():
        for method, operation in operations.items():
            for code, response in operation["responses"].items():
                if code[0] in "45":
                    assert list(response["content"]) == ["application/problem+json"], (
                        path, method, code)
    submit = doc["paths"]["/v1/jobs"]["post"]
    form = submit["requestBody"]["content"]["multipart/form-data"]["schema"]
    assert form["required"] == ["reference", "moving"]
    assert set(form["properties"]) == {"reference", "moving", "points", "options", "callback",
                                       "subscriber"}
    assert "Location" in submit["responses"]["201"]["headers"]


def test_readme_documents_every_option_and_setting() -> None:
    from pwlreg.core.options import RegistrationOptions
    from pwlreg.service.settings import Settings

    readme = (OPENAPI_PATH.parents[1] / "README.md").read_text()
    rows = {line.split("|")[1].strip().strip("`"): line.split("|")[3].strip().strip("`")
            for line in readme.splitlines() if line.startswith("| `")}
    for name, field in RegistrationOptions.model_fields.items():
        assert name in rows, f"README: no row for the option {name}"
        assert rows[name].lower() == str(field.default).lower(), (
            f"README: default of {name} is {field.default}, not {rows[name]}"
        )
    for name in Settings.model_fields:
        assert f"`PWLREG_{name.upper()}`" in readme, f"README: setting PWLREG_{name.upper()}"
