"""Clutter review through a real server: instance lists per frame, mask images, batch decisions
with versions (409 with the current state), roles, unknown ids; then the whole loop with the
worker pool on a small simulated street (run:clutter, decisions, clutter:recompute)."""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import httpx
import laspy
import numpy as np
import pytest
from sqlalchemy.engine import Engine
from sqlmodel import Session, select

from app.simulate.survey import SimulationConfig, simulate
from app.store.clutter_review import replace_instances
from app.store.db import make_engine
from app.store.models import AuditEvent, Frame, Survey
from tests.api.server import Server
from tests.pipelines.clutter.conftest import weights_dir  # noqa: F401  (the fixture)


@dataclass
class Review:
    server: Server
    admin: httpx.Client
    annotator: httpx.Client
    reviewer: httpx.Client
    engine: Engine
    survey_id: int  # frames f0, f1 with instances
    other_id: int  # another survey with one instance


def add_survey(engine: Engine, name: str, frames: list[str]) -> int:
    with Session(engine) as session:
        survey = Survey(name=name, format="sim", source_path=f"/nowhere/{name}")
        session.add(survey)
        session.flush()
        for i, frame_id in enumerate(frames):
            session.add(Frame(survey_id=survey.id, frame_index=i, frame_id=frame_id, pose=[0] * 16))
        session.commit()
        return survey.id


@pytest.fixture(scope="module")
def review(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Review]:
    """A server whose store holds two surveys with instances, written as a clutter run would
    (the store's own `replace_instances` on the server's SQLite file)."""
    root = tmp_path_factory.mktemp("clutter-review")
    server = Server(
        root / "var",
        env={"MMSCLEAN_SAMPLE_DIR": "", "MMSCLEAN_IMPORT_ROOT": str(root), "MMSCLEAN_WORKERS": "1"},
    ).start()
    engine = make_engine(f"sqlite:///{server.data_dir / 'mmsclean.sqlite3'}")
    survey_id = add_survey(engine, "street", ["f0", "f1", "f2"])
    other_id = add_survey(engine, "other", ["g0"])
    masks = root / "masks"
    masks.mkdir()
    rows = []
    for frame_id, count in (("f0", 3), ("f1", 2)):
        for k in range(count):
            path = masks / f"{frame_id}-{k}.png"
            cv2.imwrite(str(path), np.full((8, 12, 3), 40 * k, np.uint8))
            rows.append(
                {
                    "frame_id": frame_id,
                    "instance_index": k,
                    "class_name": "car" if k < 2 else "free-space",
                    "point_count": 100 + k,
                    "mask_path": str(path),
                    "bbox": [k, 2, k + 10, 9] if k < 2 else None,
                    "moving": k == 1,
                    "track_id": k if k < 2 else None,
                }
            )
    rows[-1]["mask_path"] = None  # an instance without an image
    with Session(engine) as session:
        replace_instances(session, survey_id, rows, None)
        replace_instances(session, other_id, [{**rows[0], "frame_id": "g0"}], None)
    clients = (
        server.client(),
        server.add_user("cl-annotator", "annotator"),
        server.add_user("cl-reviewer", "reviewer"),
    )
    yield Review(server, *clients, engine, survey_id, other_id)
    for client in clients:
        client.close()
    engine.dispose()
    server.stop()


def base(survey_id: int) -> str:
    return f"/surveys/{survey_id}/clutter"


def instances(client: httpx.Client, survey_id: int, **params) -> list[dict]:
    response = client.get(f"{base(survey_id)}/instances", params={"limit": 1000, **params})
    assert response.status_code == 200, response.text
    return response.json()["items"]


def by_key(items: list[dict]) -> dict[tuple[str, int], dict]:
    return {(i["frame_id"], i["instance_index"]): i for i in items}


def test_frames_list_and_masks(review: Review) -> None:
    c, url = review.annotator, base(review.survey_id)
    frames = c.get(f"{url}/frames").json()
    assert frames == [
        {"frame_id": "f0", "instances": 3, "pending": 3},
        {"frame_id": "f1", "instances": 2, "pending": 2},
        {"frame_id": "f2", "instances": 0, "pending": 0},
    ]
    items = instances(c, review.survey_id)
    assert [(i["frame_id"], i["instance_index"]) for i in items] == [
        ("f0", 0), ("f0", 1), ("f0", 2), ("f1", 0), ("f1", 1),
    ]  # fmt: skip
    first = items[0]
    assert first["decision"] == "pending" and first["version"] == 1
    assert first["class_name"] == "car" and first["bbox"] == [0, 2, 10, 9]
    assert first["mask_url"] == f"{url}/instances/{first['id']}/mask"
    # one frame, pages, filters
    assert len(instances(c, review.survey_id, frame_id="f1")) == 2
    page = c.get(f"{url}/instances", params={"limit": 2, "offset": 2}).json()
    assert page["total"] == 5 and [i["id"] for i in page["items"]] == [
        items[2]["id"],
        items[3]["id"],
    ]
    assert {i["class_name"] for i in instances(c, review.survey_id, class_name="free-space")} == {
        "free-space"
    }
    # the mask image is the PNG the run wrote
    mask = c.get(first["mask_url"])
    assert mask.status_code == 200 and mask.headers["content-type"] == "image/png"
    image = cv2.imdecode(np.frombuffer(mask.content, np.uint8), cv2.IMREAD_COLOR)
    assert image.shape == (8, 12, 3)
    no_image = by_key(items)[("f1", 1)]
    assert no_image["mask_url"] is None
    assert c.get(f"{url}/instances/{no_image['id']}/mask").status_code == 404
    assert c.get(f"{url}/instances", params={"limit": 5000}).status_code == 422


def test_reviewer_approves_and_rejects_many_at_once(review: Review) -> None:
    c, url = review.reviewer, base(review.survey_id)
    items = by_key(instances(c, review.survey_id, frame_id="f0"))
    a, b, d = items[("f0", 0)], items[("f0", 1)], items[("f0", 2)]
    body = {
        "decisions": [
            {"instance_id": a["id"], "version": a["version"], "decision": "approved"},
            {"instance_id": b["id"], "version": b["version"], "decision": "rejected"},
            {"instance_id": d["id"], "version": d["version"], "decision": "approved"},
        ]
    }
    response = c.post(f"{url}/decisions", json=body)
    assert response.status_code == 200, response.text
    out = response.json()
    assert [o["decision"] for o in out] == ["approved", "rejected", "approved"]
    assert [o["version"] for o in out] == [a["version"] + 1, b["version"] + 1, d["version"] + 1]
    assert len({o["user_id"] for o in out}) == 1 and out[0]["user_id"] is not None
    now = by_key(instances(c, review.survey_id, frame_id="f0"))
    assert now[("f0", 1)]["decision"] == "rejected"
    frames = {f["frame_id"]: f for f in c.get(f"{url}/frames").json()}
    assert frames["f0"]["pending"] == 0 and frames["f1"]["pending"] == 2
    assert len(instances(c, review.survey_id, decision="approved")) == 2
    # reset to pending: who decided is cleared
    reset = c.post(
        f"{url}/decisions",
        json={"decisions": [{"instance_id": d["id"], "version": d["version"] + 1,
                             "decision": "pending"}]},
    )  # fmt: skip
    assert reset.status_code == 200, reset.text
    assert reset.json()[0]["decision"] == "pending" and reset.json()[0]["user_id"] is None
    with Session(review.engine) as session:  # every decision is audited
        actions = session.exec(
            select(AuditEvent.action).where(AuditEvent.entity == "clutter_instance")
        ).all()
    assert actions.count("clutter.approve") >= 2 and "clutter.reject" in actions
    assert "clutter.reset" in actions


def test_stale_version_is_409_with_the_current_state(review: Review) -> None:
    c, url = review.reviewer, base(review.survey_id)
    items = by_key(instances(c, review.survey_id, frame_id="f1"))
    x, y = items[("f1", 0)], items[("f1", 1)]
    first = c.post(
        f"{url}/decisions",
        json={"decisions": [{"instance_id": x["id"], "version": x["version"],
                             "decision": "approved"}]},
    )  # fmt: skip
    assert first.status_code == 200
    stale = c.post(
        f"{url}/decisions",
        json={
            "decisions": [
                {"instance_id": y["id"], "version": y["version"], "decision": "approved"},
                {"instance_id": x["id"], "version": x["version"], "decision": "rejected"},
            ]
        },
    )
    assert stale.status_code == 409, stale.text
    body = stale.json()
    assert "changed by someone else" in body["detail"]
    assert body["current"] == [
        {
            "instance_id": x["id"],
            "decision": "approved",
            "version": x["version"] + 1,
            "user_id": first.json()[0]["user_id"],
            "decided_at": body["current"][0]["decided_at"],
        }
    ]
    after = by_key(instances(c, review.survey_id, frame_id="f1"))
    assert after[("f1", 1)]["decision"] == "pending"  # nothing of the batch was written
    assert after[("f1", 0)]["decision"] == "approved"


def test_annotator_reads_but_cannot_decide(review: Review) -> None:
    url = base(review.survey_id)
    item = instances(review.annotator, review.survey_id)[0]
    body = {"decisions": [{"instance_id": item["id"], "version": item["version"],
                           "decision": "rejected"}]}  # fmt: skip
    response = review.annotator.post(f"{url}/decisions", json=body)
    assert response.status_code == 403 and "reviewer" in response.json()["detail"]
    assert review.annotator.post(f"{url}/recompute").status_code == 403
    assert instances(review.annotator, review.survey_id)[0]["version"] == item["version"]


def test_unknown_and_foreign_ids_are_404(review: Review) -> None:
    c, url = review.reviewer, base(review.survey_id)
    assert c.get(f"{base(999)}/instances").status_code == 404
    assert c.get(f"{base(999)}/frames").status_code == 404
    assert c.post(f"{base(999)}/recompute").status_code == 404
    foreign = instances(c, review.other_id)[0]
    assert c.get(f"{url}/instances/{foreign['id']}").status_code == 404
    assert c.get(f"{url}/instances/{foreign['id']}/mask").status_code == 404
    assert c.get(f"{url}/instances/99999/mask").status_code == 404
    for instance_id in (foreign["id"], 99999):
        response = c.post(
            f"{url}/decisions",
            json={"decisions": [{"instance_id": instance_id, "version": 1,
                                 "decision": "approved"}]},
        )  # fmt: skip
        assert response.status_code == 404 and str(instance_id) in response.json()["detail"]
    assert instances(c, review.other_id)[0]["decision"] == "pending"
    bad = c.post(f"{url}/decisions", json={"decisions": [{"instance_id": 1, "version": 1,
                                                         "decision": "maybe"}]})  # fmt: skip
    assert bad.status_code == 422 and "decisions[0].decision" in bad.json()["detail"]


def test_recompute_needs_a_clutter_run(review: Review) -> None:
    empty = add_survey(review.engine, "empty", ["h0"])
    response = review.reviewer.post(f"{base(empty)}/recompute")
    assert response.status_code == 409 and "run clutter" in response.json()["detail"]


def test_bad_clutter_configs_are_refused_when_queued(review: Review) -> None:
    c = review.reviewer
    for kind, config, field in (
        ("run:clutter", {"mode": "everything"}, "config.mode"),
        ("run:clutter", {"padding": 3}, "config.padding"),
        ("run:clutter", {"tile_length": 5}, "config.tile_length"),
        ("clutter:recompute", {"force": True}, "config.force"),
    ):
        body = {"kind": kind, "survey_id": review.survey_id, "config": config}
        response = c.post("/jobs", json=body)
        assert response.status_code == 422 and response.json()["detail"].startswith(field)


def wait_for(client: httpx.Client, job_id: int, timeout: float = 600.0) -> dict:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        job = client.get(f"/jobs/{job_id}").json()
        if job["status"] in ("succeeded", "failed", "cancelled", "interrupted"):
            assert job["status"] == "succeeded", job
            return job
        time.sleep(0.5)
    raise AssertionError(f"job {job_id} still not finished after {timeout} s")


def test_review_loop_with_the_worker_pool(review: Review, weights_dir: Path) -> None:  # noqa: F811
    """run:clutter on a 7-frame simulated street through /jobs, one approval and one rejection,
    then POST /recompute: the cleaned map changes by exactly those instances' points."""
    folder = Path(review.server.env["MMSCLEAN_IMPORT_ROOT"]) / "street"
    simulate(SimulationConfig(scene="urban", length=6.0, seed=5), folder)
    c = review.reviewer
    imported = c.post("/surveys/import", json={"path": str(folder), "format": "sim"})
    assert imported.status_code == 201, imported.text
    survey_id = imported.json()["id"]
    job = c.post("/jobs", json={"kind": "run:clutter", "survey_id": survey_id,
                                "config": {"threads": 1}})  # fmt: skip
    assert job.status_code == 201, job.text
    run = wait_for(c, job.json()["id"])
    items = instances(c, survey_id)
    assert len(items) == run["result"]["counts"]["instances"] > 0
    members = {
        f: np.load(Path(run["result"]["files"]["instances"]) / f"{f}.npz")
        for f in {i["frame_id"] for i in items}
    }

    def split(item: dict) -> tuple[int, int]:
        m = members[item["frame_id"]]
        mine = m["instance"] == item["instance_index"]
        return int((mine & m["removed"]).sum()), int((mine & ~m["removed"]).sum())

    approve = max(items, key=lambda i: split(i)[1])
    reject = max((i for i in items if i["id"] != approve["id"]), key=lambda i: split(i)[0])
    assert split(approve)[1] > 0 and split(reject)[0] > 0  # both decisions change the map
    decided = c.post(
        f"{base(survey_id)}/decisions",
        json={
            "decisions": [
                {"instance_id": approve["id"], "version": 1, "decision": "approved"},
                {"instance_id": reject["id"], "version": 1, "decision": "rejected"},
            ]
        },
    )
    assert decided.status_code == 200, decided.text
    queued = c.post(f"{base(survey_id)}/recompute")
    assert queued.status_code == 202, queued.text
    assert queued.json()["kind"] == "clutter:recompute"
    done = wait_for(c, queued.json()["id"])
    cleaned = len(laspy.read(done["result"]["files"]["cleaned"]).points)
    before = len(laspy.read(run["result"]["files"]["cleaned"]).points)
    assert cleaned == before - split(approve)[1] + split(reject)[0]
    removed = len(laspy.read(done["result"]["files"]["removed"]).points)
    assert cleaned + removed == run["result"]["counts"]["points"]
