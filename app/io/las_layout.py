"""LAS / LAZ layout: every count and offset of the header, and a LAZ file's chunk table, checked
against the file's size before laspy or lazrs reads anything.

laspy trusts the header: told 4,294,967,295 VLRs or EVLRs it reads that many (nothing, past the
end of the file, for minutes). lazrs trusts the chunk table: a garbage chunk count or byte count is
allocated as given (the process aborts), and variable-size chunks without a chunk table (LASzip's
old point-wise compression) end in a Rust panic. So a field the file cannot hold is one InputError
line naming the field here; what passes cannot make laspy hang or lazrs allocate beyond the file.
A bad signature or a file too short for a header is left to laspy's own error.
"""

from __future__ import annotations

import struct
from pathlib import Path
from typing import BinaryIO

import lazrs

from app.core.errors import InputError
from app.io.point_files import is_native_panic, one_line

_MIN_SIZE = 227  # LAS 1.0-1.2 header; laspy refuses anything shorter itself
_HEADER_SIZES = {0: 227, 1: 227, 2: 227, 3: 235, 4: 375, 5: 393}  # by LAS 1.x minor version
_VLR_HEADER = 54  # bytes of a VLR before its payload
_EVLR_HEADER = 60  # bytes of an extended VLR before its payload
# bytes per point record of each point data format (LAS 1.4 R15, table 7 onwards)
_POINT_SIZES = {0: 20, 1: 28, 2: 26, 3: 34, 4: 57, 5: 63, 6: 30, 7: 36, 8: 38, 9: 59, 10: 67}
_LASZIP_USER_ID = b"laszip encoded"
_LASZIP_RECORD_ID = 22204
_POINTWISE = 1  # LASzip compressors: 1 point-wise (no chunks), 2 point-wise chunked, 3 layered
_CHUNKED = (2, 3)
_VARIABLE_CHUNKS = 0xFFFFFFFF  # chunk size that means "variable-size chunks, sizes in the table"
_RECOMPRESS = "recompress it with a current LASzip or PDAL"


def check_las_layout(path: Path) -> None:
    """Raise InputError when a header count or offset does not fit the file (LAZ: or its chunk
    table is missing where needed, or claims more than the file holds)."""
    size = path.stat().st_size
    with open(path, "rb") as f:
        head = f.read(max(_HEADER_SIZES.values()))
        if len(head) < _MIN_SIZE or head[:4] != b"LASF":
            return
        major, minor = head[24], head[25]
        if major != 1 or minor not in _HEADER_SIZES:
            raise InputError(
                path, f"not a LAS/LAZ file: version {major}.{minor} is not LAS 1.0-1.5"
            )
        header_size, data_start, vlr_count = struct.unpack_from("<HII", head, 94)
        format_byte, record_length, legacy_count = struct.unpack_from("<BHI", head, 104)
        if header_size > size:
            raise InputError(
                path, f"header size {header_size:,} bytes is larger than the file ({size:,} bytes)"
            )
        if data_start > size:
            raise InputError(
                path,
                f"header says the point data starts at byte {data_start:,} "
                f"but the file has only {size:,} bytes",
            )
        between = max(data_start - header_size, 0)
        if vlr_count * _VLR_HEADER > between:
            raise InputError(
                path,
                f"header says {vlr_count:,} variable-length records but the file has only "
                f"{between:,} bytes after the header (before the point data)",
            )
        compressed = format_byte & 0xC0 == 0x80  # bit 7 without bit 6, as laspy reads it
        point_format = format_byte & 0x3F
        if point_format not in _POINT_SIZES:
            raise InputError(path, f"point data format {point_format} is not one of LAS 0-10")
        if record_length < _POINT_SIZES[point_format]:
            raise InputError(
                path,
                f"point record length {record_length} bytes is shorter than point format "
                f"{point_format} needs ({_POINT_SIZES[point_format]} bytes)",
            )
        point_count = legacy_count
        if minor >= 4 and header_size >= _HEADER_SIZES[4] and len(head) >= _HEADER_SIZES[4]:
            evlr_start, evlr_count, point_count = struct.unpack_from("<QIQ", head, 235)
            _check_evlrs(path, size, evlr_start, evlr_count)
        if not compressed:
            available = size - data_start
            needed = point_count * record_length
            if needed > available:
                raise InputError(
                    path,
                    f"truncated: header says {point_count:,} points of {record_length} bytes "
                    f"({needed:,} bytes) but the file has only {available:,} bytes of point data",
                )
            return
        f.seek(header_size)
        laszip = _laszip_record(f.read(between), vlr_count)
        if laszip is not None:
            _check_laz(path, f, size, data_start, point_count, laszip)


def _check_evlrs(path: Path, size: int, start: int, count: int) -> None:
    if not count:
        return
    available = max(size - start, 0)
    if count * _EVLR_HEADER > available:
        raise InputError(
            path,
            f"header says {count:,} extended variable-length records from byte {start:,} "
            f"but the file has only {available:,} bytes there",
        )


def _laszip_record(vlrs: bytes, count: int) -> bytes | None:
    """Payload of the LASzip VLR, or None (laspy then names what is missing)."""
    pos = 0
    for _ in range(count):  # at most len(vlrs) / 54 records: checked against the file above
        if pos + _VLR_HEADER > len(vlrs):
            return None
        user_id = vlrs[pos + 2 : pos + 18].split(b"\0")[0]
        record_id, length = struct.unpack_from("<HH", vlrs, pos + 18)
        payload = vlrs[pos + _VLR_HEADER : pos + _VLR_HEADER + length]
        if user_id == _LASZIP_USER_ID and record_id == _LASZIP_RECORD_ID and len(payload) >= 16:
            return payload
        pos += _VLR_HEADER + length
    return None


def _check_laz(
    path: Path, f: BinaryIO, size: int, data_start: int, point_count: int, laszip: bytes
) -> None:
    compressor = struct.unpack_from("<H", laszip, 0)[0]
    chunk_size = struct.unpack_from("<I", laszip, 12)[0]
    variable = chunk_size == _VARIABLE_CHUNKS
    if compressor == _POINTWISE:
        if variable:  # lazrs panics on the first point
            raise InputError(
                path,
                "LAZ with variable-size chunks and no chunk table (point-wise compression of an "
                f"old LASzip), which lazrs cannot read; {_RECOMPRESS}",
            )
        return
    if compressor not in _CHUNKED:
        return  # lazrs names the compressor it does not support
    written, table_start = _chunk_table_start(f, size, data_start)
    if table_start is None:
        if variable:  # lazrs needs the table to know where a chunk ends
            where = (
                f"its offset {written:,} leaves no room for one in the file's {size:,} bytes"
                if written > data_start
                else f"its offset is {written} and the file's last 8 bytes do not point to one"
            )
            raise InputError(
                path, f"LAZ with variable-size chunks but no chunk table ({where}); {_RECOMPRESS}"
            )
        return  # fixed-size chunks decompress without a table
    f.seek(table_start)
    chunk_count = struct.unpack("<I", f.read(8)[4:])[0]
    data_bytes = max(table_start - data_start - 8, 0)
    most = (point_count + 1) if variable else (-(-point_count // max(chunk_size, 1)) + 1)
    if chunk_count > min(data_bytes, most):
        raise InputError(
            path,
            f"LAZ chunk table at byte {table_start:,} claims {chunk_count:,} chunks for "
            f"{point_count:,} points in {data_bytes:,} bytes of compressed data",
        )
    if chunk_count == 0:
        if point_count:
            raise InputError(
                path, f"LAZ chunk table lists no chunks but the header says {point_count:,} points"
            )
        return
    _check_chunk_entries(path, f, data_start, data_bytes, point_count, laszip, variable)


def _chunk_table_start(f: BinaryIO, size: int, data_start: int) -> tuple[int, int | None]:
    """(offset as written, where lazrs will find the chunk table or None): the offset at the start
    of the point data or, when the writer could not go back to fill it in (-1), the one in the
    file's last 8 bytes; None unless the table's 8-byte head lies after the points' start."""
    f.seek(data_start)
    raw = f.read(8)
    if len(raw) < 8:
        return 0, None
    written = start = int.from_bytes(raw, "little", signed=True)
    if start <= data_start and size >= 8:
        f.seek(size - 8)
        start = int.from_bytes(f.read(8), "little", signed=True)
    return written, (start if data_start < start <= size - 8 else None)


def _check_chunk_entries(
    path: Path,
    f: BinaryIO,
    data_start: int,
    data_bytes: int,
    point_count: int,
    laszip: bytes,
    variable: bool,
) -> None:
    """The table's chunks must cover the header's points within the compressed bytes: lazrs
    buffers a chunk's byte count as given, and runs past the table's end (panics) when a
    variable-size table holds fewer points than the header."""
    f.seek(data_start)
    try:
        entries = lazrs.read_chunk_table(f, lazrs.LazVlr(laszip))
    except BaseException as exc:
        if not (isinstance(exc, Exception) or is_native_panic(exc)):
            raise
        if not variable:
            return  # fixed-size chunks decompress without a table
        raise InputError(path, f"cannot read the LAZ chunk table: {one_line(exc)}") from exc
    table_bytes = sum(byte_count for _, byte_count in entries)
    if table_bytes > data_bytes:
        raise InputError(
            path,
            f"LAZ chunk table says the chunks take {table_bytes:,} bytes but the file has only "
            f"{data_bytes:,} bytes of compressed points",
        )
    table_points = sum(points for points, _ in entries)
    if table_points < point_count:
        raise InputError(
            path,
            f"LAZ chunk table holds {table_points:,} points but the header says {point_count:,}",
        )
