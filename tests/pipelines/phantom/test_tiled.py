"""The phantom pipeline tile by tile agrees with the whole-map run, and a tile's halo reaches
across a drive that comes back to the same street."""

from __future__ import annotations

from pathlib import Path

import laspy
import numpy as np

from app.geometry.tiles import cell_keys
from app.io import open_survey
from app.io.survey import Frame, PointCloud, Survey
from app.io.tile_index import TileIndex
from app.pipelines.phantom.evaluation.classification_metrics import (
    metric_counts,
    metrics_from_counts,
)
from app.pipelines.phantom.pillars import phantom_ground
from app.pipelines.phantom.pipeline import PhantomPipeline
from app.pipelines.phantom.tiled import phantom_halo, run_phantom_tiled
from tests.io.surveys import there_and_back

SAMPLE = Path(__file__).resolve().parents[3] / "data_samples" / "urban-60m"
PROFILE_MODEL = Path(__file__).resolve().parents[3] / "models" / "phantom" / "phantom_cnn.pt"


def _first_frames(n: int) -> Survey:
    survey = open_survey(SAMPLE, "sim")
    survey.frames = survey.frames[:n]
    return survey


def _labels(out: Path, survey: Survey) -> np.ndarray:
    return np.concatenate([np.load(out / "labels" / f"{f.frame_id}.npy") for f in survey.frames])


def test_tiled_results_agree_with_the_whole_map(tmp_path: Path) -> None:
    """The sample survey's first 36 frames (about 35 m) in 12 m tiles with the pipeline's halo:
    every point labelled once, the labels, the metrics and the pillars those of the untiled run
    (issue: >= 99.9 %), the cleaned and removed maps all the points."""
    survey = _first_frames(36)
    pipeline = PhantomPipeline(model_path=PROFILE_MODEL)
    whole = pipeline.run(survey)
    run = run_phantom_tiled(pipeline, survey, tmp_path, length=12.0)
    index = run.index
    assert index.count == 3 and index.layout.halo == phantom_halo(pipeline.config) == 11.0
    assert run.tiles_run == 3
    a = np.concatenate([whole.frame_labels()[f.frame_id] for f in survey.frames])
    b = _labels(tmp_path, survey)
    assert len(a) == len(b) == int(index.owned_points.sum()) == run.counts["points"]
    assert (a == b).mean() >= 0.999
    assert (b == 3).sum() > 1000  # the sample's phantoms are there
    assert run.counts["phantom_points"] == int((b == 3).sum())
    cleaned = laspy.read(tmp_path / "cleaned.laz")
    removed = laspy.read(tmp_path / "removed.laz")
    assert len(cleaned.points) + len(removed.points) == len(b)
    assert (np.asarray(removed["mmsclean_label"]) == 3).all()
    frame = np.asarray(removed["source_frame"]).astype(np.int64)
    index_in_frame = np.asarray(removed["source_index"]).astype(np.int64)
    offsets = np.r_[0, np.cumsum(index.frame_sizes)[:-1]]
    assert (b[offsets[frame] + index_in_frame] == 3).all()  # each removed point is a phantom
    expected = metrics_from_counts(metric_counts(whole))
    got = metrics_from_counts(run.metric_counts)
    for key in ("point", "pillar"):
        assert abs(got[key]["macro"]["f1"] - expected[key]["macro"]["f1"]) < 0.5
    with np.load(tmp_path / "pillars.npz") as pillars:
        assert len(pillars["labels"]) == run.counts["pillars"]
        assert abs(len(pillars["labels"]) - len(whole.pillar_labels)) <= 0.001 * len(b)


def test_a_resumed_run_reruns_only_the_missing_tiles(tmp_path: Path) -> None:
    """A tile whose summary is missing (its worker died before it) is run again, the others are
    kept; a different plan (here the tile length) runs every tile afresh."""
    survey = _first_frames(24)
    pipeline = PhantomPipeline(model_path=PROFILE_MODEL)
    first = run_phantom_tiled(pipeline, survey, tmp_path, length=12.0)
    before = _labels(tmp_path, survey)
    (tmp_path / "tiles" / "00001.json").unlink()
    again = run_phantom_tiled(pipeline, survey, tmp_path, length=12.0)
    assert first.index.count == 2 and again.tiles_run == 1
    assert np.array_equal(_labels(tmp_path, survey), before)
    other = run_phantom_tiled(pipeline, survey, tmp_path, length=30.0)
    assert other.index.count == 1 and other.tiles_run == 1


def test_a_tile_reads_every_frame_with_its_points_whichever_pass_measured_them() -> None:
    """A point belongs to the tile of the nearer pass (the left wall: the way back, the last
    tile near the start); the way out measured it too, so that tile reads the way out's frames."""
    survey = there_and_back()
    index = TileIndex.build(survey, length=41.0, halo=4.0)  # 120.5 m: three tiles
    assert index.count == 3 and int(index.owned_points.sum()) == 61 * 400
    for tile in range(index.count):
        holding = {
            k for k, f in enumerate(survey.frames) if index.owned(f.world_points().xyz, tile).any()
        }
        assert holding <= set(index.frames[tile].tolist())
    assert {0, 5, 9} <= set(index.frames[2].tolist())  # the way out, at the start
    start_left = survey.frames[5].world_points().xyz[:200]  # the left wall, x 0 .. 20
    assert index.owned(start_left, 2).all() and index.in_window(start_left, 2).all()


def test_a_frame_without_points_is_indexed_and_owns_nothing() -> None:
    """A scanner that returned nothing for a frame (a dropout) leaves an empty frame: it is
    indexed like the others (a 4 km simulated survey has some)."""
    survey = there_and_back()
    empty = survey.frames[7]
    survey.frames[7] = Frame(
        empty.index, empty.frame_id, empty.pose, empty.timestamp, 0,
        _load_points=lambda: PointCloud(np.zeros((0, 3))),
    )  # fmt: skip
    index = TileIndex.build(survey, length=41.0, halo=4.0)
    assert index.frame_sizes[7] == 0 and int(index.owned_points.sum()) == 60 * 400


def test_a_windows_ground_is_the_whole_maps_ground() -> None:
    """The ground grid reaches past the points by the opening's width, so its edge never
    shapes the ground under a point: a tile's window whose points end where the whole map's go
    on elsewhere (here laterally) gets the same ground under its own points."""
    survey = _first_frames(36)
    pipeline = PhantomPipeline(model_path=PROFILE_MODEL)
    index = TileIndex.build(survey, 12.0, phantom_halo(pipeline.config))
    whole = pipeline.accumulate(survey)
    last = index.count - 1
    part = pipeline.accumulate(
        index.tile_survey(survey, last), lambda xyz: index.in_window(xyz, last), index.time0
    )
    assert part.xyz[:, 1].max() < whole.xyz[:, 1].max() - 5  # the map reaches further
    own = part.xyz[index.owned(part.xyz, last)]
    np.testing.assert_allclose(
        phantom_ground(part.xyz, pipeline.config).height(own),
        phantom_ground(whole.xyz, pipeline.config).height(own),
        atol=1e-9,
    )


def test_a_point_budget_cuts_dense_tiles_shorter() -> None:
    """The same frames with a budget of a fifth of the points per window: more, shorter tiles,
    every point still owned by exactly one of them."""
    survey = _first_frames(24)
    free = TileIndex.build(survey, 12.0, 11.0, 2.0)
    total = int(free.frame_sizes.sum())
    bounded = TileIndex.build(survey, 12.0, 11.0, 2.0, max_points=total // 5)
    assert bounded.count > free.count
    assert int(bounded.owned_points.sum()) == total
    keys = np.concatenate(bounded.owned_cells)
    assert len(keys) == len(np.unique(keys))  # a cell has one owner
    assert np.all(np.diff(bounded.layout.edges) <= 12.0)


def test_a_window_over_both_passes_is_cut_again() -> None:
    """Where the drive comes back along its street, a tile's window holds both passes' points,
    more than its stations say: such a tile is cut again until its window keeps to the budget
    (or the tile is as short as it may be)."""
    survey = there_and_back()
    budget = 4_000
    index = TileIndex.build(survey, length=41.0, halo=4.0, max_points=budget)
    flat = TileIndex.build(survey, length=41.0, halo=4.0)
    assert index.count > flat.count
    assert int(index.owned_points.sum()) == 61 * 400
    for tile, window in enumerate(index.window_cells):
        held = sum(
            int(np.isin(cell_keys(f.world_points().xyz, index.cell), window).sum())
            for f in survey.frames
        )
        start, end = index.layout.bounds(tile)
        short = min(end, index.layout.total) - max(start, 0.0) < 4 * index.cell
        assert held <= budget or short, (tile, held)


def test_the_pass_in_parts_is_the_pass_in_one(monkeypatch) -> None:
    """A cluster scans the frames in parts, each reopening the survey from its source: the
    index is the one this process builds from the frames in one pass."""
    import app.io.tile_index as tile_index
    from app.pipelines.tiling import in_process

    survey = _first_frames(40)
    whole = TileIndex.build(survey, 12.0, 11.0, 2.0, max_points=200_000)
    monkeypatch.setattr(tile_index, "PART_FRAMES", 7)  # 6 parts of 6 or 7 frames
    parts = TileIndex.build(survey, 12.0, 11.0, 2.0, max_points=200_000, map_parts=in_process)
    assert parts.count == whole.count > 2
    np.testing.assert_array_equal(parts.frame_sizes, whole.frame_sizes)
    np.testing.assert_array_equal(parts.owned_points, whole.owned_points)
    for a, b in zip(
        parts.frames + parts.owned_cells, whole.frames + whole.owned_cells, strict=True
    ):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(parts.low, whole.low)
    np.testing.assert_allclose(parts.centre, whole.centre, rtol=0, atol=1e-9)
