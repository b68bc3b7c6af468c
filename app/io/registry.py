"""The reader factory: format name -> reader function `(Path) -> Survey`.

Readers are imported on first use so `mmsclean info x.las` never imports torch or open3d.
"""

from __future__ import annotations

import importlib
from pathlib import Path

from app.core.errors import InputError, UnknownFormatError
from app.io.survey import Survey

# format name -> "module:function"
_READERS: dict[str, str] = {
    "kitti-raw": "app.io.kitti_raw:read_kitti_raw",
    "semantickitti": "app.io.semantickitti:read_semantickitti",
    "las": "app.io.las:read_las",
    "ply": "app.io.ply:read_ply",
    "pcd": "app.io.pcd:read_pcd",
    "sim": "app.io.sim:read_sim",
}

FORMATS: tuple[str, ...] = tuple(_READERS)


def register_reader(name: str, target: str) -> None:
    """Add a format as `"module:function"` (plug-ins)."""
    _READERS[name] = target


def available_formats() -> tuple[str, ...]:
    return tuple(_READERS)


def open_survey(source: str | Path, fmt: str) -> Survey:
    """Open SOURCE with the reader of format FMT; frames stay on disk until asked for."""
    if fmt not in _READERS:
        known = ", ".join(sorted(_READERS))
        raise UnknownFormatError(f"unknown format {fmt!r}; known formats: {known}")
    path = Path(source)
    if not path.exists():
        raise InputError(path, "does not exist")
    module_name, func_name = _READERS[fmt].split(":")
    reader = getattr(importlib.import_module(module_name), func_name)
    return reader(path)
