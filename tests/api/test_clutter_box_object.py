"""A missed object from a 2D box on the camera image, through a real server, on a real
SemanticKITTI frame (08, frame 0; a clutter run's membership written here with one instance):
a box drawn round a parked car (the reference labels' extent on the image, 6 px wider) adds
that car's points, the facade and road around it left out; the same box round the car that is
an instance already is 422; a box off the image names `box`; the schema bounds the numbers."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import httpx
import numpy as np
import pytest
from sqlmodel import Session

from app.geometry.projection import project
from app.io import open_survey
from app.store.clutter_review import replace_instances
from app.store.db import make_engine
from app.store.surveys import register_opened_survey
from tests.api.server import Server
from tests.api.test_clutter_review import base

pytestmark = pytest.mark.real_data
FRAME = "000000"


@dataclass
class Street:
    server: Server
    reviewer: httpx.Client
    survey_id: int
    boxes: dict[int, dict[str, float]]  # label (semantic | instance << 16) -> its box
    labels: np.ndarray  # per point of the frame


@pytest.fixture(scope="module")
def street(tmp_path_factory: pytest.TempPathFactory, real_data: Path) -> Iterator[Street]:
    root = tmp_path_factory.mktemp("clutter-box-api")
    source = real_data / "semantickitti" / "sequences" / "08"
    survey = open_survey(source, "semantickitti")
    frame = next(f for f in survey.frames if f.frame_id == FRAME)
    camera = next(iter(survey.cameras.values()))
    labels = np.fromfile(source / "labels" / f"{FRAME}.label", dtype="<u4")
    proj = project(frame.points().xyz, camera.P, camera.T_cam_sensor, camera.width, camera.height)
    # the two largest parked or moving cars in view, by their points on the image
    car = np.isin(labels & 0xFFFF, (10, 252)) & proj.in_image
    ids, counts = np.unique(labels[car], return_counts=True)
    largest = ids[np.argsort(counts)[::-1][:2]]
    boxes = {}
    for label in largest:
        uv = proj.uv[car & (labels == label)]
        (u0, v0), (u1, v1) = uv.min(axis=0) - 6, uv.max(axis=0) + 6
        boxes[int(label)] = {"u0": float(u0), "v0": float(v0), "u1": float(u1), "v1": float(v1)}
    # a clutter run's membership: the second car is instance 0 already
    owner = np.where(labels == largest[1], 0, -1).astype(np.int32)
    folder = root / "run" / "instances"
    (folder / FRAME).mkdir(parents=True)
    np.savez(folder / f"{FRAME}.npz", instance=owner, removed=owner >= 0, in_view=owner >= 0)
    cv2.imwrite(str(folder / FRAME / "0.png"), np.full((8, 8, 3), 50, np.uint8))
    server = Server(root / "var", env={"MMSCLEAN_SAMPLE_DIR": "", "MMSCLEAN_WORKERS": "1"})
    server.start()
    engine = make_engine(f"sqlite:///{server.data_dir / 'mmsclean.sqlite3'}")
    with Session(engine) as session:
        record = register_opened_survey(session, survey, format="semantickitti", source_path=source)
        replace_instances(
            session, record.id,
            [{"frame_id": FRAME, "instance_index": 0, "class_name": "car",
              "point_count": int((owner == 0).sum()), "mask_path": str(folder / FRAME / "0.png"),
              "bbox": None, "moving": None, "track_id": None}],
            None,
        )  # fmt: skip
        survey_id = record.id
    engine.dispose()
    reviewer = server.add_user("box-reviewer", "reviewer")
    yield Street(server, reviewer, survey_id, boxes, labels)
    reviewer.close()
    server.stop()


def test_a_box_round_a_parked_car_adds_that_car(street: Street) -> None:
    url = f"{base(street.survey_id)}/frames/{FRAME}/objects/box"
    free_car, instance_car = list(street.boxes)
    added = street.reviewer.post(url, json={"class_name": "car", "box": street.boxes[free_car]})
    assert added.status_code == 201, added.text
    body = added.json()
    item = body["instance"]
    assert item["class_name"] == "car" and item["decision"] == "approved"
    assert item["instance_index"] == 1
    car_points = int((street.labels == free_car).sum())
    # its points: the car's (the reference labels), hardly anything else
    assert 0.9 * car_points <= body["points"] <= 1.05 * car_points
    assert item["bbox"] == [int(np.floor(street.boxes[free_car][k])) if k[1] == "0"
                            else int(np.ceil(street.boxes[free_car][k]))
                            for k in ("u0", "v0", "u1", "v1")]  # fmt: skip
    # the car that is an instance already: nothing free to add, never the facade behind it
    again = street.reviewer.post(url, json={"class_name": "car", "box": street.boxes[instance_car]})
    assert again.status_code == 422 and "box" in again.json()["detail"], again.text


def test_bad_boxes_are_4xx(street: Street) -> None:
    url = f"{base(street.survey_id)}/frames/{FRAME}/objects/box"
    off = {"u0": 5000.0, "v0": 10.0, "u1": 5100.0, "v1": 40.0}
    cases = [
        (url, {"class_name": "car", "box": off}, 422, "covers no pixel"),
        (url, {"class_name": "car", "box": {**off, "u0": -1.0}}, 422, "u0"),
        (url, {"class_name": "car", "box": {**off, "v1": 1e9}}, 422, "v1"),
        (url, {"class_name": "tree", "box": off}, 422, "class_name"),
        (url.replace(FRAME, "999999"), {"class_name": "car", "box": off}, 404, "999999"),
    ]
    for path, body, status, words in cases:
        answer = street.reviewer.post(path, json=body)
        assert answer.status_code == status, (body, answer.text)
        assert words in answer.text, answer.text
    annotator = street.server.add_user("box-annotator", "annotator")
    refused = annotator.post(url, json={"class_name": "car", "box": off})
    assert refused.status_code == 403
    annotator.close()
