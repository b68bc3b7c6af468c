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

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from app.io.survey import Survey
from app.io.tile_index import TileIndex
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


def run_phantom_tiled(
    pipeline: PhantomPipeline,
    survey: Survey,
    length: float = TILE_LENGTH,
    halo: float | None = None,
    progress: Callable[[str, float], None] | None = None,
) -> tuple[dict[str, np.ndarray], TileIndex]:
    """Per-frame point labels of the whole survey, computed tile by tile (in order here; the
    tiles are independent, so a cluster can run them side by side)."""
    halo = phantom_halo(pipeline) if halo is None else halo
    index = TileIndex.build(survey, length, halo, INDEX_CELL)
    labels = [np.zeros(int(n), dtype=np.uint8) for n in index.frame_sizes]
    written = 0
    for tile in range(index.count):
        if progress is not None:
            progress(f"tile {tile + 1} of {index.count}", tile / index.count)
        part = run_tile(pipeline, survey, index, tile)
        for f in np.unique(part.frame):
            mine = part.frame == f
            labels[int(f)][part.index[mine]] = part.labels[mine]
        written += len(part.labels)
    if written != int(index.frame_sizes.sum()):
        raise RuntimeError(
            f"tiles labelled {written} of {int(index.frame_sizes.sum())} points: a tile lost "
            "points it owns"
        )
    return {f.frame_id: lab for f, lab in zip(survey.frames, labels, strict=True)}, index
