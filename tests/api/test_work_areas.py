"""The review workflow through a real server on the sample survey (`data_samples/urban-60m`,
about 58 m of drive): work areas cut along the drive, assignment by role, the state machine
(open -> labelled -> signed_off, rejected back to open with a comment; illegal steps 409 / 422
with one line naming the field or state; stale versions 409 with `current`), coverage counted
against labels written through the API, model pre-labels, clutter instances and guardrail
slices in the store, and the export readiness the dashboard and `mmsclean export` warn with."""

from __future__ import annotations

import sqlite3
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import httpx
import numpy as np
import pytest
from sqlalchemy.engine import Engine
from sqlmodel import Session, select

from app.geometry.trajectory import arc_length
from app.io import open_survey
from app.io.accumulate import accumulate
from app.store.clutter_review import replace_instances
from app.store.db import make_engine
from app.store.model_labels import store_model_labels
from app.store.models import Frame
from app.store.pillar_labels import STORE_GRID
from tests.api.server import Server
from tests.cli import mmsclean

LENGTH = 20.0  # metres per area: the sample's drive gives three


@dataclass
class Team:
    server: Server
    engine: Engine
    survey_id: int
    admin: httpx.Client
    ann: httpx.Client  # wa-ann, annotator
    ann2: httpx.Client  # wa-ann2, annotator
    rev: httpx.Client  # wa-rev, reviewer
    rev2: httpx.Client  # wa-rev2, reviewer
    ids: dict[str, int]  # user name -> id
    drive_length: float
    cells: np.ndarray  # sorted store cells with points (computed here, not by the server)
    cell_xy: np.ndarray  # their world centres
    frame_xyz: np.ndarray  # sensor positions
    frame_station: np.ndarray

    def base(self) -> str:
        return f"/surveys/{self.survey_id}"

    def areas(self, client: httpx.Client | None = None) -> list[dict]:
        answer = (client or self.admin).get(f"{self.base()}/areas")
        assert answer.status_code == 200, answer.text
        return answer.json()

    def near(self, station: float, radius: float = 5.0) -> np.ndarray:
        """Cells with points within `radius` of the drive at `station`."""
        at = [np.interp(station, self.frame_station, self.frame_xyz[:, a]) for a in (0, 1)]
        return self.cells[np.linalg.norm(self.cell_xy - at, axis=1) < radius]


@pytest.fixture(scope="module")
def team(sample_server: Server) -> Iterator[Team]:
    admin = sample_server.client()
    survey = admin.get("/surveys").json()[0]
    clients = {
        name: sample_server.add_user(name, role)
        for name, role in (
            ("wa-ann", "annotator"),
            ("wa-ann2", "annotator"),
            ("wa-rev", "reviewer"),
            ("wa-rev2", "reviewer"),
        )
    }
    ids = {u["username"]: u["id"] for u in admin.get("/users").json()}
    opened = open_survey(Path(survey["source_path"]), survey["format"])
    world = accumulate(opened, origin=np.asarray(survey["origin"], dtype=np.float64)).world_xy
    cells = np.unique(STORE_GRID.point_cell_ids(world))
    cell_xy = STORE_GRID.cell_center(*STORE_GRID.decode(cells))
    frame_xyz = np.array([f.pose[:3, 3] for f in opened.frames])
    engine = make_engine(f"sqlite:///{sample_server.data_dir / 'mmsclean.sqlite3'}")
    yield Team(
        sample_server, engine, survey["id"], admin, clients["wa-ann"], clients["wa-ann2"],
        clients["wa-rev"], clients["wa-rev2"], ids, float(arc_length(frame_xyz)[-1]), cells,
        cell_xy, frame_xyz, arc_length(frame_xyz),
    )  # fmt: skip
    for client in (admin, *clients.values()):
        client.close()
    engine.dispose()


def post(client: httpx.Client, url: str, body: dict) -> httpx.Response:
    return client.post(url, json=body)


def detail(answer: httpx.Response) -> str:
    return answer.json()["detail"]


# --- cutting ------------------------------------------------------------------------------


def test_areas_are_cut_along_the_drive_by_reviewers_only(team: Team) -> None:
    url = f"{team.base()}/areas"
    assert team.areas() == []
    refused = post(team.ann, url, {"length_m": LENGTH})
    assert refused.status_code == 403 and "reviewer" in detail(refused)
    for body, field in (
        ({"length_m": 1}, "length_m"),
        ({"length_m": 1e9}, "length_m"),
        ({"length_m": "far"}, "length_m"),
        ({"length": 20}, "length"),  # misspelt: named, not ignored
    ):
        answer = post(team.rev, url, body)
        assert answer.status_code == 422, body
        assert detail(answer).startswith(field), detail(answer)
    assert post(team.rev, "/surveys/999/areas", {}).status_code == 404

    first = post(team.rev, url, {"length_m": 25})
    assert first.status_code == 201, first.text
    assert len(first.json()) == 3  # 58 m: 25 + 25 + 8
    again = post(team.rev, url, {"length_m": LENGTH})
    assert again.status_code == 409 and "replace" in detail(again)
    answer = post(team.rev, url, {"length_m": LENGTH, "replace": True})
    assert answer.status_code == 201, answer.text
    areas = answer.json()
    assert [a["area_index"] for a in areas] == [0, 1, 2]
    assert min(a["id"] for a in areas) > max(a["id"] for a in first.json())  # ids never reused
    starts = [a["station_start"] for a in areas]
    ends = [a["station_end"] for a in areas]
    assert starts == [0.0, 20.0, 40.0] and ends[:2] == [20.0, 40.0]
    assert ends[-1] == pytest.approx(team.drive_length, abs=1e-6)
    survey = team.admin.get(team.base()).json()
    assert ends[-1] == pytest.approx(survey["frames"]["trajectory_length_m"], abs=0.01)
    for a in areas:
        assert (a["state"], a["assignee_id"], a["reviewer_id"], a["version"]) == (
            "open",
            None,
            None,
            1,
        )
        assert a["x_min"] < a["x_max"] and a["y_min"] < a["y_max"]
        # the drive's stretch lies in the area's box
        inside = (team.frame_station >= a["station_start"]) & (
            team.frame_station <= a["station_end"]
        )
        xy = team.frame_xyz[inside, :2]
        assert (xy >= [a["x_min"], a["y_min"]]).all() and (xy <= [a["x_max"], a["y_max"]]).all()


# --- coverage -----------------------------------------------------------------------------


def test_coverage_counts_the_labels_written_through_the_api(team: Team) -> None:
    areas = team.areas(team.ann)
    assert sum(a["coverage"]["pillars"] for a in areas) == len(team.cells)
    assert all(a["coverage"]["pillars"] > 0 for a in areas)
    assert all(a["coverage"]["human_labelled"] == 0 for a in areas)

    in_first, in_last, in_middle = team.near(10.0), team.near(50.0), team.near(30.0)
    assert len(in_first) > 20 and len(in_last) > 20 and len(in_middle) > 20
    labels = [{"cell_id": int(c), "label": 0} for c in in_first[:15]]
    labels += [{"cell_id": int(c), "label": 1} for c in in_last[:7]]
    empty = int(STORE_GRID.cell_id(10**6, 10**6))  # far away: no points, counted nowhere
    labels.append({"cell_id": empty, "label": 2})
    written = team.ann.put(f"{team.base()}/pillars/labels", json={"labels": labels})
    assert written.status_code == 200, written.text
    # model pre-labels of the middle area, as a phantom run writes them
    model = in_middle[:12]
    store_model_labels(
        team.engine, team.survey_id, model, np.ones(len(model), np.int64),
        np.full(len(model), 0.7), None, None, 0,
    )  # fmt: skip
    review = [{"cell_id": int(model[0]), "label": 1}]  # a person confirms one
    assert team.ann.put(f"{team.base()}/pillars/labels", json={"labels": review}).is_success

    cov = [a["coverage"] for a in team.areas(team.ann)]
    assert [c["human_labelled"] for c in cov] == [15, 1, 7]
    assert [c["model_unreviewed"] for c in cov] == [0, 11, 0]
    assert cov[0]["labelled_fraction"] == pytest.approx(15 / cov[0]["pillars"])
    assert sum(c["pillars"] for c in cov) == len(team.cells)  # the far label added none


def frames_at(team: Team, stations: list[float]) -> list[str]:
    with Session(team.engine) as session:
        rows = session.exec(
            select(Frame.frame_id).where(Frame.survey_id == team.survey_id)
            .order_by(Frame.frame_index)
        ).all()  # fmt: skip
    return [rows[int(np.argmin(np.abs(team.frame_station - s)))] for s in stations]


def test_coverage_counts_pending_clutter_and_unreviewed_slices(team: Team) -> None:
    f_mid, f_last = frames_at(team, [30.0, 55.0])
    rows = [
        {"frame_id": frame, "instance_index": k, "class_name": "car", "point_count": 10}
        for frame, count in ((f_mid, 3), (f_last, 1))
        for k in range(count)
    ]
    with Session(team.engine) as session:
        replace_instances(session, team.survey_id, rows, None)
    with sqlite3.connect(team.server.data_dir / "mmsclean.sqlite3") as db:
        db.executemany(
            "INSERT INTO guardrail_slice (created_at, updated_at, version, survey_id,"
            " slice_index, component_id, station_m, predicted_label, label)"
            " VALUES ('2026-01-01', '2026-01-01', 1, ?, ?, 0, ?, 1, 1)",
            [(team.survey_id, k, s) for k, s in enumerate((5.0, 6.0, 45.0))],
        )
    cov = [a["coverage"] for a in team.areas()]
    assert [c["clutter_pending"] for c in cov] == [0, 3, 1]
    assert [c["slices_unreviewed"] for c in cov] == [2, 0, 1]
    instances = team.rev.get(f"{team.base()}/clutter/instances").json()["items"]
    one = next(i for i in instances if i["frame_id"] == f_mid)
    decided = post(
        team.rev, f"{team.base()}/clutter/decisions",
        {"decisions": [{"instance_id": one["id"], "version": one["version"],
                        "decision": "approved"}]},
    )  # fmt: skip
    assert decided.status_code == 200, decided.text
    assert [a["coverage"]["clutter_pending"] for a in team.areas()] == [0, 2, 1]


# --- assignment and states ----------------------------------------------------------------


def act(team: Team, client: httpx.Client, area: dict, step: str, **body) -> httpx.Response:
    url = f"{team.base()}/areas/{area['id']}/{step}"
    return post(client, url, {"version": area["version"], **body})


def test_assignment_by_role_with_versions(team: Team) -> None:
    area = team.areas()[0]
    ann, rev = team.ids["wa-ann"], team.ids["wa-rev"]
    refused = act(team, team.ann, area, "assign", assignee_id=ann)
    assert refused.status_code == 403 and "reviewer" in detail(refused)
    for body, field in (
        ({"assignee_id": 999_999}, "assignee"),
        ({"reviewer_id": ann}, "reviewer"),  # an annotator cannot review
        ({}, "assignee_id"),
        ({"assignee_id": 0}, "assignee_id"),
    ):
        answer = act(team, team.rev, area, "assign", **body)
        assert answer.status_code == 422, body
        assert detail(answer).startswith(field), detail(answer)
    assert "is annotator" in detail(act(team, team.rev, area, "assign", reviewer_id=ann))
    done = act(team, team.rev, area, "assign", assignee_id=ann, reviewer_id=rev)
    assert done.status_code == 200, done.text
    assert (done.json()["assignee_id"], done.json()["reviewer_id"]) == (ann, rev)
    assert done.json()["version"] == 2
    stale = act(team, team.admin, area, "assign", assignee_id=team.ids["wa-ann2"])
    assert stale.status_code == 409
    assert "version 2, not 1" in detail(stale)
    assert stale.json()["current"]["assignee_id"] == ann
    # only the field sent changes
    kept = act(team, team.admin, done.json(), "assign", reviewer_id=None)
    assert (kept.json()["assignee_id"], kept.json()["reviewer_id"]) == (ann, None)
    back = act(team, team.admin, kept.json(), "assign", reviewer_id=rev)
    assert back.status_code == 200
    assert post(team.rev, f"{team.base()}/areas/999999/assign", {"version": 1}).status_code == 404


def test_states_move_only_as_the_workflow_allows(team: Team) -> None:
    area = team.areas()[0]
    assert (area["assignee_id"], area["reviewer_id"]) == (team.ids["wa-ann"], team.ids["wa-rev"])
    early = act(team, team.rev, area, "sign-off")
    assert early.status_code == 409 and "is open" in detail(early)
    other = act(team, team.ann2, area, "labelled")
    assert other.status_code == 403 and "only the assignee" in detail(other)
    unassigned = act(team, team.ann, team.areas()[1], "labelled")
    assert unassigned.status_code == 409 and "no assignee" in detail(unassigned)

    labelled = act(team, team.ann, area, "labelled")
    assert labelled.status_code == 200, labelled.text
    area = labelled.json()
    assert area["state"] == "labelled"
    twice = act(team, team.ann, area, "labelled")
    assert twice.status_code == 409 and "is labelled" in detail(twice)
    assert act(team, team.ann, area, "sign-off").status_code == 403  # annotators do not review
    not_theirs = act(team, team.rev2, area, "sign-off")
    assert not_theirs.status_code == 403 and "reviewed by user" in detail(not_theirs)
    for body, field in (({}, "comment"), ({"comment": ""}, "comment"),
                        ({"comment": "x" * 1001}, "comment")):  # fmt: skip
        answer = act(team, team.rev, area, "reject", **body)
        assert answer.status_code == 422 and detail(answer).startswith(field), body
    blank = act(team, team.rev, area, "reject", comment="   ")
    assert blank.status_code == 422 and detail(blank).startswith("comment")

    rejected = act(team, team.rev, area, "reject", comment="kerb at 12 m is ground")
    assert rejected.status_code == 200, rejected.text
    area = rejected.json()
    assert (area["state"], area["comment"]) == ("open", "kerb at 12 m is ground")
    assert area["decided_by"] == team.ids["wa-rev"]
    area = act(team, team.ann, area, "labelled").json()
    signed = act(team, team.rev, area, "sign-off")
    assert signed.status_code == 200, signed.text
    area = signed.json()
    assert (area["state"], area["comment"]) == ("signed_off", "")
    locked = act(team, team.rev, area, "assign", assignee_id=team.ids["wa-ann2"])
    assert locked.status_code == 409 and "signed off" in detail(locked)
    stale = post(team.rev, f"{team.base()}/areas/{area['id']}/reject",
                 {"version": 1, "comment": "again"})  # fmt: skip
    assert stale.status_code == 409 and stale.json()["current"]["state"] == "signed_off"

    with sqlite3.connect(team.server.data_dir / "mmsclean.sqlite3") as db:
        actions = [
            r[0]
            for r in db.execute(
                "SELECT action FROM audit_event WHERE entity = 'work_area' AND entity_id = ?"
                " ORDER BY id",
                (str(area["id"]),),
            )
        ]
        cut = db.execute("SELECT count(*) FROM audit_event WHERE action = 'work_area.cut'")
        assert cut.fetchone()[0] == 2
    assert actions == ["work_area.assign"] * 3 + [
        "work_area.mark_labelled", "work_area.reject", "work_area.mark_labelled",
        "work_area.sign_off",
    ]  # fmt: skip


# --- export readiness ---------------------------------------------------------------------


def test_export_readiness_lists_what_is_pending(team: Team) -> None:
    answer = team.ann.get(f"{team.base()}/export-readiness")
    assert answer.status_code == 200, answer.text
    ready = answer.json()
    assert ready["ready"] is False
    assert ready["pending_clutter_decisions"] == 3
    assert (ready["areas"], ready["areas_not_signed_off"]) == (3, [1, 2])
    assert ready["pending_guardrail_models"] == 0
    assert ready["unreviewed_guardrail_slices"] == 3
    warning = ready["warning"]
    assert "3 clutter decisions pending" in warning
    assert "2 of 3 work areas not signed off (1, 2)" in warning
    assert team.admin.get("/surveys/999/export-readiness").status_code == 404

    out = team.server.data_dir / "labels.csv"
    done = mmsclean(
        "export", str(team.survey_id), "pillars-csv", "--out", str(out),
        env={"MMSCLEAN_DATA_DIR": str(team.server.data_dir)},
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert f"warning: {warning}" in done.stderr.splitlines()
    assert out.is_file()

    # everything decided and signed off: ready, no warning
    instances = team.rev.get(f"{team.base()}/clutter/instances").json()["items"]
    pending = [i for i in instances if i["decision"] == "pending"]
    decisions = [{"instance_id": i["id"], "version": i["version"], "decision": "rejected"}
                 for i in pending]  # fmt: skip
    assert post(team.rev, f"{team.base()}/clutter/decisions", {"decisions": decisions}).is_success
    for area in team.areas()[1:]:
        area = act(team, team.admin, area, "assign", assignee_id=team.ids["wa-ann2"]).json()
        area = act(team, team.ann2, area, "labelled").json()
        signed = act(team, team.rev2, area, "sign-off")  # no reviewer named: any reviewer
        assert signed.status_code == 200, signed.text
    ready = team.ann.get(f"{team.base()}/export-readiness").json()
    assert ready["ready"] is True and ready["warning"] is None
    assert ready["areas_not_signed_off"] == []
