"""Numbers and names no column, array or file system can hold are a 4xx naming the field, never
a 500 or a dropped connection (issue 15, section 4), through a real server: the exact probes
of the issue, then every route of the OpenAPI schema probed alike."""

from __future__ import annotations

import json
import math
from collections.abc import Iterator
from typing import Any

import httpx
import pytest

from tests.api.server import Server

BIG = 10**30


@pytest.fixture(scope="module")
def admin(sample_server: Server) -> Iterator[httpx.Client]:
    with sample_server.client() as client:
        yield client


def raw_json(value: Any) -> str:
    """JSON as Python writes it: NaN and Infinity as the bare words, as a sloppy client sends."""
    return json.dumps(value, allow_nan=True)


def send(client: httpx.Client, method: str, url: str, body: Any = None) -> httpx.Response:
    content = None if body is None else raw_json(body)
    headers = {} if body is None else {"content-type": "application/json"}
    return client.request(method, url, content=content, headers=headers)


def assert_refused(response: httpx.Response, field: str) -> None:
    """A 4xx whose one-line detail names FIELD."""
    what = f"{response.request.method} {response.request.url.path[:80]}"
    assert 400 <= response.status_code < 500, f"{what}: {response.status_code} {response.text}"
    detail = response.json()["detail"]
    assert "\n" not in detail and field in detail, f"{what}: {detail!r} does not name {field!r}"


ISSUE_PROBES = [
    ("GET", f"/surveys/{BIG}", None, "survey_id"),
    ("GET", f"/jobs/{BIG}", None, "job_id"),
    ("GET", f"/jobs?survey_id={BIG}", None, "survey_id"),
    ("POST", "/jobs", {"kind": "run:phantom", "survey_id": BIG}, "survey_id"),
    ("GET", f"/jobs/{BIG}/log", None, "job_id"),
    ("DELETE", f"/surveys/{BIG}", None, "survey_id"),
    ("GET", f"/surveys/{BIG}/pillars/stats", None, "survey_id"),
    ("PUT", "/surveys/1/pillars/labels", {"labels": [{"cell_id": 2**63, "label": 1}]}, "cell_id"),
    ("PUT", "/surveys/1/pillars/labels", {"labels": [{"cell_id": 2**70, "label": 1}]}, "cell_id"),
    (
        "PUT",
        "/surveys/1/pillars/labels",
        {"labels": [{"cell_id": 5, "label": 1, "version": BIG}]},
        "version",
    ),
    ("GET", "/surveys/1/pillars/labels?x0=-1e308&y0=-1e308&x1=1e308&y1=1e308", None, "x0"),
    ("GET", "/surveys/1/pillars/labels?x0=0&y0=-1e308&x1=1&y1=1e308", None, "y0"),
    ("GET", "/surveys/1/pillars/labels?x0=nan&y0=0&x1=1&y1=1", None, "x0"),
    ("GET", "/surveys/1/pillars/labels?x0=0&y0=0&x1=inf&y1=1", None, "x1"),
    ("GET", "/surveys/1/pillars/labels?x0=0&y0=0&x1=1&y1=Infinity", None, "y1"),
    ("POST", "/surveys/import", {"path": "a" * 300}, "path"),
    ("POST", "/surveys/import", {"path": "d/" * 2100}, "path"),
    ("GET", "/jobs/1/files/" + "a" * 5000, None, "name"),
    ("GET", "/jobs/1/files/" + "a" * 300, None, "name"),
]
for _x in (1e300, math.nan, math.inf, -math.inf, "nan"):
    for _field in ("x", "y"):
        _label = {"x": 1.0, "y": 1.0, "label": 1, _field: _x}
        ISSUE_PROBES.append(("PUT", "/surveys/1/pillars/labels", {"labels": [_label]}, _field))


@pytest.mark.parametrize(
    "method,url,body,field", ISSUE_PROBES, ids=[f"{p[0]} {p[1][:50]} {p[3]}" for p in ISSUE_PROBES]
)
def test_issue_probes_are_refused_naming_the_field(
    admin: httpx.Client, method: str, url: str, body: Any, field: str
) -> None:
    assert_refused(send(admin, method, url, body), field)


def test_the_connection_survives_refusals(admin: httpx.Client) -> None:
    """The same keep-alive connection answers again after every probe (a 500 from an
    exception used to close it, so the next request on it failed)."""
    for method, url, body, _ in ISSUE_PROBES[:6]:
        send(admin, method, url, body)
        assert admin.get("/auth/me").status_code == 200


def test_an_upload_name_longer_than_255_bytes_is_refused(admin: httpx.Client) -> None:
    name = "\u00e9" * 200 + ".laz"  # 204 characters, 404 bytes
    response = admin.post("/surveys/upload", params={"filename": name}, content=b"x" * 10)
    assert_refused(response, "filename")


def test_a_box_read_at_the_edge_of_the_grid_is_refused_not_allocated(
    admin: httpx.Client,
) -> None:
    """The largest box the coordinate bounds allow: its size check must not wrap in int64."""
    edge = "x0=-429496729.6&y0=-429496729.6&x1=429496729.4&y1=429496729.4"
    assert_refused(admin.get(f"/surveys/1/pillars/labels?{edge}"), "box")


def test_an_import_path_too_long_for_the_file_system_is_one_line(
    admin: httpx.Client,
) -> None:
    """A path inside the length limits whose resolved form is not (ENAMETOOLONG)."""
    path = "/".join(["b" * 255] * 16)  # 4,095 bytes: fits, with the data dir in front it does not
    assert_refused(send(admin, "POST", "/surveys/import", {"path": path}), "path")


# --- every route of the schema ----------------------------------------------------------------


def resolve(schema: dict, node: dict) -> dict:
    while "$ref" in node:
        node = schema["components"]["schemas"][node["$ref"].rsplit("/", 1)[-1]]
    return node


def example(schema: dict, node: dict) -> Any:
    """A plausible value of NODE: every property filled, numbers 1, strings 'x'."""
    node = resolve(schema, node)
    options = node.get("anyOf") or node.get("oneOf")
    if options:
        return example(schema, next((o for o in options if o.get("type") != "null"), options[0]))
    if "enum" in node:
        return node["enum"][0]
    if "const" in node:
        return node["const"]
    kind = node.get("type")
    if kind == "object" or "properties" in node:
        return {k: example(schema, v) for k, v in node.get("properties", {}).items()}
    if kind == "array":
        return [example(schema, node.get("items", {}))]
    if kind in ("integer", "number"):
        return 1
    if kind == "boolean":
        return False
    return "x" * max(1, node.get("minLength", 1))


def number_paths(schema: dict, node: dict, at: tuple = ()) -> Iterator[tuple]:
    """Where in a body built by `example` a number or integer sits."""
    node = resolve(schema, node)
    options = node.get("anyOf") or node.get("oneOf")
    if options:
        node = resolve(schema, next((o for o in options if o.get("type") != "null"), options[0]))
    if node.get("type") in ("integer", "number") and "enum" not in node:
        yield at
    for key, child in node.get("properties", {}).items():
        yield from number_paths(schema, child, (*at, key))
    if node.get("type") == "array":
        yield from number_paths(schema, node.get("items", {}), (*at, 0))


def with_value(body: Any, at: tuple, value: Any) -> Any:
    body = json.loads(json.dumps(body))
    target = body
    for key in at[:-1]:
        target = target[key]
    target[at[-1]] = value
    return body


def kind_of(schema: dict, node: dict) -> str | None:
    """A parameter's JSON type (the non-null one of an optional parameter)."""
    node = resolve(schema, node)
    options = node.get("anyOf") or [node]
    return next((o.get("type") for o in options if o.get("type") != "null"), None)


def url_of(path: str, values: dict, query: dict | None = None) -> str:
    text = path.format(**values)
    return text + ("?" + str(httpx.QueryParams(query)) if query else "")


SKIPPED = {("post", "/auth/logout")}  # would end the probing client's own login


def schema_probes(schema: dict) -> Iterator[tuple[str, str, Any, str]]:
    """(method, url, body, what) for every bad number each operation can be sent."""
    for path, item in schema["paths"].items():
        for method, operation in item.items():
            if (method, path) in SKIPPED:
                continue
            params = operation.get("parameters", [])
            kinds = {p["name"]: kind_of(schema, p["schema"]) for p in params}
            path_values = {
                p["name"]: 1 if kinds[p["name"]] == "integer" else "x"
                for p in params
                if p["in"] == "path"
            }
            query = [p["name"] for p in params if p["in"] == "query"]
            content = operation.get("requestBody", {}).get("content", {})
            body_schema = content.get("application/json", {}).get("schema")
            body = None if body_schema is None else example(schema, body_schema)
            for name, value in path_values.items():
                if value == 1:
                    for bad in (BIG, -1):
                        target = url_of(path, {**path_values, name: bad})
                        yield method, target, body, f"path {name}={bad}"
            for name in query:
                if kinds[name] in ("integer", "number"):
                    for bad in (str(BIG), "1e308", "nan", "-inf"):
                        target = url_of(path, path_values, {name: bad})
                        yield method, target, body, f"query {name}={bad}"
            if body_schema is not None:
                for at in number_paths(schema, body_schema):
                    for bad in (1e308, -1e308, math.nan, math.inf, BIG):
                        bad_body = with_value(body, at, bad)
                        yield method, url_of(path, path_values), bad_body, f"body {at}={bad}"


def test_no_route_answers_5xx_to_out_of_range_numbers(admin: httpx.Client) -> None:
    schema = admin.get("/openapi.json").json()
    failures, sent = [], 0
    for method, url, body, what in schema_probes(schema):
        response = send(admin, method, url, body)
        sent += 1
        if response.status_code >= 500:
            failures.append(f"{method.upper()} {url[:100]} ({what}): {response.status_code}")
        assert admin.get("/auth/me").status_code == 200, f"{method} {url}: login lost"
    assert sent > 100
    assert not failures, "\n".join(failures)
