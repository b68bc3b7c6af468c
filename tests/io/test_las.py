"""LAS / LAZ reader and writer, and the ASPRS class mapping."""

from __future__ import annotations

import struct
from pathlib import Path

import laspy
import numpy as np
import pytest
from laspy.vlrs.known import GeoKeyDirectoryVlr, GeoKeyEntryStruct

from app.core.errors import InputError
from app.io import las as las_module
from app.io.asprs import (
    GUARDRAIL_ASPRS,
    PHANTOM_LABEL_TO_ASPRS,
    REMOVED_CLUTTER_ASPRS,
    AsprsClass,
    to_asprs,
)
from app.io.las import (
    LasAppender,
    las_crs,
    las_point_count,
    read_las,
    read_las_points,
    write_laz,
)
from app.io.las_layout import check_las_layout
from app.io.point_files import guarded
from app.io.registry import open_survey
from app.io.survey import MAP_FRAME_ID
from tests.cli import assert_one_line_error, mmsclean
from tests.io.foreign_files import (
    write_las_with_garbage_vlr_count,
    write_laz_without_chunk_table,
)

SCALE = 0.001


def _utm_points(n: int, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    xyz = np.column_stack(
        [
            500000.123 + rng.uniform(0, 200, n),
            5400000.456 + rng.uniform(0, 200, n),
            100.0 + rng.uniform(-5, 30, n),
        ]
    )
    return {
        "xyz": xyz,
        "mmsclean_label": rng.integers(0, 4, n).astype(np.uint8),
        "classification": rng.choice([1, 2, 6, 64, 65], n).astype(np.uint8),
        "source_frame": rng.integers(0, 500, n).astype(np.uint32),
        "source_index": rng.integers(0, 2**32 - 1, n, dtype=np.uint64).astype(np.uint32),
        "intensity": rng.integers(0, 65536, n).astype(np.uint16),
        "gps_time": 1.3e9 + np.sort(rng.uniform(0, 600, n)),
    }


@pytest.mark.parametrize("suffix", [".laz", ".las"])
def test_round_trip_keeps_utm_precision_labels_intensity_and_time(tmp_path: Path, suffix: str):
    data = _utm_points(5000)
    path = write_laz(tmp_path / f"map{suffix}", scale=SCALE, **data)
    assert path == tmp_path / f"map{suffix}"
    assert sorted(p.name for p in tmp_path.iterdir() if p.is_file()) == [path.name]

    survey = read_las(path)
    assert (survey.name, survey.format, survey.source) == ("map", "las", path)
    assert survey.is_map and len(survey) == 1
    frame = survey.frames[0]
    assert frame.frame_id == MAP_FRAME_ID and frame.index == 0
    np.testing.assert_array_equal(frame.pose, np.eye(4))
    assert frame.point_count == 5000 and frame.source_path == path

    cloud = frame.points()
    assert cloud.xyz.dtype == np.float64
    assert np.abs(cloud.xyz - data["xyz"]).max() <= SCALE / 2 + 1e-9
    for name in ("mmsclean_label", "classification", "source_frame", "source_index"):
        assert cloud.extra[name].dtype == data[name].dtype, name
        np.testing.assert_array_equal(cloud.extra[name], data[name], err_msg=name)
    assert cloud.intensity is not None and cloud.intensity.dtype == np.float32
    np.testing.assert_array_equal(cloud.intensity, data["intensity"].astype(np.float32))
    assert cloud.time is not None
    np.testing.assert_array_equal(cloud.time, data["gps_time"])
    np.testing.assert_array_equal(cloud.extra["return_number"], 1)

    assert survey.reference_label_kinds == ("classification",)
    np.testing.assert_array_equal(
        frame.reference_labels()["classification"], data["classification"]
    )

    # laspy on its own sees a LAS 1.4 / point format 6 file with the extra dimensions
    with laspy.open(path) as reader:
        assert reader.header.are_points_compressed == (suffix == ".laz")
    raw = laspy.read(path)
    assert raw.header.version == laspy.header.Version(1, 4)
    assert raw.header.point_format.id == 6
    assert set(raw.point_format.extra_dimension_names) == {
        "mmsclean_label",
        "source_frame",
        "source_index",
    }
    np.testing.assert_array_equal(np.asarray(raw.mmsclean_label), data["mmsclean_label"])
    np.testing.assert_array_equal(np.asarray(raw.x), cloud.xyz[:, 0])


def test_defaults_and_registry(tmp_path: Path):
    xyz = _utm_points(100)["xyz"]
    path = write_laz(tmp_path / "sub" / "plain.laz", xyz)
    survey = open_survey(path, "las")
    cloud = survey.frames[0].points()
    np.testing.assert_array_equal(cloud.extra["classification"], 1)  # ASPRS unclassified
    for name in ("mmsclean_label", "source_frame", "source_index"):
        np.testing.assert_array_equal(cloud.extra[name], 0)
    np.testing.assert_array_equal(cloud.time, 0.0)
    assert np.abs(cloud.xyz - xyz).max() <= SCALE / 2 + 1e-9
    # offset is the minimum rounded down to metres, so the integers stay small
    np.testing.assert_array_equal(laspy.read(path).header.offsets, np.floor(xyz.min(axis=0)))


def test_all_zero_classification_is_no_reference(tmp_path: Path):
    xyz = _utm_points(50)["xyz"]
    path = write_laz(tmp_path / "raw.laz", xyz, classification=np.zeros(50, np.uint8))
    survey = read_las(path)
    assert survey.reference_label_kinds == ()
    assert survey.frames[0].reference_labels() == {}


def test_reads_foreign_las_without_extra_dims(tmp_path: Path):
    las = laspy.create(point_format=3, file_version="1.2")
    las.header.scales = [0.01, 0.01, 0.01]
    las.x = np.array([1.0, 2.5, 3.25])
    las.y = np.array([4.0, 5.0, 6.0])
    las.z = np.array([7.0, 8.0, 9.0])
    las.intensity = np.array([10, 20, 30], dtype=np.uint16)
    las.gps_time = np.array([0.5, 1.5, 2.5])
    path = tmp_path / "foreign.las"
    las.write(path)

    survey = read_las(path)
    assert survey.reference_label_kinds == ()
    cloud = survey.frames[0].points()
    np.testing.assert_array_equal(cloud.xyz, np.column_stack([las.x, las.y, las.z]))
    np.testing.assert_array_equal(cloud.intensity, [10, 20, 30])
    np.testing.assert_array_equal(cloud.time, [0.5, 1.5, 2.5])
    assert "mmsclean_label" not in cloud.extra
    assert cloud.extra["classification"].dtype == np.uint8


def test_empty_las_is_an_input_error(tmp_path: Path):
    path = write_laz(tmp_path / "empty.las", np.zeros((0, 3)))
    with pytest.raises(InputError, match="contains no points") as info:
        read_las(path)
    assert "empty.las" in str(info.value)


def test_text_file_named_las_is_an_input_error(tmp_path: Path):
    path = tmp_path / "notes.las"
    path.write_text("this is not a point cloud\n")
    with pytest.raises(InputError, match="not a LAS/LAZ file") as info:
        read_las(path)
    assert "notes.las" in str(info.value)
    assert info.value.path == path


def test_missing_file_is_an_input_error(tmp_path: Path):
    with pytest.raises(InputError, match="does not exist"):
        read_las(tmp_path / "nope.laz")


def test_truncated_las_is_an_input_error(tmp_path: Path):
    path = write_laz(tmp_path / "cut.las", _utm_points(1000)["xyz"])
    path.write_bytes(path.read_bytes()[:-500])
    with pytest.raises(InputError, match="truncated") as info:
        read_las(path)
    assert "cut.las" in str(info.value)


def test_truncated_laz_is_an_input_error(tmp_path: Path):
    path = write_laz(tmp_path / "cut.laz", _utm_points(5000)["xyz"])
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    with pytest.raises(InputError, match="cut.laz"):
        read_las(path).frames[0].points()


def test_a_map_read_in_chunks_is_the_whole_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    points = _utm_points(5000)
    path = write_laz(tmp_path / "map.laz", points["xyz"])
    monkeypatch.setattr(las_module, "_CHUNK", 1234)
    frame = read_las(path).frames[0]
    chunks = list(frame.world_chunks())
    assert [start for start, _ in chunks] == [0, 1234, 2468, 3702, 4936]
    np.testing.assert_array_equal(
        np.concatenate([c.xyz for _, c in chunks]), frame.world_points().xyz
    )


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_a_truncated_map_read_in_chunks_is_an_input_error(tmp_path: Path, suffix: str) -> None:
    path = write_laz(tmp_path / f"cut{suffix}", _utm_points(5000)["xyz"])
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    with pytest.raises(InputError, match=f"cut{suffix}"):
        list(read_las(path).frames[0].world_chunks())


def test_points_are_read_only_when_asked(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    path = write_laz(tmp_path / "lazy.laz", _utm_points(200)["xyz"])
    calls: list[object] = []
    real_read = laspy.read

    def spy(*args, **kwargs):
        calls.append(args)
        return real_read(*args, **kwargs)

    monkeypatch.setattr(las_module.laspy, "read", spy)
    survey = read_las(path)
    assert calls == []
    assert len(survey.frames[0].points()) == 200
    assert len(calls) == 1


def test_file_removed_after_opening_gives_input_error(tmp_path: Path):
    path = write_laz(tmp_path / "gone.laz", _utm_points(10)["xyz"])
    survey = read_las(path)
    path.unlink()
    with pytest.raises(InputError, match="gone.laz"):
        survey.frames[0].points()


def test_write_nan_fails_and_leaves_nothing(tmp_path: Path):
    xyz = _utm_points(100)["xyz"]
    xyz[[3, 7], 2] = np.nan
    xyz[9, 0] = np.inf
    out = tmp_path / "bad.laz"
    with pytest.raises(InputError, match="3 points with NaN or infinite") as info:
        write_laz(out, xyz)
    assert "bad.laz" in str(info.value)
    assert list(tmp_path.iterdir()) == []


def test_write_mismatched_lengths_fails(tmp_path: Path):
    xyz = _utm_points(100)["xyz"]
    with pytest.raises(InputError, match=r"mmsclean_label has shape \(99,\), expected \(100,\)"):
        write_laz(tmp_path / "x.laz", xyz, mmsclean_label=np.zeros(99, np.uint8))
    with pytest.raises(InputError, match="source_frame values -1..3 do not fit uint32"):
        write_laz(tmp_path / "x.laz", xyz, source_frame=np.r_[-1, np.full(99, 3)])
    with pytest.raises(InputError, match="xyz must have shape"):
        write_laz(tmp_path / "x.laz", xyz[:, :2])
    with pytest.raises(InputError, match=r"\.las or \.laz"):
        write_laz(tmp_path / "x.ply", xyz)
    with pytest.raises(InputError, match="span too far"):
        write_laz(tmp_path / "x.laz", xyz, offset=0.0)  # 5.4e9 mm does not fit int32
    assert list(tmp_path.iterdir()) == []


def test_failure_while_writing_removes_partial_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
):
    def broken_write(self, destination, do_compress=None, laz_backend=None):
        destination.write(b"LASF half a file")
        raise OSError("disk full")

    monkeypatch.setattr(laspy.LasData, "write", broken_write)
    out = tmp_path / "map.laz"
    with pytest.raises(OSError, match="disk full"):
        write_laz(out, _utm_points(10)["xyz"])
    assert list(tmp_path.iterdir()) == []


def test_overwrite_replaces_complete_file(tmp_path: Path):
    out = tmp_path / "map.laz"
    write_laz(out, _utm_points(10, seed=1)["xyz"])
    write_laz(out, _utm_points(20, seed=2)["xyz"])
    assert read_las(out).frames[0].point_count == 20
    assert [p.name for p in tmp_path.iterdir()] == ["map.laz"]


def test_asprs_mappings():
    assert AsprsClass.GROUND == 2 and AsprsClass.LOW_POINT_NOISE == 7
    assert AsprsClass.HIGH_NOISE == 18 and AsprsClass.IGNORED_GROUND == 20
    assert GUARDRAIL_ASPRS == 64 and REMOVED_CLUTTER_ASPRS == 65
    assert PHANTOM_LABEL_TO_ASPRS == {0: 2, 1: 1, 2: 1, 3: 65}
    labels = np.array([0, 1, 2, 3, 3, 0, 9], dtype=np.uint8)
    codes = to_asprs(labels, PHANTOM_LABEL_TO_ASPRS)
    assert codes.dtype == np.uint8
    np.testing.assert_array_equal(codes, [2, 1, 1, 65, 65, 2, 1])
    with pytest.raises(ValueError, match="0..255"):
        to_asprs(np.array([300]), PHANTOM_LABEL_TO_ASPRS)


def test_phantom_classification_survives_laz(tmp_path: Path):
    labels = np.array([0, 1, 2, 3], dtype=np.uint8)
    xyz = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]]) + [600000.0, 5e6, 50.0]
    path = write_laz(
        tmp_path / "phantom.laz",
        xyz,
        mmsclean_label=labels,
        classification=to_asprs(labels, PHANTOM_LABEL_TO_ASPRS),
    )
    cloud = read_las(path).frames[0].points()
    np.testing.assert_array_equal(cloud.extra["classification"], [2, 1, 1, 65])
    np.testing.assert_array_equal(cloud.extra["mmsclean_label"], labels)


# -- foreign and broken files: every header count is checked before laspy / lazrs read ----------

_READS = {
    "open": lambda path: read_las(path),
    "points": lambda path: read_las(path).frames[0].points(),
    "scan": lambda path: read_las_points(path),
    "count": lambda path: las_point_count(path),
}


def _forbid_laspy(monkeypatch: pytest.MonkeyPatch) -> None:
    """Fail the test if laspy opens or reads the file: the error must come before."""

    def forbidden(*args, **kwargs):
        raise AssertionError("laspy read a file whose header does not fit it")

    monkeypatch.setattr(las_module.laspy, "open", forbidden)
    monkeypatch.setattr(las_module.laspy, "read", forbidden)


@pytest.mark.parametrize("read", list(_READS))
def test_garbage_vlr_count_fails_before_laspy_reads(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, read: str
):
    path = write_las_with_garbage_vlr_count(tmp_path / "x.las")
    before_points = struct.unpack_from("<I", path.read_bytes(), 96)[0] - 227  # no room for VLRs
    _forbid_laspy(monkeypatch)
    with pytest.raises(InputError) as info:
        _READS[read](path)
    assert str(info.value) == (
        f"{path}: header says 4,294,967,295 variable-length records but the file has only "
        f"{before_points:,} bytes after the header (before the point data)"
    )


def _patched(path: Path, *fields: tuple[int, str, int]) -> Path:
    """`path` with header fields (byte offset, struct format, value) overwritten."""
    data = bytearray(path.read_bytes())
    for offset, fmt, value in fields:
        struct.pack_into(fmt, data, offset, value)
    path.write_bytes(bytes(data))
    return path


@pytest.mark.parametrize(
    ("fields", "problem"),
    [
        ([(96, "<I", 0xFFFFFF00)], "header says the point data starts at byte 4,294,967,040"),
        ([(94, "<H", 0xFFFF)], "header size 65,535 bytes is larger than the file"),
        ([(104, "<B", 42)], "point data format 42 is not one of LAS 0-10"),
        ([(24, "<B", 120)], "not a LAS/LAZ file: version 120.4 is not LAS 1.0-1.5"),
        ([(105, "<H", 12)], "point record length 12 bytes is shorter than point format 6 needs"),
        (
            [(235, "<Q", 2**40), (243, "<I", 0xFFFFFFFF)],
            "4,294,967,295 extended variable-length records from byte 1,099,511,627,776",
        ),
        ([(247, "<Q", 10**15)], "truncated: header says 1,000,000,000,000,000 points of 39 bytes"),
    ],
)
def test_header_fields_beyond_the_file_fail_before_laspy_reads(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, fields: list, problem: str
):
    path = _patched(write_laz(tmp_path / "bad.las", _utm_points(30)["xyz"]), *fields)
    _forbid_laspy(monkeypatch)
    with pytest.raises(InputError, match=problem) as info:
        read_las(path)
    assert str(info.value).startswith(f"{path}: ")


@pytest.mark.parametrize("read", list(_READS))
def test_old_laszip_laz_without_chunk_table_is_one_input_error(tmp_path: Path, read: str):
    """lazrs panics (pyo3_runtime.PanicException, a BaseException) on its first point."""
    path = write_laz_without_chunk_table(tmp_path / "old.laz")
    with pytest.raises(InputError, match="variable-size chunks and no chunk table") as info:
        _READS[read](path)
    assert str(info.value).startswith(f"{path}: LAZ with")


def test_lazrs_panic_past_the_header_checks_is_still_one_input_error(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
):
    path = write_laz_without_chunk_table(tmp_path / "old.laz")
    monkeypatch.setattr(las_module, "check_las_layout", lambda path: None)
    with pytest.raises(InputError, match="Variable-size chunks, but no chunk table") as info:
        read_las(path).frames[0].points()
    assert str(info.value).startswith(f"{path}: cannot read ")
    sequential = laspy.LazBackend.Lazrs
    with pytest.raises(InputError, match="cannot read points: Variable-size chunks"):
        guarded(path, "points", lambda: laspy.read(path, laz_backend=sequential))


def _chunk_table_start(path: Path) -> int:
    data = path.read_bytes()
    return struct.unpack_from("<q", data, struct.unpack_from("<I", data, 96)[0])[0]


@pytest.mark.parametrize(
    ("point_format", "version", "compress"),
    [
        (f, v, c)
        for f, v in [(0, "1.2"), (3, "1.2"), (5, "1.3"), (6, "1.4"), (10, "1.4")]
        for c in (False, True)
    ],
)
def test_valid_files_pass_the_header_checks(
    tmp_path: Path, point_format: int, version: str, compress: bool
):
    """Formats, versions, EVLRs and several LAZ chunks as laspy writes them all still read."""
    n = 120_001  # three LAZ chunks of 50,000
    las = laspy.LasData(laspy.LasHeader(point_format=point_format, version=version))
    rng = np.random.default_rng(point_format)
    las.x, las.y, las.z = rng.uniform(0, 100, n), rng.uniform(0, 100, n), np.zeros(n)
    if version == "1.4":
        las.evlrs = laspy.vlrs.vlrlist.VLRList([laspy.VLR("mmsclean", 1, "test", b"evlr" * 8)])
    path = tmp_path / ("f.laz" if compress else "f.las")
    las.write(path, do_compress=compress)
    cloud = read_las(path).frames[0].points()
    np.testing.assert_allclose(cloud.xyz[:, 0], las.x)


def test_old_laszip_point_wise_laz_with_a_chunk_size_reads(tmp_path: Path):
    """Point-wise compression itself is fine when the chunk size is not "variable"."""
    path = write_laz_without_chunk_table(tmp_path / "old.laz")
    data = bytearray(path.read_bytes())
    laszip = data.index(b"laszip encoded") - 2 + 54
    struct.pack_into("<I", data, laszip + 12, 50_000)
    path.write_bytes(bytes(data))
    cloud = read_las(path).frames[0].points()
    rng = np.random.default_rng(7)
    np.testing.assert_allclose(cloud.xyz[:, 0], rng.uniform(0, 50, 300), atol=0.005)


@pytest.mark.parametrize(
    ("write", "problem"),
    [
        (write_las_with_garbage_vlr_count, "4,294,967,295 variable-length records"),
        (write_laz_without_chunk_table, "variable-size chunks and no chunk table"),
    ],
)
def test_info_on_a_broken_file_says_one_line_fast(tmp_path: Path, write, problem: str):
    path = write(tmp_path / ("x.las" if "vlr" in write.__name__ else "x.laz"))
    result = mmsclean("info", str(path), "--format", "las", timeout=30)  # a hang fails here
    assert_one_line_error(result, str(path), problem)


def test_info_on_a_laz_with_a_garbage_chunk_count_says_one_line(tmp_path: Path):
    """lazrs would try to allocate 64 GiB for the table and abort the process."""
    path = write_laz(tmp_path / "table.laz", _utm_points(3000)["xyz"])
    _patched(path, (_chunk_table_start(path) + 4, "<I", 0xFFFFFFFF))
    result = mmsclean("info", str(path), "--format", "las", "--check", timeout=30)
    assert_one_line_error(result, str(path), "claims 4,294,967,295 chunks")


def test_parts_are_appended_into_one_file_and_a_failed_one_leaves_nothing(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    parts = []
    for k in range(3):
        xyz = rng.uniform(0, 50, (1000 + k, 3)) + [500_000.0, 5_000_000.0, 0.0]
        parts.append((write_laz(tmp_path / f"p{k}.laz", xyz, offset=[500_000, 5_000_000, 0],
                                source_index=np.arange(len(xyz))), xyz))  # fmt: skip
    appender = LasAppender(tmp_path / "all.laz")
    for path, _ in parts:
        appender.append(path)
    assert appender.close() == 3003
    merged = laspy.read(tmp_path / "all.laz")
    np.testing.assert_allclose(merged.xyz, np.concatenate([x for _, x in parts]), atol=6e-4)
    assert np.asarray(merged["source_index"])[1000] == 0  # the second part starts again
    other = write_laz(tmp_path / "other.laz", parts[0][1], offset=[499_000, 5_000_000, 0])
    failing = LasAppender(tmp_path / "bad.laz")
    failing.append(parts[0][0])
    with pytest.raises(ValueError, match="offset"):
        failing.append(other)
    failing.abort()
    assert not list(tmp_path.glob("bad.laz*"))
    assert LasAppender(tmp_path / "none.laz").close() == 0 and not (tmp_path / "none.laz").exists()


def test_laz_parts_are_joined_chunk_by_chunk_without_recompressing(tmp_path: Path) -> None:
    """Parts of several LASzip chunks each (50,000 points a chunk): the joined file holds their
    compressed bytes as they were, one table of variable-size chunks, the header recounted; every
    point reads back, whatever reader walks the chunks."""
    import lazrs

    from app.io.laz_chunks import LazPart

    rng = np.random.default_rng(1)
    sizes = (120_000, 7, 50_000)
    parts, xyz_all = [], []
    for k, n in enumerate(sizes):
        xyz = rng.uniform(0, 80, (n, 3)) + [500_000.0 + 100 * k, 5_000_000.0, 10.0 * k]
        path = tmp_path / f"p{k}.laz"
        offset = [500_000, 5_000_000, 0]
        kept = {"source_index": np.arange(n), "classification": np.full(n, 2 + k)}
        parts.append(write_laz(path, xyz, offset=offset, **kept))
        xyz_all.append(xyz)
    read = [LazPart.read(p) for p in parts]
    assert [len(p.table) for p in read] == [3, 1, 1]
    appender = LasAppender(tmp_path / "all.laz")
    for path in parts:
        appender.append(path)
    assert appender.close() == sum(sizes)
    joined = LazPart.read(tmp_path / "all.laz")
    assert joined.table == [chunk for p in read for chunk in p.table]  # copied, not re-encoded
    with (tmp_path / "all.laz").open("rb") as f, parts[0].open("rb") as first:
        first.seek(read[0].chunks_start)
        f.seek(joined.chunks_start)
        assert f.read(4096) == first.read(4096)
    whole = np.concatenate(xyz_all)
    for parallel in (False, True):
        las = laspy.read(tmp_path / "all.laz", laz_backend=laspy.LazBackend.LazrsParallel
                         if parallel else laspy.LazBackend.Lazrs)  # fmt: skip
        np.testing.assert_allclose(las.xyz, whole, atol=6e-4)
        assert np.asarray(las["source_index"])[120_000:120_007].tolist() == list(range(7))
        assert np.bincount(np.asarray(las.classification)).tolist()[2:] == list(sizes)
    header = las.header
    assert header.point_count == sum(sizes) and header.number_of_points_by_return[0] == sum(sizes)
    np.testing.assert_allclose(header.mins, whole.min(0), atol=6e-4)
    np.testing.assert_allclose(header.maxs, whole.max(0), atol=6e-4)
    assert lazrs.LazVlr(joined.record).uses_variable_size_chunks()
    for backend in (laspy.LazBackend.Lazrs, laspy.LazBackend.LazrsParallel):
        with laspy.open(tmp_path / "all.laz", laz_backend=backend) as reader:  # across chunks
            chunks = list(reader.chunk_iterator(30_001))
        walked = np.concatenate([np.column_stack([c.x, c.y, c.z]) for c in chunks])
        np.testing.assert_allclose(walked, whole, atol=6e-4)
    check_las_layout(tmp_path / "all.laz")  # what an import of the joined file checks


def test_appender_writes_a_wkt_crs_and_las_crs_reads_it(tmp_path: Path) -> None:
    """A joined LAZ (chunks copied) and a joined LAS (points copied) both get the WKT VLR and
    the WKT bit; a header without one says so."""
    wkt = 'GEOGCS["WGS 84",DATUM["WGS_1984",SPHEROID["WGS 84",6378137,298.257223563]]]'
    rng = np.random.default_rng(1)
    parts = [
        write_laz(tmp_path / f"p{i}.laz", rng.uniform(0, 9, (n, 3)), offset=np.zeros(3))
        for i, n in enumerate((2_000, 30))
    ]
    assert las_crs(parts[0]) == (None, "the header of p0.laz records no CRS")
    for name in ("joined.laz", "joined.las"):
        appender = LasAppender(tmp_path / name, wkt)
        for part in parts:
            appender.append(part)
        assert appender.close() == 2_030
        las = laspy.read(tmp_path / name)
        assert las.header.global_encoding.wkt and len(las.points) == 2_030
        assert np.array_equal(las.X, np.r_[laspy.read(parts[0]).X, laspy.read(parts[1]).X])
        assert las_crs(tmp_path / name) == (wkt, f"WKT from the header of {name}")


def _geotiff_keys(*keys: tuple[int, int, int]) -> GeoKeyDirectoryVlr:
    """A GeoKeyDirectory VLR holding (id, tiff_tag_location, value) keys."""
    vlr = GeoKeyDirectoryVlr()
    vlr.geo_keys = [
        GeoKeyEntryStruct(id=k, tiff_tag_location=loc, count=1, value_offset=v)
        for k, loc, v in [(1024, 0, 1), *keys]  # GTModelTypeGeoKey: projected
    ]
    vlr.geo_keys_header.number_of_keys = len(vlr.geo_keys)
    return vlr


def test_geotiff_keys_become_the_wkt_the_exports_carry(tmp_path: Path) -> None:
    """A LAS 1.2 file (as older tools write) recording ETRS89 / UTM 32N with DHHN2016 heights as
    GeoTIFF keys: its CRS is that compound CRS as WKT 1, which a joined map then carries; a
    user-defined CRS, an unknown code and a key held elsewhere give none, each saying why."""
    rng = np.random.default_rng(2)
    source = write_laz(tmp_path / "keys.laz", rng.uniform(0, 9, (50, 3)), offset=np.zeros(3))

    def with_keys(name: str, vlr: GeoKeyDirectoryVlr) -> Path:
        las = laspy.read(source)
        las.header.vlrs.append(vlr)
        las.write(tmp_path / name)
        return tmp_path / name

    utm = with_keys("utm.laz", _geotiff_keys((3072, 0, 25832), (4096, 0, 7837)))
    wkt, line = las_crs(utm)
    assert line == "EPSG:25832 + EPSG:7837 from the GeoTIFF keys of utm.laz, as WKT"
    assert wkt.startswith("COMPD_CS[") and "ETRS89 / UTM zone 32N" in wkt and "DHHN2016" in wkt
    appender = LasAppender(tmp_path / "joined.laz", wkt)
    appender.append(utm)
    appender.close()
    assert las_crs(tmp_path / "joined.laz") == (wkt, "WKT from the header of joined.laz")

    geographic = with_keys("wgs.laz", _geotiff_keys((2048, 0, 4326)))
    wkt, line = las_crs(geographic)
    assert wkt.startswith('GEOGCS["WGS 84"') and "EPSG:4326 from the GeoTIFF keys" in line
    cases = {
        "own.laz": (_geotiff_keys((3072, 0, 32767)), "define their own CRS (code 32767)"),
        "unknown.laz": (_geotiff_keys((3072, 0, 30000)), "EPSG:30000, which PROJ does not know"),
        "elsewhere.laz": (_geotiff_keys((3072, 34736, 0)), "name no EPSG CRS"),
    }
    for name, (vlr, words) in cases.items():
        wkt, line = las_crs(with_keys(name, vlr))
        assert wkt is None and words in line, line
