"""The phantom pipeline tile by tile: a survey of any length in bounded memory.

Each tile reads the frames that reach its window (its own points plus the halo,
`io.tile_index`), runs the whole pipeline there (`PhantomPipeline.run_map`) and keeps the results
of the points and pillars it owns, written as soon as it finishes (`tile_outputs`); the run's
files are assembled from the tiles' while later tiles run, and a rerun keeps the finished ones.
The halo covers
every step's reach, so the labels agree with a run on the whole map: the network's 11 x 11
pillar window (+-1.1 m) and its 31 x 31 pillar context (+-3.1 m), the 5 x 5 refinement vote
(+-0.4 m), the ground model's opening and cells (`PhantomConfig.ground_opening`), and the
2 m cells the window is kept on (`phantom_halo`: 11 m with the defaults).
"""

from __future__ import annotations

import resource
import time
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from app.core.progress import Progress
from app.io.survey import Survey
from app.io.tile_index import TileIndex
from app.pipelines.phantom.config import PhantomConfig
from app.pipelines.phantom.evaluation.classification_metrics import metric_counts
from app.pipelines.phantom.network import CONTEXT_SPAN
from app.pipelines.phantom.pipeline import PhantomPipeline
from app.pipelines.phantom.tile_outputs import Assembly, TileResult, write_tile
from app.pipelines.tiling import (
    TileMap,
    drive_tiles,
    file_stamp,
    finished_tiles,
    in_process,
    scan_map,
    tile_workers,
)

TILE_LENGTH = 100.0  # metres of trajectory per tile, at most
# points in a tile's window at most (the tile is cut shorter where they are denser): a worker's
# peak memory follows them (bench/RESULTS.md, "Scale")
TILE_POINTS = 4_000_000
INDEX_CELL = 2.0  # metres: the grid a tile's own points and its halo are kept on
# share of a tile's time at the start and end of each step (for progress within a tile)
TILE_STEPS = {"accumulate": (0.0, 0.15), "classify": (0.15, 0.95), "done": (1.0, 1.0)}


def phantom_halo(cfg: PhantomConfig, index_cell: float = INDEX_CELL) -> float:
    """Metres of context a phantom tile needs: the context branch's and the vote's reach in
    pillars, the ground opening's (it erodes then dilates: twice its half-width), one ground
    cell and one index cell, rounded up to whole metres."""
    pillars = CONTEXT_SPAN // 2 + cfg.refine_window // 2 + 1
    ground = (cfg.ground_opening - 1) * cfg.ground_cell + cfg.ground_cell
    return float(np.ceil(pillars * cfg.cell_size + ground + index_cell))


def run_tile(
    pipeline: PhantomPipeline,
    survey: Survey,
    index: TileIndex,
    tile: int,
    baselines: bool = False,
    progress: Progress | None = None,
) -> TileResult:
    """One tile: its frames accumulated, cut to its window, classified; the results for the
    points and pillars it owns (and their share of the metrics when the survey has reference
    labels). `progress` gets the pipeline's steps (`PhantomPipeline.run`)."""
    started = time.perf_counter()
    if progress is not None:
        progress("accumulate", 0.0)
    part = pipeline.accumulate(
        index.tile_survey(survey, tile), lambda xyz: index.in_window(xyz, tile), index.time0
    )
    if len(part.xyz) == 0:
        empty = np.zeros(0, dtype=np.int64)
        return TileResult(tile, empty, empty, np.zeros((0, 3)), np.zeros(0, np.uint8), 0)
    timings = {"accumulate": round(time.perf_counter() - started, 3)}
    result = pipeline.run_map(part, progress, timings)
    own = index.owned(part.xyz, tile)
    pm = result.pillar_map
    centres = np.column_stack([(pm.pillars + 0.5) * pm.config.cell_size, np.zeros(len(pm.pillars))])
    own_pillars = index.owned(centres, tile)
    counts = None
    if "semantic" in part.reference:
        flags = baseline_flags(part.xyz) if baselines else None
        counts = metric_counts(result, own, own_pillars, flags)
    pillars = {
        "pillars": pm.pillars[own_pillars],
        "probabilities": result.probabilities[own_pillars],
        "classified": result.classified[own_pillars],
        "raw_labels": result.raw_labels[own_pillars],
        "labels": result.pillar_labels[own_pillars],
        "cell_size": np.array([pm.config.cell_size]),
    }
    return TileResult(
        tile,
        frame=index.frames[tile][part.source_frame[own].astype(np.int64)],
        index=part.source_index[own].astype(np.int64),
        xyz=part.xyz[own],
        labels=result.point_labels[own],
        in_layer=int((pm.point_pillar[own] >= 0).sum()),
        pillars=pillars,
        metric_counts=counts,
        timings=result.timings,
        peak_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,  # Linux: kB
    )


def baseline_flags(xyz: np.ndarray) -> dict[str, np.ndarray]:
    """The paper's two baselines' phantom flags (Table II) on a tile's window."""
    from app.pipelines.phantom.evaluation.baselines import avg_distances, num_neighbors

    return {"num_neighbors": num_neighbors(xyz), "avg_distances": avg_distances(xyz)}


@dataclass(frozen=True)
class PhantomTileSpec:
    """What a worker process needs to run a phantom tile: names, not objects (a cluster's
    workers open the survey and load the model themselves; the data and the output folder must
    be readable and writable there)."""

    survey_source: str
    survey_format: str
    model_path: str
    config: str  # PhantomConfig as JSON
    out: str  # the run's output folder: tiles are written under it
    offset: tuple[float, float, float]  # the LAZ parts' shared offset
    dense: bool = True
    baselines: bool = False

    def plan(self, index: TileIndex) -> dict:
        """What a tile's results depend on: a resumed run reuses tiles of the same plan only."""
        layout = index.layout
        return {
            "survey": [self.survey_source, self.survey_format],
            "model": [self.model_path, file_stamp(Path(self.model_path))],
            "config": self.config, "dense": self.dense, "baselines": self.baselines,
            "offset": list(self.offset),
            "tiles": [index.count, layout.length, layout.halo, index.cell, list(layout.edges)],
            "frame_sizes": [len(index.frame_sizes), int(index.frame_sizes.sum())],
        }  # fmt: skip


@lru_cache(maxsize=2)
def _worker_pipeline(model_path: str, config: str, dense: bool) -> PhantomPipeline:
    """One loaded network per worker process and model (tiles of a job share it)."""
    return PhantomPipeline(PhantomConfig.model_validate_json(config), Path(model_path), dense)


def phantom_tile(
    spec: PhantomTileSpec, index: TileIndex, tile: int, progress: Progress | None = None
) -> dict:
    """A tile as a worker runs it: open the survey, load the model (once), run the tile, write
    its files under the run's folder; returns its summary (small: it travels back)."""
    from app.io import open_survey

    pipeline = _worker_pipeline(spec.model_path, spec.config, spec.dense)
    survey = open_survey(Path(spec.survey_source), spec.survey_format)
    result = run_tile(pipeline, survey, index, tile, spec.baselines, progress)
    return write_tile(Path(spec.out), result, np.asarray(spec.offset))


@dataclass
class TiledRun:
    """A tiled run's outcome: the assembled files and totals (`tile_outputs.Assembly`), the
    tile index, and how many tiles this attempt ran (the rest came from an earlier one)."""

    files: dict[str, str]
    counts: dict
    metric_counts: dict | None
    timings: dict[str, float]
    worker_peak_mb: float  # the largest peak memory of a process that ran a tile
    index: TileIndex
    tiles_run: int


def run_phantom_tiled(
    pipeline: PhantomPipeline,
    survey: Survey,
    out: Path,
    length: float = TILE_LENGTH,
    halo: float | None = None,
    progress: Progress | None = None,
    map_tiles: TileMap = in_process,
    baselines: bool = False,
    max_points: int | None = TILE_POINTS,
) -> TiledRun:
    """The survey tile by tile into `out`: each tile's files as it finishes, then the
    contract's files assembled from them. Tiles an earlier attempt finished with the same plan
    are not run again. The tiles are independent, so `map_tiles` may run them side by side on
    a cluster. Tiles are `length` metres, shorter where their window would hold more than
    `max_points` points (None: no bound)."""
    halo = phantom_halo(pipeline.config) if halo is None else halo
    index = TileIndex.build(
        survey, length, halo, INDEX_CELL, max_points, scan_map(map_tiles), tile_workers(map_tiles)
    )
    spec = PhantomTileSpec(  # absolute paths: a cluster's workers run elsewhere
        str(Path(survey.source).resolve()), survey.format, str(pipeline.model_path.resolve()),
        pipeline.config.model_dump_json(), str(Path(out).resolve()),
        tuple(np.floor(index.low).tolist()), pipeline.dense, baselines,
    )  # fmt: skip
    done = finished_tiles(out, spec.plan(index))
    assembly = Assembly(out, [f.frame_id for f in survey.frames], index.frame_sizes)
    try:
        ran = drive_tiles(
            phantom_tile, spec, index, index.count, done, assembly.add, map_tiles, progress,
            TILE_STEPS, cost=index.points_read(),
        )  # fmt: skip
        owned = sum(s["points"] for s in done.values())
        if owned != int(index.frame_sizes.sum()):
            raise RuntimeError(
                f"tiles labelled {owned} of {int(index.frame_sizes.sum())} points: a tile lost "
                "points it owns"
            )
        assembled = assembly.finish()
    except BaseException:
        assembly.abort()
        raise
    return TiledRun(**assembled, index=index, tiles_run=ran)
