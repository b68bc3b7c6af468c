"""Bounded types for every number and name a request carries (path, query and body alike).

Routes and request models use these instead of bare `int` / `float` / `str`, so a value no
column, array or file system can hold is a 422 naming the field, never an OverflowError,
"Python int too large to convert to SQLite INTEGER" or ENAMETOOLONG inside a route:

- `Id`: a record id, 1 .. 2**63 - 1 (SQLite INTEGER PRIMARY KEY).
- `CellId`: a packed pillar id, any signed 64-bit integer (`app.geometry.pillars`).
- `Version`, `Offset`: non-negative 64-bit counters; `Int64` any other stored integer.
- `Coordinate`: world metres, finite and inside the store's pillar grid, whose cell ids pack a
  32-bit cell index per axis (about +-429,000 km around the origin).
- `FileName`, `FilePath` (`ImportPath`): names of at most 255 bytes, paths of at most 4096.
"""

from __future__ import annotations

import math
from typing import Annotated

from annotated_types import Ge, Le, MinLen
from pydantic import AfterValidator, AllowInfNan

from app.core.limits import INT64_MAX, INT64_MIN, NAME_MAX_BYTES, path_length_problem
from app.store.pillar_labels import STORE_GRID

_LOWEST, _HIGHEST = STORE_GRID.addressable()
WORLD_MIN = math.ceil(float(_LOWEST.max()) * 10) / 10  # metres, on both axes (readable in
WORLD_MAX = math.floor(float(_HIGHEST.min()) * 10) / 10  # messages: -429496729.6 .. 429496729.4)

Int64 = Annotated[int, Ge(INT64_MIN), Le(INT64_MAX)]
Id = Annotated[int, Ge(1), Le(INT64_MAX)]
CellId = Int64
Version = Annotated[int, Ge(0), Le(INT64_MAX)]
Offset = Annotated[int, Ge(0), Le(INT64_MAX)]
Coordinate = Annotated[float, AllowInfNan(False), Ge(WORLD_MIN), Le(WORLD_MAX)]


def _fits_path(value: str) -> str:
    problem = path_length_problem(value)
    if problem is not None:
        raise ValueError(problem)
    return value


def _fits_name(value: str) -> str:
    size = len(value.encode("utf-8", errors="surrogateescape"))
    if size > NAME_MAX_BYTES:
        raise ValueError(f"is {size} bytes long; names may have at most {NAME_MAX_BYTES}")
    return value


FileName = Annotated[str, MinLen(1), AfterValidator(_fits_name)]
FilePath = Annotated[str, MinLen(1), AfterValidator(_fits_path)]
ImportPath = FilePath
