"""The clutter pipeline tile by tile agrees with the whole-drive run, joins the tracks that cross
tiles, and a rerun keeps the finished tiles (synthetic streets)."""

from __future__ import annotations

import shutil
from dataclasses import replace
from pathlib import Path

import laspy
import numpy as np
import pytest

from app.io import open_survey
from app.io.frame_tiles import FrameTiles
from app.pipelines.clutter.config import ClutterConfig
from app.pipelines.clutter.evaluation.removal_metrics import removal_metrics
from app.pipelines.clutter.map_budget import MB_PER_RAY_KM, ROTATING_FRAME_MB, frame_map_mb
from app.pipelines.clutter.pipeline import ClutterPipeline
from app.pipelines.clutter.run import run_clutter_report
from app.pipelines.clutter.segmenter import ESPNetv2Segmenter, segmented_class_maps
from app.pipelines.clutter.tile_assembly import join_tracks
from app.pipelines.clutter.tiled import clutter_halo, run_clutter_tiled
from app.pipelines.tiling import TILES
from app.simulate.survey import SimulationConfig, simulate
from tests.io.surveys import there_and_back

# a rotating scanner (its frames overlap: free space and tracks reach across tiles), 40 m reach
CONFIG = ClutterConfig(mode="dynamic", use_camera=False, max_range=40.0, threads=1)


@pytest.fixture(scope="module")
def street(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("clutter-tiles") / "sim"
    simulate(
        SimulationConfig(scene="urban", length=40.0, seed=3, scanner="hdl64", camera=False), out
    )
    return out


@pytest.fixture(scope="module")
def tiled(street: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict, object]:
    """The street in 15 m tiles (review units too), run once for the tests that read it: the
    folder, the report and the run (the rerun test copies the folder)."""
    out = tmp_path_factory.mktemp("clutter-tiled")
    report, run = run_clutter_report(
        open_survey(street, "sim"), out, CONFIG, tile_length=15.0, review=True
    )
    return out, report, run


def _labels(out: Path, survey) -> np.ndarray:
    return np.concatenate([np.load(out / "labels" / f"{f.frame_id}.npy") for f in survey.frames])


def test_tiled_clutter_agrees_with_the_whole_drive(street: Path, tiled) -> None:
    """40 m in 15 m tiles with the pipeline's halo (half the reach): the labels those of the
    untiled run (issue: >= 99.9 %), the tracks joined into as many as one run finds, the maps
    holding every point once, the scores those of the labels written."""
    survey = open_survey(street, "sim")
    whole = ClutterPipeline(CONFIG).run(survey)
    tmp_path, report, run = tiled
    assert run.tiles.count == 3 and run.tiles_run == 3
    assert report["tiles"]["halo_m"] == clutter_halo(CONFIG) == 20.0
    assert all(len(run.tiles.frames[t]) < len(survey.frames) for t in (0, 2))  # context, not all
    a = np.concatenate(whole.removed)
    b = _labels(tmp_path, survey).astype(bool)
    assert len(a) == len(b) == report["counts"]["points"]
    assert (a == b).mean() >= 0.999 and b.sum() > 1000
    assert abs(report["counts"]["tracks"] - len(whole.tracks.tracks)) <= 0.02 * len(
        whole.tracks.tracks
    )
    cleaned, removed = laspy.read(tmp_path / "cleaned.laz"), laspy.read(tmp_path / "removed.laz")
    assert len(cleaned.points) == len(b) - b.sum() and len(removed.points) == b.sum()
    frame = np.asarray(removed["source_frame"]).astype(np.int64)
    index = np.asarray(removed["source_index"]).astype(np.int64)
    sizes = np.array([len(np.load(tmp_path / "labels" / f"{f.frame_id}.npy")) for f in survey])
    assert b[np.r_[0, np.cumsum(sizes)[:-1]][frame] + index].all()  # each removed point is removed
    references = [f.reference_labels() for f in survey.frames]
    expected = removal_metrics(
        np.concatenate([r["semantic"] for r in references]), b, np.zeros(len(b), bool),
        np.concatenate([r["moving"] for r in references]),
    )  # fmt: skip
    assert report["metrics"]["full"] == expected["full"]
    # review rows: one per instance of every frame, track ids of the joined tracks
    assert {r["frame_id"] for r in run.rows} <= {f.frame_id for f in survey.frames}
    ids = {r["track_id"] for r in run.rows if r["track_id"] is not None}
    assert ids and max(ids) < report["counts"]["tracks"]
    assert all((tmp_path / "instances" / f"{f.frame_id}.npz").is_file() for f in survey.frames)


def test_a_rerun_keeps_the_finished_clutter_tiles(street: Path, tiled, tmp_path: Path) -> None:
    """Only the tile whose summary is missing runs again: the other tiles' frames keep their
    label files as they were, and the run's labels and counts come out as before (to 0.1 %:
    DUFOMap with several threads need not repeat itself bit for bit). The first run is the
    module's (`tiled`), copied."""
    survey = open_survey(street, "sim")
    shutil.copytree(tiled[0], tmp_path, dirs_exist_ok=True)
    first, run = tiled[1], tiled[2]
    kept = [survey.frames[k].frame_id for t in (0, 2) for k in run.tiles.own(t)]
    before = {f: np.load(tmp_path / "labels" / f"{f}.npy") for f in kept}
    labels = _labels(tmp_path, survey)
    (tmp_path / TILES / "00001.json").unlink()
    again, run = run_clutter_report(survey, tmp_path, CONFIG, tile_length=15.0, review=True)
    assert run.tiles_run == 1 and again["tiles"]["kept_from_earlier_attempt"] == 2
    assert all(np.array_equal(np.load(tmp_path / "labels" / f"{f}.npy"), before[f]) for f in kept)
    assert (_labels(tmp_path, survey) == labels).mean() >= 0.999
    assert again["counts"]["points"] == first["counts"]["points"]
    assert abs(again["counts"]["removed_points"] - first["counts"]["removed_points"]) <= (
        0.001 * first["counts"]["points"]
    )


def test_tracks_sharing_an_observation_are_one_track(tmp_path: Path) -> None:
    """Tile 0's track 4 and tile 1's track 0 both hold frame 7's cluster 2: one track; tile 1's
    track 1 stands alone. Ids follow the tiles' order."""
    for tile, (track, frame, cluster) in enumerate(
        [([4, 4, 9], [6, 7, 2], [1, 2, 5]), ([0, 0, 1], [7, 8, 8], [2, 3, 0])]
    ):
        np.savez(
            tmp_path / f"{tile:05d}.tracks.npz",
            track=np.array(track), frame=np.array(frame), cluster=np.array(cluster),
        )  # fmt: skip
    joined = join_tracks(tmp_path, [0, 1])
    assert joined == {0: {4: 0, 9: 1}, 1: {0: 0, 1: 2}}


def test_tiles_share_the_segmentation_cache(weights_dir: Path, tmp_path: Path) -> None:
    """With the camera: each tile segments its frames through the shared cache, so a frame
    that several tiles read is segmented once; the labels agree with the untiled run's."""
    sim = tmp_path / "sim"
    simulate(SimulationConfig(scene="urban", length=12.0, seed=3, scanner="hdl64"), sim)
    survey = open_survey(sim, "sim")
    config = ClutterConfig(mode="clutter", max_range=20.0)
    cache = tmp_path / "cache"
    pipeline = ClutterPipeline(config)
    pipeline.class_maps, _ = segmented_class_maps(
        survey,
        pipeline.camera(survey).name,
        ESPNetv2Segmenter(weights_dir, gamma=config.image_gamma),  # as the tiles segment
        None,
        cache,
    )
    whole = pipeline.run(survey)
    report, run = run_clutter_report(
        survey, tmp_path / "out", config, tile_length=5.0, cache_dir=cache, weights_dir=weights_dir
    )
    assert run.tiles.count >= 2
    assert sum(len(f) for f in run.tiles.frames) > len(survey.frames)  # frames read twice
    assert report["segmenter"]["segmented"] == 0  # the untiled run segmented every frame
    a = np.concatenate(whole.removed)
    b = _labels(tmp_path / "out", survey).astype(bool)
    assert (a == b).mean() >= 0.999 and b.sum() > 0
    assert report["counts"]["points_in_view"] > 0


def test_a_tile_without_frames_is_empty(street: Path, tmp_path: Path) -> None:
    """Frames far apart (a gap in the recording) leave tiles that own no frame: they finish
    empty, and the others' results are whole."""
    survey = open_survey(street, "sim")
    frames = list(survey.frames)[:4]
    far = frames[3].pose.copy()
    far[0, 3] += 250.0  # the last frame 250 m further on
    frames[3] = replace(frames[3], pose=far)
    gap = replace(survey, frames=frames)
    run = run_clutter_tiled(CONFIG, gap, tmp_path, 100.0, map_mb=None)  # tiles by length
    assert run.tiles.count == 3 and len(run.tiles.own(1)) == 0
    assert run.counts["frames"] == 4
    assert run.counts["points"] == sum(len(f.points()) for f in frames)


def test_a_frame_budget_cuts_tiles_shorter(street: Path) -> None:
    """Read frames are bounded: a tile ends before it would read more than the budget, its
    own frames' halo included."""
    survey = open_survey(street, "sim")
    free = FrameTiles.build(survey, 100.0, 5.0)
    bounded = FrameTiles.build(survey, 100.0, 5.0, budget=20)
    assert free.count == 1 and bounded.count > 1
    assert max(len(f) for f in bounded.frames) <= 20
    assert sorted(np.concatenate([bounded.own(t) for t in range(bounded.count)])) == list(
        range(len(survey.frames))
    )


def test_budget_cut_tiles_are_evened_over_the_workers(street: Path) -> None:
    """On 2 workers, 8 m tiles that a 15-frame budget cuts into an odd count are cut again from
    shorter equal tiles into an even one, within the budget; where the budget alone decides
    every edge (8 frames), no shorter length helps and the cut stays as it was. Tiles by length
    alone (no budget) are the nearest multiple."""
    survey = open_survey(street, "sim")
    alone = FrameTiles.build(survey, 8.0, 5.0, budget=15)
    evened = FrameTiles.build(survey, 8.0, 5.0, budget=15, workers=2)
    assert alone.count % 2 == 1 and evened.count % 2 == 0 and evened.count > 1
    assert max(len(f) for f in evened.frames) <= 15
    assert sorted(np.concatenate([evened.own(t) for t in range(evened.count)])) == list(
        range(len(survey.frames))
    )
    tight = FrameTiles.build(survey, 8.0, 5.0, budget=8)
    assert tight.count % 2 == 1
    assert (
        FrameTiles.build(survey, 8.0, 5.0, budget=8, workers=2).layout.edges == tight.layout.edges
    )
    assert FrameTiles.build(survey, 25.0, 5.0, workers=2).count % 2 == 0


def test_the_way_back_has_its_own_tiles() -> None:
    """A drive that comes back along its street: each frame's tile follows its own station
    (the way back's frames are not put at the way out's stations), each frame's context holds
    both passes, and a tile owns more than one frame although one frame's context alone is
    over the budget (that context and a third of the budget more at most)."""
    survey = there_and_back()
    tiles = FrameTiles.build(survey, 41.0, 10.0, budget=8)
    assert np.all(np.diff(tiles.owner) >= 0)  # tiles follow the drive
    assert tiles.owner[-1] == tiles.count - 1 and tiles.owner[30] < tiles.count - 1
    context = max(len(f) for f in FrameTiles.build(survey, 0.5, 10.0).frames)  # one frame's
    assert context > 8
    assert all(len(tiles.own(t)) > 1 for t in range(tiles.count))
    assert max(len(f) for f in tiles.frames) <= context + 8 // 3
    way_back = tiles.frames[tiles.owner[-1]]
    assert (way_back <= 30).any()  # its context reads the way out too


def test_heavier_frames_make_shorter_tiles(street: Path) -> None:
    """Frames weigh what they add to the free-space map: where they weigh three times as much,
    a tile reads a third as many, and the weight it reads stays within the budget."""
    survey = open_survey(street, "sim")
    n = len(survey.frames)
    weights = np.where(np.arange(n) < n // 2, 1.0, 3.0)
    light = FrameTiles.build(survey, 100.0, 5.0, budget=60)
    mixed = FrameTiles.build(survey, 100.0, 5.0, budget=60, weights=weights)
    assert light.count == 1 and mixed.count > 1
    assert max(weights[f].sum() for f in mixed.frames) <= 60
    heavy = [t for t in range(mixed.count) if (weights[mixed.own(t)] == 3).all()]
    assert heavy and max(len(mixed.frames[t]) for t in heavy) <= 20
    with pytest.raises(ValueError, match="frame weights"):
        FrameTiles.build(survey, 100.0, 5.0, budget=60, weights=weights[:-1])


def test_the_map_budget_weighs_a_profile_scanners_rays() -> None:
    """A profile scanner's frame adds to the map by its rays' length (measured on every 5th
    frame, interpolated between); a rotating scanner's, a fixed amount per frame."""
    survey = open_survey(Path(__file__).resolve().parents[3] / "data_samples" / "urban-60m", "sim")
    assert survey.scanner == "profile"
    config = ClutterConfig()
    every = frame_map_mb(survey, config, every=1)
    rays = np.array([np.linalg.norm(f.points().xyz, axis=1).sum() for f in survey.frames])
    np.testing.assert_allclose(every, rays / 1e3 * MB_PER_RAY_KM)
    sampled = frame_map_mb(survey, config)
    np.testing.assert_allclose(sampled[::5], every[::5])
    np.testing.assert_allclose(sampled[-1], every[-1])
    between = (sampled[1:5] - every[0]) * (sampled[1:5] - every[5])
    assert (between <= 1e-12).all()  # between its sampled neighbours
    coarse = frame_map_mb(survey, config.model_copy(update={"dufomap_resolution": 0.2}))
    np.testing.assert_allclose(coarse, sampled * 0.5**1.6)
    rotating = frame_map_mb(replace(survey, scanner="hdl64"), config)
    np.testing.assert_allclose(rotating, ROTATING_FRAME_MB)
