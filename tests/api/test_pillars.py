"""Pillar labels through a real server: batch writes attributed to the user, tile reads, stale
versions, undo / redo, roles and validation."""

from __future__ import annotations

import sqlite3

import httpx
import pytest

from tests.api.server import Server


@pytest.fixture(scope="module")
def survey_id(server: Server) -> int:
    database = server.data_dir / "mmsclean.sqlite3"
    with sqlite3.connect(database) as conn:
        cursor = conn.execute(
            "INSERT INTO survey (created_at, updated_at, version, name, format, source_path,"
            " frame_count, point_count, has_reference_labels, poses_estimated, origin_x,"
            " origin_y, origin_z) VALUES (datetime('now'), datetime('now'), 1, 'p', 'sim', '/p',"
            " 0, 0, 0, 0, 0, 0, 0)"
        )
        return int(cursor.lastrowid)


def test_labels_written_by_position_are_stored_for_the_user(server: Server, survey_id: int) -> None:
    anna = server.add_user("pillar-anna", "annotator")
    url = f"/surveys/{survey_id}/pillars"
    body = {"labels": [{"x": 10.05, "y": 20.05, "label": 3}, {"x": 10.25, "y": 20.05, "label": 0}]}
    written = anna.put(f"{url}/labels", json=body)
    assert written.status_code == 200, written.text
    out = written.json()
    assert out["written"] == 2 and out["version"] == [1, 1]
    tile = anna.get(f"{url}/labels", params={"x0": 9, "y0": 19, "x1": 11, "y1": 21}).json()
    assert sorted(tile["label"]) == [0, 3]
    me = anna.get("/auth/me").json()["id"]
    assert set(tile["user_id"]) == {me} and set(tile["source"]) == {"human"}
    i = tile["label"].index(3)
    centre_x = tile["origin"][0] + (tile["ix"][i] + 0.5) * tile["cell_size"]
    assert centre_x == pytest.approx(10.1)
    stats = anna.get(f"{url}/stats").json()
    assert stats["human"] == [1, 0, 0, 1]

    # a stale version: 409 with the pillar as it is now, nothing written
    cell = out["cell_id"][0]
    stale = anna.put(
        f"{url}/labels", json={"labels": [{"cell_id": cell, "label": 1, "version": 0}]}
    )
    assert stale.status_code == 409
    assert stale.json()["current"][0]["label"] == 3
    assert anna.put(
        f"{url}/labels", json={"labels": [{"cell_id": cell, "label": 1, "version": 1}]}
    ).json()["version"] == [2]

    # undo restores, redo re-applies
    assert anna.post(f"{url}/undo").status_code == 200
    tile = anna.get(f"{url}/labels", params={"x0": 9, "y0": 19, "x1": 11, "y1": 21}).json()
    assert sorted(tile["label"]) == [0, 3]
    assert anna.post(f"{url}/redo").status_code == 200
    tile = anna.get(f"{url}/labels", params={"x0": 9, "y0": 19, "x1": 11, "y1": 21}).json()
    assert sorted(tile["label"]) == [0, 1]
    assert anna.post(f"{url}/redo").status_code == 409  # nothing left to redo
    anna.close()


def test_bad_payloads_name_the_field(server: Server, survey_id: int) -> None:
    with server.client() as admin:
        url = f"/surveys/{survey_id}/pillars/labels"
        bad = admin.put(
            url, json={"labels": [{"cell_id": 1, "label": 0}, {"cell_id": 2, "label": 9}]}
        )
        assert bad.status_code == 422
        assert bad.json()["detail"].startswith("labels[1].label:")
        nowhere = admin.put(url, json={"labels": [{"label": 1}]})
        assert nowhere.status_code == 422 and "cell_id" in nowhere.json()["detail"]
        twice = admin.put(
            url, json={"labels": [{"cell_id": 1, "label": 0}, {"cell_id": 1, "label": 1}]}
        )
        assert twice.status_code == 422 and "appears twice" in twice.json()["detail"]
        assert admin.put("/surveys/999/pillars/labels", json={"labels": []}).status_code == 404
        huge = admin.get(url, params={"x0": 0, "y0": 0, "x1": 5000, "y1": 5000})
        assert huge.status_code == 422 and huge.json()["detail"].startswith("box:")


def test_writes_need_a_token(server: Server, survey_id: int) -> None:
    response = httpx.put(
        f"{server.url}/surveys/{survey_id}/pillars/labels",
        json={"labels": [{"cell_id": 1, "label": 0}]},
    )
    assert response.status_code == 401


def test_a_write_over_an_erase_must_have_seen_the_erase(server: Server, survey_id: int) -> None:
    """The issue's lost update (ABA): ann labels a pillar, rev reads it (version 1), ann2
    erases it, ann labels it again; rev's write at version 1 must be 409, not replace ann's
    label unseen. An erase is a version: a tile lists it, and a write over it must send it."""
    ann, rev, ann2 = (server.add_user(f"aba-{n}", "annotator") for n in ("ann", "rev", "ann2"))
    url = f"/surveys/{survey_id}/pillars/labels"
    box = {"x0": 50.0, "y0": 60.0, "x1": 50.3, "y1": 60.3}
    first = ann.put(url, json={"labels": [{"x": 50.1, "y": 60.1, "label": 1, "version": 0}]})
    assert first.status_code == 200 and first.json()["version"] == [1]
    cell = first.json()["cell_id"][0]
    tile = rev.get(url, params=box).json()
    rev_saw = tile["version"][tile["cell_id"].index(cell)]
    erased = ann2.put(url, json={"labels": [{"cell_id": cell, "label": None, "version": 1}]})
    assert erased.status_code == 200 and erased.json()["version"] == [2]
    tile = ann.get(url, params=box).json()
    assert cell not in tile["cell_id"]  # no label, but a version to write over
    assert (tile["erased_cell_id"], tile["erased_version"]) == ([cell], [2])
    unseen = ann.put(url, json={"labels": [{"cell_id": cell, "label": 2, "version": 0}]})
    assert unseen.status_code == 409  # 0 is "never labelled": ann did not see the erase
    assert unseen.json()["current"][0] | {"updated_at": None} == {
        "cell_id": cell, "label": None, "version": 2,
        "user_id": ann2.get("/auth/me").json()["id"], "updated_at": None,
    }  # fmt: skip
    again = ann.put(url, json={"labels": [{"cell_id": cell, "label": 2, "version": 2}]})
    assert again.status_code == 200 and again.json()["version"] == [3]
    late = rev.put(url, json={"labels": [{"cell_id": cell, "label": 3, "version": rev_saw}]})
    assert late.status_code == 409, late.text
    assert late.json()["detail"].startswith("versions: 1 pillar(s) changed by someone else")
    assert late.json()["current"][0]["label"] == 2
    tile = rev.get(url, params=box).json()
    assert (tile["label"], tile["version"], tile["erased_cell_id"]) == ([2], [3], [])
    for client in (ann, rev, ann2):
        client.close()
