"""Web app backend benchmark: a real `mmsclean serve` on loopback with a fresh SQLite file.

1. Batch upsert: PUT of 10,000 pillar labels (one undoable action each), p50 / p90 over
   `--batches` batches to fresh cells, then the same over cells that already have labels.
   Target p50 <= 300 ms.
2. Tile read: GET the labels of a 100 m x 100 m tile (500 x 500 pillars of 0.2 m). Two tile
   densities: a street tile where every pillar that holds points (45,000, measured on the
   sample survey: 25,822 occupied pillars on 60 m of street) has a human label AND a model
   pre-label (90,000 entries; in practice the model labels only the ~7 % of pillars with
   objects), and the worst case, every pillar of the tile labelled by both (500,000 entries).
   Target <= 100 ms. Baseline in the same run: the same rows read without the covering index
   (`NOT INDEXED`), straight from SQLite in this process.
3. Concurrency: 20 clients, each its own user, writing batches of 100 labels for 60 s to their
   own cells (each cell written several times). Afterwards every acknowledged write is checked
   in the database: the final label of each cell is the last acknowledged one (0 lost), its
   version equals the number of acknowledged writes to it and the edit log holds exactly one
   row per acknowledged label (0 duplicated). p50 / p99 latency of the writes.
4. Contention: the same clients all label the same 100 pillars with the versions they saw,
   `--erase-share` (30 %) of the pillar writes erasing; no acknowledged write may replace a
   label (or an erase) its client never saw (0 replaced unseen), checked against the server's
   edit log in commit order, and every pillar must end as its last write left it (0 wrong).

    .venv/bin/python -m bench.api [--batches 20] [--clients 20] [--seconds 60] [--no-record]
        [--only upsert tile concurrency contention] [--erase-share 0.3] [--note TEXT]
"""

from __future__ import annotations

import argparse
import shlex
import sqlite3
import statistics
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path

import httpx
import numpy as np

from app.store.pillar_labels import STORE_GRID
from bench.common import append_results, markdown_table
from tests.api.server import Server

SCENARIOS = ("upsert", "tile", "concurrency", "contention")
TILE_PILLARS = 500  # 100 m / 0.2 m
# The sample survey (60 m of urban street) has 25,822 occupied pillars, ~43,000 per 100 m: a
# street tile is 45,000 pillars (an 18 m corridor), each with a human label and a model one.
STREET_CORRIDOR = 90


def percentile(values: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(values), q)) if values else float("nan")


def grid_cells(ix0: int, iy0: int, nx: int, ny: int) -> np.ndarray:
    ix, iy = np.meshgrid(np.arange(ix0, ix0 + nx), np.arange(iy0, iy0 + ny), indexing="ij")
    return STORE_GRID.cell_id(ix.ravel(), iy.ravel())


def new_survey(database: Path, name: str) -> int:
    with sqlite3.connect(database) as conn:
        cursor = conn.execute(
            "INSERT INTO survey (created_at, updated_at, version, name, format, source_path,"
            " frame_count, point_count, has_reference_labels, poses_estimated, origin_x,"
            " origin_y, origin_z) VALUES (datetime('now'), datetime('now'), 1, ?, 'sim', '/b',"
            " 0, 0, 0, 0, 0, 0, 0)",
            (name,),
        )
        return int(cursor.lastrowid)


def put(client: httpx.Client, survey: int, cells: np.ndarray, labels: np.ndarray) -> float:
    body = {
        "labels": [
            {"cell_id": c, "label": v} for c, v in zip(cells.tolist(), labels.tolist(), strict=True)
        ]
    }
    t0 = time.perf_counter()
    response = client.put(f"/surveys/{survey}/pillars/labels", json=body)
    elapsed = (time.perf_counter() - t0) * 1e3
    response.raise_for_status()
    return elapsed


def bench_upsert(server: Server, batches: int) -> list[list[str]]:
    survey = new_survey(server.data_dir / "mmsclean.sqlite3", "upsert")
    rng = np.random.default_rng(0)
    rows = []
    with server.client() as client:
        for what, offset in (("new cells", 0), ("cells already labelled", 0)):
            times = []
            for b in range(batches + 2):  # 2 warm-up batches
                cells = grid_cells(offset + 100 * (b % (batches + 2)), 0, 100, 100)
                ms = put(client, survey, cells, rng.integers(0, 4, len(cells)))
                if b >= 2:
                    times.append(ms)
            rows.append(
                [
                    f"PUT 10,000 labels ({what})",
                    f"{statistics.median(times):.0f}",
                    f"{percentile(times, 90):.0f}",
                    "<= 300",
                ]
            )
    return rows


def fill_tile(database: Path, survey: int, cells: np.ndarray) -> None:
    """Human and model labels for the cells, written straight into the database."""
    labels = (np.arange(len(cells)) % 4).tolist()
    with sqlite3.connect(database) as conn:
        for source, confidence in (("human", None), ("model", 0.8)):
            conn.executemany(
                "INSERT INTO pillar_label (survey_id, cell_id, label, source, confidence,"
                " version, created_at, updated_at) VALUES (?, ?, ?, ?, ?, 1, datetime('now'),"
                " datetime('now'))",
                [
                    (survey, c, v, source, confidence)
                    for c, v in zip(cells.tolist(), labels, strict=True)
                ],
            )


def bench_tile(server: Server, repeats: int) -> list[list[str]]:
    database = server.data_dir / "mmsclean.sqlite3"
    rows = []
    with server.client() as client:
        tiles = (("street tile", 200, STREET_CORRIDOR), ("full tile", 0, TILE_PILLARS))
        for what, iy0, corridor in tiles:
            survey = new_survey(database, what)
            fill_tile(database, survey, grid_cells(0, iy0, TILE_PILLARS, corridor))
            box = {"x0": 0.0, "y0": 0.0, "x1": 99.99, "y1": 99.99}
            url = f"/surveys/{survey}/pillars/labels"
            entries = len(client.get(url, params=box).json()["cell_id"])
            times = []
            for _ in range(repeats):
                t0 = time.perf_counter()
                response = client.get(url, params=box)
                response.raise_for_status()
                times.append((time.perf_counter() - t0) * 1e3)
            baseline = _baseline_read_ms(database, survey, repeats=3)
            rows.append(
                [
                    f"GET 100 m x 100 m tile, {what} ({entries:,} labels)",
                    f"{statistics.median(times):.0f}",
                    f"{percentile(times, 90):.0f}",
                    "<= 100",
                    f"{baseline:.0f} ms in-process SQL without the covering index",
                ]
            )
    return rows


def _baseline_read_ms(database: Path, survey: int, repeats: int) -> float:
    times = []
    with sqlite3.connect(database) as conn:
        for _ in range(repeats):
            t0 = time.perf_counter()
            conn.execute(
                "SELECT cell_id, source, label, version, confidence, user_id FROM pillar_label "
                "NOT INDEXED WHERE survey_id = ?",
                (survey,),
            ).fetchall()
            times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)


def run_clients(writer: Callable[[int], None], sessions: list[httpx.Client]) -> None:
    """writer(k) for every client k on its own thread; then the clients are closed."""
    threads = [threading.Thread(target=writer, args=(k,)) for k in range(len(sessions))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for session in sessions:
        session.close()


def stored_human_labels(database: Path, survey: int) -> dict[int, tuple[int | None, int]]:
    """cell_id -> (label, version) of the survey's human labels, read straight from SQLite;
    label None for an erased one (its tombstone)."""
    with sqlite3.connect(database) as conn:
        rows = conn.execute(
            "SELECT cell_id, label, version FROM pillar_label WHERE survey_id = ? AND "
            "source = 'human' UNION ALL SELECT cell_id, NULL, version FROM pillar_tombstone "
            "WHERE survey_id = ?",
            (survey, survey),
        )
        return {c: (label, version) for c, label, version in rows}


def edit_log(database: Path, survey: int) -> dict[int, list[tuple[int, int | None]]]:
    """cell_id -> [(batch id, label after)] of every committed write, in commit order (SQLite
    has one writer at a time: batch ids are handed out in commit order)."""
    log: dict[int, list[tuple[int, int | None]]] = {}
    with sqlite3.connect(database) as conn:
        rows = conn.execute(
            "SELECT e.cell_id, e.batch_id, e.after_label FROM pillar_edit AS e "
            "JOIN pillar_edit_batch AS b ON b.id = e.batch_id WHERE b.survey_id = ? "
            "ORDER BY e.batch_id",
            (survey,),
        )
        for cell, batch, label in rows:
            log.setdefault(cell, []).append((batch, label))
    return log


def bench_concurrency(server: Server, clients: int, seconds: float) -> tuple[list[list[str]], dict]:
    database = server.data_dir / "mmsclean.sqlite3"
    survey = new_survey(database, "concurrency")
    sessions = [server.add_user(f"writer{i}", "annotator") for i in range(clients)]
    cells_per_client = 1000
    acked: list[list[tuple[np.ndarray, np.ndarray]]] = [[] for _ in range(clients)]
    latencies: list[list[float]] = [[] for _ in range(clients)]
    failures: list[str] = []
    stop = time.monotonic() + seconds

    def writer(k: int) -> None:
        rng = np.random.default_rng(k)
        mine = grid_cells(10_000 + 50 * k, 0, 50, cells_per_client // 50)
        while time.monotonic() < stop:
            cells = rng.choice(mine, size=100, replace=False)
            labels = rng.integers(0, 4, size=100)
            try:
                latencies[k].append(put(sessions[k], survey, cells, labels))
                acked[k].append((cells, labels))
            except httpx.HTTPError as exc:  # a failed write is reported, not counted as acked
                failures.append(f"client {k}: {exc}")

    run_clients(writer, sessions)

    expected_label: dict[int, int] = {}
    expected_writes: dict[int, int] = {}
    total_acked = 0
    for batches in acked:
        for cells, labels in batches:
            total_acked += len(cells)
            for c, v in zip(cells.tolist(), labels.tolist(), strict=True):
                expected_label[c] = v
                expected_writes[c] = expected_writes.get(c, 0) + 1
    stored = stored_human_labels(database, survey)
    with sqlite3.connect(database) as conn:
        edits = conn.execute(
            "SELECT count(*) FROM pillar_edit JOIN pillar_edit_batch b ON b.id = batch_id "
            "WHERE b.survey_id = ?",
            (survey,),
        ).fetchone()[0]
    lost = sum(1 for c, v in expected_label.items() if stored.get(c, (None,))[0] != v)
    wrong_versions = sum(1 for c, n in expected_writes.items() if stored.get(c, (None, -1))[1] != n)
    duplicated = (edits - total_acked) + sum(1 for c in stored if c not in expected_label)
    everything = [ms for per in latencies for ms in per]
    row = [
        f"{clients} clients x {seconds:g} s, batches of 100",
        f"{len(everything):,} writes ({total_acked:,} labels)",
        f"{statistics.median(everything):.0f}",
        f"{percentile(everything, 99):.0f}",
        str(lost),
        str(duplicated + wrong_versions),
        str(len(failures)),
    ]
    return [row], {"failures": failures[:5]}


def bench_contention(
    server: Server, clients: int, seconds: float, erase_share: float
) -> tuple[list[list[str]], dict]:
    """Every client labels the same 100 pillars (5 per batch, `erase_share` of them erased),
    each write carrying the versions the client last saw; a 409 tells it the current ones.
    Afterwards, against the server's edit log in commit order: a write whose client saw version
    v must be the pillar's (v + 1)-th write (versions count writes: v is the state after the
    v-th), else it replaced a state its client never saw; each pillar must end with its last
    write's label and as many versions as writes, and no write may be in the log unacknowledged.
    """
    database = server.data_dir / "mmsclean.sqlite3"
    survey = new_survey(database, "contention")
    sessions = [server.add_user(f"contender{i}", "annotator") for i in range(clients)]
    shared = grid_cells(20_000, 0, 10, 10)
    acked: list[tuple[int, int, int | None, int]] = []  # (cell, version seen, label, batch id)
    refused: list[int] = [0]
    latencies: list[float] = []
    failures: list[str] = []
    lock = threading.Lock()
    stop = time.monotonic() + seconds

    def writer(k: int) -> None:
        rng = np.random.default_rng(100 + k)
        seen = dict.fromkeys(shared.tolist(), 0)
        url = f"/surveys/{survey}/pillars/labels"
        while time.monotonic() < stop:
            cells = rng.choice(shared, size=5, replace=False).tolist()
            labels = [
                None if erase else int(v)
                for v, erase in zip(rng.integers(0, 4, 5), rng.random(5) < erase_share, strict=True)
            ]
            body = [
                {"cell_id": c, "label": v, "version": seen[c]}
                for c, v in zip(cells, labels, strict=True)
            ]
            t0 = time.perf_counter()
            try:
                response = sessions[k].put(url, json={"labels": body})
            except httpx.HTTPError as exc:
                failures.append(f"client {k}: {exc}")
                continue
            ms = (time.perf_counter() - t0) * 1e3
            if response.status_code == 409:
                for current in response.json()["current"]:
                    seen[current["cell_id"]] = current["version"]
                with lock:
                    refused[0] += 1
                    latencies.append(ms)
                continue
            if response.status_code != 200:
                failures.append(f"client {k}: {response.status_code} {response.text[:200]}")
                continue
            out = response.json()
            with lock:
                acked.extend(
                    (c, seen[c], v, out["batch_id"]) for c, v in zip(cells, labels, strict=True)
                )
                latencies.append(ms)
            seen.update(zip(out["cell_id"], out["version"], strict=True))

    run_clients(writer, sessions)

    log = edit_log(database, survey)
    position = {(c, batch): n for c, writes in log.items() for n, (batch, _) in enumerate(writes)}
    unseen = sum(1 for c, v, _, batch in acked if position.get((c, batch)) != v)
    unacknowledged = sum(len(w) for w in log.values()) - len(acked)
    stored = stored_human_labels(database, survey)
    wrong = sum(1 for c, writes in log.items() if stored.get(c) != (writes[-1][1], len(writes)))
    erased = sum(1 for _, _, v, _ in acked if v is None)
    row = [
        f"{clients} clients x {seconds:g} s on the same 100 pillars, batches of 5 with versions, "
        f"{erase_share:.0%} of the pillar writes erase",
        f"{len(acked) // 5:,} writes acknowledged ({erased:,} of {len(acked):,} pillar writes "
        f"erases), {refused[0]:,} refused (409)",
        f"{statistics.median(latencies):.0f}",
        f"{percentile(latencies, 99):.0f}",
        str(unseen),
        str(wrong),
        str(len(failures) + unacknowledged),
    ]
    return [row], {"failures": failures[:5]}


CONTENTION_NOTE = (
    "Replaced unseen: acknowledged pillar writes whose client saw version v while the server's "
    "edit log (commit order) has a number of earlier writes of that pillar other than v: the "
    "write replaced a label (or an erase) its client never saw. Wrong: pillars whose stored "
    "label (none: erased) / version is not their last write's / their number of writes. Failed: "
    "failed requests plus writes in the log nobody acknowledged. p50 / p99 over all answers, "
    "409 included."
)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batches", type=int, default=20)
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--clients", type=int, default=20)
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--only", nargs="+", choices=SCENARIOS, default=list(SCENARIOS))
    parser.add_argument("--erase-share", type=float, default=0.3, help="of contention writes")
    parser.add_argument("--note", default="", help="added to the recorded entry (e.g. load)")
    parser.add_argument("--no-record", action="store_true")
    args = parser.parse_args()
    if not 0.0 <= args.erase_share <= 1.0:
        parser.error(f"--erase-share: must be 0-1, got {args.erase_share}")

    upsert: list[list[str]] = []
    tile: list[list[str]] = []
    concurrency: list[list[str]] = []
    contention: list[list[str]] = []
    failures: list[str] = []
    with tempfile.TemporaryDirectory(prefix="mmsclean-bench-api-") as tmp:
        env = {"MMSCLEAN_SAMPLE_DIR": "", "MMSCLEAN_WORKERS": "1", "MMSCLEAN_RETRAIN_EVERY": "0"}
        server = Server(Path(tmp) / "var", env=env)
        server.start()
        try:
            if "upsert" in args.only:
                upsert = bench_upsert(server, args.batches)
            if "tile" in args.only:
                tile = bench_tile(server, args.repeats)
            if "concurrency" in args.only:
                concurrency, info = bench_concurrency(server, args.clients, args.seconds)
                failures += info["failures"]
            if "contention" in args.only:
                contention, info = bench_contention(
                    server, args.clients, args.seconds, args.erase_share
                )
                failures += info["failures"]
        finally:
            server.stop()

    sections: list[str] = []
    speed = upsert + [r[:4] for r in tile]
    if speed:
        sections.append(markdown_table(["operation", "p50 ms", "p90 ms", "target"], speed))
        sections.append(
            "Server: `mmsclean serve` (one uvicorn process, SQLite WAL file, one job worker "
            "idle) on 127.0.0.1, client httpx in the same machine. Times are client-side, "
            "JSON encoding and HTTP included."
        )
    if tile:
        sections.append("\n".join(f"- {r[0]}: baseline {r[4]}" for r in tile))
    if concurrency:
        sections.append(
            markdown_table(
                ["load", "acknowledged", "p50 ms", "p99 ms", "lost", "duplicated", "failed"],
                concurrency,
            )
        )
        sections.append(
            "Lost: acknowledged labels whose cell does not hold the last acknowledged value. "
            "Duplicated: edit-log rows beyond the acknowledged labels, stored labels nobody "
            "acknowledged, and cells whose version differs from their acknowledged writes."
        )
    if contention:
        sections.append(
            markdown_table(
                ["load", "writes", "p50 ms", "p99 ms", "replaced unseen", "wrong", "failed"],
                contention,
            )
        )
        sections.append(CONTENTION_NOTE)
    if args.note:
        sections.append(args.note)
    print(*sections, sep="\n\n")
    if failures:
        print("first failures:", *failures, sep="\n  ")
    if not args.no_record:
        command = (
            f".venv/bin/python -m bench.api --batches {args.batches} --repeats {args.repeats} "
            f"--clients {args.clients} --seconds {args.seconds:g}"
        )
        if list(args.only) != list(SCENARIOS):
            command += " --only " + " ".join(args.only)
        if "contention" in args.only:
            command += f" --erase-share {args.erase_share:g}"
        if args.note:
            command += f" --note {shlex.quote(args.note)}"
        append_results(
            "Web app backend: pillar label API", command, sections[0], "\n\n".join(sections[1:])
        )


if __name__ == "__main__":
    main()
