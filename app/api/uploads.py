"""Getting survey files onto the server safely: uploads streamed to disk under a size limit,
zip archives unpacked without escaping their folder (import paths are confined to the import
root by `app.io.import_root`).

Every refusal is one line naming the upload or zip member: an upload or unpacked archive over
`max_upload_mb` (413), a malformed archive (422).
"""

from __future__ import annotations

import shutil
import stat
import zipfile
import zlib
from pathlib import Path, PurePosixPath

from fastapi import Request

from app.api.disk_space import is_disk_full
from app.core.errors import ConfigError, InputError, UploadTooLargeError
from app.io.detect import FILE_SUFFIXES, detect_format

UPLOAD_SUFFIXES = (*sorted(FILE_SUFFIXES), ".zip")
MAX_ZIP_MEMBERS = 500_000  # a 5,000-frame KITTI drive with images has ~30,000
COPY_CHUNK = 1 << 20
SKIPPED_ZIP_FOLDERS = ("__MACOSX/",)  # resource forks macOS adds to archives


def check_upload_name(filename: str) -> str:
    """The upload's suffix (lower case) after checking FILENAME is a plain, known file name."""
    name = filename.strip()
    if not name or name != Path(name).name or "\\" in name or name.startswith("."):
        raise ConfigError("filename", f"{filename!r} must be a plain file name like survey.laz")
    suffix = Path(name).suffix.lower()
    if suffix not in UPLOAD_SUFFIXES:
        raise ConfigError("filename", f"{filename!r}: expected one of {', '.join(UPLOAD_SUFFIXES)}")
    return suffix


def limit_bytes(limit_mb: float) -> int:
    return int(limit_mb * 1024 * 1024)


async def receive_upload(request: Request, dest: Path, name: str, limit_mb: float) -> int:
    """Stream the request body to DEST; stops reading and deletes DEST as soon as the body
    passes the limit. Returns the byte count."""
    limit = limit_bytes(limit_mb)
    declared = request.headers.get("content-length", "")
    if declared.isdigit() and int(declared) > limit:
        raise UploadTooLargeError(name, limit_mb)
    size = 0
    try:
        with dest.open("wb") as out:
            async for chunk in request.stream():
                size += len(chunk)
                if size > limit:
                    raise UploadTooLargeError(name, limit_mb)
                out.write(chunk)
    except BaseException:
        dest.unlink(missing_ok=True)
        raise
    if size == 0:
        dest.unlink(missing_ok=True)
        raise InputError(name, "the upload is empty (send the file as the request body)")
    return size


def _member_path(archive: str, info: zipfile.ZipInfo) -> PurePosixPath:
    """The member's relative path; refuses absolute paths, `..`, drive letters, backslashes,
    symbolic links and encrypted members."""
    raw = info.filename
    path = PurePosixPath(raw)
    escapes = (
        "\\" in raw
        or path.is_absolute()
        or ".." in path.parts
        or (path.parts and ":" in path.parts[0])
    )
    if escapes:
        raise InputError(archive, f"zip member {raw!r} points outside the archive's folder")
    if stat.S_ISLNK(info.external_attr >> 16):
        raise InputError(archive, f"zip member {raw!r} is a symbolic link; links are refused")
    if info.flag_bits & 0x1:
        raise InputError(archive, f"zip member {raw!r} is encrypted")
    return path


def extract_zip(archive: Path, dest: Path, name: str, limit_mb: float) -> Path:
    """Unpack ARCHIVE into DEST (checked member by member before anything is written), delete
    the archive and return the survey folder (see `survey_folder`)."""
    limit = limit_bytes(limit_mb)
    try:
        zf = zipfile.ZipFile(archive)
    except (zipfile.BadZipFile, OSError) as exc:
        raise InputError(name, f"is not a readable zip archive ({exc})") from None
    with zf:
        infos = [i for i in zf.infolist() if not i.filename.startswith(SKIPPED_ZIP_FOLDERS)]
        if len(infos) > MAX_ZIP_MEMBERS:
            raise InputError(name, f"has {len(infos)} members, more than {MAX_ZIP_MEMBERS}")
        members = [(_member_path(name, info), info) for info in infos]
        if sum(info.file_size for _, info in members) > limit:
            raise UploadTooLargeError(f"{name} (unpacked)", limit_mb)
        if not any(not info.is_dir() for _, info in members):
            raise InputError(name, "the archive holds no files")
        dest.mkdir(parents=True, exist_ok=True)
        written = 0
        for path, info in members:
            target = dest.joinpath(*path.parts)
            try:
                if info.is_dir():
                    target.mkdir(parents=True, exist_ok=True)
                    continue
                target.parent.mkdir(parents=True, exist_ok=True)
                with zf.open(info) as src, target.open("wb") as out:
                    while chunk := src.read(COPY_CHUNK):
                        written += len(chunk)
                        if written > limit:  # sizes in the directory can lie
                            raise UploadTooLargeError(f"{name} (unpacked)", limit_mb)
                        out.write(chunk)
            except (zipfile.BadZipFile, zlib.error, EOFError, NotImplementedError, OSError) as exc:
                if is_disk_full(exc):
                    raise  # the server's problem (507), not the archive's
                raise InputError(name, f"zip member {info.filename!r}: {exc}") from None
    archive.unlink(missing_ok=True)
    return survey_folder(dest)


def survey_folder(folder: Path) -> Path:
    """Archives usually wrap the survey in one or more top folders: follow the chain of single
    subfolders down to the first folder holding more, then take the deepest folder of the chain
    whose format can be told (else FOLDER itself, so the error names the archive's top)."""
    chain = [folder]
    while True:
        entries = [e for e in chain[-1].iterdir() if not e.name.startswith(".")]
        if len(entries) != 1 or not entries[0].is_dir() or entries[0].is_symlink():
            break
        chain.append(entries[0])
    for candidate in reversed(chain):
        try:
            detect_format(candidate)
        except InputError:
            continue
        return candidate
    return folder


def remove_tree(folder: Path) -> None:
    """Delete a folder the server made (links inside are removed, never followed)."""
    shutil.rmtree(folder, ignore_errors=True)
