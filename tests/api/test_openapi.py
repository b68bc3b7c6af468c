"""The OpenAPI schema is valid and documents every route with its error answers."""

from __future__ import annotations

import pytest
from openapi_spec_validator import validate

from app.api.main import create_app
from app.core.settings import Settings

PUBLIC = {("/health", "get"), ("/auth/login", "post")}  # the only routes without a token


@pytest.fixture(scope="module")
def schema() -> dict:
    return create_app(Settings()).openapi()


def operations(schema: dict):
    for path, item in schema["paths"].items():
        for method, operation in item.items():
            if method in {"get", "post", "put", "patch", "delete"}:
                yield path, method, operation


def test_schema_is_valid_openapi(schema: dict) -> None:
    validate(schema)
    assert len(list(operations(schema))) >= 40


def test_every_route_documents_its_errors(schema: dict) -> None:
    undocumented = []
    for path, method, operation in operations(schema):
        codes = {int(c) for c in operation["responses"] if c.isdigit()}
        errors = {c for c in codes if c >= 400}
        needs_login = (path, method) not in PUBLIC
        if not errors or (needs_login and 401 not in errors):
            undocumented.append(f"{method.upper()} {path}: {sorted(codes)}")
        if "{" in path and needs_login and 404 not in errors:
            undocumented.append(f"{method.upper()} {path}: an id in the path but no 404")
        for code in errors - {422}:
            content = operation["responses"][str(code)].get("content", {})
            ref = content.get("application/json", {}).get("schema", {}).get("$ref", "")
            if not ref.endswith("/ErrorBody"):
                undocumented.append(f"{method.upper()} {path}: {code} without the error body")
        if not operation.get("summary") and not operation.get("description"):
            undocumented.append(f"{method.upper()} {path}: no description")
    assert not undocumented, "\n".join(undocumented)
