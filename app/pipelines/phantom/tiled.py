"""The phantom pipeline tile by tile: a survey of any length in bounded memory.

Each tile reads the frames that reach its window (its own points plus the halo,
`io.tile_index`), runs the whole pipeline there (`PhantomPipeline.run_map`) and keeps the labels
of the points it owns; the frames' label arrays are filled from the tiles. The halo covers
every step's reach, so the labels agree with a run on the whole map: the network's 11 x 11
pillar window (+-1.1 m) and its 31 x 31 pillar context (+-3.1 m), the 5 x 5 refinement vote
(+-0.4 m), the ground model's opening and cells (`PhantomConfig.ground_opening`), and the
2 m cells the window is kept on (`phantom_halo`: 11 m with the defaults).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from app.io.survey import Survey
from app.io.tile_index import TileIndex
from app.pipelines.phantom.config import PhantomConfig
from app.pipelines.phantom.network import CONTEXT_SPAN
from app.pipelines.phantom.pipeline import PhantomPipeline

TILE_LENGTH = 100.0  # metres of trajectory per tile
INDEX_CELL = 2.0  # metres: the grid a tile's own points and its halo are kept on


def phantom_halo(pipeline: PhantomPipeline, index_cell: float = INDEX_CELL) -> float:
    """Metres of context a phantom tile needs: the context branch's and the vote's reach in
    pillars, the ground opening's (it erodes then dilates: twice its half-width), one ground
    cell and one index cell, rounded up to whole metres."""
    cfg = pipeline.config
    pillars = CONTEXT_SPAN // 2 + cfg.refine_window // 2 + 1
    ground = (cfg.ground_opening - 1) * cfg.ground_cell + cfg.ground_cell
    return float(np.ceil(pillars * cfg.cell_size + ground + index_cell))


@dataclass
class TileLabels:
    """The labels of the points one tile owns, by (frame of the survey, point of the frame)."""

    tile: int
    frame: np.ndarray  # (n,) int64 frame index in the survey
    index: np.ndarray  # (n,) int64 point index in its frame
    labels: np.ndarray  # (n,) uint8 pillar class


def run_tile(pipeline: PhantomPipeline, survey: Survey, index: TileIndex, tile: int) -> TileLabels:
    """One tile: its frames accumulated, cut to its window, classified; its own points' labels."""
    amap = pipeline.accumulate(index.tile_survey(survey, tile))
    part = amap.select(index.in_window(amap.xyz, tile))
    if len(part.xyz) == 0:
        empty = np.zeros(0, dtype=np.int64)
        return TileLabels(tile, empty, empty, np.zeros(0, dtype=np.uint8))
    result = pipeline.run_map(part)
    own = index.owned(part.xyz, tile)
    frames = index.frames[tile][part.source_frame[own].astype(np.int64)]
    return TileLabels(
        tile, frames, part.source_index[own].astype(np.int64), result.point_labels[own]
    )


@dataclass(frozen=True)
class PhantomTileSpec:
    """What a worker process needs to run a phantom tile: names, not objects (a cluster's
    workers open the survey and load the model themselves; the data must be readable there)."""

    survey_source: str
    survey_format: str
    model_path: str
    config: str  # PhantomConfig as JSON
    dense: bool = True

    @classmethod
    def of(cls, pipeline: PhantomPipeline, survey: Survey) -> PhantomTileSpec:
        return cls(
            str(survey.source), survey.format, str(pipeline.model_path),
            pipeline.config.model_dump_json(), pipeline.dense,
        )  # fmt: skip


@lru_cache(maxsize=2)
def _worker_pipeline(model_path: str, config: str, dense: bool) -> PhantomPipeline:
    """One loaded network per worker process and model (tiles of a job share it)."""
    return PhantomPipeline(PhantomConfig.model_validate_json(config), Path(model_path), dense)


def phantom_tile(spec: PhantomTileSpec, index: TileIndex, tile: int) -> TileLabels:
    """A tile as a worker runs it: open the survey, load the model (once), run the tile."""
    from app.io import open_survey

    pipeline = _worker_pipeline(spec.model_path, spec.config, spec.dense)
    survey = open_survey(Path(spec.survey_source), spec.survey_format)
    return run_tile(pipeline, survey, index, tile)


# runs `phantom_tile(spec, index, tile)` for the tiles given and yields the results as they
# finish, in any order: in this process by default, on a Dask cluster from `app.jobs.cluster`
TileMap = Callable[[Callable[..., TileLabels], PhantomTileSpec, TileIndex, list[int]],
                   Iterable[TileLabels]]  # fmt: skip


def in_process(fn, spec: PhantomTileSpec, index: TileIndex, tiles: list[int]):
    """The tiles one after the other in this process."""
    for tile in tiles:
        yield fn(spec, index, tile)


def run_phantom_tiled(
    pipeline: PhantomPipeline,
    survey: Survey,
    length: float = TILE_LENGTH,
    halo: float | None = None,
    progress: Callable[[str, float], None] | None = None,
    map_tiles: TileMap = in_process,
) -> tuple[dict[str, np.ndarray], TileIndex]:
    """Per-frame point labels of the whole survey, computed tile by tile; the tiles are
    independent, so `map_tiles` may run them side by side on a cluster."""
    halo = phantom_halo(pipeline) if halo is None else halo
    index = TileIndex.build(survey, length, halo, INDEX_CELL)
    labels = [np.zeros(int(n), dtype=np.uint8) for n in index.frame_sizes]
    spec = PhantomTileSpec.of(pipeline, survey)
    written = 0
    for done, part in enumerate(map_tiles(phantom_tile, spec, index, list(range(index.count)))):
        for f in np.unique(part.frame):
            mine = part.frame == f
            labels[int(f)][part.index[mine]] = part.labels[mine]
        written += len(part.labels)
        if progress is not None:
            progress(f"{done + 1} of {index.count} tiles", (done + 1) / index.count)
    if written != int(index.frame_sizes.sum()):
        raise RuntimeError(
            f"tiles labelled {written} of {int(index.frame_sizes.sum())} points: a tile lost "
            "points it owns"
        )
    return {f.frame_id: lab for f, lab in zip(survey.frames, labels, strict=True)}, index
