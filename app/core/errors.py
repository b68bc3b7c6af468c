"""One error hierarchy for the whole product.

Every error a user can cause (bad file, bad field, unknown format) is a `MmscleanError` whose
message is one line naming the file or field and the problem. The CLI prints that line and exits
with `exit_code`; the API answers with `http_status` and the same message.
"""

from __future__ import annotations

from pathlib import Path


class MmscleanError(Exception):
    """Base class: a problem the user can fix, reported in one line."""

    exit_code: int = 1
    http_status: int = 400

    def __init__(self, message: str):
        super().__init__(message)
        self.message = message

    def __str__(self) -> str:
        return self.message


class InputError(MmscleanError):
    """A file or folder given as input is missing, unreadable or malformed."""

    exit_code = 2
    http_status = 422

    def __init__(self, path: str | Path | None, problem: str):
        self.path = None if path is None else Path(path)
        super().__init__(f"{path}: {problem}" if path is not None else problem)


class UnknownFormatError(MmscleanError):
    """A format name that no reader or writer knows."""

    exit_code = 2
    http_status = 422


class ConfigError(MmscleanError):
    """A configuration field with an invalid value."""

    exit_code = 2
    http_status = 422

    def __init__(self, field: str, problem: str):
        self.field = field
        super().__init__(f"{field}: {problem}")


class NotFoundError(MmscleanError):
    """A requested record (survey, job, label, model) does not exist."""

    exit_code = 3
    http_status = 404


class ConflictError(MmscleanError):
    """A write based on a stale version, or a duplicate of something that must be unique."""

    exit_code = 4
    http_status = 409


class StaleWriteError(ConflictError):
    """A write based on an old version; `current` is the state now, for the 409 answer."""

    def __init__(self, message: str, current: object):
        super().__init__(message)
        self.current = current


class PermissionDeniedError(MmscleanError):
    """The user is known but their role does not allow the action."""

    exit_code = 5
    http_status = 403


class DependencyMissingError(MmscleanError):
    """A file the product needs at run time (model weights, a system library) is absent."""

    exit_code = 6
    http_status = 503


class PathOutsideRootError(MmscleanError):
    """A path that resolves (symlinks followed) outside the folder the server may read from."""

    exit_code = 2
    http_status = 400

    def __init__(self, path: str | Path, root: str | Path):
        self.path = Path(path)
        super().__init__(f"{path}: outside the allowed import root {root}")


class UploadTooLargeError(MmscleanError):
    """An upload (or the files a zip would unpack to) larger than `max_upload_mb`."""

    exit_code = 2
    http_status = 413

    def __init__(self, name: str, limit_mb: float):
        self.limit_mb = limit_mb
        super().__init__(f"{name}: larger than the upload limit of {limit_mb:g} MB")


class DiskFullError(MmscleanError):
    """The data directory's disk has (almost) no space left: a write is refused (507) before it
    half-happens; reads go on."""

    exit_code = 7
    http_status = 507

    def __init__(self, free_mb: float):
        self.free_mb = free_mb
        super().__init__(f"the data directory's disk is full ({free_mb:.0f} MB free)")
