"""The viewer's map: re-centred float32, exact pillars, tiles as slices, overview cap, cache."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from sqlalchemy.engine import Engine

from app.core.errors import ConfigError
from app.core.settings import Settings
from app.jobs.survey_tasks import prepare_viewer
from app.review import survey_map as survey_map_module
from app.review.survey_map import TILE_GRID, MapSource, accumulate_local, load_map
from app.store.models import Survey
from app.store.pillar_labels import STORE_GRID
from tests.jobs.conftest import job_context
from tests.viewer.conftest import street_points


def source_of(record: Survey) -> MapSource:
    return MapSource.of(record)


def test_map_is_recentred_float32_with_exact_pillars(ply_survey: Survey, tmp_path: Path) -> None:
    m = load_map(source_of(ply_survey), tmp_path / "cache", overview_points=10_000)
    world = street_points()
    assert m.xyz.dtype == np.float32 and len(m) == len(world)
    assert np.abs(m.xyz).max() < 200  # local: near the origin, not 5e6
    np.testing.assert_allclose(m.origin, np.floor(world.min(axis=0)))
    # same multiset of points back in world coordinates (to float32 precision, ~1e-5 m here)
    back = np.sort(m.xyz.astype(np.float64)[:, 0] + m.origin[0])
    np.testing.assert_allclose(back, np.sort(world[:, 0]), atol=1e-4)
    # each point's pillar is the store-grid cell of its world xy
    rebuilt = m.xyz.astype(np.float64)[:, :2] + m.origin[:2]
    inside = (np.abs(np.modf(rebuilt / STORE_GRID.cell_size)[0] - 0.5) < 0.49).all(axis=1)
    expected = STORE_GRID.point_cell_ids(rebuilt[inside])
    np.testing.assert_array_equal(m.cells[m.cell[inside]], expected)


def test_tiles_are_contiguous_slices_and_overview_is_capped(
    ply_survey: Survey, tmp_path: Path
) -> None:
    m = load_map(source_of(ply_survey), tmp_path / "cache", overview_points=10_000)
    assert len(m.tile_ids) == 3  # 120 m x 30 m at 50 m tiles
    total = 0
    for tile in m.tile_ids:
        points = m.tile_points(int(tile))
        ids = TILE_GRID.point_cell_ids(m.xyz[points, :2])
        assert (ids == tile).all()
        total += len(points)
    assert total == len(m)
    assert len(m.tile_points(int(m.tile_ids.max()) + 12345)) == 0
    assert len(m.overview) == 10_000 and np.all(np.diff(m.overview) > 0)
    # the ground under the box is found, not the box top (the street rises 2 % along x)
    np.testing.assert_allclose(m.ground.height(np.array([[21.0, 11.0]])), 0.42, atol=0.1)


def test_second_open_reads_the_cache(
    ply_survey: Survey, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    first = load_map(source_of(ply_survey), tmp_path / "cache", overview_points=10_000)
    assert len(list((tmp_path / "cache" / "viewer").glob("survey-*"))) == 1
    assert isinstance(first.xyz, np.memmap)  # read from disk as shown, not held

    def no_build(*_: object) -> None:
        raise AssertionError("the map was rebuilt although it is cached")

    monkeypatch.setattr(survey_map_module, "build_map", no_build)
    second = load_map(source_of(ply_survey), tmp_path / "cache", overview_points=10_000)
    np.testing.assert_array_equal(first.xyz, second.xyz)
    np.testing.assert_array_equal(first.overview, second.overview)


def test_a_build_that_finds_the_map_finished_keeps_that_one(
    ply_survey: Survey, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Two processes build the same map (the prepare:viewer job and a viewer's first open):
    the one that finishes second finds the other's map under the final name and keeps it."""
    build = survey_map_module.build_map
    cache = tmp_path / "cache" / "viewer"

    def build_while_another_finishes(source: MapSource, overview: int, folder: Path) -> None:
        build(source, overview, folder)
        other = cache / source.cache_name(overview)
        shutil.copytree(folder, other)  # the other process's rename

    monkeypatch.setattr(survey_map_module, "build_map", build_while_another_finishes)
    m = load_map(source_of(ply_survey), tmp_path / "cache", overview_points=10_000)
    assert len(m) == len(street_points())
    assert [p.name for p in cache.iterdir()] == [source_of(ply_survey).cache_name(10_000)]


def test_the_prepare_job_builds_the_map_the_viewer_opens(
    ply_survey: Survey, engine: Engine, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """`prepare:viewer` (queued when a survey is imported) writes the map; the viewer's open
    then reads it without building; options are refused."""
    settings = Settings(data_dir=tmp_path / "var", sample_dir="")
    result = prepare_viewer(job_context(settings, engine, 1, ply_survey.id), {})
    assert result["points"] == len(street_points()) and result["tiles"] >= 1

    def no_build(*_: object) -> None:
        raise AssertionError("the map was rebuilt although the job built it")

    monkeypatch.setattr(survey_map_module, "build_map", no_build)
    opened = load_map(source_of(ply_survey), settings.cache_dir, settings.viewer_overview_points)
    assert len(opened) == result["points"]
    with pytest.raises(ConfigError, match="takes no options"):
        prepare_viewer(job_context(settings, engine, 2, ply_survey.id), {"tile": 1})


def test_another_overview_cap_rebuilds_and_replaces(ply_survey: Survey, tmp_path: Path) -> None:
    load_map(source_of(ply_survey), tmp_path / "cache", overview_points=10_000)
    smaller = load_map(source_of(ply_survey), tmp_path / "cache", overview_points=5_000)
    assert len(smaller.overview) == 5_000
    assert len(list((tmp_path / "cache" / "viewer").glob("survey-*"))) == 1


def test_the_streamed_map_is_the_whole_map_sorted_by_tile(tmp_path: Path) -> None:
    """Built frame by frame into memory-mapped files, the map of the sample survey (1.4 M
    points in 59 frames) holds what accumulating the whole survey and sorting it by tile
    (stable: frame order within a tile) gives, with the same pillar of every point."""
    sample = Path(__file__).resolve().parents[2] / "data_samples" / "urban-60m"
    source = MapSource(1, str(sample), "sim", (3.0, -41.0, -2.0), 0, 0)
    m = load_map(source, tmp_path / "cache", overview_points=10_000)
    local, world_xy = accumulate_local(source)
    order = np.argsort(TILE_GRID.point_cell_ids(local[:, :2]), kind="stable")
    np.testing.assert_array_equal(np.asarray(m.xyz), local[order])
    np.testing.assert_array_equal(m.cells[m.cell], STORE_GRID.point_cell_ids(world_xy[order]))
    low, high = m.bounds()
    np.testing.assert_array_equal(low, local.min(axis=0))
    np.testing.assert_array_equal(high, local.max(axis=0))


def test_real_kitti_points_carry_intensity_and_their_camera_colour(
    real_data: Path, tmp_path: Path
) -> None:
    """SemanticKITTI 05, real (ten HDL-64E frames with image_2): every point keeps its
    reflectance; the points in front of the camera take the colour of the image pixel they
    project to (checked for one frame against the image itself), the others none."""
    from app.geometry.projection import pixel_indices, project
    from app.io import open_survey

    sequence = real_data / "semantickitti" / "sequences" / "05"
    survey = open_survey(sequence, "semantickitti")
    origin = np.floor(survey.frames[0].world_points().xyz.min(axis=0))
    source = MapSource(5, str(sequence), "semantickitti", tuple(origin.tolist()), 0, 0)
    m = load_map(source, tmp_path / "cache", overview_points=10_000)
    assert np.isfinite(np.asarray(m.intensity)).all()
    assert float(np.min(m.intensity)) >= 0.0 and float(np.max(m.intensity)) <= 1.0
    seen = np.asarray(m.has_rgb)
    assert 0.05 < seen.mean() < 0.5  # the forward camera sees a slice of the 360 degree scan
    assert (np.asarray(m.rgb)[~seen] == 0).all()
    # frame 0 alone: its points' colours are the image's pixels where they project
    frame = survey.frames[0]
    camera = next(iter(survey.cameras.values()))
    proj = project(frame.points().xyz, camera.P, camera.T_cam_sensor, camera.width, camera.height)
    rows, cols = pixel_indices(proj)
    expected = frame.image(camera.name)[rows, cols, :3]
    local = (frame.world_points().xyz - origin).astype(np.float32)[proj.in_image]
    # find frame 0's points in the map (tile-sorted): match by exact local coordinates
    key = {tuple(p): i for i, p in enumerate(np.asarray(m.xyz)[seen].tolist())}
    at = [key.get(tuple(p)) for p in local[:500].tolist()]
    found = [i for i in at if i is not None]
    assert len(found) > 450
    colours = np.asarray(m.rgb)[seen][found]
    matched = [j for j, i in enumerate(at) if i is not None]
    assert (colours == expected[:500][matched]).all(axis=1).mean() > 0.95
