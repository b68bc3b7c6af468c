"""What every tiled pipeline run shares: the tiles folder, resuming, and the loop that hands the
tiles to a `map_tiles` and each finished tile's summary to the run's assembly.

Each tile writes its files under OUT/tiles/ and last `NNNNN.json`, its summary: a tile is done
when its summary exists. A rerun into the same folder keeps the finished tiles as long as
`plan.json` (what the tiles' results depend on: survey, model, configuration, tiles) is the
same; a changed plan starts afresh.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable, Generator
from contextlib import closing
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from app.core.progress import Progress
from app.io.las import LasAppender
from app.pipelines.outputs import write_json

TILES = "tiles"
PLAN = "plan.json"
MAPS = ("cleaned", "removed")  # the maps a removing pipeline writes, OUT/<map>.laz

# runs `fn(spec, index, tile)` for the tiles given and yields the summaries as they finish, in
# any order: in this process by default, on a Dask cluster from `app.jobs.cluster` (whose
# `workers` attribute says how many tiles run at once: `tile_workers`)
TileMap = Callable[[Callable[..., dict], Any, Any, list[int]], Generator[dict]]


def in_process(fn: Callable[..., dict], spec: Any, index: Any, tiles: list[int]):
    """The tiles one after the other in this process."""
    for tile in tiles:
        yield fn(spec, index, tile)


def tile_workers(map_tiles: TileMap) -> int | None:
    """How many tiles `map_tiles` runs at once (its `workers`, set by `app.jobs.cluster`), None
    for tiles one after the other: the tile layouts round a short survey's tile count up to a
    multiple of it (`TileLayout.along`)."""
    return getattr(map_tiles, "workers", None)


def scan_map(map_tiles: TileMap) -> TileMap | None:
    """The `map_parts` of `TileIndex.build`: a cluster's, whose workers scan the survey's frames
    in parts side by side; None in this process, which scans the frames as they are (a survey
    built in memory has no source to reopen)."""
    return None if map_tiles is in_process else map_tiles


def tile_name(tile: int) -> str:
    return f"{tile:05d}"


def file_stamp(path: Path) -> list[int]:
    """Size and modification time: a plan names a model file by these too."""
    stat = Path(path).stat()
    return [stat.st_size, stat.st_mtime_ns]


def finished_tiles(out: Path, plan: dict) -> dict[int, dict]:
    """Summaries of the tiles an earlier attempt with the same plan finished; a different plan
    (or none) clears the tiles folder and records this one."""
    folder = Path(out) / TILES
    plan_path = folder / PLAN
    recorded = json.loads(plan_path.read_text()) if plan_path.is_file() else None
    if recorded != json.loads(json.dumps(plan)):
        shutil.rmtree(folder, ignore_errors=True)
        folder.mkdir(parents=True)
        write_json(plan_path, plan)
        return {}
    done = {}
    for path in sorted(folder.glob("[0-9]" * 5 + ".json")):
        summary = json.loads(path.read_text())
        done[int(summary["tile"])] = summary
    return done


def tiles_report(layout: Any, tiles_run: int, worker_peak_mb: float) -> dict:
    """A tiled run's `report.json` "tiles": how it was cut, and what this attempt ran."""
    return {
        "count": layout.count,
        "length_m": layout.length,
        "halo_m": layout.halo,
        "run": tiles_run,
        "kept_from_earlier_attempt": layout.count - tiles_run,
        "worker_peak_mb": worker_peak_mb,
    }


def tile_totals(summaries: list[dict]) -> dict:
    """What every tiled run adds up from its tiles' summaries: the seconds per step, summed,
    and the largest peak memory of a process that ran a tile."""
    timings: dict[str, float] = {}
    for s in summaries:
        for step, seconds in s["timings"].items():
            timings[step] = round(timings.get(step, 0.0) + seconds, 3)
    peak = max((s.get("worker_peak_mb", 0.0) for s in summaries), default=0.0)
    return {"timings": timings, "worker_peak_mb": peak}


def save_tile_arrays(out: Path, tile: int, **arrays: Any) -> Path:
    """A tile's arrays as OUT/tiles/NNNNN.npz, whole or not at all."""
    folder = Path(out) / TILES
    folder.mkdir(parents=True, exist_ok=True)
    partial = folder / f"{tile_name(tile)}.partial.npz"
    np.savez(partial, **arrays)
    return partial.replace(folder / f"{tile_name(tile)}.npz")


def write_summary(out: Path, tile: int, summary: dict) -> dict:
    """A tile's summary, written last: it marks the tile done."""
    write_json(Path(out) / TILES / f"{tile_name(tile)}.json", {"tile": tile, **summary})
    return {"tile": tile, **summary}


class TileMaps:
    """The run's maps (`kinds`: OUT/<kind>.laz) appended from the tiles' LAZ parts (a summary's
    "maps": {kind: part file under OUT/tiles/}) as soon as every tile before them is in: the
    maps keep tile order whatever order tiles finish in."""

    def __init__(self, out: Path, kinds: tuple[str, ...] = MAPS):
        self.folder = Path(out) / TILES
        self.appenders = {kind: LasAppender(Path(out) / f"{kind}.laz") for kind in kinds}
        self.summaries: dict[int, dict] = {}
        self._next = 0  # the first tile whose maps are not appended yet

    def add(self, summary: dict) -> None:
        self.summaries[int(summary["tile"])] = summary
        while self._next in self.summaries:
            for kind, part in self.summaries[self._next]["maps"].items():
                self.appenders[kind].append(self.folder / part)
            self._next += 1

    def close(self) -> dict[str, int]:
        """{map: points written} (0: nothing appended, and no file made)."""
        return {kind: appender.close() for kind, appender in self.appenders.items()}

    def abort(self) -> None:
        for appender in self.appenders.values():
            appender.abort()


def placed(report: Progress, steps: dict[str, tuple[float, float]]) -> Progress:
    """A step's own progress (0-1 within it) placed where the step lies in the whole (`steps`:
    {step: (start, end)}). A step may say how far it is in brackets, "crop embeddings (120 of
    900)": it is placed by its name. Unknown steps sit at the end."""

    def step(stage: str, fraction: float = 0.0) -> None:
        start, end = steps.get(stage.split(" (", 1)[0], (1.0, 1.0))
        report(stage, start + (end - start) * fraction)

    return step


def drive_tiles(
    fn: Callable[..., dict],
    spec: Any,
    index: Any,
    count: int,
    done: dict[int, dict],
    add: Callable[[dict], None],
    map_tiles: TileMap = in_process,
    progress: Progress | None = None,
    steps: dict[str, tuple[float, float]] | None = None,
    cost: np.ndarray | None = None,
) -> int:
    """Every tile of `count` not in `done` through `map_tiles` (`fn(spec, index, tile)`), each
    summary to `add` as it arrives, the earlier attempt's first; returns how many tiles ran.
    `progress` sees tiles done / tiles; tiles run in this process also report their own steps
    (`fn`'s `progress`, placed within the tile by `steps`: {step: (start, end)}). A cancel
    raised by `progress` closes `map_tiles`, which cancels a cluster's queued tiles.

    With `cost` (per tile, what its work grows with), the costliest tiles are sent first: the
    last to finish are then short ones, and no worker waits long for another's last tile."""
    missing = [t for t in range(count) if t not in done]
    if cost is not None:
        missing.sort(key=lambda t: -float(cost[t]))  # stable: equal costs in tile order

    def report(stage: str, within: float = 0.0) -> None:
        if progress is not None:
            progress(stage, (len(done) + within) / count)

    def tile_report(stage: str, within: float) -> None:
        report(f"tile {len(done) + 1} of {count}: {stage}", within)

    local = partial(fn, progress=placed(tile_report, steps or {}))
    if len(missing) <= 1:  # one tile fits a worker's memory anyway: no round trip to a cluster
        fn, map_tiles = local, in_process
    elif map_tiles is in_process:
        fn = local
    report(f"{len(done)} of {count} tiles")
    for summary in done.values():
        add(summary)
    with closing(map_tiles(fn, spec, index, missing)) as finished:
        for summary in finished:
            done[int(summary["tile"])] = summary
            add(summary)  # while the other tiles run
            report(f"{len(done)} of {count} tiles")
    return len(missing)
