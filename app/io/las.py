"""LAS / LAZ: read an accumulated map, write the cleaned map.

`read_las` reads the header eagerly (to validate the file and know the point count) and the points
only when `Frame.points()` is called. World coordinates are float64 exactly as laspy computes them
(`X * scale + offset`).

`write_laz` writes LAS 1.4 point format 6 (with GPS time) and three extra dimensions that carry
mmsclean's own bookkeeping: `mmsclean_label` (uint8, the pipeline label), `source_frame` and
`source_index` (uint32, which input frame and which point of it each map point came from). The
file is written next to its destination as `<name>.partial` and renamed when complete.
"""

from __future__ import annotations

import copy
import datetime
import os
from collections.abc import Iterator
from functools import partial
from pathlib import Path

import laspy
import numpy as np
from laspy.vlrs.known import WktCoordinateSystemVlr

from app.core.errors import InputError
from app.io.las_crs import header_crs
from app.io.las_layout import check_las_layout
from app.io.laz_chunks import LazJoin, LazPart
from app.io.point_files import (
    guarded,
    is_native_panic,
    map_survey,
    one_line,
    writable_xyz,
    write_atomically,
)
from app.io.survey import PointCloud, Survey

# extra dimensions mmsclean writes, with the dtype the reader hands back
EXTRA_DIMS: dict[str, np.dtype] = {
    "mmsclean_label": np.dtype(np.uint8),
    "source_frame": np.dtype(np.uint32),
    "source_index": np.dtype(np.uint32),
}
_EXTRA_DESCRIPTIONS = {
    "mmsclean_label": "mmsclean pipeline label",
    "source_frame": "index of the source frame",
    "source_index": "point index in the source frame",
}
_RETURN_DIMS = ("return_number", "number_of_returns")
_CHUNK = 1_000_000  # points per chunk when scanning classification


def read_las(path: str | Path) -> Survey:
    """Open a .las / .laz file as an accumulated map (one frame `map`, identity pose)."""
    path = Path(path)
    header = _read_header(path)
    n = int(header.point_count)
    if n == 0:
        raise InputError(path, "contains no points")
    scales = np.asarray(header.scales, dtype=np.float64)
    if not (np.all(np.isfinite(scales)) and np.all(scales > 0)):
        raise InputError(path, f"has invalid scale factors {scales.tolist()} (must be finite, > 0)")
    offsets = np.asarray(header.offsets, dtype=np.float64)
    if not np.all(np.isfinite(offsets)):
        raise InputError(path, f"has invalid offsets {offsets.tolist()} (must be finite)")

    has_classes = _has_nonzero_classification(path)
    return map_survey(
        path,
        "las",
        n,
        partial(_load_points, path, n),
        partial(_load_reference, path, n) if has_classes else None,
        ("classification",) if has_classes else (),
        partial(_first_points, path),
        partial(_chunks, path, n),
    )


def _first_points(path: Path, n: int) -> PointCloud:
    """The first n points' coordinates and times (one read of n records, not the whole file)."""

    def read() -> PointCloud:
        with laspy.open(path) as reader:
            points = reader.read_points(min(n, int(reader.header.point_count)))
        xyz = np.stack(
            [np.asarray(points.x), np.asarray(points.y), np.asarray(points.z)], axis=1
        ).astype(np.float64)
        dims = set(points.point_format.dimension_names)
        time = np.asarray(points.gps_time, dtype=np.float64) if "gps_time" in dims else None
        return PointCloud(xyz, time=time)

    return guarded(path, "points", read)


def _read_header(path: Path) -> laspy.LasHeader:
    """The header, after its counts and offsets were checked against the file (`las_layout`), so
    laspy cannot loop over a garbage VLR count nor lazrs allocate a garbage chunk table."""
    if not path.is_file():
        raise InputError(path, "does not exist" if not path.exists() else "is not a file")
    guarded(path, "header", lambda: check_las_layout(path))
    try:
        with laspy.open(path) as reader:
            return reader.header
    except InputError:
        raise
    except MemoryError:
        raise
    except Exception as exc:  # laspy raises LaspyException, struct / value errors, lazrs errors
        raise InputError(path, f"not a LAS/LAZ file: {one_line(exc)}") from exc
    except BaseException as exc:  # a Rust panic in lazrs
        if not is_native_panic(exc):
            raise
        raise InputError(path, f"cannot read LAZ data: {one_line(exc)}") from exc


def _has_nonzero_classification(path: Path) -> bool:
    """True when some point has a classification other than 0 ("never classified").

    Reads chunk by chunk and stops at the first classified chunk; for LAZ with point formats 6-10
    only the xy and classification layers are decompressed.
    """
    selection = (
        laspy.DecompressionSelection.XY_RETURNS_CHANNEL
        | laspy.DecompressionSelection.CLASSIFICATION
    )

    def scan() -> bool:
        with laspy.open(path, decompression_selection=selection) as reader:
            for chunk in reader.chunk_iterator(_CHUNK):
                if np.any(np.asarray(chunk.classification)):
                    return True
        return False

    return bool(guarded(path, "point data", scan))


def read_las_chunks(path: str | Path) -> Iterator[tuple[int, PointCloud]]:
    """A LAS / LAZ file's points a million at a time (index of the first, points with their
    intensity, classification and mmsclean's extra dimensions): a map of any size in bounded
    memory."""
    path = Path(path)
    return _chunks(path, las_point_count(path))


def _has_wkt(header: laspy.LasHeader) -> bool:
    return any(isinstance(v, WktCoordinateSystemVlr) for v in header.vlrs)


def las_crs(path: str | Path) -> tuple[str | None, str]:
    """The coordinate system a LAS / LAZ header records, as (WKT or None, what was found):
    `las_crs.header_crs` (a WKT VLR as it is, GeoTIFF keys' EPSG codes through PROJ)."""
    return header_crs(_read_header(Path(path)), Path(path).name)


def las_point_count(path: Path) -> int:
    """Points promised by a LAS/LAZ header (nothing else is read)."""
    return int(_read_header(path).point_count)


def read_las_points(path: Path) -> PointCloud:
    """All points of a LAS/LAZ file (used for single scans stored as LAZ)."""
    return _load_points(path, las_point_count(path))


def _read_all(path: Path, n: int) -> laspy.LasData:
    las = guarded(path, "points", lambda: laspy.read(path))
    assert isinstance(las, laspy.LasData)
    if len(las.points) != n:
        raise InputError(path, f"truncated: header promises {n} points, file has {len(las.points)}")
    return las


def _load_points(path: Path, n: int) -> PointCloud:
    return _cloud_of(_read_all(path, n))


def _cloud_of(points) -> PointCloud:
    """A PointCloud from laspy points (a whole file's `LasData` or a chunk's point record)."""
    dims = set(points.point_format.dimension_names)
    xyz = np.empty((len(points), 3), dtype=np.float64)
    xyz[:, 0] = points.x
    xyz[:, 1] = points.y
    xyz[:, 2] = points.z
    intensity = (
        np.asarray(points.intensity).astype(np.float32, copy=False) if "intensity" in dims else None
    )
    time = np.asarray(points.gps_time, dtype=np.float64) if "gps_time" in dims else None
    extra: dict[str, np.ndarray] = {
        "classification": np.asarray(points.classification).astype(np.uint8, copy=False)
    }
    for name, dtype in EXTRA_DIMS.items():
        if name in dims:
            extra[name] = np.asarray(points[name]).astype(dtype, copy=False)
    for name in _RETURN_DIMS:
        if name in dims:
            extra[name] = np.asarray(points[name]).astype(np.uint8, copy=False)
    return PointCloud(xyz, intensity=intensity, time=time, extra=extra)


def _chunks(path: Path, n: int) -> Iterator[tuple[int, PointCloud]]:
    """The file's points `_CHUNK` at a time (index of the first, points): a map of any size in
    bounded memory. A file with fewer points than its header promises is an error naming it."""
    start = 0
    reader = guarded(path, "points", lambda: laspy.open(path))
    with reader:
        iterator = reader.chunk_iterator(_CHUNK)
        while True:
            points = guarded(path, "points", lambda: next(iterator, None))
            if points is None or not len(points):
                break
            yield start, _cloud_of(points)
            start += len(points)
    if start != n:
        raise InputError(path, f"truncated: header promises {n} points, file has {start}")


def _load_reference(path: Path, n: int) -> dict[str, np.ndarray]:
    las = _read_all(path, n)
    return {"classification": np.asarray(las.classification).astype(np.uint8, copy=False)}


def write_laz(
    path: str | Path,
    xyz: np.ndarray,
    *,
    mmsclean_label: np.ndarray | None = None,
    classification: np.ndarray | None = None,
    source_frame: np.ndarray | None = None,
    source_index: np.ndarray | None = None,
    intensity: np.ndarray | None = None,
    gps_time: np.ndarray | None = None,
    scale: float = 0.001,
    offset: np.ndarray | float | None = None,
    creation_date: datetime.date | None = None,
) -> Path:
    """Write points as LAS 1.4 point format 6: compressed for `.laz`, plain for `.las`.

    - `xyz` (N, 3) float64 world coordinates, stored as integers `round((xyz - offset) / scale)`,
      so each coordinate comes back within `scale / 2`.
    - `offset` defaults to the minimum coordinate rounded down to whole metres, which keeps
      millimetre precision for large UTM coordinates.
    - `classification` (ASPRS codes, see `app.io.asprs`) defaults to 1 (unclassified);
      `mmsclean_label`, `source_frame`, `source_index` default to 0; `intensity` is rounded to the
      LAS uint16 range 0..65535 (scale reflectance 0..1 yourself); `gps_time` defaults to 0.
    - `creation_date` defaults to today; pass a fixed date for byte-identical output.

    Any invalid input raises `InputError` naming `path`; nothing is left at `path` or at the
    `.partial` file when writing fails.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".las", ".laz"):
        raise InputError(path, "output name must end in .las or .laz")
    xyz = writable_xyz(path, xyz)
    n = len(xyz)
    if not (np.isfinite(scale) and scale > 0):
        raise InputError(path, f"scale must be finite and > 0, got {scale}")
    if offset is None:
        offset_arr = np.floor(xyz.min(axis=0)) if n else np.zeros(3)
    else:
        offset_arr = np.broadcast_to(np.asarray(offset, dtype=np.float64), (3,)).copy()
        if not np.all(np.isfinite(offset_arr)):
            raise InputError(path, f"offset must be finite, got {offset_arr.tolist()}")

    ints = np.round((xyz - offset_arr) / scale)
    i32 = np.iinfo(np.int32)
    if n and (ints.min() < i32.min or ints.max() > i32.max):
        raise InputError(
            path,
            f"coordinates span too far from offset {offset_arr.tolist()} for scale {scale} "
            "(LAS stores 32-bit integers); use a larger scale",
        )

    columns = {
        "mmsclean_label": _column(path, "mmsclean_label", mmsclean_label, n, np.uint8, 0),
        "classification": _column(path, "classification", classification, n, np.uint8, 1),
        "source_frame": _column(path, "source_frame", source_frame, n, np.uint32, 0),
        "source_index": _column(path, "source_index", source_index, n, np.uint32, 0),
        "intensity": _column(path, "intensity", intensity, n, np.uint16, 0, rounding=True),
    }
    if gps_time is None:
        times = np.zeros(n, dtype=np.float64)
    else:
        times = _check_length(path, "gps_time", np.asarray(gps_time, dtype=np.float64), n)
        if not np.all(np.isfinite(times)):
            raise InputError(path, "gps_time has NaN or infinite values")

    header = laspy.LasHeader(point_format=6, version="1.4")
    header.creation_date = creation_date or datetime.date.today()
    header.add_extra_dims(
        [
            laspy.ExtraBytesParams(name, dtype, description=_EXTRA_DESCRIPTIONS[name])
            for name, dtype in EXTRA_DIMS.items()
        ]
    )
    header.offsets = offset_arr
    header.scales = np.full(3, scale, dtype=np.float64)
    las = laspy.LasData(header, points=laspy.ScaleAwarePointRecord.zeros(n, header=header))
    las.X = ints[:, 0].astype(np.int32)
    las.Y = ints[:, 1].astype(np.int32)
    las.Z = ints[:, 2].astype(np.int32)
    for name, values in columns.items():
        las[name] = values
    las.gps_time = times
    las.return_number = np.ones(n, dtype=np.uint8)
    las.number_of_returns = np.ones(n, dtype=np.uint8)

    write_atomically(path, lambda f: las.write(f, do_compress=suffix == ".laz"))
    return path


def _check_length(path: Path, name: str, values: np.ndarray, n: int) -> np.ndarray:
    if values.ndim != 1 or len(values) != n:
        raise InputError(path, f"{name} has shape {values.shape}, expected ({n},) like xyz")
    return values


def _column(
    path: Path,
    name: str,
    values: np.ndarray | None,
    n: int,
    dtype: type[np.integer],
    default: int,
    *,
    rounding: bool = False,
) -> np.ndarray:
    """A per-point integer column of length n, range-checked against `dtype`."""
    if values is None:
        return np.full(n, default, dtype=dtype)
    arr = _check_length(path, name, np.asarray(values), n)
    if arr.dtype.kind not in "biuf":
        raise InputError(path, f"{name} must be numeric, got dtype {arr.dtype}")
    if arr.dtype.kind == "f":
        if not np.all(np.isfinite(arr)):
            raise InputError(path, f"{name} has NaN or infinite values")
        if rounding:
            arr = np.round(arr)
        elif not np.array_equal(arr, np.round(arr)):
            raise InputError(path, f"{name} must hold whole numbers")
    info = np.iinfo(dtype)
    if n and (arr.min() < info.min or arr.max() > info.max):
        raise InputError(
            path, f"{name} values {arr.min()}..{arr.max()} do not fit {np.dtype(dtype).name}"
        )
    return arr.astype(dtype)


MERGE_CHUNK = 1_000_000  # points per chunk when files are concatenated


class LasAppender:
    """One LAS / LAZ file written from part files as they come (a tiled run appends each tile's
    part once the tiles before it are in), with the coordinate system `wkt` in its header when
    given. The parts share one scale and offset. LAZ parts into a
    LAZ file are joined chunk by chunk, their compressed bytes copied (`laz_chunks`); other parts
    are copied a million points at a time through laspy. Written through `<path>.partial`,
    renamed by `close`; `abort` leaves nothing."""

    def __init__(self, path: str | Path, wkt: str | None = None):
        self.path = Path(path)
        self.wkt = wkt  # a coordinate system for the header (a WKT VLR)
        self.partial = self.path.with_suffix(self.path.suffix + ".partial")
        self.count = 0
        self._file = None
        self._join: LazJoin | None = None
        self._writer = None
        self._first: Path | None = None
        self._scales = self._offsets = None

    def append(self, part: Path) -> None:
        part = Path(part)
        joined = None
        if self._file is None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._file = open(self.partial, "wb")  # noqa: SIM115 (closed by close / abort)
            joined = _joinable(part) if self.path.suffix.lower() == ".laz" else None
            if joined is not None:
                self._join = LazJoin(self._file, self.wkt)
        if self._join is not None:
            self._join.add(joined or LazPart.read(part))
            self.count = self._join.count
        else:
            self._copy_points(part)

    def _copy_points(self, part: Path) -> None:
        with laspy.open(part) as reader:
            header = reader.header
            if self._writer is None:
                header = copy.deepcopy(header)  # recounted on close
                if self.wkt and not _has_wkt(header):
                    header.vlrs.append(WktCoordinateSystemVlr(self.wkt))
                    header.global_encoding.wkt = True
                self._writer = laspy.open(
                    self._file, mode="w", header=header,
                    do_compress=self.path.suffix.lower() == ".laz", closefd=False,
                )  # fmt: skip
                self._first, self._scales, self._offsets = part, header.scales, header.offsets
            elif not (np.array_equal(header.scales, self._scales)
                      and np.array_equal(header.offsets, self._offsets)):  # fmt: skip
                raise ValueError(f"{part}: scale or offset differs from {self._first}")
            for chunk in reader.chunk_iterator(MERGE_CHUNK):
                self._writer.write_points(chunk)
                self.count += len(chunk)

    def close(self) -> int:
        """Finish the file under its name; the points written (0: nothing was appended, and
        no file is made)."""
        if self._file is None:
            return 0
        if self._join is not None:
            self._join.finish()
        elif self._writer is not None:
            self._writer.close()
        self._file.close()
        self._writer = self._file = self._join = None
        os.replace(self.partial, self.path)
        return self.count

    def abort(self) -> None:
        for handle in (self._writer, self._file):
            try:
                if handle is not None:
                    handle.close()
            except Exception:  # already failing: the partial file goes either way
                pass
        self._writer = self._file = self._join = None
        self.partial.unlink(missing_ok=True)


def _joinable(part: Path) -> LazPart | None:
    """The part, read for joining, where its compressed chunks can be copied as they are
    (`laz_chunks`); None where they cannot."""
    try:
        return LazPart.read(part)
    except ValueError:
        return None
