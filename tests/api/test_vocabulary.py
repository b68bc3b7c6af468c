"""`/vocabulary`: the label vocabulary the dashboard reads instead of keeping a copy of it."""

from __future__ import annotations

import httpx

from app.core.labels import PILLAR_CLASS_NAMES
from tests.api.server import Server


def test_the_vocabulary_is_the_core_labels_for_logged_in_users(server: Server) -> None:
    with server.client() as admin:
        answer = admin.get("/vocabulary")
    assert answer.status_code == 200
    assert answer.json() == {"pillar_classes": list(PILLAR_CLASS_NAMES)}
    assert list(PILLAR_CLASS_NAMES) == ["ground", "high object", "short object", "phantom"]
    assert httpx.get(f"{server.url}/vocabulary").status_code == 401
