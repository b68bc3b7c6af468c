"""Security and fault probes against real servers: what issue 15's attack pass tried, as a table.

Three `mmsclean serve` processes on free loopback ports, each with its own data dir:

- main: the sample survey loaded, a fixed viewer port; users of each role;
- disk: `MMSCLEAN_MIN_FREE_MB` above the free space of its disk (a full disk as the app sees
  it) and orphaned upload / job folders left in its data dir before it started;
- limits: the sample survey, `MMSCLEAN_JOB_MEMORY_MB=64` (the lowest limit allowed) and the
  login throttle.

Every probe counts what it tried and how the server answered:

- clear: the answer the issue asks for (a 4xx or 507 whose `detail` is one line, or the
  documented success for files that must read);
- 5xx: any other 5xx, or a dropped connection / timeout;
- harm: the attack worked (code ran from a file, a label was replaced unseen, a revoked token
  still worked, a file was served to a role that may not have it, a bad number was accepted...).

The last two columns must be 0.

    .venv/bin/python -m bench.security [--no-record]
"""

from __future__ import annotations

import argparse
import io
import json
import os
import pickle
import stat
import sys
import tempfile
import time
import zipfile
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

import httpx

from bench.common import append_results, markdown_table
from tests.api.server import Server, free_port
from tests.io.foreign_files import (
    write_las_with_garbage_vlr_count,
    write_laz_without_chunk_table,
    write_uppercase_pcd,
)
from tests.io.kitti_fixtures import make_semantickitti

CANCEL_LIMIT_S = 10.0
PASSWORD = "password-123"


@dataclass
class Probe:
    section: str
    name: str
    tried: int = 0
    clear: int = 0
    server_errors: int = 0
    harm: int = 0
    notes: str = ""

    def row(self) -> list[str]:
        return [
            self.section,
            self.name,
            str(self.tried),
            str(self.clear),
            str(self.server_errors),
            str(self.harm),
            self.notes,
        ]

    def note(self, text: str) -> None:
        self.notes = f"{self.notes}; {text}" if self.notes else text


def one_line_detail(response: httpx.Response) -> bool:
    try:
        detail = response.json().get("detail")
    except (ValueError, AttributeError):
        return False
    return isinstance(detail, str) and bool(detail.strip()) and "\n" not in detail


def expect_refusal(
    probe: Probe,
    send: Callable[[], httpx.Response],
    codes: Iterable[int] = (422,),
    mentions: str | None = None,
) -> httpx.Response | None:
    """One request that must be refused with one of `codes` and a one-line detail (naming
    `mentions` when given); a 2xx is harm (the bad input was accepted)."""
    probe.tried += 1
    try:
        response = send()
    except httpx.HTTPError as exc:
        probe.server_errors += 1
        probe.note(f"{type(exc).__name__}")
        return None
    status = response.status_code
    if status in codes and one_line_detail(response):
        named = mentions is None or mentions in response.json()["detail"]
        if named:
            probe.clear += 1
        else:
            probe.note(f"detail does not name {mentions!r}: {response.json()['detail'][:80]}")
    elif status >= 500:
        probe.server_errors += 1
        probe.note(f"{status}")
    elif status < 300:
        probe.harm += 1
        probe.note(f"accepted with {status}")
    else:
        probe.note(f"{status}: {response.text[:80]}")
    return response


def expect_status(probe: Probe, response: httpx.Response, ok: Iterable[int], harm: bool) -> bool:
    """Count one answer: `ok` is clear; anything else is a 5xx or, when `harm`, harm."""
    probe.tried += 1
    if response.status_code in ok:
        probe.clear += 1
        return True
    if response.status_code >= 500 and response.status_code != 507:
        probe.server_errors += 1
    elif harm:
        probe.harm += 1
    probe.note(f"{response.status_code}: {response.text[:80]}")
    return False


def login(server: Server, username: str, password: str = PASSWORD) -> tuple[httpx.Client, str]:
    response = httpx.post(
        f"{server.url}/auth/login", json={"username": username, "password": password}
    )
    response.raise_for_status()
    token = response.json()["access_token"]
    client = httpx.Client(
        base_url=server.url, timeout=60, headers={"Authorization": f"Bearer {token}"}
    )
    return client, token


def add_users(server: Server) -> dict[str, int]:
    ids = {}
    with server.client() as admin:
        for name, role in (
            ("ann", "annotator"),
            ("ann2", "annotator"),
            ("rev", "reviewer"),
            ("victim", "annotator"),
        ):
            response = admin.post(
                "/users", json={"username": name, "password": PASSWORD, "role": role}
            )
            response.raise_for_status()
            ids[name] = response.json()["id"]
    return ids


def wait_job(client: httpx.Client, job_id: int, timeout: float) -> dict:
    deadline = time.monotonic() + timeout
    job = client.get(f"/jobs/{job_id}").json()
    while job["status"] in ("queued", "running") and time.monotonic() < deadline:
        time.sleep(0.25)
        job = client.get(f"/jobs/{job_id}").json()
    return job


# -- 1. code execution from a file named as a model -------------------------------------------


class _Touch:
    """Unpickling this creates the marker file: a stand-in for any code a pickle can run."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (Path.touch, (self.marker,))


def sequence_zip(tmp: Path, marker: Path | None = None) -> bytes:
    """A zip of a small SemanticKITTI sequence; with `marker`, a pickle `evil.pt` beside the
    scans that creates it when unpickled."""
    sequence = make_semantickitti(tmp / "seq", frames=2)
    if marker is not None:
        (sequence / "evil.pt").write_bytes(pickle.dumps({"heads": _Touch(marker)}))
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as zf:
        for path in sorted(sequence.rglob("*")):
            if path.is_file():
                zf.write(path, f"seq/{path.relative_to(sequence).as_posix()}")
    return buffer.getvalue()


def probe_model_files(server: Server, ann: httpx.Client, tmp: Path) -> Probe:
    probe = Probe("1", "pickle uploaded as a model: run:guardrail / run:phantom")
    marker = tmp / "pwned-marker"
    upload = ann.post(
        "/surveys/upload",
        params={"filename": "seq.zip", "name": "evil"},
        content=sequence_zip(tmp, marker),
    )
    upload.raise_for_status()
    survey = upload.json()
    evil = Path(survey["source_path"]) / "evil.pt"
    for kind in ("run:guardrail", "run:phantom"):
        for config in (
            {"model_path": str(evil)},
            {"model_path": "models/phantom/../../var/evil.pt"},
            {"model_id": 10**6},
            {"model_id": str(evil)},
        ):
            expect_refusal(
                probe,
                lambda kind=kind, config=config: ann.post(
                    "/jobs", json={"kind": kind, "survey_id": survey["id"], "config": config}
                ),
                mentions="config.model",
            )
    time.sleep(3)  # a worker that had taken such a job would have loaded it by now
    if marker.exists():
        probe.harm += 1
        probe.note("the pickle ran")
    return probe


# -- 2. stale write after an erase -------------------------------------------------------------


def probe_erase_aba(server: Server, survey_id: int, ann, ann2, rev) -> Probe:
    """The issue's sequence: rev's write with the version it saw before an erase must be 409."""
    probe = Probe("2", "stale write after an erase (ABA)")
    url = f"/surveys/{survey_id}/pillars/labels"
    for cell in (9_000_001, 9_000_002, 9_000_003):
        first = ann.put(url, json={"labels": [{"cell_id": cell, "label": 1, "version": 0}]})
        first.raise_for_status()
        seen = first.json()["version"][0]  # rev reads the same version
        ann2.put(url, json={"labels": [{"cell_id": cell, "label": None, "version": seen}]})
        ann.put(url, json={"labels": [{"cell_id": cell, "label": 2}]}).raise_for_status()
        expect_refusal(
            probe,
            lambda cell=cell, seen=seen: rev.put(
                url, json={"labels": [{"cell_id": cell, "label": 3, "version": seen}]}
            ),
            codes=(409,),
        )
    return probe


# -- 3. job configs and cancel -----------------------------------------------------------------

BAD_CLUTTER_CONFIGS = {
    "dufomap_resolution": 0.001,
    "mask_padding_px": 1e9,
    "threads": 1e6,
    "min_track_frames": 1e12,
    "max_range": 1e308,
    "ground_cell": 1e-4,
}


def probe_job_bounds(ann: httpx.Client, survey_id: int) -> Probe:
    probe = Probe("3", "unbounded run:clutter config values")
    for field, value in BAD_CLUTTER_CONFIGS.items():
        expect_refusal(
            probe,
            lambda field=field, value=value: ann.post(
                "/jobs",
                json={"kind": "run:clutter", "survey_id": survey_id, "config": {field: value}},
            ),
            mentions=field,
        )
    for kind, config in (
        ("run:guardrail", {"spacing": 1e-9}),
        ("run:guardrail", {"max_gap": 10**12}),
        ("run:guardrail", {"join_gap": 1e308}),
        ("run:clutter", {"max_range": "NaN"}),
    ):
        expect_refusal(
            probe,
            lambda kind=kind, config=config: ann.post(
                "/jobs", json={"kind": kind, "survey_id": survey_id, "config": config}
            ),
        )
    return probe


def probe_job_memory(survey_id: int, client: httpx.Client) -> Probe:
    """Configs inside their bounds whose estimate exceeds MMSCLEAN_JOB_MEMORY_MB=64 on the
    sample survey: refused when queued, with the estimate in MB."""
    probe = Probe("3", "jobs over MMSCLEAN_JOB_MEMORY_MB=64 (sample survey)")
    for kind, config in (
        ("run:clutter", {"dufomap_resolution": 0.02}),
        ("run:clutter", {}),
        ("run:phantom", {}),
    ):
        expect_refusal(
            probe,
            lambda kind=kind, config=config: client.post(
                "/jobs", json={"kind": kind, "survey_id": survey_id, "config": config}
            ),
            mentions="MB",
        )
    return probe


def probe_cancel(admin: httpx.Client, survey_id: int) -> Probe:
    """A running job of each pipeline is cancelled 2 s after it started: ends `cancelled`
    within CANCEL_LIMIT_S."""
    probe = Probe("3", f"cancel a running job: cancelled within {CANCEL_LIMIT_S:.0f} s")
    slowest = 0.0
    for kind in ("run:clutter", "run:phantom"):
        job = admin.post("/jobs", json={"kind": kind, "survey_id": survey_id, "config": {}})
        job.raise_for_status()
        job_id = job.json()["id"]
        deadline = time.monotonic() + 120
        while admin.get(f"/jobs/{job_id}").json()["status"] == "queued":
            if time.monotonic() > deadline:
                break
            time.sleep(0.2)
        time.sleep(2.0)
        asked = time.monotonic()
        admin.post(f"/jobs/{job_id}/cancel")
        final = wait_job(admin, job_id, timeout=60)
        took = time.monotonic() - asked
        slowest = max(slowest, took)
        probe.tried += 1
        if final["status"] == "cancelled" and took <= CANCEL_LIMIT_S:
            probe.clear += 1
        elif final["status"] == "succeeded":
            probe.note(f"{kind} finished before the cancel")
            probe.clear += 1
        else:
            probe.harm += 1
            probe.note(f"{kind}: {final['status']} after {took:.1f} s")
    probe.note(f"slowest {slowest:.1f} s")
    return probe


# -- 4. numbers and names ----------------------------------------------------------------------


def probe_numbers(server: Server, ann: httpx.Client, survey_id: int) -> Probe:
    probe = Probe("4", "ids > 64 bit, non-finite coordinates, long names")
    huge = 10**30
    raw = {"Content-Type": "application/json"}
    pillars = f"/surveys/{survey_id}/pillars/labels"
    requests: list[tuple[Callable[[], httpx.Response], tuple[int, ...], str | None]] = [
        (lambda: ann.get(f"/surveys/{huge}"), (404, 422), "survey_id"),
        (lambda: ann.get(f"/jobs/{huge}"), (404, 422), "job_id"),
        (lambda: ann.get(f"/jobs/{-1}"), (404, 422), "job_id"),
        (lambda: ann.get("/jobs", params={"survey_id": huge}), (422,), "survey_id"),
        (
            lambda: ann.post("/jobs", json={"kind": "run:phantom", "survey_id": huge}),
            (422,),
            "survey_id",
        ),
        (lambda: ann.get(f"/surveys/{huge}/pillars/stats"), (404, 422), "survey_id"),
        (lambda: ann.get(f"/models/{huge}"), (404, 422), "model_id"),
    ]
    for value in ("1e300", "NaN", "Infinity", "-Infinity", '"nan"'):
        body = f'{{"labels": [{{"x": {value}, "y": 0.0, "label": 1}}]}}'
        requests.append(
            (lambda body=body: ann.put(pillars, content=body, headers=raw), (422,), "x")
        )
    for cell in (2**63, 2**70, -(2**63) - 1):
        body = json.dumps({"labels": [{"cell_id": cell, "label": 1}]})
        requests.append(
            (lambda body=body: ann.put(pillars, content=body, headers=raw), (422,), "cell_id")
        )
    for box in ((-1e308, -1e308, 1e308, 1e308), (0, 0, float("inf"), 1)):
        params = dict(zip(("x0", "y0", "x1", "y1"), (str(v) for v in box), strict=True))
        requests.append((lambda params=params: ann.get(pillars, params=params), (422,), None))
    requests += [
        (lambda: ann.post("/surveys/import", json={"path": "a" * 300}), (400, 404, 422), "path"),
        (
            lambda: ann.post("/surveys/import", json={"path": "/".join(["b" * 200] * 30)}),
            (400, 404, 422),
            "path",
        ),
        (lambda: ann.get(f"/jobs/1/files/{'c' * 5000}"), (404, 422), None),
        # 4,001 bytes in 2,001 short names fits the limits: the download rule answers first
        (lambda: ann.get(f"/jobs/1/files/{'d/' * 2000}x"), (403, 404, 422), None),
    ]
    for send, codes, field in requests:
        expect_refusal(probe, send, codes=codes, mentions=field)
    return probe


def probe_every_int_path(server: Server, admin: httpx.Client) -> Probe:
    """Every GET route of the OpenAPI schema with integer path parameters set to 10**30."""
    probe = Probe("4", "every GET route, integer path parameters = 10**30")
    schema = admin.get("/openapi.json").json()
    for path, methods in schema["paths"].items():
        if "get" not in methods or "{" not in path:
            continue
        params = methods["get"].get("parameters", [])
        ints = {
            p["name"]
            for p in params
            if p.get("in") == "path" and p.get("schema", {}).get("type") == "integer"
        }
        if not ints:
            continue
        for name in ints:
            target = path
            for p in params:
                if p.get("in") == "path":
                    value = str(10**30) if p["name"] == name else "1"
                    if p.get("schema", {}).get("type") != "integer":
                        value = "x"
                    target = target.replace(f"{{{p['name']}}}", value)
            expect_refusal(probe, lambda target=target: admin.get(target), codes=(404, 422))
    return probe


# -- 5. full disk and orphans ------------------------------------------------------------------


def leave_orphans(data_dir: Path) -> list[Path]:
    """What a server killed mid-upload / mid-job leaves: folders no row owns."""
    upload = data_dir / "surveys" / ("f" * 32)
    upload.mkdir(parents=True)
    (upload / ".upload.zip").write_bytes(b"\0" * 1_000_000)
    job = data_dir / "jobs" / "424242"
    job.mkdir(parents=True)
    (job / "cleaned.laz.partial").write_bytes(b"\0" * 1000)
    return [upload, job]


def probe_disk(disk: Server, orphans: list[Path]) -> list[Probe]:
    full = Probe("5", "writes with the disk full: 507, reads and login work")
    health = httpx.get(f"{disk.url}/health")
    full.tried += 1
    if health.json().get("status") == "degraded":
        full.clear += 1
    else:
        full.harm += 1
        full.note(f"/health says {health.json().get('status')}")
    response = httpx.post(
        f"{disk.url}/auth/login", json={"username": "admin", "password": "admin-password-1"}
    )
    if expect_status(full, response, ok=(200,), harm=True):
        token = response.json()["access_token"]
        client = httpx.Client(
            base_url=disk.url, timeout=60, headers={"Authorization": f"Bearer {token}"}
        )
        with client:
            expect_status(full, client.get("/surveys"), ok=(200,), harm=True)
            writes = [
                lambda: client.post("/jobs", json={"kind": "run:phantom", "survey_id": 1}),
                lambda: client.post(
                    "/users", json={"username": "x", "password": PASSWORD, "role": "annotator"}
                ),
                lambda: client.post(
                    "/surveys/upload", params={"filename": "a.laz"}, content=b"\0" * 1000
                ),
                lambda: client.put(
                    "/surveys/1/pillars/labels", json={"labels": [{"cell_id": 1, "label": 1}]}
                ),
            ]
            for send in writes:
                expect_refusal(full, send, codes=(507,), mentions="disk is full")
    leftovers = Probe("5", "orphaned upload / job folders removed at start-up")
    for orphan in orphans:
        leftovers.tried += 1
        if orphan.exists():
            leftovers.harm += 1
            leftovers.note(f"{orphan.name} still there")
        else:
            leftovers.clear += 1
    return [full, leftovers]


# -- 6. sessions and roles ---------------------------------------------------------------------


def probe_sessions(server: Server, user_ids: dict[str, int]) -> Probe:
    probe = Probe("6", "revoked tokens: logout, password / role change, deactivation, revoke")

    def refused_after(action: Callable[[httpx.Client, str], object], what: str) -> None:
        client, _ = login(server, "victim")
        with client:
            client.get("/auth/me").raise_for_status()
            action(client, what)
            probe.tried += 1
            status = client.get("/auth/me").status_code
            if status == 401:
                probe.clear += 1
            else:
                probe.harm += 1
                probe.note(f"{what}: {status}")

    with server.client() as admin:
        victim = user_ids["victim"]
        refused_after(lambda c, _: c.post("/auth/logout"), "logout")
        refused_after(
            lambda c, _: admin.patch(f"/users/{victim}", json={"password": PASSWORD}),
            "password change",
        )
        refused_after(
            lambda c, _: admin.patch(f"/users/{victim}", json={"role": "reviewer"}), "role change"
        )
        refused_after(
            lambda c, _: (
                admin.patch(f"/users/{victim}", json={"is_active": False}),
                admin.patch(f"/users/{victim}", json={"is_active": True}),
            ),
            "deactivation",
        )

        def revoke_other(client: httpx.Client, _: str) -> None:
            other, _token = login(server, "victim")
            with other:
                sessions = other.get("/auth/sessions").json()
                mine = [s for s in sessions if not s.get("current")]
                for s in mine:
                    other.delete(f"/auth/sessions/{s['id']}")

        refused_after(revoke_other, "revoked from another session")
    return probe


def probe_token_in_logs(server: Server) -> Probe:
    probe = Probe("6", "tokens in the access log")
    client, token = login(server, "ann")
    with client:
        httpx.get(f"{server.url}/viewer/ws", params={"token": token})
        httpx.get(f"{server.url}/surveys", params={"token": token})
        client.get("/auth/me")
    time.sleep(0.5)
    probe.tried += 1
    signature = token.rsplit(".", 1)[-1]
    if signature in server.log():
        probe.harm += 1
        probe.note("token found in the server log")
    else:
        probe.clear += 1
    return probe


def probe_job_files(server: Server, admin, ann, rev, survey_id: int) -> Probe:
    """A finished run's map: the same rule for /jobs/{id}/files as for the survey's exports."""
    probe = Probe("6", "job output map for an annotator vs exports rule")
    job = admin.post("/jobs", json={"kind": "run:phantom", "survey_id": survey_id, "config": {}})
    job.raise_for_status()
    final = wait_job(admin, job.json()["id"], timeout=600)
    if final["status"] != "succeeded":
        probe.note(f"run:phantom {final['status']}: {final['message'][:80]}")
        probe.tried += 1
        probe.server_errors += 1
        return probe
    files = [f["name"] for f in rev.get(f"/jobs/{final['id']}/results").json()["files"]]
    maps = [name for name in files if name.endswith((".laz", ".las", ".ply", ".npz"))]
    export = ann.get(f"/surveys/{survey_id}/exports/cleaned.laz")
    for name in maps:
        response = ann.get(f"/jobs/{final['id']}/files/{name}")
        probe.tried += 1
        if (response.status_code == 200) == (export.status_code == 200):
            probe.clear += 1
        else:
            probe.harm += 1
            probe.note(f"{name}: job file {response.status_code}, export {export.status_code}")
        expect_status(probe, rev.get(f"/jobs/{final['id']}/files/{name}"), ok=(200,), harm=False)
    probe.note(f"{len(maps)} map files")
    return probe


def probe_viser_port(port: int) -> Probe:
    """A websocket straight to viser's loopback port, without a ticket: closed, no frame."""
    import viser
    from websockets.exceptions import ConnectionClosed, InvalidHandshake, InvalidStatus
    from websockets.sync.client import connect

    probe = Probe("6", "websocket straight to the viser port without a ticket")
    protocol = f"viser-v{viser.__version__}"
    for subprotocols in ([protocol], None):
        probe.tried += 1
        try:
            with connect(f"ws://127.0.0.1:{port}", subprotocols=subprotocols, open_timeout=5) as ws:
                frame = ws.recv(timeout=3)
                probe.harm += 1
                probe.note(f"received a frame of {len(frame)} bytes")
        except (ConnectionClosed, InvalidHandshake, InvalidStatus, ConnectionRefusedError):
            probe.clear += 1
        except TimeoutError:
            probe.harm += 1
            probe.note("connection stayed open")
    return probe


def probe_file_modes(server: Server) -> Probe:
    probe = Probe("6", "data dir 0700, database 0600")
    for path in (server.data_dir, server.data_dir / "mmsclean.sqlite3"):
        probe.tried += 1
        mode = stat.S_IMODE(path.stat().st_mode)
        if mode & 0o077:
            probe.harm += 1
            probe.note(f"{path.name} {oct(mode)}")
        else:
            probe.clear += 1
    return probe


def probe_retraining(server: Server, ann: httpx.Client, admin: httpx.Client) -> Probe:
    """100,000 labels from one annotator: no train:phantom job is queued that then fails."""
    probe = Probe("6", "100k labels from one annotator: retraining queues only what trains")
    survey = ann.post(
        "/surveys/upload",
        params={"filename": "r.zip", "name": "retrain"},
        content=sequence_zip(Path(tempfile.mkdtemp())),
    )
    survey.raise_for_status()
    survey_id = survey.json()["id"]
    before = {j["id"] for j in admin.get("/jobs", params={"kind": "train:phantom"}).json()}
    for batch in range(10):
        cells = range(20_000_000 + batch * 10_000, 20_000_000 + (batch + 1) * 10_000)
        ann.put(
            f"/surveys/{survey_id}/pillars/labels",
            json={"labels": [{"cell_id": c, "label": c % 4} for c in cells]},
        ).raise_for_status()
    time.sleep(3)
    queued = [
        j
        for j in admin.get("/jobs", params={"kind": "train:phantom"}).json()
        if j["id"] not in before
    ]
    probe.tried += 1
    if not queued:
        probe.clear += 1
        state = admin.get("/models/retraining").json()
        reason = state.get("blocked_by") or state.get("reason")
        probe.note(f"not queued: {str(reason)[:90]}")
        return probe
    final = wait_job(admin, queued[0]["id"], timeout=300)
    if final["status"] == "failed":
        probe.harm += 1
        probe.note(f"queued and failed: {final['message'][:80]}")
    else:
        probe.clear += 1
        probe.note(f"queued, {final['status']}")
    return probe


def probe_throttle(limits: Server) -> Probe:
    probe = Probe("6", "40 wrong passwords: 429 with Retry-After")
    throttled = 0
    for _ in range(40):
        response = httpx.post(
            f"{limits.url}/auth/login", json={"username": "admin", "password": "wrong-password"}
        )
        if response.status_code == 429 and response.headers.get("retry-after"):
            throttled += 1
        elif response.status_code >= 500:
            probe.server_errors += 1
    probe.tried += 1
    if throttled:
        probe.clear += 1
        probe.note(f"{throttled} of 40 answered 429")
    else:
        probe.harm += 1
        probe.note("never throttled")
    return probe


# -- 7. foreign files --------------------------------------------------------------------------


def probe_foreign_files(server: Server, ann: httpx.Client, tmp: Path) -> Probe:
    probe = Probe("7", "foreign files: upper-case PCD, LAZ without chunk table, garbage LAS")
    imports = server.data_dir / "imports"
    imports.mkdir(exist_ok=True)
    for binary in (False, True):
        path = write_uppercase_pcd(imports / f"upper-{binary}.pcd", binary=binary)
        response = ann.post("/surveys/import", json={"path": str(path), "format": "pcd"})
        expect_status(probe, response, ok=(201,), harm=False)
    for writer in (write_laz_without_chunk_table, write_las_with_garbage_vlr_count):
        path = writer(tmp / ("broken.laz" if "laz" in writer.__name__ else "broken.las"))
        expect_refusal(
            probe,
            lambda path=path: ann.post(
                "/surveys/upload", params={"filename": path.name}, content=path.read_bytes()
            ),
            mentions=path.name,
        )
    return probe


# -- run ---------------------------------------------------------------------------------------


def run(record: bool) -> list[Probe]:
    probes: list[Probe] = []
    with tempfile.TemporaryDirectory(prefix="mmsclean-security-") as scratch:
        tmp = Path(scratch)
        viewer_port = free_port()
        main = Server(tmp / "main", env={"MMSCLEAN_VIEWER_PORT": str(viewer_port)}).start(300)
        disk_dir = tmp / "disk"
        orphans = leave_orphans(disk_dir)
        disk = Server(
            disk_dir, env={"MMSCLEAN_SAMPLE_DIR": "", "MMSCLEAN_MIN_FREE_MB": "100000000"}
        )
        limits = Server(tmp / "limits", env={"MMSCLEAN_JOB_MEMORY_MB": "64"})
        try:
            disk.start()
            limits.start(300)
            ids = add_users(main)
            clients = {name: login(main, name)[0] for name in ("ann", "ann2", "rev")}
            admin = main.client()
            sample = admin.get("/surveys").json()[0]["id"]
            ann, ann2, rev = clients["ann"], clients["ann2"], clients["rev"]

            probes.append(probe_model_files(main, ann, tmp))
            probes.append(probe_erase_aba(main, sample, ann, ann2, rev))
            probes.append(probe_job_bounds(ann, sample))
            with limits.client() as limits_admin:
                limits_sample = limits_admin.get("/surveys").json()[0]["id"]
                probes.append(probe_job_memory(limits_sample, limits_admin))
            probes.append(probe_cancel(admin, sample))
            probes.append(probe_numbers(main, ann, sample))
            probes.append(probe_every_int_path(main, admin))
            probes.extend(probe_disk(disk, orphans))
            probes.append(probe_sessions(main, ids))
            probes.append(probe_token_in_logs(main))
            probes.append(probe_job_files(main, admin, ann, rev, sample))
            probes.append(probe_viser_port(viewer_port))
            probes.append(probe_file_modes(main))
            probes.append(probe_retraining(main, ann, admin))
            probes.append(probe_throttle(limits))
            probes.append(probe_foreign_files(main, ann, tmp))
            for client in (*clients.values(), admin):
                client.close()
            server_tracebacks = sum(s.log().count("Traceback") for s in (main, disk, limits))
        finally:
            for server in (main, disk, limits):
                server.stop()
    header = ["section", "probe", "tried", "clear", "5xx", "harm", "notes"]
    rows = [p.row() for p in probes]
    totals = [sum(getattr(p, f) for p in probes) for f in ("tried", "clear", "server_errors")]
    harm = sum(p.harm for p in probes)
    rows.append(["", "**all**", *(str(t) for t in totals), str(harm), ""])
    table = markdown_table(header, rows)
    print(table)
    print(f"server tracebacks in the logs: {server_tracebacks}")
    if record:
        append_results(
            "Security probes (issue 15)",
            "python -m bench.security",
            table,
            "Three real servers on loopback (sample survey; a disk below MMSCLEAN_MIN_FREE_MB "
            "with orphaned folders left before start; MMSCLEAN_JOB_MEMORY_MB=64 and the login "
            f"throttle). Server tracebacks in their logs: {server_tracebacks}.",
        )
    return probes


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--no-record", action="store_true", help="do not append to RESULTS.md")
    args = parser.parse_args(argv)
    os.environ.setdefault("MMSCLEAN_WORKERS", "2")
    probes = run(record=not args.no_record)
    return 1 if any(p.harm or p.server_errors for p in probes) else 0


if __name__ == "__main__":
    sys.exit(main())
