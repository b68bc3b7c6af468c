"""Browser fixtures for the viewer tests: Debian's Chromium driven by Playwright (headless,
software WebGL; never a downloaded browser), a server with the sample survey whose scenes stay
under 100,000 points, and a logged-in viewer tab.

Screenshots go to the test's tmp dir (`artefacts`); `save_screenshot(..., docs=NAME)` also
writes `docs/NAME` when MMSCLEAN_UPDATE_SCREENSHOTS=1 or the file is missing, so ordinary runs
leave the checkout clean.
"""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import httpx
import pytest

from tests.api.server import Server

ROOT = Path(__file__).resolve().parents[2]
CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader"]
VIEWER_VIEWPORT = {"width": 1280, "height": 800}
VIEWER_OVERVIEW_POINTS = 60_000  # overview + focus tile <= 100,000 points in the browser
VIEWER_TILE_POINTS = 35_000
SCENE_TIMEOUT_MS = 180_000  # first open builds the sample's map on two shared cores


@pytest.fixture(scope="session")
def viewer_browser() -> Iterator[object]:
    if not CHROMIUM.is_file():
        pytest.skip(f"Debian's Chromium is not installed at {CHROMIUM} (make system-deps)")
    sync_api = pytest.importorskip("playwright.sync_api", reason="the playwright package")
    with sync_api.sync_playwright() as playwright:
        browser = playwright.chromium.launch(
            executable_path=str(CHROMIUM), headless=True, args=CHROMIUM_ARGS
        )
        yield browser
        browser.close()


@pytest.fixture(scope="module")
def viewer_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    """A server with the sample survey, small browser scenes, no retraining, one worker."""
    data_dir = tmp_path_factory.mktemp("viewer-e2e") / "var"
    env = {
        "MMSCLEAN_VIEWER_OVERVIEW_POINTS": str(VIEWER_OVERVIEW_POINTS),
        "MMSCLEAN_VIEWER_TILE_POINTS": str(VIEWER_TILE_POINTS),
        "MMSCLEAN_RETRAIN_EVERY": "0",
        "MMSCLEAN_WORKERS": "1",
    }
    running = Server(data_dir, env=env).start()
    yield running
    running.stop()


@pytest.fixture
def artefacts(tmp_path: Path) -> Path:
    folder = tmp_path / "screenshots"
    folder.mkdir()
    return folder


def save_screenshot(page, artefacts: Path, name: str, docs: str | None = None) -> Path:
    path = artefacts / f"{name}.png"
    page.screenshot(path=str(path))
    if docs:
        target = ROOT / "docs" / docs
        if os.environ.get("MMSCLEAN_UPDATE_SCREENSHOTS") or not target.exists():
            target.parent.mkdir(exist_ok=True)
            page.screenshot(path=str(target))
    return path


WAIT_S = 30.0


def shift_drag(page, start: tuple[float, float], end: tuple[float, float]) -> None:
    """A shift-drag across the canvas (the viewer's rectangle), in small mouse steps."""
    page.keyboard.down("Shift")
    page.mouse.move(*start)
    page.mouse.down()
    page.mouse.move(*end, steps=12)
    page.mouse.up()
    page.keyboard.up("Shift")


def wait_until(what: str, check, timeout: float = WAIT_S):
    """check()'s first truthy value, polled every 0.2 s; AssertionError naming `what` after
    `timeout` seconds."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = check()
        if value:
            return value
        time.sleep(0.2)
    raise AssertionError(f"timed out waiting for {what}")


def close_notifications(page) -> None:
    """Close the "software WebGL" notice before a screenshot (best effort)."""
    for close in page.locator(".mantine-Notification-root button").all():
        with contextlib.suppress(Exception):  # already gone
            close.click(timeout=2000)


def api_login(server: Server, username: str, password: str) -> str:
    response = httpx.post(
        f"{server.url}/auth/login", json={"username": username, "password": password}
    )
    response.raise_for_status()
    return response.json()["access_token"]


@pytest.fixture
def open_viewer(viewer_browser, viewer_server: Server, artefacts: Path) -> Iterator[Callable]:
    """open_viewer(username, password, survey_id) -> a tab on /viewer, logged in through the
    API (the login cookie set in a fresh context), once the viewer's GUI is there. Any
    JavaScript error on the page fails the test."""
    contexts, errors = [], []

    def open_tab(username: str, password: str, survey_id: int = 1):
        token = api_login(viewer_server, username, password)
        context = viewer_browser.new_context(viewport=VIEWER_VIEWPORT)
        context.set_default_timeout(30_000)
        context.add_cookies([{"name": "mmsclean_token", "value": token, "url": viewer_server.url}])
        contexts.append(context)
        tab = context.new_page()
        tab.on("pageerror", lambda exc: errors.append(str(exc)))
        tab.goto(f"{viewer_server.url}/viewer?survey={survey_id}")
        tab.get_by_text(f"Logged in as {username}").wait_for(timeout=SCENE_TIMEOUT_MS)
        return tab

    yield open_tab
    for i, context in enumerate(contexts):
        for tab in context.pages:
            tab.screenshot(path=str(artefacts / f"last-page-{i}.png"))
        context.close()
    assert not errors, errors
