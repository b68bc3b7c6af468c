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
from app.geometry.voxels import voxel_indices
from app.io.asprs import REMOVED_CLUTTER_ASPRS
from app.io.frame_tiles import FrameTiles
from app.io.las import LasAppender, write_laz
from app.io.survey import Camera, PointCloud, Survey
from app.pipelines.clutter.config import ClutterConfig
from app.pipelines.clutter.evaluation.removal_metrics import add_removal_counts, removal_counts
from app.pipelines.clutter.pipeline import ClutterPipeline, ClutterResult
from app.pipelines.clutter.review_units import write_review_units
from app.pipelines.clutter.segmenter import CachedSegmenter, Segmenter, segmented_class_maps
from app.pipelines.clutter.tile_assembly import MAPS, ClutterAssembly
from app.pipelines.outputs import write_frame_labels
from app.pipelines.tiling import (
    TILES,
    TileMap,
    drive_tiles,
    finished_tiles,
    in_process,
    tile_name,
    write_summary,
)

TILE_LENGTH = 100.0  # metres of trajectory per tile
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
    labels agree with the untiled run at this halo, 99.999 % at the full reach, which reads
    twice as many frames (bench/RESULTS.md)."""
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
            "tiles": [tiles.count, layout.length, layout.halo, len(tiles.owner)],
        }  # fmt: skip


@lru_cache(maxsize=2)
def _worker_segmenter(weights_dir: str | None) -> Segmenter:
    """One segmentation network per worker process (the tiles of a run share it)."""
    from app.pipelines.clutter.segmenter import ESPNetv2Segmenter

    return ESPNetv2Segmenter(None if weights_dir is None else Path(weights_dir))


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
        return write_summary(out, tile, _summary({}, None, {}, None, [], {}, started))
    pipeline = ClutterPipeline(config)
    camera = pipeline.camera(survey)
    cached = None
    if camera is not None:
        reads = tiles.tile_survey(survey, tile)
        cache = None if spec.cache_dir is None else Path(spec.cache_dir)
        segmenter = _worker_segmenter(spec.weights_dir)
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
    maps = _write_maps(out, survey, own, [result.removed[i] for i in keep], config, spec, tile)
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
    metrics = _error_counts(survey, result, keep)
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


def _write_maps(
    out: Path,
    survey: Survey,
    own: np.ndarray,
    removed: list[np.ndarray],
    config: ClutterConfig,
    spec: ClutterTileSpec,
    tile: int,
) -> dict:
    """The own frames' kept and removed points as this tile's LAZ parts, a frame at a time
    (each frame's part appended, then dropped). `voxel_dedup` keeps the first kept point of
    each voxel of a grid fixed for the run (`spec.offset`): one key per kept point is held,
    and within the tile only (a voxel on a tile border may keep one point from each side)."""
    folder = out / TILES
    folder.mkdir(parents=True, exist_ok=True)
    name = tile_name(tile)
    first = None
    if config.voxel_dedup:
        first = _first_in_voxel(survey, own, removed, config.voxel_dedup, np.asarray(spec.offset))
    appenders = {kind: LasAppender(folder / f"{name}.{kind}.laz") for kind in MAPS}
    kept_points = 0
    try:
        for n, (k, gone) in enumerate(zip(own.tolist(), removed, strict=True)):
            cloud = survey.frames[k].world_points()
            if len(cloud.xyz) != len(gone):
                raise ValueError(f"frame {survey.frames[k].frame_id}: {len(cloud.xyz)} points, "
                                 f"{len(gone)} decisions")  # fmt: skip
            keep = ~gone if first is None else ~gone & first[n]
            kept_points += int(keep.sum())
            for kind, which, label in (("cleaned", keep, 0), ("removed", gone, 1)):
                if which.any():
                    part = folder / f"{name}.{kind}.frame.laz"
                    _write_points(part, cloud, np.flatnonzero(which), k, label, spec)
                    appenders[kind].append(part)
                    part.unlink()
        maps: dict = {"map_points": kept_points}
        for kind in MAPS:
            if appenders[kind].close():
                maps[kind] = f"{name}.{kind}.laz"
        return maps
    except BaseException:
        for appender in appenders.values():
            appender.abort()
        raise


def _write_points(
    path: Path, cloud: PointCloud, index: np.ndarray, frame: int, label: int, spec
) -> None:
    n = len(index)
    write_laz(
        path,
        cloud.xyz[index],
        mmsclean_label=np.full(n, label, dtype=np.uint8),
        classification=np.full(n, REMOVED_CLUTTER_ASPRS if label else 1, dtype=np.uint8),
        source_frame=np.full(n, frame, dtype=np.uint32),
        source_index=index.astype(np.uint32),
        intensity=None if cloud.intensity is None else reflectance(cloud.intensity[index]),
        offset=np.asarray(spec.offset),
    )


_HALF = 1 << 20  # voxel indices from the run's origin within +-2^20 pack into one int64


def _voxel_key(ijk: np.ndarray) -> np.ndarray:
    """(N,) int64 key of voxel indices (N, 3), the same in every frame (unlike
    `geometry.voxels.voxel_keys`, whose keys hold within one call)."""
    if len(ijk) and int(np.abs(ijk).max()) >= _HALF:
        raise ValueError("voxel_dedup: the survey reaches over 2^20 voxels from its first "
                         "sensor position; use larger voxels")  # fmt: skip
    shifted = ijk.astype(np.int64) + _HALF
    return (shifted[:, 0] << 42) | (shifted[:, 1] << 21) | shifted[:, 2]


def _first_in_voxel(
    survey: Survey, own: np.ndarray, removed: list[np.ndarray], voxel: float, origin: np.ndarray
) -> list[np.ndarray]:
    """Per own frame, (N,) bool: the point is the first kept point of its voxel (frame order)."""
    keys, sizes = [], []
    for k, gone in zip(own.tolist(), removed, strict=True):
        xyz = survey.frames[k].world_points().xyz
        keys.append(_voxel_key(voxel_indices(xyz[~gone], voxel, origin)))
        sizes.append(len(gone))
    flat = np.concatenate(keys) if keys else np.zeros(0, dtype=np.int64)
    chosen = np.zeros(len(flat), dtype=bool)
    chosen[np.unique(flat, return_index=True)[1]] = True
    out, start = [], 0
    for gone, part in zip(removed, keys, strict=True):
        flags = np.zeros(len(gone), dtype=bool)
        flags[~gone] = chosen[start : start + len(part)]
        start += len(part)
        out.append(flags)
    return out


def reflectance(values: np.ndarray) -> np.ndarray:
    """Reflectance 0..1 to the LAS 16-bit range; values already above 1 are kept as they are."""
    values = np.asarray(values, dtype=np.float64)
    return values * 65535.0 if values.size and values.max() <= 1.0 else values


def _write_tracks(out: Path, tile: int, result: ClutterResult, keep: np.ndarray) -> None:
    """The observations (survey frame, cluster) of every track that touches the tile's own
    frames, so that `tile_assembly.join_tracks` can join a track seen by several tiles."""
    track, frame, cluster = [], [], []
    if result.tracks is not None and result.frame_numbers is not None:
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


def _error_counts(survey: Survey, result: ClutterResult, keep: np.ndarray) -> dict | None:
    """The own frames' error matrices against the reference labels, added frame by frame;
    None without them."""
    if "semantic" not in survey.reference_label_kinds or result.frame_numbers is None:
        return None
    total = None
    for i in keep.tolist():
        reference = survey.frames[int(result.frame_numbers[i])].reference_labels()
        moving = reference.get("moving") if "moving" in survey.reference_label_kinds else None
        counts = removal_counts(reference["semantic"], result.removed[i], result.in_view[i], moving)
        total = add_removal_counts(total, counts)
    return total


def cached_segmentation(cache_dir: Path | None, weights_dir: Path | None) -> CachedSegmenter:
    """The run's segmentation cache, for what is drawn after the tiles (overlays)."""
    segmenter = _worker_segmenter(None if weights_dir is None else str(weights_dir))
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
) -> ClutterTiledRun:
    """The survey tile by tile into `out`: each tile's files as it finishes, the maps and
    totals assembled from them. Tiles an earlier attempt finished with the same plan are not
    run again; `map_tiles` may run the tiles side by side on a cluster."""
    halo = clutter_halo(config) if halo is None else halo
    tiles = FrameTiles.build(survey, length, halo)
    first = survey.frames[0].pose[:3, 3]
    spec = ClutterTileSpec(  # absolute paths: a cluster's workers run elsewhere
        str(Path(survey.source).resolve()), survey.format, config.model_dump_json(),
        str(Path(out).resolve()), tuple(np.floor(first).tolist()),
        None if cache_dir is None else str(Path(cache_dir).resolve()),
        None if weights_dir is None else str(Path(weights_dir).resolve()), review,
    )  # fmt: skip
    Path(out).mkdir(parents=True, exist_ok=True)
    done = finished_tiles(out, spec.plan(tiles))
    assembly = ClutterAssembly(out)
    try:
        ran = drive_tiles(
            clutter_tile, spec, tiles, tiles.count, done, assembly.add, map_tiles, progress,
            TILE_STEPS,
        )  # fmt: skip
        frames = sum(s["counts"]["frames"] for s in done.values())
        if frames != len(survey.frames):
            raise RuntimeError(f"tiles labelled {frames} of {len(survey.frames)} frames")
        assembled = assembly.finish()
    except BaseException:
        assembly.abort()
        raise
    return ClutterTiledRun(**assembled, tiles=tiles, tiles_run=ran)
