"""Small point-cloud files as other tools write them, or as they arrive broken: made in a temp dir
by the reader tests and by bench/security.py (nothing downloaded, nothing binary committed).

- `write_uppercase_pcd`: a PCD with PDAL's upper-case field names (`X Y Z INTENSITY ...`).
- `write_laz_without_chunk_table`: a LAZ as an old LASzip wrote it: point-wise compression, chunk
  size "variable", no chunk table (lazrs panics on its first point).
- `write_las_with_garbage_vlr_count`: a LAS whose header claims 4,294,967,295 VLRs (laspy reads
  them one by one, past the end of the file, for minutes).
"""

from __future__ import annotations

import io
import struct
from pathlib import Path

import laspy
import numpy as np

GARBAGE_VLR_COUNT = 0xFFFFFFFF
UPPERCASE_PCD_FIELDS = "X Y Z INTENSITY RGB GpsTime Classification"
_LASZIP_USER_ID = b"laszip encoded"


def uppercase_pcd_table(n: int = 50) -> np.ndarray:
    """The points `write_uppercase_pcd` writes (structured, little-endian, in field order)."""
    i = np.arange(n)
    table = np.zeros(
        n,
        dtype=[
            ("X", "<f8"),
            ("Y", "<f8"),
            ("Z", "<f8"),
            ("INTENSITY", "<u2"),
            ("RGB", "<u4"),
            ("GpsTime", "<f8"),
            ("Classification", "<u1"),
        ],
    )
    table["X"] = 500_000.125 + i * 0.5
    table["Y"] = 5_400_000.25 - i * 0.25
    table["Z"] = 100.0 + (i % 7) * 0.125
    table["INTENSITY"] = i * 100
    table["RGB"] = (i << 16) | (2 * i << 8) | (3 * i)
    table["GpsTime"] = 1.3e9 + i * 0.01
    table["Classification"] = i % 3 + 1
    return table


def write_uppercase_pcd(path: str | Path, binary: bool) -> Path:
    """A PCD v0.7 with upper-case field names, `DATA binary` or `DATA ascii`."""
    path = Path(path)
    table = uppercase_pcd_table()
    sizes = " ".join(str(table.dtype[name].itemsize) for name in table.dtype.names or ())
    types = " ".join({"f": "F", "u": "U"}[table.dtype[n].kind] for n in table.dtype.names or ())
    head = (
        "# .PCD v0.7 - Point Cloud Data file format\n"
        "VERSION 0.7\n"
        f"FIELDS {UPPERCASE_PCD_FIELDS}\n"
        f"SIZE {sizes}\n"
        f"TYPE {types}\n"
        f"COUNT {' '.join('1' * len(table.dtype.names or ()))}\n"
        f"WIDTH {len(table)}\n"
        "HEIGHT 1\n"
        "VIEWPOINT 0 0 0 1 0 0 0\n"
        f"POINTS {len(table)}\n"
        f"DATA {'binary' if binary else 'ascii'}\n"
    )
    if binary:
        body = table.tobytes()
    else:
        text = io.StringIO()
        formats = ["%.17g" if table.dtype[n].kind == "f" else "%d" for n in table.dtype.names or ()]
        np.savetxt(text, table, fmt=formats, delimiter=" ")
        body = text.getvalue().encode("ascii")
    path.write_bytes(head.encode("ascii") + body)
    return path


def write_laz_without_chunk_table(path: str | Path) -> Path:
    """A LAZ like an old LASzip's: the points one point-wise compressed stream (no chunk table
    offset, no chunk table) and the LASzip VLR saying compressor 1 (point-wise) with chunk size
    0xFFFFFFFF, which lazrs reads as variable-size chunks."""
    path = Path(path)
    n = 300
    rng = np.random.default_rng(7)
    las = laspy.LasData(laspy.LasHeader(point_format=3, version="1.2"))
    las.x = rng.uniform(0, 50, n)
    las.y = rng.uniform(0, 50, n)
    las.z = rng.uniform(0, 5, n)
    las.classification = rng.integers(1, 3, n).astype(np.uint8)
    buffer = io.BytesIO()
    las.write(buffer, do_compress=True)  # one chunk (fewer points than the chunk size)
    data = bytearray(buffer.getvalue())
    data_start = struct.unpack_from("<I", data, 96)[0]
    table_start = struct.unpack_from("<q", data, data_start)[0]
    laszip = _vlr_payload_offset(data, _LASZIP_USER_ID)
    struct.pack_into("<H", data, laszip, 1)  # compressor: point-wise
    struct.pack_into("<I", data, laszip + 12, 0xFFFFFFFF)  # chunk size: variable
    # the one chunk's stream is what a point-wise writer wrote: drop the offset and the table
    path.write_bytes(bytes(data[:data_start]) + bytes(data[data_start + 8 : table_start]))
    return path


def write_las_with_garbage_vlr_count(path: str | Path) -> Path:
    """A small valid LAS whose header then says 4,294,967,295 variable-length records."""
    path = Path(path)
    las = laspy.LasData(laspy.LasHeader(point_format=3, version="1.2"))
    las.x = np.arange(20, dtype=np.float64)
    las.y = np.zeros(20)
    las.z = np.ones(20)
    buffer = io.BytesIO()
    las.write(buffer)
    data = bytearray(buffer.getvalue())
    struct.pack_into("<I", data, 100, GARBAGE_VLR_COUNT)  # "number of variable length records"
    path.write_bytes(bytes(data))
    return path


def _vlr_payload_offset(data: bytes | bytearray, user_id: bytes) -> int:
    """Byte offset of the payload of the first VLR with `user_id`."""
    pos = struct.unpack_from("<H", data, 94)[0]  # header size
    for _ in range(struct.unpack_from("<I", data, 100)[0]):
        length = struct.unpack_from("<H", data, pos + 20)[0]
        if bytes(data[pos + 2 : pos + 18]).split(b"\0")[0] == user_id:
            return pos + 54
        pos += 54 + length
    raise ValueError(f"no VLR {user_id!r}")
