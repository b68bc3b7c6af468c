"""Limits every number and name from outside is held to, so that a request can reach neither
SQLite's 64-bit integers nor the operating system's name limits with a value past them (which
would be an OverflowError or ENAMETOOLONG deep inside, not an answer naming the field)."""

from __future__ import annotations

INT64_MAX = 2**63 - 1  # SQLite INTEGER, numpy int64
INT64_MIN = -(2**63)
NAME_MAX_BYTES = 255  # one path component (Linux NAME_MAX), UTF-8 encoded
PATH_MAX_BYTES = 4096  # a whole path (Linux PATH_MAX)


def path_length_problem(path: str) -> str | None:
    """Why PATH is too long for the file system (one line), or None when it is not."""
    size = len(path.encode("utf-8", errors="surrogateescape"))
    if size > PATH_MAX_BYTES:
        return f"is {size} bytes long; paths may have at most {PATH_MAX_BYTES}"
    parts = path.replace("\\", "/").split("/")
    size = max(len(p.encode("utf-8", errors="surrogateescape")) for p in parts)
    if size > NAME_MAX_BYTES:
        return f"has a {size}-byte name in it; names may have at most {NAME_MAX_BYTES} bytes"
    return None
