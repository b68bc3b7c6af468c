"""The clutter pipeline tile by tile: a drive of any length in bounded memory.

The clutter pipeline's unit is the frame (labels per frame, rays per frame, objects tracked from
frame to frame), so its tiles are tiles of frames (`io.frame_tiles`): a frame belongs to the
tile of its sensor position, and a tile reads, as context, every frame whose sensor was within
the halo of one of its own (`clutter_halo`: half the sensor's reach). Each tile runs
the whole pipeline on those frames (segmentation from the shared cache, DUFOMap over the
tile's rays, tracking) numbered, timed and re-centred as in the whole drive, and keeps the
results of its own frames: their labels, their share of the cleaned and removed maps, their
error matrices, the tracks that touch them, and (for the web app's review) their instances.
`tile_assembly` joins the tracks that cross tiles and appends the maps.
"""

from __future__ import annotations

import resource
import time
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from app.core.progress import Progress
from app.io.frame_tiles import FrameTiles
from app.io.survey import Camera, Survey
from app.pipelines.clutter.config import ClutterConfig
from app.pipelines.clutter.evaluation.removal_metrics import survey_removal_counts
from app.pipelines.clutter.map_budget import frame_loads
from app.pipelines.clutter.maps import maps_offset, write_frame_maps
from app.pipelines.clutter.pipeline import ClutterPipeline, ClutterResult
from app.pipelines.clutter.review_units import write_review_units
from app.pipelines.clutter.segmenter import CachedSegmenter, Segmenter, segmented_class_maps
from app.pipelines.clutter.tile_assembly import ClutterAssembly
from app.pipelines.outputs import write_frame_labels
from app.pipelines.tiling import (
    TILES,
    TileMap,
    drive_tiles,
    finished_tiles,
    in_process,
    tile_name,
    tile_workers,
    write_summary,
)

# metres of trajectory per tile, at most. A tile reads its halo's frames on both sides as well
# (80 m of frames with the defaults), so longer tiles read each frame fewer times; what a tile
# holds is bounded by `TILE_MAP_MB` whatever its length (`python -m bench.clutter_memory`: a
# worker's peak grows by about 50 bytes per point read, DUFOMap's map included)
TILE_LENGTH = 200.0
# megabytes of free-space map a tile's frames may add up to (`map_budget.frame_map_mb`: what each
# frame adds, estimated). A tile's worker held about 220 MB besides the map (simulated profile
# surveys), so a full tile stays near 850 MB, and one whose single frame's context is over the
# budget (a drive back along its street) reads that context and 200 MB more.
TILE_MAP_MB = 600.0
# share of a tile's time at the start and end of each step (for progress within a tile)
TILE_STEPS = {
    "segmentation": (0.0, 0.4),
    "frames": (0.4, 0.75),
    "free space": (0.75, 0.9),
    "tracking": (0.9, 0.95),
    "done": (0.95, 1.0),
}


def clutter_halo(cfg: ClutterConfig) -> float:
    """Metres of context a clutter tile reads around its own frames' sensors: half the sensor's
    reach (`max_range`). Frames that near saw the tile's own points through their rays (free
    space) and saw the same objects (tracks); what frames farther away add is the far end of
    their rays: on a simulated 150 m rotating-scanner street in 50 m tiles, 99.997 % of the
    labels agreed with the untiled run at this halo, 99.999 % at the full reach, which reads
    twice as many frames (a one-off check, bench/RESULTS.md; `bench.scale agreement`)."""
    return float(cfg.max_range) / 2


@dataclass(frozen=True)
class ClutterTileSpec:
    """What a worker process needs to run a clutter tile: names, not objects (a cluster's
    workers open the survey and the segmentation network themselves; the data, the
    segmentation cache and the output folder must be readable and writable there)."""

    survey_source: str
    survey_format: str
    config: str  # ClutterConfig as JSON
    out: str  # the run's output folder: labels and tiles are written under it
    offset: tuple[float, float, float]  # the LAZ parts' shared offset
    cache_dir: str | None = None  # the segmentation cache (None: the settings')
    weights_dir: str | None = None  # the ESPNetv2 weights (None: the settings')
    review: bool = False  # write the review units of the web app (instances/)

    def plan(self, tiles: FrameTiles) -> dict:
        """What a tile's results depend on: a resumed run reuses tiles of the same plan only."""
        layout = tiles.layout
        return {
            "survey": [self.survey_source, self.survey_format],
            "config": self.config, "offset": list(self.offset), "review": self.review,
            "segmentation": [self.cache_dir, self.weights_dir],
            "tiles": [tiles.count, layout.length, layout.halo, len(tiles.owner),
                      list(layout.edges)],
        }  # fmt: skip


@lru_cache(maxsize=2)
def _worker_segmenter(weights_dir: str | None, gamma: float) -> Segmenter:
    """One segmentation network per worker process (the tiles of a run share it)."""
    from app.pipelines.clutter.segmenter import ESPNetv2Segmenter

    return ESPNetv2Segmenter(None if weights_dir is None else Path(weights_dir), gamma=gamma)


def clutter_tile(
    spec: ClutterTileSpec, tiles: FrameTiles, tile: int, progress: Progress | None = None
) -> dict:
    """A tile as a worker runs it: open the survey, run the pipeline on the tile's frames,
    write its own frames' results; returns its summary (small: it travels back)."""
    from app.io import open_survey

    started = time.perf_counter()
    out = Path(spec.out)
    own = tiles.own(tile)
    survey = open_survey(Path(spec.survey_source), spec.survey_format)
    config = ClutterConfig.model_validate_json(spec.config)
    if len(own) == 0:  # a stretch of trajectory between two frames
        _write_tracks(out, tile, None, own)
        return write_summary(out, tile, _summary({}, None, {}, None, [], {}, started))
    pipeline = ClutterPipeline(config)
    camera = pipeline.camera(survey)
    cached = None
    if camera is not None:
        reads = tiles.tile_survey(survey, tile)
        cache = None if spec.cache_dir is None else Path(spec.cache_dir)
        segmenter = _worker_segmenter(spec.weights_dir, config.image_gamma)
        pipeline.class_maps, cached = segmented_class_maps(
            reads, camera.name, segmenter, progress, cache
        )
    evidence = out / TILES / f"{tile_name(tile)}.evidence"  # on disk: a tile can be dense
    result = pipeline.run(survey, progress, only=tiles.frames[tile], spill=evidence)
    try:
        return _keep_own(spec, survey, config, tiles, tile, own, result, camera, cached, started)
    finally:
        result.evidence.close()


def _keep_own(
    spec: ClutterTileSpec,
    survey: Survey,
    config: ClutterConfig,
    tiles: FrameTiles,
    tile: int,
    own: np.ndarray,
    result: ClutterResult,
    camera: Camera | None,
    cached: CachedSegmenter | None,
    started: float,
) -> dict:
    """The tile's own frames' results written: labels, map parts, review units, tracks; returns
    the summary."""
    out = Path(spec.out)
    keep = np.searchsorted(tiles.frames[tile], own)  # own frames' places in the result
    write_frame_labels(out, {result.frame_ids[i]: result.removed[i] for i in keep})
    removed = [result.removed[i] for i in keep]
    maps = write_frame_maps(
        out / TILES, tile_name(tile), survey, own, removed, config.voxel_dedup, spec.offset
    )
    counts = {
        "frames": len(own),
        "points": int(sum(len(result.removed[i]) for i in keep)),
        "points_in_view": int(sum(int(result.in_view[i].sum()) for i in keep)),
        "removed_points": int(sum(int(result.removed[i].sum()) for i in keep)),
        "map_points": maps.pop("map_points"),
    }
    rows = []
    if spec.review:
        rows = write_review_units(
            survey, result, config, camera, cached, out / "instances", keep=keep
        )
    _write_tracks(out, tile, result, keep)
    metrics = survey_removal_counts(survey, own, removed, [result.in_view[i] for i in keep])
    return write_summary(
        out, tile, _summary(counts, cached, maps, metrics, rows, result.timings, started)
    )


def _summary(
    counts: dict,
    cached: CachedSegmenter | None,
    maps: dict,
    metric_counts: dict | None,
    rows: list,
    timings: dict,
    started: float,
) -> dict:
    empty = {"frames": 0, "points": 0, "points_in_view": 0, "removed_points": 0, "map_points": 0}
    return {
        "counts": {**empty, **counts},
        # images found in the segmentation cache, images the network segmented
        "segmentation": {
            "cache_hits": 0 if cached is None else cached.hits,
            "segmented": 0 if cached is None else cached.misses,
        },
        "maps": maps,
        "metric_counts": metric_counts,
        "rows": rows,
        "timings": {**timings, "tile": round(time.perf_counter() - started, 3)},
        "worker_peak_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
    }


def _write_tracks(out: Path, tile: int, result: ClutterResult | None, keep: np.ndarray) -> None:
    """The observations (survey frame, cluster) of every track that touches the tile's own
    frames (none without a result), so that `tile_assembly.join_tracks` can join a track seen
    by several tiles."""
    track, frame, cluster = [], [], []
    if result is not None and result.tracks is not None and result.frame_numbers is not None:
        own_numbers = set(result.frame_numbers[keep].tolist())
        for t, trk in enumerate(result.tracks.tracks):
            if own_numbers.isdisjoint(trk.frames):
                continue
            track += [t] * len(trk.frames)
            frame += trk.frames
            cluster += trk.clusters
    np.savez(
        Path(out) / TILES / f"{tile_name(tile)}.tracks.npz",
        track=np.asarray(track, dtype=np.int64),
        frame=np.asarray(frame, dtype=np.int64),
        cluster=np.asarray(cluster, dtype=np.int64),
    )


def cached_segmentation(
    cache_dir: Path | None, weights_dir: Path | None, gamma: float
) -> CachedSegmenter:
    """The run's segmentation cache, for what is drawn after the tiles (overlays)."""
    segmenter = _worker_segmenter(None if weights_dir is None else str(weights_dir), gamma)
    return CachedSegmenter(segmenter, cache_dir)


@dataclass
class ClutterTiledRun:
    """A tiled run's outcome: the assembled files and totals (`tile_assembly`), the tiles, and
    how many tiles this attempt ran (the rest came from an earlier one)."""

    files: dict[str, str]
    counts: dict
    metric_counts: dict | None
    timings: dict[str, float]
    worker_peak_mb: float  # the largest peak memory of a process that ran a tile
    segmentation: dict[str, int]  # images found in the cache, images segmented (`_summary`)
    rows: list[dict]  # the review units' store rows (with `review`), track ids joined
    tiles: FrameTiles
    tiles_run: int


def run_clutter_tiled(
    config: ClutterConfig,
    survey: Survey,
    out: Path,
    length: float = TILE_LENGTH,
    halo: float | None = None,
    progress: Progress | None = None,
    map_tiles: TileMap = in_process,
    review: bool = False,
    cache_dir: Path | None = None,
    weights_dir: Path | None = None,
    map_mb: float | None = TILE_MAP_MB,
) -> ClutterTiledRun:
    """The survey tile by tile into `out`: each tile's files as it finishes, the maps and
    totals assembled from them. Tiles an earlier attempt finished with the same plan are not
    run again; `map_tiles` may run the tiles side by side on a cluster. A tile ends at
    `length` metres or before its frames would add more than `map_mb` megabytes to its
    free-space map (None, or no free space: tiles by length only)."""
    halo = clutter_halo(config) if halo is None else halo
    budget = map_mb if config.use_free_space else None
    loads = frame_loads(survey, config)
    tiles = FrameTiles.build(
        survey, length, halo, budget, loads.map_mb, tile_workers(map_tiles), loads.work
    )
    spec = ClutterTileSpec(  # absolute paths: a cluster's workers run elsewhere
        str(Path(survey.source).resolve()), survey.format, config.model_dump_json(),
        str(Path(out).resolve()), tuple(maps_offset(survey).tolist()),
        None if cache_dir is None else str(Path(cache_dir).resolve()),
        None if weights_dir is None else str(Path(weights_dir).resolve()), review,
    )  # fmt: skip
    Path(out).mkdir(parents=True, exist_ok=True)
    done = finished_tiles(out, spec.plan(tiles))
    assembly = ClutterAssembly(out)
    try:
        ran = drive_tiles(
            clutter_tile, spec, tiles, tiles.count, done, assembly.add, map_tiles, progress,
            TILE_STEPS, cost=tiles.reads(),
        )  # fmt: skip
        frames = sum(s["counts"]["frames"] for s in done.values())
        if frames != len(survey.frames):
            raise RuntimeError(f"tiles labelled {frames} of {len(survey.frames)} frames")
        assembled = assembly.finish()
    except BaseException:
        assembly.abort()
        raise
    return ClutterTiledRun(**assembled, tiles=tiles, tiles_run=ran)
