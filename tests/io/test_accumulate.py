"""The one accumulation gives its three users (clutter's kept / removed maps, the phantom map
with reference labels, the viewer's re-centred map) the arrays their own loops gave (synthetic)."""

from __future__ import annotations

from pathlib import Path

import laspy
import numpy as np
import pytest

from app.io import open_survey
from app.io.accumulate import accumulate
from app.io.survey import Survey
from app.pipelines.clutter.maps import write_frame_maps
from app.review.survey_map import MapSource, accumulate_local
from app.simulate.survey import SimulationConfig, simulate


@pytest.fixture(scope="module")
def survey(tmp_path_factory: pytest.TempPathFactory) -> Survey:
    out = tmp_path_factory.mktemp("accumulate") / "sim"
    simulate(SimulationConfig(scene="mixed", length=6.0, seed=3, camera=False), out)
    return open_survey(out, "sim")


def posed(survey: Survey):
    """(frame number, frame, cloud, world xyz) frame by frame, as each user computed them."""
    for i, frame in enumerate(survey.frames):
        cloud = frame.points()
        yield i, frame, cloud, cloud.xyz @ frame.pose[:3, :3].T + frame.pose[:3, 3]


def same(a: np.ndarray, b: np.ndarray) -> None:
    assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


@pytest.mark.parametrize("voxel", [None, 0.3])
def test_clutter_maps_are_the_selected_points_of_each_frame(
    survey: Survey, voxel, tmp_path: Path
) -> None:
    """Written a frame at a time, the maps hold each frame's kept (with `voxel_dedup`: the first
    kept point of each voxel of the offset's grid) and removed points, with their intensities
    and source frame / index."""
    rng = np.random.default_rng(0)
    removed = [rng.random(len(f.points())) < 0.3 for f in survey.frames]
    frames = np.arange(len(survey.frames))
    offset = np.floor(survey.frames[0].pose[:3, 3])
    maps = write_frame_maps(tmp_path, "", survey, frames, removed, voxel, offset)
    assert (maps["cleaned"], maps["removed"]) == ("cleaned.laz", "removed.laz")
    for flag, name in ((False, "cleaned"), (True, "removed")):
        xyz, intensity, frame, index = [], [], [], []
        for i, _, cloud, world in posed(survey):
            picked = np.flatnonzero(removed[i] == flag)
            xyz.append(world[picked])
            intensity.append(np.round(np.asarray(cloud.intensity, np.float64)[picked] * 65535))
            frame.append(np.full(len(picked), i))
            index.append(picked)
        want = [np.concatenate(v) for v in (xyz, intensity, frame, index)]
        if voxel and not flag:
            ijk = np.floor((want[0] - offset) / voxel).astype(np.int64)
            first = np.sort(np.unique(ijk, axis=0, return_index=True)[1])
            want = [v[first] for v in want]
        las = laspy.read(tmp_path / maps[name])
        got = np.column_stack([las.x, las.y, las.z])
        assert len(got) == len(want[0]) and np.abs(got - want[0]).max() <= 0.0005 + 1e-9
        assert np.array_equal(np.asarray(las.intensity), want[1].astype(np.uint16))
        assert np.array_equal(np.asarray(las["source_frame"]), want[2])
        assert np.array_equal(np.asarray(las["source_index"]), want[3])
    assert maps["map_points"] == len(laspy.read(tmp_path / "cleaned.laz").points)
    with pytest.raises(ValueError, match="decisions"):
        write_frame_maps(tmp_path, "x", survey, frames, [r[:-1] for r in removed], None, offset)


def test_phantom_map_keeps_reference_labels_and_splits_back(survey: Survey) -> None:
    amap = accumulate(survey, with_reference=True)
    parts = list(posed(survey))
    same(amap.xyz, np.concatenate([world for *_, world in parts]))
    references = [frame.reference_labels() for _, frame, _, _ in parts]
    assert set(amap.reference) == set(references[0]) and "semantic" in amap.reference
    for name, values in amap.reference.items():
        same(values, np.concatenate([r[name] for r in references]))
    same(amap.source_index, np.concatenate([np.arange(len(c), dtype=np.uint32) for *_, c in parts]))
    split = amap.split(np.arange(len(amap.xyz)))
    assert list(split) == [f.frame_id for f in survey.frames]
    assert [len(v) for v in split.values()] == [len(c) for *_, c in parts]
    assert accumulate(survey).reference == {} and accumulate(survey).intensity is None


def test_viewer_map_is_recentred_float32_beside_exact_world_xy(survey: Survey) -> None:
    origin = (1.5, -2.25, 0.125)
    local, world_xy = accumulate_local(MapSource(1, str(survey.source), "sim", origin, 0, 0))
    worlds = [world for *_, world in posed(survey)]
    same(local, np.concatenate([(w - np.asarray(origin)).astype(np.float32) for w in worlds]))
    same(world_xy, np.concatenate([w[:, :2] for w in worlds]))


def test_a_survey_without_frames_gives_empty_maps(tmp_path: Path) -> None:
    empty = Survey("empty", Path("."), "sim", [])
    same(accumulate(empty).xyz, np.zeros((0, 3)))
    local = accumulate(empty, origin=np.zeros(3))
    same(local.xyz, np.zeros((0, 3), np.float32))
    same(local.world_xy, np.zeros((0, 2)))

    maps = write_frame_maps(tmp_path, "", empty, np.zeros(0, np.int64), [], 0.3, np.zeros(3))
    assert maps["map_points"] == 0
    assert len(laspy.read(tmp_path / "cleaned.laz").points) == 0  # written, empty


def test_a_label_file_of_another_length_names_its_frame() -> None:
    from app.core.errors import InputError
    from app.io.survey import Frame, PointCloud

    frames = [
        Frame(
            i, f"{i:06d}", np.eye(4),
            _load_points=lambda: PointCloud(np.zeros((5, 3))),
            _load_reference=lambda i=i: {"semantic": np.zeros(5 if i == 0 else 4, np.uint32)},
        )
        for i in range(2)
    ]  # fmt: skip
    survey = Survey("s", Path("/s"), "sim", frames, reference_label_kinds=("semantic",))
    with pytest.raises(InputError, match="frame 000001 has 5 points and 4 semantic labels"):
        accumulate(survey, with_reference=True)
