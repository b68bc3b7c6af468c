"""LAZ files joined by copying their compressed chunks: no point is decompressed or compressed.

LASzip compresses points in chunks that each start afresh, listed in a chunk table at the end of
the point data (point count and byte count per chunk). Files of one point layout, scale and
offset are therefore joined by copying every file's chunk bytes in turn and writing one table
for all of them, with variable-size chunks (the last chunk of each file is short), as the LAZ
specification allows and COPC files use (tested here with lazrs, whole and in chunks; lazrs
0.8.2's seek into any variable-chunk file lands on wrong points, so this project never seeks). A
tiled run's maps are appended this way: re-encoding every point of a survey in the process that
assembles the tiles took it a good part of a core, beside the tile workers.

Header fields the join changes (point counts, points by return, bounds) are written at their
fixed places of the LAS 1.4 header (ASPRS LAS 1.4 R15, table 3).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import laspy
import lazrs
import numpy as np

VARIABLE_CHUNKS = 0xFFFFFFFF  # the LASzip VLR's chunk size that says chunks vary in size
LASZIP_USER = b"laszip encoded"
LASZIP_RECORD = 22204
VLR_HEADER = 54  # bytes before a VLR's record data
CHUNK_SIZE_AT = 12  # bytes into the LASzip record: compressor, coder, version (4), options (4)
COPY_BLOCK = 16 * 2**20

# LAS header places (bytes from the file's start)
LEGACY_COUNT, LEGACY_BY_RETURN, BOUNDS = 107, 111, 179  # u32, 5 x u32, max/min x, y, z (f64)
COUNT_14, BY_RETURN_14 = 247, 255  # u64, 15 x u64 (LAS 1.4)


@dataclass(frozen=True)
class LazPart:
    """What joining needs of one LAZ file: where its chunks are and how many points each has."""

    path: Path
    header: laspy.LasHeader
    record: bytes  # the LASzip VLR's record data
    chunks_start: int  # first byte of the chunks (after the 8-byte chunk table offset)
    chunks_end: int  # first byte of the chunk table
    table: list[tuple[int, int]]  # per chunk: (points, bytes)

    @classmethod
    def read(cls, path: Path) -> LazPart:
        """The file's header and chunk table; a ValueError names a file that is not a chunked
        LAZ file joining can copy (no LASzip record, extended VLRs after the points)."""
        path = Path(path)
        with laspy.open(path) as reader:
            header = reader.header
        laszip = [v for v in header.vlrs if v.user_id == "laszip encoded"]
        if not laszip:
            raise ValueError(f"{path}: not LAZ compressed (no LASzip record)")
        if header.number_of_evlrs:
            raise ValueError(f"{path}: extended VLRs after the points; not joined chunk by chunk")
        record = bytes(laszip[0].record_data)
        vlr = lazrs.LazVlr(record)
        with path.open("rb") as f:
            f.seek(header.offset_to_point_data)
            table_at = int.from_bytes(f.read(8), "little", signed=True)
            if table_at < 0:  # written as a stream: the offset is the file's last 8 bytes
                f.seek(-8, 2)
                table_at = int.from_bytes(f.read(8), "little", signed=True)
            f.seek(table_at)
            entries = lazrs.read_chunk_table_only(f, vlr)
        return cls(
            path, header, record, header.offset_to_point_data + 8, table_at,
            _point_counts(entries, vlr, header.point_count, path),
        )  # fmt: skip


def _point_counts(
    entries: list[tuple[int, int]], vlr: lazrs.LazVlr, total: int, path: Path
) -> list[tuple[int, int]]:
    """(points, bytes) per chunk: a table of fixed-size chunks holds byte counts only (its
    last chunk holds what is left)."""
    if vlr.uses_variable_size_chunks():
        table = [(int(n), int(b)) for n, b in entries]
    else:
        size = int(vlr.chunk_size())
        counts = [size] * len(entries)
        if counts:
            counts[-1] = total - size * (len(entries) - 1)
        table = [(n, int(b)) for n, (_, b) in zip(counts, entries, strict=True)]
    if sum(n for n, _ in table) != total or any(n <= 0 for n, _ in table):
        raise ValueError(f"{path}: its chunk table does not add up to its {total} points")
    return table


WKT_USER, WKT_RECORD = b"LASF_Projection", 2112  # the OGC WKT coordinate system record
HEADER_SIZE_AT, POINT_DATA_AT, VLR_COUNT_AT, ENCODING_AT = 94, 96, 100, 6  # u16, u32, u32, u16
WKT_BIT = 1 << 4  # global encoding: the CRS is WKT (required for point formats 6-10)


def wkt_vlr(wkt: str) -> bytes:
    """The OGC WKT coordinate system VLR (LAS 1.4 R15, 2.5.1): header and null-ended text."""
    data = wkt.encode("utf-8") + b"\0"
    if len(data) > 0xFFFF:
        raise ValueError(f"a WKT of {len(data)} bytes does not fit one VLR")
    description = b"OGC Transformation Record".ljust(32, b"\0")
    return struct.pack("<H16sHH32s", 0, WKT_USER, WKT_RECORD, len(data), description) + data


def vlrs_end(head: bytes | bytearray) -> tuple[int, bool]:
    """Where a LAS header's VLRs end, and whether one of them is a WKT record."""
    (at,) = struct.unpack_from("<H", head, HEADER_SIZE_AT)
    (count,) = struct.unpack_from("<I", head, VLR_COUNT_AT)
    has_wkt = False
    for _ in range(count):
        user, record, length = struct.unpack_from("<16sHH", head, at + 2)
        has_wkt |= user.rstrip(b"\0") == WKT_USER and record == WKT_RECORD
        at += VLR_HEADER + length
    return at, has_wkt


class LazJoin:
    """One LAZ file written from parts as they come (`add`), chunk bytes copied; `finish` writes
    the chunk table and the header's counts and bounds. With `wkt`, the first part's header gets
    that coordinate system (a WKT VLR, unless it has one)."""

    def __init__(self, file: BinaryIO, wkt: str | None = None):
        self.file = file
        self.wkt = wkt
        self._head = b""  # the header and VLRs written, as written
        self.first: LazPart | None = None
        self.record = b""  # the first part's LASzip record, chunks made variable
        self.table: list[tuple[int, int]] = []
        self.count = 0
        self.by_return = np.zeros(15, dtype=np.uint64)
        self.mins = np.full(3, np.inf)
        self.maxs = np.full(3, -np.inf)

    def add(self, part: LazPart) -> None:
        if self.first is None:
            self._start(part)
        elif not (np.array_equal(part.header.scales, self.first.header.scales)
                  and np.array_equal(part.header.offsets, self.first.header.offsets)):  # fmt: skip
            raise ValueError(f"{part.path}: scale or offset differs from {self.first.path}")
        elif not same_layout(self.first.header, part.header):
            raise ValueError(f"{part.path}: point layout differs from {self.first.path}")
        with part.path.open("rb") as f:
            f.seek(part.chunks_start)
            _copy(f, self.file, part.chunks_end - part.chunks_start)
        self.table.extend(part.table)
        self.count += part.header.point_count
        returns = np.asarray(part.header.number_of_points_by_return, dtype=np.uint64)
        self.by_return[: len(returns)] += returns
        if part.header.point_count:
            self.mins = np.minimum(self.mins, part.header.mins)
            self.maxs = np.maximum(self.maxs, part.header.maxs)

    def _start(self, part: LazPart) -> None:
        """The first part's header and VLRs, its LASzip record saying variable-size chunks."""
        with part.path.open("rb") as f:
            head = bytearray(f.read(part.header.offset_to_point_data))
        if self.wkt:
            head = with_wkt(head, self.wkt)
        at = _laszip_record_at(head, part.path)
        head[at + CHUNK_SIZE_AT : at + CHUNK_SIZE_AT + 4] = struct.pack("<I", VARIABLE_CHUNKS)
        self.file.write(bytes(head))
        self._head = bytes(head)
        self.file.write(struct.pack("<q", -1))  # the chunk table's place, known at the end
        self.first = part
        self.record = bytes(head[at : at + len(part.record)])

    def finish(self) -> int:
        """The chunk table and the header completed; the points written."""
        if self.first is None:
            return 0
        table_at = self.file.tell()
        lazrs.write_chunk_table(self.file, self.table, lazrs.LazVlr(self.record))
        end = self.file.tell()
        (start,) = struct.unpack_from("<I", self._head, POINT_DATA_AT)
        self.file.seek(start)
        self.file.write(struct.pack("<q", table_at))
        self._write_header()
        self.file.seek(end)
        return self.count

    def _write_header(self) -> None:
        header = self.first.header  # type: ignore[union-attr]
        if self.count:
            bounds = np.column_stack([self.maxs, self.mins]).ravel()  # max x, min x, max y ...
            self.file.seek(BOUNDS)
            self.file.write(struct.pack("<6d", *bounds))
        legacy = header.point_format.id < 6 and self.count <= 0xFFFFFFFF
        self.file.seek(LEGACY_COUNT)
        self.file.write(struct.pack("<I", self.count if legacy else 0))
        self.file.seek(LEGACY_BY_RETURN)
        five = self.by_return[:5] if legacy and self.by_return.max() <= 0xFFFFFFFF else [0] * 5
        self.file.write(struct.pack("<5I", *[int(n) for n in five]))
        if header.version.minor >= 4:
            self.file.seek(COUNT_14)
            self.file.write(struct.pack("<Q", self.count))
            self.file.seek(BY_RETURN_14)
            self.file.write(struct.pack("<15Q", *[int(n) for n in self.by_return]))


def with_wkt(head: bytearray, wkt: str) -> bytearray:
    """A LAS header and its VLRs (up to the point data) with a WKT VLR added after the others,
    the offset to the points, the VLR count and the WKT bit set to match; unchanged where it
    has a WKT record already."""
    end, has_wkt = vlrs_end(head)
    if has_wkt:
        return head
    record = wkt_vlr(wkt)
    out = bytearray(head[:end]) + record + head[end:]
    (offset,) = struct.unpack_from("<I", out, POINT_DATA_AT)
    (count,) = struct.unpack_from("<I", out, VLR_COUNT_AT)
    (encoding,) = struct.unpack_from("<H", out, ENCODING_AT)
    struct.pack_into("<I", out, POINT_DATA_AT, offset + len(record))
    struct.pack_into("<I", out, VLR_COUNT_AT, count + 1)
    struct.pack_into("<H", out, ENCODING_AT, encoding | WKT_BIT)
    return out


def same_layout(a: laspy.LasHeader, b: laspy.LasHeader) -> bool:
    """Records of `b` are laid out as those of `a`: one version and point format (with its
    extra bytes); `LazJoin.add` checks the scale and offset apart, to say which differs."""
    return a.version == b.version and a.point_format == b.point_format


def _laszip_record_at(head: bytearray, path: Path) -> int:
    """Where the LASzip VLR's record data starts in the header bytes."""
    at = head.find(LASZIP_USER)
    while at >= 0:
        start = at - 2  # the VLR begins with two reserved bytes
        (record_id,) = struct.unpack_from("<H", head, start + 18)
        if record_id == LASZIP_RECORD:
            return start + VLR_HEADER
        at = head.find(LASZIP_USER, at + 1)
    raise ValueError(f"{path}: no LASzip record in its header")


def _copy(source: BinaryIO, dest: BinaryIO, n: int) -> None:
    while n > 0:
        block = source.read(min(n, COPY_BLOCK))
        if not block:
            raise ValueError(f"{getattr(source, 'name', 'a LAZ part')}: shorter than its chunks")
        dest.write(block)
        n -= len(block)
