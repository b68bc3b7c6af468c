"""The dashboard: `/` is its single page, `/assets/<file>` its scripts and styles, all plain files
from `frontend_assets/` (no build step). Everything it shows comes from the JSON API, so these
routes need no login and stay out of the OpenAPI schema.

The page sends a Content-Security-Policy that allows only this origin: nothing is fetched from a
CDN, and an injected script or a foreign form target would be refused by the browser.
"""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter
from fastapi.responses import FileResponse

import app as app_package
from app.core.errors import NotFoundError

router = APIRouter(include_in_schema=False)

MEDIA_TYPES = {
    ".html": "text/html; charset=utf-8",
    ".js": "text/javascript; charset=utf-8",  # module scripts need a JavaScript type
    ".css": "text/css; charset=utf-8",
    ".svg": "image/svg+xml",
    ".png": "image/png",
    ".ico": "image/x-icon",
}
CSP = (
    "default-src 'self'; script-src 'self'; style-src 'self'; img-src 'self' data: blob:; "
    "connect-src 'self'; frame-ancestors 'none'; base-uri 'none'; form-action 'self'"
)
HEADERS = {
    "Content-Security-Policy": CSP,
    "X-Content-Type-Options": "nosniff",
    "Cache-Control": "no-cache",  # revalidate (ETag) so an upgrade never mixes old and new files
}


def assets_dir() -> Path:
    """`frontend_assets/` beside the package (a checkout, an editable install), else in the
    working directory (the Docker image installs the package and copies the assets to its
    working directory)."""
    candidates = (Path(app_package.__file__).resolve().parents[1], Path.cwd())
    for root in candidates:
        folder = root / "frontend_assets"
        if (folder / "index.html").is_file():
            return folder.resolve()
    return (candidates[0] / "frontend_assets").resolve()


def asset(name: str) -> FileResponse:
    folder = assets_dir()
    target = (folder / name).resolve()
    # resolved, so `..` and symlinks cannot leave the folder
    if not target.is_relative_to(folder) or not target.is_file():
        raise NotFoundError(f"no dashboard file {name}")
    media = MEDIA_TYPES.get(target.suffix.lower(), "application/octet-stream")
    return FileResponse(target, media_type=media, headers=HEADERS)


@router.get("/")
def index() -> FileResponse:
    """The dashboard page."""
    return asset("index.html")


@router.get("/assets/{name:path}")
def assets(name: str) -> FileResponse:
    """A script, style sheet or image of the dashboard."""
    return asset(name)
