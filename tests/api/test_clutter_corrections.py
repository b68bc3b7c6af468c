"""Corrections of clutter instances through a real server: points taken out of an instance
(versions, 409 with the current state), a missed object added (201), and the 4xx answers for
bad input, roles, unknown ids and a survey without a run. The membership is a run folder
written here as a clutter run writes it; recompute on a real run: tests/jobs."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import cv2
import httpx
import numpy as np
import pytest
from sqlmodel import Session

from app.store.clutter_review import replace_instances
from app.store.db import make_engine
from tests.api.server import Server
from tests.api.test_clutter_review import add_survey, base, instances

# frame f0: 10 points; instance 0 owns 0-2 (0 and 1 removed by the pipeline), instance 1 owns
# 3-4, the rest belong to no instance
OWNER = np.array([0, 0, 0, 1, 1, -1, -1, -1, -1, -1], np.int32)
REMOVED = np.array([1, 1, 0, 1, 1, 0, 0, 0, 0, 0], bool)


@dataclass
class Review:
    server: Server
    annotator: httpx.Client
    reviewer: httpx.Client
    survey_id: int
    bare_id: int  # a survey without a clutter run


@pytest.fixture(scope="module")
def review(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Review]:
    root = tmp_path_factory.mktemp("clutter-corrections-api")
    server = Server(root / "var", env={"MMSCLEAN_SAMPLE_DIR": "", "MMSCLEAN_WORKERS": "1"})
    server.start()
    engine = make_engine(f"sqlite:///{server.data_dir / 'mmsclean.sqlite3'}")
    survey_id = add_survey(engine, "street", ["f0", "f1"])
    bare_id = add_survey(engine, "bare", ["g0"])
    folder = root / "run" / "instances"
    (folder / "f0").mkdir(parents=True)
    for frame_id in ("f0", "f1"):
        np.savez(folder / f"{frame_id}.npz", instance=OWNER, removed=REMOVED, in_view=REMOVED)
    rows = []
    for k in (0, 1):
        cv2.imwrite(str(folder / "f0" / f"{k}.png"), np.full((8, 8, 3), 50, np.uint8))
        rows.append(
            {"frame_id": "f0", "instance_index": k, "class_name": "car",
             "point_count": int((k == OWNER).sum()), "mask_path": str(folder / "f0" / f"{k}.png"),
             "bbox": None, "moving": None, "track_id": None}
        )  # fmt: skip
    with Session(engine) as session:
        replace_instances(session, survey_id, rows, None)
    engine.dispose()
    clients = (
        server.add_user("cc-annotator", "annotator"),
        server.add_user("cc-reviewer", "reviewer"),
    )
    yield Review(server, *clients, survey_id, bare_id)
    for client in clients:
        client.close()
    server.stop()


def test_remove_points_is_versioned(review: Review) -> None:
    c, url = review.reviewer, base(review.survey_id)
    first = instances(c, review.survey_id)[0]
    done = c.post(
        f"{url}/instances/{first['id']}/remove-points",
        json={"version": first["version"], "points": [1, 2, 3, 7]},  # 3: instance 1's, 7: none's
    )
    assert done.status_code == 200, done.text
    body = done.json()
    assert body["points"] == 2
    assert body["instance"]["version"] == first["version"] + 1
    assert body["instance"]["point_count"] == 1
    # the same version again: 409 with the instance as it is now
    stale = c.post(
        f"{url}/instances/{first['id']}/remove-points",
        json={"version": first["version"], "points": [0]},
    )
    assert stale.status_code == 409
    assert stale.json()["current"][0]["version"] == first["version"] + 1
    # the points already taken out are no longer the instance's: 422
    gone = c.post(
        f"{url}/instances/{first['id']}/remove-points",
        json={"version": first["version"] + 1, "points": [1, 2]},
    )
    assert gone.status_code == 422 and "none of the 2 points" in gone.json()["detail"]
    # a decision with the version seen before the correction is stale too
    decided = c.post(
        f"{url}/decisions",
        json={"decisions": [{"instance_id": first["id"], "version": 1, "decision": "approved"}]},
    )
    assert decided.status_code == 409


def test_add_object_takes_free_points_only(review: Review) -> None:
    c, url = review.reviewer, base(review.survey_id)
    added = c.post(f"{url}/frames/f0/objects", json={"class_name": "person", "points": [4, 5, 6]})
    assert added.status_code == 201, added.text
    body = added.json()
    assert body["points"] == 2  # point 4 stays instance 1's
    item = body["instance"]
    assert item["class_name"] == "person" and item["decision"] == "approved"
    assert item["version"] == 1 and item["instance_index"] == 2 and item["point_count"] == 2
    assert item["mask_url"] is None
    listed = {(i["frame_id"], i["instance_index"]) for i in instances(c, review.survey_id)}
    assert ("f0", 2) in listed
    # points already in an instance (one just added included): 422
    again = c.post(f"{url}/frames/f0/objects", json={"class_name": "car", "points": [5, 6]})
    assert again.status_code == 422 and "already belong" in again.json()["detail"]


def test_bad_corrections_are_4xx(review: Review) -> None:
    c, url = review.reviewer, base(review.survey_id)
    first = instances(c, review.survey_id)[0]
    remove = f"{url}/instances/{first['id']}/remove-points"
    cases = [
        (remove, {"version": first["version"], "points": [99]}, 422, "points[0]"),
        (remove, {"version": first["version"], "points": []}, 422, "points"),
        (remove, {"version": first["version"], "points": [-1]}, 422, "points"),
        (remove, {"version": 0, "points": [0]}, 422, "version"),
        (f"{url}/instances/999999/remove-points", {"version": 1, "points": [0]}, 404, "999999"),
        (f"{url}/frames/f0/objects", {"class_name": "tree", "points": [8]}, 422, "class_name"),
        (f"{url}/frames/nope/objects", {"class_name": "car", "points": [8]}, 404, "nope"),
        (f"{url}/frames/{'x' * 65}/objects", {"class_name": "car", "points": [8]}, 422, ""),
        (
            f"{base(review.bare_id)}/frames/g0/objects",
            {"class_name": "car", "points": [0]},
            409,
            "no clutter run",
        ),
    ]
    for path, body, status, words in cases:
        answer = c.post(path, json=body)
        assert answer.status_code == status, (path, body, answer.text)
        assert words in answer.text
    # annotators may not correct
    denied = review.annotator.post(
        f"{url}/frames/f0/objects", json={"class_name": "car", "points": [8]}
    )
    assert denied.status_code == 403
