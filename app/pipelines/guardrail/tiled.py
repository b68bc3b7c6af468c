"""The guardrail pipeline tile by tile: a survey of any length in bounded memory.

Tiles are the phantom pipeline's (`io.tile_index`: stretches of trajectory, each read with the
points of its window, its own cells plus a halo). Each tile loads its window's points (frame by
frame, after their scanner lattice is known), and runs road removal, connected components, the
0.5 m slices, the camera crops, the classifier and the adjacency correction there. It keeps the
slices it owns (a slice belongs to the tile of its centre's station) and their points, and the
points outside every slice in its own cells. Camera crops, the costly step, are taken only for
the slices whose labels it keeps or that their correction looks at.

The halo (`guardrail_halo`) covers what an owned slice's label depends on: the road's edge
window and its smoothed heights, the neighbouring slices the shape features and the correction
look at, and one guardrail unit more for the components (a rail cut at the window's edge is
whole again inside it). Stations come from the whole drive's trajectory, so slices are cut at
the same places in every tile. Guardrails are grouped, joined and reconstructed once all tiles
are in (`tile_assembly`): a guardrail is one model from its first pole to its last, whatever
the tiles.
"""

from __future__ import annotations

import resource
import time
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from app.core.progress import Progress
from app.geometry.tiles import TileLayout
from app.io.las import write_laz
from app.io.survey import Survey
from app.io.tile_index import TileIndex
from app.metrics.classification import binary_counts
from app.pipelines.guardrail.classifier import CropEncoder
from app.pipelines.guardrail.config import GuardrailConfig
from app.pipelines.guardrail.evaluation.reference import (
    guardrail_truth,
    point_reference,
    reference_kind,
    slice_truth,
)
from app.pipelines.guardrail.features import CONTEXT_SLICES
from app.pipelines.guardrail.pipeline import (
    GuardrailPipeline,
    ReconstructionInput,
    StoredStage,
    slice_point_labels,
)
from app.pipelines.guardrail.road import EDGE_WINDOW, STATION_BIN
from app.pipelines.guardrail.scan_points import load_scan_points
from app.pipelines.guardrail.segmentation import SliceStage, slice_stage
from app.pipelines.guardrail.slices import SliceSet
from app.pipelines.guardrail.tile_assembly import RAILS, GuardrailAssembly, SliceTable
from app.pipelines.tiling import (
    TILES,
    TileMap,
    drive_tiles,
    file_stamp,
    finished_tiles,
    in_process,
    save_tile_arrays,
    scan_map,
    tile_name,
    tile_workers,
    write_summary,
)

TILE_LENGTH = 100.0  # metres of trajectory per tile, at most
# points in a tile's window at most (the tile is cut shorter where they are denser). Measured on
# the simulated 4 km profile survey of bench.scale, one tile in its own process: the fullest
# window (3.98 M points) peaked at 1.36 GB (0.31 GB of it libraries), in the road removal. At
# 2.5 M the dense half of that survey had tiles of 4-8 m, each reading 36 m of halo
TILE_POINTS = 4_000_000
INDEX_CELL = 2.0  # metres: the grid a tile's own points and its halo are kept on
UNIT_LENGTH = 4.0  # metres: a guardrail unit (post to post), the components' extra context
LINK_BAND = 1.0  # metres each side of a tile edge whose slice points tie components across
# share of a tile's time at the start and end of each step (for progress within a tile)
TILE_STEPS = {
    "points": (0.0, 0.1),
    "road removal": (0.1, 0.2),
    "components": (0.2, 0.3),
    "crops": (0.3, 0.4),
    "crop embeddings": (0.4, 0.9),
    "classifier": (0.9, 1.0),
}


def correction_reach(cfg: GuardrailConfig) -> float:
    """Metres along a chain of slices that one slice's corrected label depends on: a gap is
    filled when guardrails flank it (`max_gap` + 1 slices away), then a run is dropped as
    isolated from its filled neighbours' labels (`max_isolated` + 1 further)."""
    return float((2 * int(cfg.max_gap or 0) + int(cfg.max_isolated or 0) + 2) * cfg.spacing)


def guardrail_halo(cfg: GuardrailConfig, index_cell: float = INDEX_CELL) -> float:
    """Metres of context a guardrail tile needs (see the module docstring), rounded up."""
    road = EDGE_WINDOW + 2 * STATION_BIN  # the edge's window, the 3-bin median of the heights
    slices = correction_reach(cfg) + CONTEXT_SLICES * cfg.spacing
    return float(np.ceil(road + slices + UNIT_LENGTH + index_cell))


@dataclass
class GuardrailTileResult:
    """What one tile found for the slices and points it owns."""

    tile: int
    owned_slices: np.ndarray  # (k,) int64 indices into stage.slices
    stage: SliceStage
    probability: np.ndarray  # (k,) per owned slice
    raw: np.ndarray  # (k,) bool
    corrected: np.ndarray  # (k,) bool
    owned_points: int
    rail_points: np.ndarray  # (r,) indices into stage.points: owned points on guardrails
    links: dict[str, np.ndarray]  # per tile edge: slice points' keys and their components
    metric_counts: dict | None
    timings: dict[str, float]
    peak_mb: float


def point_keys(frame: np.ndarray, point: np.ndarray) -> np.ndarray:
    """One int64 per point of the survey: (frame, index in the frame)."""
    return (frame.astype(np.int64) << 32) | point.astype(np.int64)


def run_tile(
    pipeline: GuardrailPipeline,
    survey: Survey,
    index: TileIndex,
    tile: int,
    progress: Progress | None = None,
) -> GuardrailTileResult:
    """One tile: its window's points sliced and classified, the slices and points it owns."""
    cfg = pipeline.config
    started = time.perf_counter()
    if progress is not None:
        progress("points", 0.0)
    frames = index.frames[tile].tolist()
    points = load_scan_points(survey, frames=frames, keep=lambda xyz: index.in_window(xyz, tile))
    trajectory = survey.poses()[:, :3, 3]
    layout = index.layout
    start, end = layout.bounds(tile)
    reach = correction_reach(cfg)

    def near_own(s: SliceSet) -> np.ndarray:  # slices worth a crop: owned or what they look at
        station = layout.stations(s.centre)
        return np.flatnonzero((station >= start - reach) & (station < end + reach))

    uses_image = "image" in pipeline.head
    encoder = _worker_encoder() if uses_image and survey.cameras else None
    stage = slice_stage(
        survey, points, trajectory, encoder, cfg.spacing, progress, crop_only=near_own,
        origin=index.centre,
    )  # fmt: skip
    timings = {"load": round(time.perf_counter() - started, 3) - sum(stage.timings.values())}
    clock = time.perf_counter()
    if progress is not None:
        progress("classifier", 0.0)
    probability, raw, corrected = pipeline.label(stage)
    timings = {**timings, **stage.timings, "classify": round(time.perf_counter() - clock, 3)}
    s = stage.slices
    station = layout.stations(s.centre)  # a slice belongs to the tile of its centre's station
    owner = layout.owner(station)
    own = np.flatnonzero(owner == tile)
    # a point in a slice goes with its slice; one in none, with its cell
    in_slice = s.point_slice >= 0
    mine = index.owned(stage.points.xyz, tile)
    mine[in_slice] = owner[s.point_slice[in_slice]] == tile
    labels = slice_point_labels(s, corrected)
    rail_points = np.flatnonzero(mine & (labels == 1))
    counts = None
    kind = reference_kind(survey.reference_label_kinds)
    if kind is not None:
        truth = guardrail_truth(kind, point_reference(survey, stage.points, kind))
        slice_ref = slice_truth(stage, np.where(truth, 0, -1)).astype(bool)[own]
        counts = {
            "slice_raw": binary_counts(slice_ref, raw[own]),
            "slice": binary_counts(slice_ref, corrected[own]),
            "point": binary_counts(truth[mine], labels[mine] == 1),
            "reference_guardrail_slices": int(slice_ref.sum()),
        }
    return GuardrailTileResult(
        tile, own, stage, probability[own], raw[own], corrected[own], int(mine.sum()),
        rail_points, _edge_links(stage, station, layout, tile), counts, timings,
        resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,  # Linux: kilobytes
    )  # fmt: skip


def _edge_links(
    stage: SliceStage, station: np.ndarray, layout: TileLayout, tile: int
) -> dict[str, np.ndarray]:
    """The points of the slices within `LINK_BAND` of the tile's start and end (`station`: of
    each slice's centre), with their components: the next tile sees the same points, and a
    component that crosses the edge is one (`tile_assembly`)."""
    s = stage.slices
    out = {}
    edges = {"start": layout.edges[tile] if tile > 0 else None,
             "end": layout.edges[tile + 1] if tile + 1 < layout.count else None}  # fmt: skip
    in_slice = np.flatnonzero(s.point_slice >= 0)
    for name, edge in edges.items():
        near = np.zeros(len(s), dtype=bool) if edge is None else np.abs(station - edge) <= LINK_BAND
        members = in_slice[near[s.point_slice[in_slice]]]
        pts = stage.points
        out[f"{name}_keys"] = point_keys(pts.frame[members], pts.index[members])
        out[f"{name}_components"] = s.component[s.point_slice[members]].astype(np.int64)
    return out


@lru_cache(maxsize=1)
def _worker_encoder() -> CropEncoder:
    """One image network per worker process (the tiles of a run share it)."""
    return CropEncoder()


@lru_cache(maxsize=2)
def _worker_pipeline(model_path: str, config: str) -> GuardrailPipeline:
    """One loaded classifier per worker process and model."""
    return GuardrailPipeline(GuardrailConfig.model_validate_json(config), Path(model_path))


@dataclass(frozen=True)
class GuardrailTileSpec:
    """What a worker process needs to run a guardrail tile: names, not objects (a cluster's
    workers open the survey and load the classifier themselves; the data and the output folder
    must be readable and writable there). `keep_stage`: also keep every owned slice's points
    and classifier inputs (what the web app's review, rebuild and retraining read)."""

    survey_source: str
    survey_format: str
    model_path: str
    config: str  # GuardrailConfig as JSON (the correction settings resolved)
    out: str
    offset: tuple[float, float, float]  # the LAZ parts' shared offset
    keep_stage: bool = False

    def plan(self, index: TileIndex, model_stamp: list[int]) -> dict:
        """What a tile's results depend on: a resumed run reuses tiles of the same plan only."""
        layout = index.layout
        return {
            "survey": [self.survey_source, self.survey_format],
            "model": [self.model_path, model_stamp],
            "config": self.config, "keep_stage": self.keep_stage, "offset": list(self.offset),
            "tiles": [index.count, layout.length, layout.halo, index.cell, list(layout.edges)],
            "frame_sizes": [len(index.frame_sizes), int(index.frame_sizes.sum())],
        }  # fmt: skip


def guardrail_tile(
    spec: GuardrailTileSpec, index: TileIndex, tile: int, progress: Progress | None = None
) -> dict:
    """A tile as a worker runs it: open the survey, load the classifier (once), run the tile,
    write its files under the run's folder; returns its summary (small: it travels back)."""
    from app.io import open_survey

    pipeline = _worker_pipeline(spec.model_path, spec.config)
    survey = open_survey(Path(spec.survey_source), spec.survey_format)
    result = run_tile(pipeline, survey, index, tile, progress)
    return write_tile(spec, pipeline.config, result)


def write_tile(spec: GuardrailTileSpec, cfg: GuardrailConfig, r: GuardrailTileResult) -> dict:
    """The tile's files under OUT/tiles/, its summary last (what marks it done):
    `NNNNN.npz` (per owned slice its key and labels; the owned guardrail points' frame and
    index; the edge links), `NNNNN.rails.npz` (the owned guardrail slices with their points:
    what grouping and reconstruction read), `NNNNN.stage.npz` and `NNNNN.features.npz` with
    `keep_stage`, and `NNNNN.guardrail_points.laz`."""
    folder = Path(spec.out) / TILES
    name = tile_name(r.tile)
    s, pts = r.stage.slices, r.stage.points
    columns = {
        "component": s.component[r.owned_slices].astype(np.int64),
        "slice_index": s.station_index[r.owned_slices],
        "station": s.station[r.owned_slices],
        "probability": r.probability,
        "raw": r.raw,
        "corrected": r.corrected,
        "has_crop": r.stage.has_crop[r.owned_slices],
        "rail_frame": pts.frame[r.rail_points].astype(np.int64),
        "rail_index": pts.index[r.rail_points],
        **r.links,
    }
    save_tile_arrays(spec.out, r.tile, **columns)
    rails = r.owned_slices[r.corrected]
    ReconstructionInput.of(r.stage, cfg, rails).save(folder / f"{name}.rails.npz")
    if spec.keep_stage:
        ReconstructionInput.of(r.stage, cfg, r.owned_slices).save(folder / f"{name}.stage.npz")
        from app.pipelines.guardrail.segmentation import save_slice_features

        save_slice_features(folder / f"{name}.features.npz", r.stage, r.owned_slices)
    maps = {}
    if len(r.rail_points):
        part = f"{name}.{RAILS}.laz"
        write_rail_points(folder / part, r.stage, r.rail_points, np.asarray(spec.offset))
        maps[RAILS] = part
    k = len(r.owned_slices)
    return write_summary(Path(spec.out), r.tile, {
        "points": r.owned_points, "slices": k, "components": int(r.stage.components.count),
        "slices_with_crop": int(columns["has_crop"].sum()),
        "guardrail_slices": int(r.corrected.sum()), "guardrail_points": int(len(r.rail_points)),
        "metric_counts": r.metric_counts, "timings": r.timings, "worker_peak_mb": r.peak_mb,
        "maps": maps,
    })  # fmt: skip


def write_rail_points(
    path: Path, stage: SliceStage, which: np.ndarray, offset: np.ndarray | None = None
) -> None:
    """The points `which` (indices into stage.points) as guardrail points: LAZ with the
    guardrail class and where each point came from."""
    import datetime

    from app.io.asprs import GUARDRAIL_ASPRS

    pts = stage.points
    n = len(which)
    write_laz(
        path,
        pts.xyz[which],
        mmsclean_label=np.ones(n, dtype=np.uint8),
        classification=np.full(n, GUARDRAIL_ASPRS, dtype=np.uint8),
        source_frame=pts.frame[which].astype(np.uint32),
        source_index=pts.index[which].astype(np.uint32),
        creation_date=datetime.date.today(),
        offset=offset,
    )


@dataclass
class GuardrailTiledRun:
    """A tiled run's outcome: the assembled files and totals, every slice (`SliceTable`), the
    guardrail slices stored (`rails`: opened, their points in the tiles' parts, what the
    guardrails are built from, one at a time), every slice with its points when the stage was
    kept, the tile index, and how many tiles this attempt ran."""

    files: dict[str, str]
    counts: dict
    metric_counts: dict | None
    timings: dict[str, float]
    worker_peak_mb: float
    slices: SliceTable
    rails: StoredStage | None  # the guardrail slices stored, their points in the tiles' parts
    stage_path: Path | None  # every slice, its points in the tiles' parts (`keep_stage`)
    features_path: Path | None  # every slice's classifier inputs (`keep_stage`)
    index: TileIndex
    tiles_run: int


def run_guardrail_tiled(
    pipeline: GuardrailPipeline,
    survey: Survey,
    out: Path,
    length: float = TILE_LENGTH,
    halo: float | None = None,
    progress: Progress | None = None,
    map_tiles: TileMap = in_process,
    max_points: int | None = TILE_POINTS,
    keep_stage: bool = False,
    stage_path: Path | None = None,
    features_path: Path | None = None,
) -> GuardrailTiledRun:
    """The survey tile by tile into `out` (see the module docstring): each tile's files as it
    finishes, then the labels, the guardrail points and the slices assembled. Tiles an earlier
    attempt finished with the same plan are not run again; `map_tiles` may run them side by
    side on a cluster. With `keep_stage`, `stage_path` indexes every slice (their points stay in
    the tiles' parts: `ReconstructionInput.save_parts`) and `features_path` holds their
    classifier inputs (the web app's review, rebuild and retraining read them)."""
    halo = guardrail_halo(pipeline.config) if halo is None else halo
    index = TileIndex.build(
        survey, length, halo, INDEX_CELL, max_points, scan_map(map_tiles), tile_workers(map_tiles)
    )
    model = pipeline.model_path.resolve()
    spec = GuardrailTileSpec(  # absolute paths: a cluster's workers run elsewhere
        str(Path(survey.source).resolve()), survey.format, str(model),
        pipeline.config.model_dump_json(), str(Path(out).resolve()),
        tuple(np.floor(index.low).tolist()), keep_stage,
    )  # fmt: skip
    done = finished_tiles(out, spec.plan(index, file_stamp(model)))
    assembly = GuardrailAssembly(out, [f.frame_id for f in survey.frames], index.frame_sizes)
    try:
        ran = drive_tiles(
            guardrail_tile, spec, index, index.count, done, assembly.add, map_tiles, progress,
            TILE_STEPS, cost=index.points_read(),
        )  # fmt: skip
        assembled = assembly.finish()
    except BaseException:
        assembly.abort()
        raise
    numbers = assembled.pop("numbers")
    if keep_stage:
        if stage_path is None or features_path is None:
            raise ValueError("keep_stage needs a stage_path and a features_path")
        assembly.save_stage(stage_path, numbers)
        assembly.features(features_path, numbers)
    rails_path = assembly.save_rails(numbers)
    rails = None if rails_path is None else StoredStage.open(rails_path)
    return GuardrailTiledRun(
        **assembled, rails=rails,
        stage_path=stage_path if keep_stage else None,
        features_path=features_path if keep_stage else None, index=index, tiles_run=ran,
    )  # fmt: skip
