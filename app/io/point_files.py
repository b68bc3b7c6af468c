"""What the single-file map readers (LAS, PLY, PCD) share.

One-line errors for any failure while reading a file, atomic writes (`<path>.partial`, then
rename), text headers, structured point tables -> `PointCloud`, and the one-frame map `Survey`.
"""

from __future__ import annotations

import io
import itertools
import os
from collections.abc import Callable, Iterator
from functools import partial
from pathlib import Path
from typing import TypeVar

import numpy as np

from app.core.errors import InputError
from app.io.survey import MAP_FRAME_ID, Frame, PointCloud, Survey

T = TypeVar("T")

INTENSITY_NAMES = ("intensity",)
TIME_NAMES = ("time", "gps_time", "gpstime", "timestamp")
LABEL_NAMES = ("label", "class", "classification")
CANONICAL_NAMES = ("x", "y", "z", "rgb", "rgba")
TABLE_CHUNK = 1_000_000  # rows per piece when a map file is read in pieces (`Frame.world_chunks`)


def map_survey(
    path: Path,
    fmt: str,
    point_count: int | None,
    load_points: Callable[[], PointCloud],
    load_reference: Callable[[], dict[str, np.ndarray]] | None,
    labels: tuple[str, ...],
    sample_points: Callable[[int], PointCloud] | None = None,
    load_chunks: Callable[[], Iterator[tuple[int, PointCloud]]] | None = None,
) -> Survey:
    """An accumulated map: one frame `map`, identity pose, points already in world coordinates.

    `sample_points(n)` reads the first n points; by default the whole file is read and cut.
    `load_chunks()` yields the points in pieces (`Frame.world_chunks`), where the format can."""
    frame = Frame(
        index=0,
        frame_id=MAP_FRAME_ID,
        pose=np.eye(4),
        point_count=point_count,
        source_path=path,
        _load_points=load_points,
        _load_reference=load_reference,
        _load_chunks=load_chunks,
    )
    return Survey(
        name=path.stem,
        source=path,
        format=fmt,
        frames=[frame],
        reference_label_kinds=labels,
        sample_points=sample_points or partial(_first_points, load_points),
    )


def _first_points(load_points: Callable[[], PointCloud], n: int) -> PointCloud:
    cloud = load_points()
    return PointCloud(
        cloud.xyz[:n],
        None if cloud.intensity is None else cloud.intensity[:n],
        None if cloud.time is None else cloud.time[:n],
    )


def one_line(exc: BaseException) -> str:
    """The exception's message on one line (numpy's `; use usecols ...` advice cut off)."""
    text = " ".join(str(exc).split()).split("; use `usecols`")[0]
    return text or type(exc).__name__


def is_native_panic(exc: BaseException) -> bool:
    """A Rust panic from a native extension (lazrs, through pyo3): `pyo3_runtime.PanicException`
    derives from BaseException, so `except Exception` lets it through as a traceback."""
    kind = type(exc)
    return kind.__name__ == "PanicException" and kind.__module__ == "pyo3_runtime"


def guarded(path: Path, what: str, fn: Callable[[], T]) -> T:
    """Run a read, turning any failure of the file (a native panic too) into one InputError line."""
    try:
        return fn()
    except (InputError, MemoryError):
        raise
    except FileNotFoundError as exc:
        raise InputError(path, "does not exist") from exc
    except Exception as exc:
        raise InputError(path, f"cannot read {what}: {one_line(exc)}") from exc
    except BaseException as exc:
        if not is_native_panic(exc):
            raise
        raise InputError(path, f"cannot read {what}: {one_line(exc)}") from exc


def writable_xyz(path: Path, xyz: np.ndarray) -> np.ndarray:
    """(N, 3) float64 coordinates to write to `path`; NaN/inf are refused, never written."""
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise InputError(path, f"xyz must have shape (N, 3), got {xyz.shape}")
    bad = int(np.count_nonzero(~np.isfinite(xyz).all(axis=1)))
    if bad:
        raise InputError(path, f"cannot write {bad} points with NaN or infinite coordinates")
    return xyz


def write_atomically(path: Path, write: Callable[[io.BufferedWriter], None]) -> None:
    """Write through `<path>.partial` and rename, removing the partial file on any failure."""
    path.parent.mkdir(parents=True, exist_ok=True)
    partial_path = path.with_suffix(path.suffix + ".partial")
    try:
        with open(partial_path, "wb") as f:
            write(f)
        os.replace(partial_path, path)
    except BaseException:
        partial_path.unlink(missing_ok=True)
        raise


def read_header_bytes(path: Path, end_keyword: bytes, limit: int) -> bytes:
    """The header of a text-headed format: everything up to and including the line that starts
    with `end_keyword` (and its newline)."""
    if not path.is_file():
        raise InputError(path, "does not exist" if not path.exists() else "is not a file")
    try:
        with open(path, "rb") as f:
            head = f.read(limit)
    except OSError as exc:
        raise InputError(path, f"cannot read: {one_line(exc)}") from exc
    start = 0
    while start < len(head):
        end = head.find(b"\n", start)
        if end < 0:
            break
        if head[start:end].lstrip().startswith(end_keyword):
            return head[: end + 1]
        start = end + 1
    if head[start:].lstrip().startswith(end_keyword):  # keyword on the last line, no newline
        return head
    keyword = end_keyword.decode()
    raise InputError(path, f"has no '{keyword}' line in its first {len(head)} bytes")


def canonical_name(name: str) -> str:
    """A field's key in the reader's output: x, y, z, rgb and rgba in lower case whatever case the
    writer used (PDAL writes `X Y Z`), every other name as written (matched via `normalized`)."""
    key = name.lower()
    return key if key in CANONICAL_NAMES else name


def check_text_fits(path: Path, offset: int, rows: int, noun: str) -> None:
    """Refuse a header count that a text body cannot hold before parsing anything: every row takes
    at least two bytes (a value and a line break)."""
    available = max(path.stat().st_size - offset, 0)
    needed = 2 * rows - 1
    if rows and needed > available:
        raise InputError(
            path,
            f"truncated: header says {rows:,} {noun} (one text line each) "
            f"but the file has only {available:,} bytes after the header",
        )


def normalized(name: str) -> str:
    """Property name for matching: lower case, without CloudCompare's `scalar_` prefix."""
    name = name.lower()
    return name.removeprefix("scalar_")


def load_text_table(path: Path, offset: int, dtype: np.dtype, skip: int, rows: int) -> np.ndarray:
    """Up to `rows` whitespace-separated text rows from byte `offset` on, after `skip` lines.

    Float columns are parsed as float64, so x, y, z keep every digit the text has (even when the
    header says float32); other float columns are then cast to their declared type.
    """
    parse, result = _text_types(dtype)

    def load() -> np.ndarray:
        with open(path, "rb") as raw:
            raw.seek(offset)
            text = io.TextIOWrapper(raw, encoding="latin-1")
            return np.loadtxt(
                text, dtype=parse, skiprows=skip, max_rows=rows, ndmin=1, comments=None
            )

    return guarded(path, "point data", load).astype(result, copy=False)


def _text_types(dtype: np.dtype) -> tuple[np.dtype, np.dtype]:
    """(parsed as, returned as) of a text table's columns: floats parsed as float64, x, y, z
    kept so, other floats cast back to their declared type."""
    names = dtype.names or ()
    parse = np.dtype(
        [
            (n, np.float64 if dtype[n].base.kind == "f" else dtype[n].base, dtype[n].shape)
            for n in names
        ]
    )
    result = np.dtype(
        [(n, np.float64 if n in ("x", "y", "z") else dtype[n].base, dtype[n].shape) for n in names]
    )
    return parse, result


def text_table_chunks(
    path: Path, offset: int, dtype: np.dtype, skip: int, n: int, noun: str, rows: int = 0
) -> Iterator[tuple[int, np.ndarray]]:
    """`load_text_table`'s `n` rows in pieces of `rows` (default `TABLE_CHUNK`): (index of the
    first row, rows), read on from one open file, blank lines skipped as `np.loadtxt` skips them.
    Fewer rows than `n` is an error naming the file."""
    rows = rows or TABLE_CHUNK
    parse, result = _text_types(dtype)
    with guarded(path, "point data", lambda: open(path, "rb")) as raw:
        raw.seek(offset)
        text = io.TextIOWrapper(raw, encoding="latin-1")
        for _ in itertools.islice(text, skip):
            pass
        start = 0
        while start < n:
            lines = [line for line in itertools.islice(text, min(rows, n - start)) if line.strip()]
            if not lines:
                raise InputError(path, f"truncated: header promises {n} {noun}, file has {start}")
            load = partial(np.loadtxt, lines, dtype=parse, ndmin=1, comments=None)
            data = guarded(path, "point data", load)
            yield start, data.astype(result, copy=False)
            start += len(data)


def binary_table_chunks(
    path: Path, offset: int, dtype: np.dtype, n: int, noun: str, rows: int = 0
) -> Iterator[tuple[int, np.ndarray]]:
    """`n` records of `dtype` from byte `offset` on, in pieces of `rows` (default `TABLE_CHUNK`):
    (index of the first record, records in native byte order). Fewer records than `n` is an
    error naming the file."""
    rows = rows or TABLE_CHUNK
    for start in range(0, n, rows):
        count = min(rows, n - start)
        at = offset + start * dtype.itemsize
        load = partial(np.fromfile, path, dtype=dtype, count=count, offset=at)
        data = guarded(path, "point data", load)
        if len(data) < count:
            raise InputError(
                path, f"truncated: header promises {n} {noun}, file has {start + len(data)}"
            )
        yield start, data.astype(dtype.newbyteorder("="), copy=False)


def cloud_from_fields(path: Path, data: np.ndarray, start: int | None = None) -> PointCloud:
    """Build a PointCloud from a structured array with x, y, z fields (shared with PCD); `start`:
    the index of its first row, where it is one piece of a file.

    Points with NaN / infinite coordinates raise InputError: they are never silently dropped.
    """
    xyz = np.empty((len(data), 3), dtype=np.float64)
    for column, axis in enumerate("xyz"):
        xyz[:, column] = data[axis]
    finite = np.isfinite(xyz).all(axis=1)
    bad = len(xyz) - int(np.count_nonzero(finite))
    if bad and start is not None:
        first = start + int(np.argmin(finite))
        raise InputError(path, f"has points with NaN or infinite coordinates (the first: {first})")
    if bad:
        raise InputError(path, f"has {bad} points with NaN or infinite coordinates")
    intensity = None
    time = None
    extra: dict[str, np.ndarray] = {}
    for name in data.dtype.names or ():
        if name in ("x", "y", "z"):
            continue
        key = normalized(name)
        values = np.ascontiguousarray(data[name])
        if key in INTENSITY_NAMES and intensity is None and values.ndim == 1:
            intensity = values.astype(np.float32, copy=False)
        elif key in TIME_NAMES and time is None and values.ndim == 1:
            time = values.astype(np.float64, copy=False)
        else:
            extra[name] = values
    return PointCloud(xyz, intensity=intensity, time=time, extra=extra)
