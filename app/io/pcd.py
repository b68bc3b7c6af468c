"""PCD (Point Cloud Library, v0.7): read an accumulated map; write one with labels
(`write_labelled_pcd`).

A small reader of its own for `DATA ascii` and `DATA binary` (header parsed eagerly, data read on
`Frame.points()` with one `np.loadtxt` / `np.fromfile`, or a million points at a time by
`Frame.world_chunks` where the cloud is unorganized). `DATA binary_compressed` (LZF, one block:
read whole) is handed
to open3d's tensor reader when the points are loaded (open3d only knows lower-case `x y z`, so a
file that spells them otherwise goes to it as a temporary copy whose FIELDS line does); if that
fails the error names the file. Counts the file cannot hold (POINTS beyond the data, the
compressed sizes) fail when the file is opened, before anything is parsed or allocated.

Fields map like PLY's properties (see `app.io.ply`), in any case (PDAL writes `X Y Z`): `x y z`
-> xyz float64, `intensity` -> intensity, `time` / `gps_time` / `timestamp` -> time, everything
else -> `PointCloud.extra` (`rgb` / `rgba` under the lower-case key, others as written);
`label` / `class` / `classification` are also reference labels. PCL's `_` padding fields are
skipped.

NaN coordinates: in an *organized* cloud (HEIGHT > 1, e.g. a range image from a sensor driver) a
NaN point is the usual way of saying "no return at this pixel", so those points are dropped and
`PointCloud.extra["grid_index"]` keeps each remaining point's row-major index in the
WIDTH x HEIGHT grid; the frame's `point_count` is then unknown (None) until the points are loaded.
In an unorganized cloud (HEIGHT == 1) a NaN / infinite coordinate is an error, as in PLY.
"""

from __future__ import annotations

import shutil
import struct
import tempfile
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import numpy as np

from app.core.errors import InputError
from app.io.point_files import (
    LABEL_NAMES,
    binary_table_chunks,
    canonical_name,
    check_text_fits,
    cloud_from_fields,
    guarded,
    load_text_table,
    map_survey,
    normalized,
    read_header_bytes,
    text_table_chunks,
    write_atomically,
)
from app.io.survey import PointCloud, Survey

_KEYS = ("VERSION", "FIELDS", "SIZE", "TYPE", "COUNT", "WIDTH", "HEIGHT", "VIEWPOINT", "POINTS")
_DATA_KINDS = ("ascii", "binary", "binary_compressed")
_SIZES = {"I": (1, 2, 4, 8), "U": (1, 2, 4, 8), "F": (4, 8)}
_MAX_HEADER = 1 << 20  # bytes
_LZF_MAX_RATIO = 88  # an LZF back-reference of 3 bytes yields at most 264 bytes


@dataclass
class _PcdHeader:
    fields: list[tuple[str, np.dtype, int]]  # (name, little-endian scalar dtype, count)
    width: int
    height: int
    points: int
    data: str  # "ascii", "binary", "binary_compressed"
    data_offset: int

    @property
    def organized(self) -> bool:
        return self.height > 1

    def dtype(self) -> np.dtype:
        return np.dtype(
            [(name, dt, (count,)) if count > 1 else (name, dt) for name, dt, count in self.fields]
        )


def read_pcd(path: str | Path) -> Survey:
    """Open a .pcd file as an accumulated map (one frame `map`, identity pose)."""
    path = Path(path)
    header = _parse_header(path)
    if header.points == 0:
        raise InputError(path, "contains no points")
    if header.data == "ascii":
        check_text_fits(path, header.data_offset, header.points, "points")
    elif header.data == "binary_compressed":
        _check_compressed_sizes(path, header)
    elif header.data == "binary":
        nbytes = header.points * header.dtype().itemsize
        available = max(path.stat().st_size - header.data_offset, 0)
        if available < nbytes:
            raise InputError(
                path,
                f"truncated: header promises {header.points} points ({nbytes} bytes), "
                f"file has {available} bytes",
            )
    labels = tuple(name for name, _, count in header.fields if normalized(name) in LABEL_NAMES)
    return map_survey(
        path,
        "pcd",
        None if header.organized else header.points,
        partial(_load_points, path, header),
        partial(_load_reference, path, header, labels) if labels else None,
        labels,
        # a sensor's organized range image is small, and LZF is one block: those are read whole
        load_chunks=(
            partial(_chunks, path, header)
            if header.data != "binary_compressed" and not header.organized
            else None
        ),
    )


def _check_compressed_sizes(path: Path, header: _PcdHeader) -> None:
    """`DATA binary_compressed` starts with its compressed and uncompressed byte counts; both must
    agree with POINTS and fit the file before open3d allocates anything."""
    with open(path, "rb") as f:
        f.seek(header.data_offset)
        sizes = f.read(8)
    if len(sizes) < 8:
        raise InputError(path, "truncated: binary_compressed PCD has no data after its header")
    compressed, uncompressed = struct.unpack("<II", sizes)
    available = max(path.stat().st_size - header.data_offset - 8, 0)
    point_size = sum(
        dt.itemsize * count for name, dt, count in header.fields if not name.startswith("_pad")
    )
    expected = header.points * point_size
    if uncompressed != expected:
        raise InputError(
            path,
            f"header says {header.points:,} points ({expected:,} bytes) but the "
            f"binary_compressed data holds {uncompressed:,} bytes",
        )
    if compressed > available or uncompressed > _LZF_MAX_RATIO * compressed:
        raise InputError(
            path,
            f"truncated: binary_compressed data says {compressed:,} compressed bytes for "
            f"{uncompressed:,}, file has {available:,} bytes after the header",
        )


def _parse_header(path: Path) -> _PcdHeader:
    raw = read_header_bytes(path, b"DATA", _MAX_HEADER)
    values: dict[str, list[str]] = {}
    data_kind = ""
    for number, line in enumerate(raw.decode("ascii", errors="replace").splitlines(), start=1):
        words = line.split()
        if not words or words[0].startswith("#"):
            continue
        key = words[0].upper()
        if key == "DATA":
            if len(words) != 2 or words[1].lower() not in _DATA_KINDS:
                raise InputError(
                    path, f"bad header line {number}: DATA must be one of {', '.join(_DATA_KINDS)}"
                )
            data_kind = words[1].lower()
        elif key in _KEYS:
            if key in values:
                raise InputError(path, f"bad header line {number}: {key} given twice")
            values[key] = words[1:]
        else:
            raise InputError(
                path, f"not a PCD file: unknown header line {number}: {line.strip()!r}"
            )

    for key in ("FIELDS", "SIZE", "TYPE", "WIDTH"):
        if key not in values:
            raise InputError(path, f"PCD header has no {key} line")
    names = values["FIELDS"]
    if not names:
        raise InputError(path, "PCD header: FIELDS is empty")
    for key in ("SIZE", "TYPE", "COUNT"):
        given = values.get(key)
        if given is not None and len(given) != len(names):
            raise InputError(
                path, f"PCD header: {key} has {len(given)} values, FIELDS has {len(names)}"
            )
    sizes = _ints(path, "SIZE", values["SIZE"])
    counts = _ints(path, "COUNT", values.get("COUNT", ["1"] * len(names)))
    types = [t.upper() for t in values["TYPE"]]
    width = _single_int(path, "WIDTH", values["WIDTH"])
    height = _single_int(path, "HEIGHT", values.get("HEIGHT", ["1"]))
    points = _single_int(path, "POINTS", values.get("POINTS", [str(width * height)]))
    if points != width * height:
        raise InputError(
            path, f"PCD header: POINTS {points} is not WIDTH x HEIGHT = {width} x {height}"
        )
    if "VIEWPOINT" in values and len(values["VIEWPOINT"]) != 7:
        raise InputError(
            path, f"PCD header: VIEWPOINT has {len(values['VIEWPOINT'])} values, expected 7"
        )

    fields: list[tuple[str, np.dtype, int]] = []
    seen: set[str] = set()
    for i, (name, size, kind, count) in enumerate(zip(names, sizes, types, counts, strict=True)):
        if kind not in _SIZES or size not in _SIZES[kind]:
            raise InputError(
                path, f"PCD header: field {name!r} has unsupported TYPE {kind} SIZE {size}"
            )
        if count < 1:
            raise InputError(path, f"PCD header: field {name!r} has COUNT {count}")
        if name == "_":  # PCL padding; several may occur
            name = f"_pad{i}"
        name = canonical_name(name)  # `X Y Z` (PDAL) read as `x y z`
        if name in seen:
            raise InputError(path, f"PCD header: field {name!r} given twice")
        seen.add(name)
        code = {"I": "i", "U": "u", "F": "f"}[kind]
        fields.append((name, np.dtype(f"<{code}{size}"), count))
    for axis in "xyz":
        if axis not in seen:
            raise InputError(path, "has no x/y/z fields")
        if next(c for n, _, c in fields if n == axis) != 1:
            raise InputError(path, f"PCD header: field {axis} must have COUNT 1")
    if not data_kind:
        raise InputError(path, "PCD header has no DATA line")
    return _PcdHeader(fields, width, height, points, data_kind, len(raw))


def _ints(path: Path, key: str, words: list[str]) -> list[int]:
    try:
        return [int(w) for w in words]
    except ValueError:
        raise InputError(path, f"PCD header: {key} values must be integers: {words}") from None


def _single_int(path: Path, key: str, words: list[str]) -> int:
    if len(words) != 1:
        raise InputError(path, f"PCD header: {key} has {len(words)} values, expected 1")
    value = _ints(path, key, words)[0]
    if value < 0:
        raise InputError(path, f"PCD header: {key} is negative ({value})")
    return value


def _load_data(path: Path, header: _PcdHeader) -> np.ndarray:
    """All points of the file as a structured array (native byte order), padding removed."""
    n = header.points
    dtype = header.dtype()
    if header.data == "ascii":
        data = load_text_table(path, header.data_offset, dtype.newbyteorder("="), 0, n)
        if len(data) < n:
            raise InputError(
                path, f"truncated: header promises {n} points, file has {len(data)} point lines"
            )
    elif header.data == "binary":
        data = guarded(
            path,
            "point data",
            lambda: np.fromfile(path, dtype=dtype, count=n, offset=header.data_offset),
        )
        if len(data) < n:
            available = max(path.stat().st_size - header.data_offset, 0)
            raise InputError(
                path,
                f"truncated: header promises {n} points ({n * dtype.itemsize} bytes), "
                f"file has {available} bytes",
            )
        data = data.astype(dtype.newbyteorder("="), copy=False)
    else:
        data = _load_compressed(path, header)
    return _without_padding(data)


def _without_padding(data: np.ndarray) -> np.ndarray:
    keep = [name for name in data.dtype.names or () if not name.startswith("_pad")]
    return data[keep] if len(keep) < len(data.dtype.names or ()) else data


def _chunks(path: Path, header: _PcdHeader) -> Iterator[tuple[int, PointCloud]]:
    """An unorganized cloud's points in pieces (index of the first, points): a map of any size
    in bounded memory."""
    n, dtype = header.points, header.dtype()
    if header.data == "ascii":
        pieces = text_table_chunks(path, header.data_offset, dtype, 0, n, "points")
    else:
        pieces = binary_table_chunks(path, header.data_offset, dtype, n, "points")
    for start, data in pieces:
        yield start, cloud_from_fields(path, _without_padding(data), start)


def _load_compressed(path: Path, header: _PcdHeader) -> np.ndarray:
    """`DATA binary_compressed` through open3d's tensor reader."""

    def read(source: Path) -> dict[str, np.ndarray]:
        import open3d as o3d

        cloud = o3d.t.io.read_point_cloud(str(source), remove_nan_points=False)
        return {key: cloud.point[key].numpy() for key in cloud.point}

    def load() -> dict[str, np.ndarray]:
        raw = read_header_bytes(path, b"DATA", _MAX_HEADER)
        canonical = _canonical_fields_line(raw)
        if canonical == raw:
            return read(path)
        # open3d only knows lower-case `x y z`: give it a copy whose FIELDS line says so
        with tempfile.TemporaryDirectory(prefix="mmsclean-pcd-") as tmp:
            copy = Path(tmp) / path.name
            with open(path, "rb") as src, open(copy, "wb") as dst:
                src.seek(len(raw))
                dst.write(canonical)
                shutil.copyfileobj(src, dst)
            return read(copy)

    try:
        attributes = load()
    except MemoryError:
        raise
    except ImportError:
        raise InputError(
            path, "DATA binary_compressed needs open3d, which is not installed"
        ) from None
    except Exception as exc:
        raise InputError(path, f"cannot read binary_compressed PCD data: {exc}") from exc
    positions = attributes.pop("positions", None)
    if positions is None or len(positions) != header.points:
        found = 0 if positions is None else len(positions)
        raise InputError(
            path,
            f"cannot read binary_compressed PCD data: header promises {header.points} points, "
            f"open3d read {found}",
        )
    columns: list[tuple[str, np.ndarray]] = [
        (axis, positions[:, i]) for i, axis in enumerate("xyz")
    ]
    for key, values in attributes.items():
        columns.append((key, values[:, 0] if values.ndim == 2 and values.shape[1] == 1 else values))
    data = np.empty(header.points, dtype=[(name, v.dtype, v.shape[1:]) for name, v in columns])
    for name, values in columns:
        data[name] = values
    return data


def _canonical_fields_line(raw: bytes) -> bytes:
    """The header with its FIELDS names as `canonical_name` keys them (other lines unchanged)."""
    lines = raw.splitlines(keepends=True)
    for i, line in enumerate(lines):
        words = line.split()
        if words and words[0].upper() == b"FIELDS":
            names = [canonical_name(w.decode("ascii", "replace")) for w in words[1:]]
            ending = line[len(line.rstrip(b"\r\n")) :]
            lines[i] = (" ".join(["FIELDS", *names])).encode("ascii", "replace") + ending
    return b"".join(lines)


def _organized_finite(data: np.ndarray) -> np.ndarray:
    """Mask of points with finite x, y, z."""
    return np.isfinite(data["x"]) & np.isfinite(data["y"]) & np.isfinite(data["z"])


def _load_points(path: Path, header: _PcdHeader) -> PointCloud:
    data = _load_data(path, header)
    if not header.organized:
        return cloud_from_fields(path, data)
    finite = _organized_finite(data)
    grid_index = np.flatnonzero(finite)
    cloud = cloud_from_fields(path, data[finite])
    index_dtype = np.uint32 if header.points <= np.iinfo(np.uint32).max else np.int64
    cloud.extra["grid_index"] = grid_index.astype(index_dtype)
    return cloud


def _load_reference(path: Path, header: _PcdHeader, labels: tuple[str, ...]) -> dict:
    data = _load_data(path, header)
    if header.organized:
        data = data[_organized_finite(data)]
    return {name: np.ascontiguousarray(data[name]) for name in labels}


# what `write_labelled_pcd` writes: PCL's float x y z intensity and its uint32 `label`
LABELLED_PCD = np.dtype(
    [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4"), ("label", "<u4")]
)


def write_labelled_pcd(
    path: str | Path,
    points: int,
    pieces: Iterable[tuple[np.ndarray, np.ndarray, np.ndarray]],
    comments: Iterable[str] = (),
) -> Path:
    """A `DATA binary` PCD v0.7 of `points` points with fields x y z intensity label, written
    a piece at a time from `pieces` ((N, 3) xyz, (N,) intensity, (N,) label each), so a map of
    any size passes in bounded memory. The count goes in the header before any point, so the
    pieces must add up to it; `comments` become `#` lines of the header. Through
    `<path>.partial`: a failed write leaves nothing."""
    path = Path(path)
    lines = ["# .PCD v0.7 - Point Cloud Data file format"]
    lines += [f"# {c}" for c in comments if "\n" not in c and "\r" not in c]
    lines += [
        "VERSION 0.7",
        "FIELDS " + " ".join(LABELLED_PCD.names or ()),
        "SIZE 4 4 4 4 4",
        "TYPE F F F F U",
        "COUNT 1 1 1 1 1",
        f"WIDTH {points}",
        "HEIGHT 1",
        "VIEWPOINT 0 0 0 1 0 0 0",
        f"POINTS {points}",
        "DATA binary",
    ]

    def write(f) -> None:
        f.write(("\n".join(lines) + "\n").encode("ascii", "replace"))
        written = 0
        for xyz, intensity, label in pieces:
            xyz = np.asarray(xyz)
            if not np.isfinite(xyz).all():
                raise InputError(path, "NaN or infinite coordinates")
            record = np.empty(len(xyz), dtype=LABELLED_PCD)
            for i, axis in enumerate("xyz"):
                record[axis] = xyz[:, i]
            record["intensity"] = intensity
            record["label"] = label
            written += len(record)
            if written > points:
                break
            f.write(record.tobytes())
        if written != points:
            raise InputError(path, f"the header says {points} points, the pieces held {written}")

    write_atomically(path, write)
    return path
