"""PCD reader."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from app.core.errors import InputError
from app.io import pcd as pcd_module
from app.io import point_files
from app.io.pcd import read_pcd
from app.io.registry import open_survey
from app.io.survey import MAP_FRAME_ID
from tests.io.foreign_files import uppercase_pcd_table, write_uppercase_pcd


def _points(n: int = 400, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.column_stack(
        [rng.uniform(-50, 50, n), rng.uniform(-50, 50, n), rng.uniform(-2, 10, n)]
    )


def _write_pcd(
    path: Path,
    data: np.ndarray,
    *,
    kind: str = "binary",
    width: int | None = None,
    height: int = 1,
    header_override: dict[str, str] | None = None,
) -> Path:
    """A hand-made PCD v0.7 file from a little-endian structured array."""
    names, sizes, types, counts = [], [], [], []
    for name in data.dtype.names:
        dt, shape = data.dtype[name].base, data.dtype[name].shape
        names.append("_" if name.startswith("pad") else name)
        sizes.append(str(dt.itemsize))
        types.append({"f": "F", "i": "I", "u": "U"}[dt.kind])
        counts.append(str(shape[0] if shape else 1))
    width = len(data) // height if width is None else width
    header = {
        "VERSION": "0.7",
        "FIELDS": " ".join(names),
        "SIZE": " ".join(sizes),
        "TYPE": " ".join(types),
        "COUNT": " ".join(counts),
        "WIDTH": str(width),
        "HEIGHT": str(height),
        "VIEWPOINT": "0 0 0 1 0 0 0",
        "POINTS": str(len(data)),
        "DATA": kind,
    }
    header.update(header_override or {})
    head = "# .PCD v0.7 - test\n" + "".join(f"{k} {v}\n" for k, v in header.items())
    if kind == "binary":
        body = data.tobytes()
    else:
        flat = [data[n].reshape(len(data), -1).astype(np.float64) for n in data.dtype.names]
        rows = np.hstack(flat)
        body = "".join(" ".join(f"{v:.17g}" for v in row) + "\n" for row in rows).encode()
    path.write_bytes(head.encode() + body)
    return path


@pytest.mark.parametrize("ascii_", [True, False])
def test_open3d_written_pcd_reads_back_exactly(tmp_path: Path, ascii_: bool):
    xyz = _points()
    path = tmp_path / "o3d.pcd"
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
    assert o3d.io.write_point_cloud(str(path), cloud, write_ascii=ascii_)

    survey = open_survey(path, "pcd")
    assert (survey.name, survey.format) == ("o3d", "pcd")
    frame = survey.frames[0]
    assert frame.frame_id == MAP_FRAME_ID and frame.point_count == len(xyz)
    np.testing.assert_array_equal(frame.pose, np.eye(4))
    ours = frame.points().xyz
    assert ours.dtype == np.float64
    np.testing.assert_array_equal(ours, np.asarray(o3d.io.read_point_cloud(str(path)).points))
    if ascii_:  # open3d prints 10 significant digits of the float32 value
        np.testing.assert_allclose(ours, xyz, rtol=0, atol=1e-5)
    else:  # open3d's legacy writer stores float32; we read exactly those
        np.testing.assert_array_equal(ours, xyz.astype(np.float32).astype(np.float64))


@pytest.mark.parametrize("compressed", [False, True])
def test_open3d_tensor_pcd_double_precision_and_intensity(tmp_path: Path, compressed: bool):
    xyz = _points(300) + [500000.0, 5400000.0, 100.0]
    intensity = np.linspace(0, 1, 300, dtype=np.float32)
    cloud = o3d.t.geometry.PointCloud(o3d.core.Tensor(xyz))
    cloud.point["intensity"] = o3d.core.Tensor(intensity.reshape(-1, 1))
    path = tmp_path / "t.pcd"
    assert o3d.t.io.write_point_cloud(str(path), cloud, compressed=compressed)
    expected_kind = b"DATA binary_compressed" if compressed else b"DATA binary\n"
    assert expected_kind in path.read_bytes()[:400]

    points = read_pcd(path).frames[0].points()
    np.testing.assert_array_equal(points.xyz, xyz)
    np.testing.assert_array_equal(points.intensity, intensity)


def test_padding_multi_count_fields_and_labels(tmp_path: Path):
    n = 6
    data = np.zeros(
        n,
        dtype=[
            ("x", "<f8"),
            ("y", "<f8"),
            ("z", "<f8"),
            ("pad0", "u1"),
            ("normal", "<f4", (3,)),
            ("pad1", "<u2"),
            ("label", "<u4"),
            ("timestamp", "<f8"),
        ],
    )
    data["x"], data["y"], data["z"] = np.arange(n), np.arange(n) * 2.0, 0.5
    data["normal"] = [0, 0, 1]
    data["label"] = [1, 1, 2, 2, 3, 40]
    data["timestamp"] = 1.6e9 + np.arange(n) / 10
    for kind in ("binary", "ascii"):
        path = _write_pcd(tmp_path / f"{kind}.pcd", data, kind=kind)
        survey = read_pcd(path)
        assert survey.reference_label_kinds == ("label",)
        cloud = survey.frames[0].points()
        np.testing.assert_array_equal(cloud.xyz[:, 1], np.arange(n) * 2.0)
        np.testing.assert_array_equal(cloud.time, data["timestamp"])
        np.testing.assert_array_equal(cloud.extra["normal"], np.tile([0, 0, 1], (n, 1)))
        assert cloud.extra["label"].dtype == np.uint32
        assert sorted(cloud.extra) == ["label", "normal"]  # padding gone
        np.testing.assert_array_equal(survey.frames[0].reference_labels()["label"], data["label"])


@pytest.mark.parametrize("kind", ["binary", "ascii"])
def test_organized_cloud_drops_nan_returns(tmp_path: Path, kind: str):
    width, height = 4, 3
    data = np.zeros(width * height, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("i", "<f4")])
    data["x"] = np.arange(12)
    data["y"] = 1.0
    data["z"] = 2.0
    data["i"] = np.arange(12) * 10
    missing = [1, 5, 6, 11]
    data["x"][missing] = np.nan
    data["z"][5] = np.nan
    path = _write_pcd(tmp_path / "organized.pcd", data, kind=kind, width=width, height=height)

    survey = read_pcd(path)
    assert survey.frames[0].point_count is None  # unknown until the NaN returns are dropped
    cloud = survey.frames[0].points()
    kept = np.setdiff1d(np.arange(12), missing)
    assert len(cloud) == 8
    np.testing.assert_array_equal(cloud.xyz[:, 0], kept)
    np.testing.assert_array_equal(cloud.extra["grid_index"], kept)
    np.testing.assert_array_equal(cloud.extra["i"], kept * 10)


def test_unorganized_nan_is_an_input_error(tmp_path: Path):
    data = np.zeros(5, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    data["y"][[0, 3]] = np.nan
    path = _write_pcd(tmp_path / "nan.pcd", data)
    with pytest.raises(InputError, match="has 2 points with NaN or infinite coordinates") as info:
        read_pcd(path).frames[0].points()
    assert "nan.pcd" in str(info.value)


def test_truncated_binary_is_an_input_error(tmp_path: Path):
    data = np.zeros(50, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    path = _write_pcd(tmp_path / "cut.pcd", data)
    path.write_bytes(path.read_bytes()[:-7])
    with pytest.raises(InputError, match="truncated") as info:
        read_pcd(path)
    assert "cut.pcd" in str(info.value)
    assert "header promises 50 points (600 bytes), file has 593 bytes" in str(info.value)


def test_truncated_ascii_is_an_input_error(tmp_path: Path):
    data = np.zeros(5, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    path = _write_pcd(tmp_path / "cut.pcd", data, kind="ascii")
    path.write_bytes(b"".join(path.read_bytes().splitlines(keepends=True)[:-2]))
    with pytest.raises(InputError, match="truncated: header promises 5 points, file has 3"):
        read_pcd(path).frames[0].points()


@pytest.mark.parametrize(
    ("override", "problem"),
    [
        ({"SIZE": "4 4"}, "SIZE has 2 values, FIELDS has 3"),
        ({"TYPE": "F F F F"}, "TYPE has 4 values, FIELDS has 3"),
        ({"COUNT": "1 1"}, "COUNT has 2 values, FIELDS has 3"),
        ({"POINTS": "7"}, "POINTS 7 is not WIDTH x HEIGHT"),
        ({"VIEWPOINT": "0 0 0"}, "VIEWPOINT has 3 values, expected 7"),
        ({"WIDTH": "two"}, "WIDTH values must be integers"),
        ({"TYPE": "F F X"}, "unsupported TYPE X"),
        ({"FIELDS": "x y intensity"}, "has no x/y/z fields"),
        ({"DATA": "zipped"}, "DATA must be one of"),
    ],
)
def test_bad_header_is_an_input_error(tmp_path: Path, override: dict[str, str], problem: str):
    data = np.zeros(3, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    path = _write_pcd(tmp_path / "bad.pcd", data, header_override=override)
    with pytest.raises(InputError, match=problem) as info:
        read_pcd(path)
    assert "bad.pcd" in str(info.value)


def test_not_a_pcd(tmp_path: Path):
    path = tmp_path / "junk.pcd"
    path.write_text("hello world\nDATA ascii\n")
    with pytest.raises(InputError, match="not a PCD file"):
        read_pcd(path)
    path.write_text("VERSION 0.7\nFIELDS x y z\n")
    with pytest.raises(InputError, match="no 'DATA' line"):
        read_pcd(path)


def test_points_are_read_only_when_asked(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    data = np.zeros(30, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    path = _write_pcd(tmp_path / "lazy.pcd", data)
    calls: list[Path] = []
    real = pcd_module._load_data

    def spy(p, header):
        calls.append(p)
        return real(p, header)

    monkeypatch.setattr(pcd_module, "_load_data", spy)
    survey = read_pcd(path)
    assert calls == []
    assert len(survey.frames[0].points()) == 30
    assert calls == [path]


# -- foreign and broken headers -------------------------------------------------------------------


@pytest.mark.parametrize("binary", [True, False])
def test_upper_case_field_names_as_pdal_writes_them(tmp_path: Path, binary: bool):
    path = write_uppercase_pcd(tmp_path / "pdal.pcd", binary=binary)
    assert b"FIELDS X Y Z INTENSITY RGB GpsTime Classification" in path.read_bytes()[:200]
    table = uppercase_pcd_table()

    survey = read_pcd(path)
    assert survey.frames[0].point_count == len(table)
    assert survey.reference_label_kinds == ("Classification",)
    cloud = survey.frames[0].points()
    np.testing.assert_array_equal(cloud.xyz, np.column_stack([table[a] for a in "XYZ"]))
    np.testing.assert_array_equal(cloud.intensity, table["INTENSITY"].astype(np.float32))
    np.testing.assert_array_equal(cloud.time, table["GpsTime"])
    np.testing.assert_array_equal(cloud.extra["rgb"], table["RGB"])
    np.testing.assert_array_equal(
        survey.frames[0].reference_labels()["Classification"], table["Classification"]
    )


def test_upper_case_binary_compressed(tmp_path: Path):
    """open3d itself only knows lower-case `x y z`; the reader hands it a copy that says so."""
    xyz = _points(200) + [500000.0, 5400000.0, 100.0]
    intensity = np.linspace(0, 1, 200, dtype=np.float32)
    cloud = o3d.t.geometry.PointCloud(o3d.core.Tensor(xyz))
    cloud.point["intensity"] = o3d.core.Tensor(intensity.reshape(-1, 1))
    path = tmp_path / "upper.pcd"
    assert o3d.t.io.write_point_cloud(str(path), cloud, compressed=True)
    data = path.read_bytes()
    assert b"FIELDS x y z intensity\n" in data[:200]
    path.write_bytes(data.replace(b"FIELDS x y z intensity\n", b"FIELDS X Y Z INTENSITY\n", 1))

    points = read_pcd(path).frames[0].points()
    np.testing.assert_array_equal(points.xyz, xyz)
    np.testing.assert_array_equal(points.intensity, intensity)
    assert path.read_bytes() == data.replace(b"x y z intensity", b"X Y Z INTENSITY", 1)


def test_same_field_in_two_cases_is_an_input_error(tmp_path: Path):
    data = np.zeros(3, dtype=[("x", "<f4"), ("X", "<f4"), ("y", "<f4"), ("z", "<f4")])
    path = _write_pcd(tmp_path / "twice.pcd", data)
    with pytest.raises(InputError, match="field 'x' given twice"):
        read_pcd(path)


def _huge(kind: str, tmp_path: Path) -> Path:
    """A 3-point file whose header says 4,000,000,000 points."""
    data = np.zeros(3, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    override = {"WIDTH": "4000000000", "POINTS": "4000000000"}
    if kind != "binary_compressed":
        return _write_pcd(tmp_path / f"{kind}.pcd", data, kind=kind, header_override=override)
    cloud = o3d.t.geometry.PointCloud(o3d.core.Tensor(np.zeros((3, 3))))
    path = tmp_path / "compressed.pcd"
    assert o3d.t.io.write_point_cloud(str(path), cloud, compressed=True)
    text = path.read_bytes()
    for key in (b"WIDTH", b"POINTS"):
        text = text.replace(key + b" 3\n", key + b" 4000000000\n", 1)
    path.write_bytes(text)
    return path


@pytest.mark.parametrize(
    ("kind", "problem"),
    [
        ("ascii", "truncated: header says 4,000,000,000 points \\(one text line each\\)"),
        ("binary", "truncated: header promises 4000000000 points"),
        ("binary_compressed", "header says 4,000,000,000 points \\(96,000,000,000 bytes\\)"),
    ],
)
def test_more_points_than_the_file_can_hold_fail_when_opened(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, kind: str, problem: str
):
    path = _huge(kind, tmp_path)
    monkeypatch.setattr(pcd_module, "_load_data", None)  # nothing may be read or allocated
    with pytest.raises(InputError, match=problem) as info:
        read_pcd(path)
    assert str(info.value).startswith(f"{path}: ")


def test_binary_compressed_sizes_beyond_the_file(tmp_path: Path):
    cloud = o3d.t.geometry.PointCloud(o3d.core.Tensor(np.zeros((3, 3))))
    path = tmp_path / "sizes.pcd"
    assert o3d.t.io.write_point_cloud(str(path), cloud, compressed=True)
    data = bytearray(path.read_bytes())
    start = data.index(b"DATA binary_compressed\n") + len(b"DATA binary_compressed\n")
    data[start : start + 4] = (10**9).to_bytes(4, "little")  # compressed size
    path.write_bytes(bytes(data))
    with pytest.raises(InputError, match="says 1,000,000,000 compressed bytes for 72"):
        read_pcd(path)


@pytest.mark.parametrize("kind", ["binary", "ascii"])
def test_a_map_read_in_chunks_is_the_whole_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, kind: str
):
    """An unorganized cloud is read a million points at a time (here 150), padding dropped."""
    n = 400
    data = np.zeros(n, dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("pad0", "u1"),
                              ("label", "<u4")])  # fmt: skip
    xyz = _points(n)
    data["x"], data["y"], data["z"], data["label"] = *xyz.T, np.arange(n)
    path = _write_pcd(tmp_path / f"{kind}.pcd", data, kind=kind)
    monkeypatch.setattr(point_files, "TABLE_CHUNK", 150)
    frame = read_pcd(path).frames[0]
    chunks = list(frame.world_chunks())
    assert [start for start, _ in chunks] == [0, 150, 300]
    np.testing.assert_array_equal(np.concatenate([c.xyz for _, c in chunks]), xyz)
    assert all(sorted(c.extra) == ["label"] for _, c in chunks)
    np.testing.assert_array_equal(
        np.concatenate([c.extra["label"] for _, c in chunks]), data["label"]
    )


def test_an_organized_cloud_is_read_whole(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    """Its NaN returns are dropped and the grid index kept, which one piece keeps right."""
    data = np.zeros(400, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    data["x"] = np.arange(400)
    data["x"][::7] = np.nan
    path = _write_pcd(tmp_path / "organized.pcd", data, height=20)
    monkeypatch.setattr(point_files, "TABLE_CHUNK", 150)
    chunks = list(read_pcd(path).frames[0].world_chunks())
    assert len(chunks) == 1 and len(chunks[0][1].xyz) == 400 - 58


def test_labelled_pcd_written_in_pieces_reads_back(tmp_path: Path) -> None:
    """`write_labelled_pcd`: binary PCD with x y z intensity label that PCL's layout and this
    reader agree on; pieces that do not add up to the header's count leave no file."""
    xyz = _points(1_000)
    labels = np.arange(1_000, dtype=np.uint32) % 4
    intensity = np.linspace(0, 65535, 1_000)
    pieces = [
        (xyz[i : i + 300], intensity[i : i + 300], labels[i : i + 300])
        for i in range(0, 1_000, 300)
    ]
    path = pcd_module.write_labelled_pcd(tmp_path / "m.pcd", 1_000, iter(pieces), ["a note"])
    survey = read_pcd(path)
    assert survey.reference_label_kinds == ("label",)
    cloud = survey.frames[0].points()
    np.testing.assert_allclose(cloud.xyz, xyz.astype(np.float32))
    assert cloud.extra["label"].tolist() == labels.tolist()
    np.testing.assert_allclose(cloud.intensity, intensity.astype(np.float32))
    assert b"# a note\n" in path.read_bytes()[:300]
    with pytest.raises(InputError, match="the header says 1001 points, the pieces held 1000"):
        pcd_module.write_labelled_pcd(tmp_path / "short.pcd", 1_001, iter(pieces))
    assert list(tmp_path.glob("short.pcd*")) == []
