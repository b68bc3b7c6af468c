"""PLY: read an accumulated map, write points with per-point fields.

A small reader of its own (no open3d): the header is parsed eagerly, the vertex data only when
`Frame.points()` is called. Binary bodies are read with one `np.fromfile` into a packed structured
dtype, ASCII bodies with one `np.loadtxt` (float columns parsed as float64, so coordinates keep
every digit of the text even when declared `float`); `Frame.world_chunks` reads either a million
vertices at a time (a tiled run reads a map of any size in bounded memory).

Vertex properties are mapped, case-insensitively and ignoring CloudCompare's `scalar_` prefix:
`x`, `y`, `z` -> xyz (float64); `intensity` -> intensity (float32); `time` / `gps_time` /
`timestamp` -> time (float64); everything else -> `PointCloud.extra` under its own name (`rgb` /
`rgba` in lower case). Label properties (`label`, `class`, `classification`) are also the survey's
reference labels. A vertex count the file cannot hold fails when the file is opened.

Elements before the vertex element are skipped (in binary files only when they have no list
properties, since their size must be computed); elements after it are ignored.
"""

from __future__ import annotations

import io
from collections.abc import Iterator
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
    writable_xyz,
    write_atomically,
)
from app.io.survey import PointCloud, Survey

_PLY_TYPES: dict[str, str] = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}
# numpy dtype -> PLY type name, for the writer
_PLY_NAMES: dict[str, str] = {
    "i1": "char",
    "u1": "uchar",
    "i2": "short",
    "u2": "ushort",
    "i4": "int",
    "u4": "uint",
    "f4": "float",
    "f8": "double",
}
_FORMATS = {"ascii": "", "binary_little_endian": "<", "binary_big_endian": ">"}
_MAX_HEADER = 1 << 20  # bytes


@dataclass
class _Element:
    name: str
    count: int
    properties: list[tuple[str, str]]  # (name, numpy type code) of scalar properties
    lists: list[str]  # names of list properties


@dataclass
class _PlyHeader:
    format: str  # "ascii", "binary_little_endian", "binary_big_endian"
    elements: list[_Element]
    data_offset: int  # byte offset of the body

    @property
    def vertex_index(self) -> int:
        return next(i for i, e in enumerate(self.elements) if e.name == "vertex")

    @property
    def vertex(self) -> _Element:
        return self.elements[self.vertex_index]


def read_ply(path: str | Path) -> Survey:
    """Open a .ply file as an accumulated map (one frame `map`, identity pose)."""
    path = Path(path)
    header = _parse_header(path)
    vertex = header.vertex
    names = [name for name, _ in vertex.properties]
    if vertex.lists:
        raise InputError(
            path, f"vertex element has list properties {vertex.lists}; only scalars are supported"
        )
    if not {"x", "y", "z"} <= set(names):
        raise InputError(path, "has no x/y/z vertex properties")
    if vertex.count == 0:
        raise InputError(path, "contains no points")
    if header.format == "ascii":
        lines_before = sum(e.count for e in header.elements[: header.vertex_index])
        noun = "vertices and records before them" if lines_before else "vertices"
        check_text_fits(path, header.data_offset, lines_before + vertex.count, noun)
    else:
        offset, nbytes = _binary_layout(path, header)
        available = max(path.stat().st_size - offset, 0)
        if available < nbytes:
            raise InputError(
                path,
                f"truncated: header promises {vertex.count} vertices ({nbytes} bytes), "
                f"file has {available} bytes",
            )

    labels = tuple(name for name in names if normalized(name) in LABEL_NAMES)
    return map_survey(
        path,
        "ply",
        vertex.count,
        partial(_load_points, path, header),
        partial(_load_reference, path, header, labels) if labels else None,
        labels,
        load_chunks=partial(_vertex_chunks, path, header),
    )


def _parse_header(path: Path) -> _PlyHeader:
    raw = read_header_bytes(path, b"end_header", _MAX_HEADER)
    lines = raw.decode("ascii", errors="replace").splitlines()
    if not lines or lines[0].strip() != "ply":
        raise InputError(path, "not a PLY file (does not start with 'ply')")
    fmt: str | None = None
    elements: list[_Element] = []
    for number, line in enumerate(lines[1:-1], start=2):
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        bad = f"bad header line {number}: {line.strip()!r}"
        if words[0] == "format":
            if len(words) != 3 or words[1] not in _FORMATS:
                raise InputError(path, f"{bad} (format must be one of {', '.join(_FORMATS)})")
            fmt = words[1]
        elif words[0] == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise InputError(path, bad)
            elements.append(_Element(words[1], int(words[2]), [], []))
        elif words[0] == "property":
            if not elements:
                raise InputError(path, f"{bad} (property before any element)")
            element = elements[-1]
            if len(words) == 5 and words[1] == "list":
                element.lists.append(words[4])
            elif len(words) == 3 and words[1] in _PLY_TYPES:
                name = canonical_name(words[2])  # `X Y Z` read as `x y z`
                if any(name == p for p, _ in element.properties):
                    raise InputError(path, f"{bad} (duplicate property {words[2]!r})")
                element.properties.append((name, _PLY_TYPES[words[1]]))
            else:
                raise InputError(path, f"{bad} (unknown property type)")
        else:
            raise InputError(path, bad)
    if fmt is None:
        raise InputError(path, "has no 'format' line in its header")
    if not any(e.name == "vertex" for e in elements):
        raise InputError(path, "has no vertex element")
    return _PlyHeader(fmt, elements, len(raw))


def _vertex_dtype(header: _PlyHeader) -> np.dtype:
    order = _FORMATS[header.format] if header.format != "ascii" else "="
    return np.dtype([(name, order + code) for name, code in header.vertex.properties])


def _binary_layout(path: Path, header: _PlyHeader) -> tuple[int, int]:
    """(byte offset, byte size) of the vertex data of a binary PLY."""
    offset = header.data_offset
    for element in header.elements[: header.vertex_index]:
        if element.lists:
            raise InputError(
                path,
                f"element {element.name!r} before the vertex element has list properties "
                f"{element.lists}; cannot skip it in a binary file",
            )
        size = (
            np.dtype([(n, c) for n, c in element.properties]).itemsize if element.properties else 0
        )
        offset += element.count * size
    return offset, header.vertex.count * _vertex_dtype(header).itemsize


def _load_vertices(path: Path, header: _PlyHeader) -> np.ndarray:
    """The vertex element as a structured array in native byte order."""
    n = header.vertex.count
    if header.format == "ascii":
        lines_before = sum(e.count for e in header.elements[: header.vertex_index])
        data = load_text_table(path, header.data_offset, _vertex_dtype(header), lines_before, n)
        if len(data) < n:
            raise InputError(
                path, f"truncated: header promises {n} vertices, file has {len(data)} vertex lines"
            )
        return data

    offset, nbytes = _binary_layout(path, header)
    dtype = _vertex_dtype(header)
    data = guarded(
        path, "vertex data", lambda: np.fromfile(path, dtype=dtype, count=n, offset=offset)
    )
    if len(data) < n:
        available = max(path.stat().st_size - offset, 0)
        raise InputError(
            path,
            f"truncated: header promises {n} vertices ({nbytes} bytes), file has {available} bytes",
        )
    return data.astype(dtype.newbyteorder("="), copy=False)


def _load_points(path: Path, header: _PlyHeader) -> PointCloud:
    return cloud_from_fields(path, _load_vertices(path, header))


def _vertex_chunks(path: Path, header: _PlyHeader) -> Iterator[tuple[int, PointCloud]]:
    """The vertices in pieces (index of the first, points): a map of any size in bounded memory."""
    n, dtype = header.vertex.count, _vertex_dtype(header)
    if header.format == "ascii":
        lines_before = sum(e.count for e in header.elements[: header.vertex_index])
        pieces = text_table_chunks(path, header.data_offset, dtype, lines_before, n, "vertices")
    else:
        pieces = binary_table_chunks(path, _binary_layout(path, header)[0], dtype, n, "vertices")
    for start, data in pieces:
        yield start, cloud_from_fields(path, data, start)


def _load_reference(path: Path, header: _PlyHeader, labels: tuple[str, ...]) -> dict:
    data = _load_vertices(path, header)
    return {name: np.ascontiguousarray(data[name]) for name in labels}


def write_ply(
    path: str | Path,
    xyz: np.ndarray,
    *,
    fields: dict[str, np.ndarray] | None = None,
    binary: bool = True,
) -> Path:
    """Write points as PLY: `double x, y, z` plus one scalar property per entry of `fields`.

    Field arrays must have one value per point and a dtype PLY knows (int8..uint32, float32,
    float64; bool is written as uchar). Binary little-endian by default, ASCII with
    `binary=False` (full float precision). Written through `<path>.partial`, renamed when complete;
    invalid input raises InputError naming `path`.
    """
    path = Path(path)
    xyz = writable_xyz(path, xyz)
    n = len(xyz)
    columns: list[tuple[str, np.ndarray]] = [("x", xyz[:, 0]), ("y", xyz[:, 1]), ("z", xyz[:, 2])]
    for name, values in (fields or {}).items():
        if not name or any(c.isspace() for c in name) or not name.isascii():
            raise InputError(path, f"field name {name!r} is not a valid PLY property name")
        if name in {c for c, _ in columns}:
            raise InputError(path, f"field {name!r} given twice (x, y, z are the coordinates)")
        arr = np.asarray(values)
        if arr.dtype == np.bool_:
            arr = arr.astype(np.uint8)
        if arr.shape != (n,):
            raise InputError(path, f"field {name!r} has shape {arr.shape}, expected ({n},)")
        if arr.dtype.str[1:] not in _PLY_NAMES:
            raise InputError(path, f"field {name!r} has dtype {arr.dtype}, which PLY cannot store")
        columns.append((name, arr))

    dtype = np.dtype([(name, "<" + arr.dtype.str[1:]) for name, arr in columns])
    table = np.empty(n, dtype=dtype)
    for name, arr in columns:
        table[name] = arr
    lines = [
        "ply",
        f"format {'binary_little_endian' if binary else 'ascii'} 1.0",
        "comment written by mmsclean",
        f"element vertex {n}",
        *(f"property {_PLY_NAMES[arr.dtype.str[1:]]} {name}" for name, arr in columns),
        "end_header",
    ]
    head = ("\n".join(lines) + "\n").encode("ascii")

    def write(f: io.BufferedWriter) -> None:
        f.write(head)
        if binary:
            f.write(table.tobytes())
        elif n:
            formats = [_text_format(arr.dtype) for _, arr in columns]
            np.savetxt(f, table, fmt=formats, delimiter=" ", newline="\n")

    write_atomically(path, write)
    return path


def _text_format(dtype: np.dtype) -> str:
    """printf format that writes a value back exactly."""
    if dtype.kind == "f":
        return "%.17g" if dtype.itemsize == 8 else "%.9g"
    return "%d"
