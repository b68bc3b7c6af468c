"""Import paths confined to the import root: a path outside it, or a folder inside it holding a
link that leads outside, is refused (PathOutsideRootError, 400 in the API) before any reader
opens it. The API's import route and the `import:survey` job both check with this."""

from __future__ import annotations

import os
from pathlib import Path

from app.core.errors import ConfigError, InputError, PathOutsideRootError
from app.core.limits import path_length_problem


def resolve_import_path(raw: str, root: Path) -> Path:
    """RAW (absolute, or relative to ROOT) with symlinks resolved; it and every link inside it
    must stay within ROOT (PathOutsideRootError), and it must exist (InputError)."""
    if not raw.strip():
        raise ConfigError("path", "must not be empty")
    root = root.resolve()
    try:
        given = Path(raw)
        resolved = (given if given.is_absolute() else root / given).resolve()
        too_long = path_length_problem(str(resolved))
        if too_long is not None:  # ENAMETOOLONG from every stat below otherwise
            raise ConfigError("path", f"{_short(raw)} {too_long}")
        if not resolved.is_relative_to(root):
            raise PathOutsideRootError(raw, root)
        if not resolved.exists():
            raise InputError(raw, "does not exist")
        if resolved.is_dir():
            check_links_inside(resolved, root)
    except (ValueError, OSError) as exc:  # a name the file system refuses, a loop of links
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else exc
        raise ConfigError("path", f"{_short(raw)} is not a usable path ({reason})") from None
    return resolved


def _short(raw: str, keep: int = 80) -> str:
    """RAW quoted for a message, cut to its first KEEP characters (a 5,000-character path
    must not make a 5,000-character error line)."""
    return repr(raw if len(raw) <= keep else raw[:keep] + "...")


def check_links_inside(folder: Path, root: Path) -> None:
    """A reader follows links, so a folder inside ROOT holding a link to /etc is refused."""
    for dirpath, dirnames, filenames in os.walk(folder, followlinks=False):
        for name in (*dirnames, *filenames):
            entry = Path(dirpath) / name
            if entry.is_symlink() and not entry.resolve().is_relative_to(root):
                raise PathOutsideRootError(entry, root)
