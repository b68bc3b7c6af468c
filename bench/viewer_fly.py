"""The viewer on a long survey through a real server (`bench.scale viewer-wire`): a real
`mmsclean serve` on loopback with the survey imported, and a client speaking viser's wire
format through the `/viewer/ws` relay, as the browser does (`tests/viewer/wire.py`; nothing is
drawn). Measured: how long the import's `prepare:viewer` job takes to build the viewer's map,
the first scene of the first open after it and of a second open, then a camera flying along
the drive: at every 50 m of trajectory the look-at point moves there and the client waits for
the tile in focus; the server process's memory is read after every tile.
"""

from __future__ import annotations

import asyncio
import statistics
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from app.geometry.trajectory import arc_length
from bench.common import process_memory_mb
from bench.viewer import first_scene, import_survey, login, relay_url
from tests.api.server import ADMIN_PASSWORD, Server
from tests.viewer.wire import WireClient, camera_message, is_point_cloud

FLY_STEP_M = 50.0  # metres of trajectory between camera moves (the viewer's tiles are 50 m)
TILE_TIMEOUT_S = 60.0


def _stations_along(trajectory: np.ndarray, step: float) -> np.ndarray:
    """Positions every `step` metres along the trajectory (horizontal arc length)."""
    along = arc_length(np.column_stack([trajectory[:, :2], np.zeros(len(trajectory))]))
    at = np.arange(0.0, along[-1], step)
    return np.column_stack([np.interp(at, along, trajectory[:, k]) for k in range(3)])


def _camera_at(look: np.ndarray) -> tuple[tuple, tuple]:
    """(look_at, position): looking down at `look` from behind-left, as the viewer does."""
    at = tuple(float(v) for v in look)
    return at, (at[0] - 20.0, at[1] - 20.0, at[2] + 25.0)


async def fly(server: Server, token: str, survey_id: int, path_local: np.ndarray) -> dict:
    """The camera moved along `path_local` (scene coordinates); per move, seconds to the new
    tile's points (moves that stay in the shown tile get none: counted apart)."""
    pid = server.process.pid
    client = await WireClient.open(relay_url(server, survey_id), token)
    await client.hello()
    await client.wait_for(is_point_cloud, 600)  # the overview
    seconds, points, rss, anon, same = [], [], [], [], 0
    for look in path_local:
        started = time.perf_counter()
        await client.send(camera_message(*_camera_at(look)))
        try:
            arrived, tile = await client.wait_for(is_point_cloud, TILE_TIMEOUT_S)
        except TimeoutError:
            same += 1
            continue
        seconds.append(arrived - started)
        points.append(len(tile["props"]["points"]) // 3)
        r, a = process_memory_mb(pid)
        rss.append(r)
        anon.append(a)
    await client.close()
    return {
        "moves": len(path_local), "tiles": len(seconds), "no_new_tile": same,
        "tile_s_median": statistics.median(seconds), "tile_s_max": max(seconds),
        "tile_points_median": statistics.median(points),
        "rss_mb_max": max(rss), "anon_mb_max": max(anon), "anon_mb_first": anon[0],
    }  # fmt: skip


@contextmanager
def imported(source: Path) -> Iterator[tuple[Server, dict, float | None, str]]:
    """A fresh server on loopback with `source` (a simulated survey folder) imported and the
    map its import queued built: (server, survey record, seconds to that map, admin token)."""
    with tempfile.TemporaryDirectory() as tmp:
        env = {
            "MMSCLEAN_SAMPLE_DIR": "",
            "MMSCLEAN_IMPORT_ROOT": str(source.parent),
            "MMSCLEAN_RETRAIN_EVERY": "0",
            "MMSCLEAN_WORKERS": "1",
        }
        server = Server(Path(tmp) / "var", env=env).start()
        try:
            api = server.client()
            started = time.perf_counter()
            record = import_survey(api, source)
            prepared_s = _prepared(api, record["id"], started)
            token = login(server, "admin", ADMIN_PASSWORD)
            time.sleep(5.0)  # the server's worker processes finish starting
            yield server, record, prepared_s, token
        finally:
            server.stop()


def measure(source: Path) -> dict:
    """Import `source` (a simulated survey folder) into a fresh server, wait for the map the
    import queued, then two first scenes and the flight."""
    from app.io import open_survey

    trajectory = open_survey(source, "sim").poses()[:, :3, 3]
    with imported(source) as (server, record, prepared_s, token):
        survey_id = record["id"]
        api = server.client()
        origin = np.asarray(api.get(f"/surveys/{survey_id}").json()["origin"], dtype=float)
        path = _stations_along(trajectory, FLY_STEP_M) - origin
        start = _camera_at(path[0])  # the map's middle may hold no point on a looping drive
        first = asyncio.run(first_scene(server, token, survey_id, False, start))
        again = asyncio.run(first_scene(server, token, survey_id, False, start))
        after_open = process_memory_mb(server.process.pid)
        flight = asyncio.run(fly(server, token, survey_id, path))
    return {"points": int(record["point_count"]), "prepared_s": prepared_s, "first": first,
            "again": again, "after_open_mb": after_open, "flight": flight}  # fmt: skip


def _prepared(api, survey_id: int, since: float) -> float | None:
    """Seconds from the import's request until the `prepare:viewer` job it queued finished
    (None where it queued none: a small survey's map is built on its first open)."""
    job = api.get(f"/surveys/{survey_id}").json()["latest_jobs"].get("prepare:viewer")
    if job is None:
        return None
    while True:
        state = api.get(f"/jobs/{job['id']}").json()
        if state["status"] == "succeeded":
            return time.perf_counter() - since
        if state["status"] in ("failed", "cancelled", "interrupted"):
            raise RuntimeError(f"prepare:viewer job {job['id']} {state['status']}: {state}")
        time.sleep(0.5)
