"""PLY reader and writer."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from app.core.errors import InputError
from app.io import ply as ply_module
from app.io import point_files
from app.io.ply import read_ply, write_ply
from app.io.registry import open_survey
from app.io.survey import MAP_FRAME_ID


def _points(n: int = 500, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.column_stack(
        [
            500000.123 + rng.uniform(0, 100, n),
            5400000.456 + rng.uniform(0, 100, n),
            rng.uniform(90, 120, n),
        ]
    )


def _header(fmt: str, n: int, props: list[str], extra: str = "") -> bytes:
    lines = ["ply", f"format {fmt} 1.0", f"element vertex {n}"]
    lines += [f"property {p}" for p in props]
    return ("\n".join(lines) + "\n" + extra + "end_header\n").encode()


@pytest.mark.parametrize("binary", [True, False])
def test_own_writer_round_trip(tmp_path: Path, binary: bool):
    xyz = _points()
    n = len(xyz)
    rng = np.random.default_rng(1)
    fields = {
        "intensity": rng.uniform(0, 1, n).astype(np.float32),
        "gps_time": 1.3e9 + rng.uniform(0, 100, n),
        "label": rng.integers(0, 4, n).astype(np.uint8),
        "source_frame": rng.integers(0, 2**32 - 1, n, dtype=np.uint64).astype(np.uint32),
        "offset": rng.integers(-100, 100, n).astype(np.int16),
    }
    path = write_ply(tmp_path / "map.ply", xyz, fields=fields, binary=binary)
    assert [p.name for p in tmp_path.iterdir()] == ["map.ply"]

    survey = read_ply(path)
    assert (survey.name, survey.format, survey.source) == ("map", "ply", path)
    frame = survey.frames[0]
    assert frame.frame_id == MAP_FRAME_ID and frame.point_count == n
    np.testing.assert_array_equal(frame.pose, np.eye(4))
    assert survey.reference_label_kinds == ("label",)

    cloud = frame.points()
    np.testing.assert_array_equal(cloud.xyz, xyz)
    np.testing.assert_array_equal(cloud.intensity, fields["intensity"])
    np.testing.assert_array_equal(cloud.time, fields["gps_time"])
    for name in ("label", "source_frame", "offset"):
        assert cloud.extra[name].dtype == fields[name].dtype
        np.testing.assert_array_equal(cloud.extra[name], fields[name])
    np.testing.assert_array_equal(frame.reference_labels()["label"], fields["label"])


@pytest.mark.parametrize("ascii_", [True, False])
def test_open3d_written_files_read_like_open3d(tmp_path: Path, ascii_: bool):
    xyz = _points(300)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
    path = tmp_path / "o3d.ply"
    assert o3d.io.write_point_cloud(str(path), cloud, write_ascii=ascii_)

    ours = open_survey(path, "ply").frames[0].points().xyz
    theirs = np.asarray(o3d.io.read_point_cloud(str(path)).points)
    np.testing.assert_array_equal(ours, theirs)
    if not ascii_:  # binary keeps every bit (open3d writes doubles)
        np.testing.assert_array_equal(ours, xyz)


def test_open3d_tensor_attributes(tmp_path: Path):
    xyz = _points(50)
    cloud = o3d.t.geometry.PointCloud(o3d.core.Tensor(xyz))
    cloud.point["intensity"] = o3d.core.Tensor(np.arange(50, dtype=np.float32).reshape(-1, 1))
    path = tmp_path / "t.ply"
    o3d.t.io.write_point_cloud(str(path), cloud)
    points = read_ply(path).frames[0].points()
    np.testing.assert_array_equal(points.xyz, xyz)
    np.testing.assert_array_equal(points.intensity, np.arange(50, dtype=np.float32))


def test_mesh_faces_after_vertices_are_ignored(tmp_path: Path):
    xyz = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    vertices = xyz.astype("<f4").tobytes()
    faces = b"".join(
        np.array([3], "u1").tobytes() + np.array(f, "<i4").tobytes() for f in ([0, 1, 2], [0, 2, 3])
    )
    head = _header(
        "binary_little_endian",
        4,
        ["float x", "float y", "float z"],
        extra="element face 2\nproperty list uchar int vertex_indices\n",
    )
    path = tmp_path / "mesh.ply"
    path.write_bytes(head + vertices + faces)
    np.testing.assert_array_equal(read_ply(path).frames[0].points().xyz, xyz)


def test_element_before_vertices_is_skipped(tmp_path: Path):
    # binary: a fixed-size element before the vertices is skipped by its size
    head = (
        b"ply\nformat binary_big_endian 1.0\ncomment camera first\n"
        b"element camera 2\nproperty float px\nproperty uchar flag\n"
        b"element vertex 3\nproperty double x\nproperty double y\nproperty double z\n"
        b"property ushort intensity\nend_header\n"
    )
    camera = np.zeros(2, dtype=[("px", ">f4"), ("flag", "u1")]).tobytes()
    vertex = np.zeros(3, dtype=[("x", ">f8"), ("y", ">f8"), ("z", ">f8"), ("i", ">u2")])
    vertex["x"], vertex["y"], vertex["z"], vertex["i"] = [1.5, 2, 3], [4, 5, 6], [7, 8, 9], 300
    path = tmp_path / "big.ply"
    path.write_bytes(head + camera + vertex.tobytes())
    cloud = read_ply(path).frames[0].points()
    np.testing.assert_array_equal(cloud.xyz, [[1.5, 4, 7], [2, 5, 8], [3, 6, 9]])
    np.testing.assert_array_equal(cloud.intensity, [300, 300, 300])

    # ascii: any element before the vertices is one line per item, lists included
    text = (
        "ply\nformat ascii 1.0\nelement face 1\nproperty list uchar int vertex_indices\n"
        "element vertex 2\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
        "3 0 1 2\n1 2 3\n4 5 6\n"
    )
    path = tmp_path / "ascii.ply"
    path.write_text(text)
    np.testing.assert_array_equal(read_ply(path).frames[0].points().xyz, [[1, 2, 3], [4, 5, 6]])

    # binary with a list element before the vertices cannot be skipped
    head = _header("binary_little_endian", 1, ["float x", "float y", "float z"])
    head = head.replace(
        b"element vertex", b"element face 1\nproperty list uchar int vertex_indices\nelement vertex"
    )
    path = tmp_path / "listfirst.ply"
    path.write_bytes(head + b"\x00" * 64)
    with pytest.raises(InputError, match="before the vertex element has list properties"):
        read_ply(path)


def test_truncated_binary_is_an_input_error(tmp_path: Path):
    path = write_ply(tmp_path / "cut.ply", _points(100))
    path.write_bytes(path.read_bytes()[:-10])
    with pytest.raises(InputError, match="truncated") as info:
        read_ply(path)
    message = str(info.value)
    assert "cut.ply" in message
    assert "header promises 100 vertices (2400 bytes), file has 2390 bytes" in message


def test_truncated_ascii_is_an_input_error(tmp_path: Path):
    path = write_ply(tmp_path / "cut.ply", _points(10), binary=False)
    lines = path.read_text().splitlines(keepends=True)
    path.write_text("".join(lines[:-3]))
    survey = read_ply(path)
    with pytest.raises(InputError, match="truncated: header promises 10 vertices, file has 7"):
        survey.frames[0].points()


def test_nan_coordinates_are_an_input_error(tmp_path: Path):
    head = _header("binary_little_endian", 3, ["float x", "float y", "float z"])
    body = np.array([[0, 0, 0], [np.nan, 1, 1], [2, np.inf, 2]], dtype="<f4").tobytes()
    path = tmp_path / "nan.ply"
    path.write_bytes(head + body)
    survey = read_ply(path)
    with pytest.raises(InputError, match="has 2 points with NaN or infinite coordinates") as info:
        survey.frames[0].points()
    assert "nan.ply" in str(info.value)


@pytest.mark.parametrize(
    ("props", "problem"),
    [
        (["float x", "float y", "float intensity"], "has no x/y/z vertex properties"),
        (["float x", "float y", "float z", "list uchar int idx"], "list properties"),
        (["float x", "float y", "float z", "complex w"], "unknown property type"),
        (["float x", "float y", "float x"], "duplicate property"),
    ],
)
def test_bad_vertex_properties(tmp_path: Path, props: list[str], problem: str):
    path = tmp_path / "bad.ply"
    path.write_bytes(_header("binary_little_endian", 1, props) + b"\x00" * 64)
    with pytest.raises(InputError, match=problem) as info:
        read_ply(path)
    assert "bad.ply" in str(info.value)


def test_not_a_ply_and_empty(tmp_path: Path):
    path = tmp_path / "junk.ply"
    path.write_text("hello\nend_header\n")
    with pytest.raises(InputError, match="not a PLY file"):
        read_ply(path)
    path.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 0\n")  # no end_header
    with pytest.raises(InputError, match="no 'end_header' line"):
        read_ply(path)
    path.write_bytes(_header("ascii", 0, ["float x", "float y", "float z"]))
    with pytest.raises(InputError, match="contains no points"):
        read_ply(path)


def test_write_rejects_bad_input_and_leaves_nothing(tmp_path: Path):
    xyz = _points(10)
    bad = xyz.copy()
    bad[4, 1] = np.nan
    with pytest.raises(InputError, match="1 points with NaN") as info:
        write_ply(tmp_path / "out.ply", bad)
    assert "out.ply" in str(info.value)
    with pytest.raises(InputError, match=r"has shape \(9,\)"):
        write_ply(tmp_path / "out.ply", xyz, fields={"label": np.zeros(9, np.uint8)})
    with pytest.raises(InputError, match="PLY cannot store"):
        write_ply(tmp_path / "out.ply", xyz, fields={"big": np.zeros(10, np.int64)})
    with pytest.raises(InputError, match="given twice"):
        write_ply(tmp_path / "out.ply", xyz, fields={"x": np.zeros(10, np.float32)})
    assert list(tmp_path.iterdir()) == []


def test_vertices_are_read_only_when_asked(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    path = write_ply(tmp_path / "lazy.ply", _points(20))
    calls: list[Path] = []
    real = ply_module._load_vertices

    def spy(p, header):
        calls.append(p)
        return real(p, header)

    monkeypatch.setattr(ply_module, "_load_vertices", spy)
    survey = read_ply(path)
    assert calls == []
    assert len(survey.frames[0].points()) == 20
    assert calls == [path]


# -- foreign and broken headers -------------------------------------------------------------------


@pytest.mark.parametrize("fmt", ["binary_little_endian", "ascii"])
def test_upper_case_coordinates(tmp_path: Path, fmt: str):
    xyz = _points(20)
    props = ["double X", "double Y", "double Z", "float INTENSITY", "uchar Classification"]
    table = np.zeros(
        20, dtype=[("X", "<f8"), ("Y", "<f8"), ("Z", "<f8"), ("I", "<f4"), ("C", "u1")]
    )
    table["X"], table["Y"], table["Z"] = xyz.T
    table["I"] = np.arange(20) / 4
    table["C"] = np.arange(20) % 3
    if fmt == "ascii":
        body = "".join(f"{r[0]!r} {r[1]!r} {r[2]!r} {r[3]!r} {r[4]}\n" for r in table.tolist())
        body = body.encode()
    else:
        body = table.tobytes()
    path = tmp_path / "upper.ply"
    path.write_bytes(_header(fmt, 20, props) + body)

    survey = read_ply(path)
    assert survey.reference_label_kinds == ("Classification",)
    cloud = survey.frames[0].points()
    np.testing.assert_array_equal(cloud.xyz, xyz)
    np.testing.assert_array_equal(cloud.intensity, table["I"])
    np.testing.assert_array_equal(survey.frames[0].reference_labels()["Classification"], table["C"])


def test_same_coordinate_in_two_cases_is_an_input_error(tmp_path: Path):
    path = tmp_path / "twice.ply"
    props = ["float x", "float X", "float y", "float z"]
    path.write_bytes(_header("binary_little_endian", 1, props) + b"\x00" * 16)
    with pytest.raises(InputError, match="duplicate property 'X'"):
        read_ply(path)


@pytest.mark.parametrize(
    ("fmt", "problem"),
    [
        ("ascii", "truncated: header says 4,000,000,000 vertices \\(one text line each\\)"),
        ("binary_little_endian", "truncated: header promises 4000000000 vertices"),
    ],
)
def test_more_vertices_than_the_file_can_hold_fail_when_opened(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, fmt: str, problem: str
):
    path = tmp_path / "huge.ply"
    body = b"1 2 3\n4 5 6\n" if fmt == "ascii" else np.zeros(6, "<f4").tobytes()
    path.write_bytes(_header(fmt, 4_000_000_000, ["float x", "float y", "float z"]) + body)
    monkeypatch.setattr(ply_module, "_load_vertices", None)  # nothing may be read or allocated
    with pytest.raises(InputError, match=problem) as info:
        read_ply(path)
    assert str(info.value).startswith(f"{path}: ")


def test_ascii_records_before_the_vertices_count_too(tmp_path: Path):
    lines = ["ply", "format ascii 1.0", "element camera 900000000", "property float f"]
    lines += ["element vertex 2", "property float x", "property float y", "property float z"]
    path = tmp_path / "camera.ply"
    path.write_bytes(("\n".join(lines) + "\nend_header\n1\n1 2 3\n4 5 6\n").encode())
    with pytest.raises(InputError, match="900,000,002 vertices and records before them"):
        read_ply(path)


@pytest.mark.parametrize("binary", [True, False])
def test_a_map_read_in_chunks_is_the_whole_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, binary: bool
):
    """A tiled run reads a map a million vertices at a time (here 150), in bounded memory; an
    element before the vertices and faces after them are stepped over."""
    xyz = _points(500)
    fields = {"label": np.arange(500).astype(np.uint16)}
    path = write_ply(tmp_path / "map.ply", xyz, fields=fields, binary=binary)
    monkeypatch.setattr(point_files, "TABLE_CHUNK", 150)
    frame = read_ply(path).frames[0]
    chunks = list(frame.world_chunks())
    assert [start for start, _ in chunks] == [0, 150, 300, 450]
    np.testing.assert_array_equal(np.concatenate([c.xyz for _, c in chunks]), xyz)
    labels = np.concatenate([c.extra["label"] for _, c in chunks])
    np.testing.assert_array_equal(labels, fields["label"])
    np.testing.assert_array_equal(frame.world_points().xyz, xyz)


@pytest.mark.parametrize("binary", [True, False])
def test_a_bad_map_read_in_chunks_is_an_input_error(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, binary: bool
):
    xyz = _points(400)
    xyz[310, 2] = np.nan
    path = write_ply(tmp_path / "cut.ply", _points(400), binary=binary)
    monkeypatch.setattr(point_files, "TABLE_CHUNK", 150)
    survey = read_ply(path)
    path.write_bytes(path.read_bytes()[: path.stat().st_size * 2 // 3])  # cut after opening
    with pytest.raises(InputError, match="cut.ply"):
        list(survey.frames[0].world_chunks())
    head = _header("ascii", 400, ["double x", "double y", "double z"])
    body = "".join(f"{x} {y} {z}\n" for x, y, z in xyz).encode()
    (tmp_path / "nan2.ply").write_bytes(head + body)
    with pytest.raises(InputError, match=r"nan2.ply.*NaN or infinite coordinates \(the first: 310"):
        list(read_ply(tmp_path / "nan2.ply").frames[0].world_chunks())
