"""The viewer on a long survey in a real browser (`bench.scale viewer-browser`): a real
`mmsclean serve` on loopback with the survey imported (its `prepare:viewer` job done), and
Debian's Chromium (headless, software WebGL: SwiftShader) driven by Playwright, logged in as a
user is; the page's websocket frames are decoded as they arrive (viser's wire format).
Measured per open of /viewer: seconds from the page's request to its websocket (the viewer's
page and scripts loaded), to the overview's points received and drawn, and to the tile in focus
drawn (drawn: the point cloud's message received, then three animation frames of the page, so
the frame that draws it has passed); then the camera panned by right-button drags across the
canvas, round a square, as a user moves about the street: per drag, the seconds to the next
tile drawn; the server's memory after each. Last, a flight along the drive: the viewer's "Ahead
100 m" button (`app/viewer/drive.py`) pressed from the drive's start to its end, as an operator
goes through a survey: per step, the seconds to the next tile drawn and the server's memory.

Run through `python -m bench.scale viewer-browser` (the longest of --lengths).
"""

from __future__ import annotations

import statistics
import time
from pathlib import Path

from bench.common import process_memory_mb
from bench.viewer_fly import imported
from tests.api.server import Server
from tests.viewer.wire import decode_frame, is_point_cloud

CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader"]
VIEWPORT = {"width": 1280, "height": 800}
SCENE_TIMEOUT_S = 300.0
DRAG_TIMEOUT_S = 30.0
# resolves after three animation frames: the frame that handles a received message has drawn
AFTER_DRAWING = (
    "() => new Promise(done => requestAnimationFrame(() => requestAnimationFrame(() => "
    "requestAnimationFrame(() => done(null)))))"
)


class Tab:
    """One logged-in viewer tab; its point cloud messages time-stamped."""

    def __init__(self, browser, server: Server, token: str, survey_id: int):
        self.context = browser.new_context(viewport=VIEWPORT)
        self.context.add_cookies([{"name": "mmsclean_token", "value": token, "url": server.url}])
        self.page = self.context.new_page()
        self.clouds: list[float] = []  # arrival time of each point cloud message
        self.socket_at: float | None = None  # when the page opened its websocket
        self.errors: list[str] = []
        self.page.on("pageerror", lambda exc: self.errors.append(str(exc)))
        self.page.on("websocket", self._watch)
        self.url = f"{server.url}/viewer?survey={survey_id}"

    def _watch(self, ws) -> None:
        self.socket_at = self.socket_at or time.perf_counter()

        def received(payload) -> None:
            if not isinstance(payload, bytes):
                return
            arrived = time.perf_counter()
            # viser batches messages: one frame may carry the overview and the tile in focus
            clouds = sum(1 for m in decode_frame(payload) if is_point_cloud(m))
            self.clouds.extend([arrived] * clouds)

        ws.on("framereceived", received)

    def drawn_after(self, count: int, timeout: float) -> float | None:
        """Time at which the `count`-th point cloud message has been drawn (None: timeout)."""
        deadline = time.perf_counter() + timeout
        while len(self.clouds) < count:
            if time.perf_counter() > deadline:
                return None
            self.page.wait_for_timeout(20)
        self.page.evaluate(AFTER_DRAWING)
        return time.perf_counter()

    def close(self) -> None:
        self.context.close()


def open_scene(tab: Tab) -> dict:
    """The page requested; the overview's points drawn, then the tile in focus drawn."""
    started = time.perf_counter()
    tab.page.goto(tab.url)
    overview = tab.drawn_after(1, SCENE_TIMEOUT_S)
    tile = tab.drawn_after(2, SCENE_TIMEOUT_S)
    if overview is None or tile is None:
        raise RuntimeError(f"no scene within {SCENE_TIMEOUT_S:.0f} s ({len(tab.clouds)} clouds)")
    return {"socket_s": (tab.socket_at or started) - started,
            "overview_received_s": tab.clouds[0] - started, "overview_s": overview - started,
            "tile_s": tile - started}  # fmt: skip


# drag directions in turn (screen x, y): the camera goes round a square about where it started
SQUARE = [(-1, 0)] * 3 + [(0, -1)] * 3 + [(1, 0)] * 3 + [(0, 1)] * 3


def pan(tab: Tab, server: Server, drags: int, pixels: int) -> dict:
    """Right-button drags of `pixels` across the canvas's middle (the camera pans along the
    screen, round a square); per drag, seconds from the release to the next tile drawn."""
    box = tab.page.locator("canvas").first.bounding_box()
    x, y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    seconds, rss, anon, stayed = [], [], [], 0
    for k in range(drags):
        dx, dy = (pixels / 2 * v for v in SQUARE[k % len(SQUARE)])
        before = len(tab.clouds)
        tab.page.mouse.move(x - dx, y - dy)
        tab.page.mouse.down(button="right")
        tab.page.mouse.move(x + dx, y + dy, steps=10)
        tab.page.mouse.up(button="right")
        released = time.perf_counter()
        drawn = tab.drawn_after(before + 1, DRAG_TIMEOUT_S)
        if drawn is None:
            stayed += 1
            continue
        seconds.append(drawn - released)
        r, a = process_memory_mb(server.process.pid)
        rss.append(r)
        anon.append(a)
    return {
        "drags": drags, "tiles": len(seconds), "no_new_tile": stayed,
        "tile_s_median": statistics.median(seconds) if seconds else None,
        "tile_s_max": max(seconds) if seconds else None,
        "rss_mb_max": max(rss) if rss else None, "anon_mb_max": max(anon) if anon else None,
    }  # fmt: skip


def fly_along(tab: Tab, server: Server, steps: int) -> dict:
    """The Drive folder opened, its slider at the start, then "Ahead 100 m" pressed `steps`
    times; per press, seconds to the next tile drawn, the server's memory after it."""
    tab.page.get_by_text("Drive", exact=True).click()
    ahead = tab.page.get_by_role("button", name="Ahead 100 m")
    ahead.wait_for(timeout=10_000)
    seconds, rss, anon, stayed = [], [], [], 0
    for _ in range(steps):
        before = len(tab.clouds)
        ahead.click()
        pressed = time.perf_counter()
        drawn = tab.drawn_after(before + 1, DRAG_TIMEOUT_S)
        if drawn is None:
            stayed += 1
            continue
        seconds.append(drawn - pressed)
        r, a = process_memory_mb(server.process.pid)
        rss.append(r)
        anon.append(a)
    return {
        "steps": steps, "tiles": len(seconds), "no_new_tile": stayed,
        "tile_s_median": statistics.median(seconds) if seconds else None,
        "tile_s_p90": statistics.quantiles(seconds, n=10)[-1] if len(seconds) > 1 else None,
        "tile_s_max": max(seconds) if seconds else None,
        "rss_mb_max": max(rss) if rss else None, "anon_mb_max": max(anon) if anon else None,
    }  # fmt: skip


def measure(source: Path, drags: int = 12, pixels: int = 500, steps: int = 40) -> dict:
    """Import `source` into a fresh server, wait for its map, open it twice in the browser and
    pan along it in the second tab."""
    from playwright.sync_api import sync_playwright

    if not CHROMIUM.is_file():
        raise SystemExit(f"Debian's Chromium is not installed at {CHROMIUM} (make system-deps)")
    with imported(source) as (server, record, prepared_s, token):
        survey_id = record["id"]
        with sync_playwright() as playwright:
            browser = playwright.chromium.launch(
                executable_path=str(CHROMIUM), headless=True, args=CHROMIUM_ARGS
            )
            first_tab = Tab(browser, server, token, survey_id)
            first = open_scene(first_tab)
            first_tab.close()
            tab = Tab(browser, server, token, survey_id)
            again = open_scene(tab)
            after_open = process_memory_mb(server.process.pid)
            flight = pan(tab, server, drags, pixels)
            drive = fly_along(tab, server, steps)
            errors = first_tab.errors + tab.errors
            tab.close()
            browser.close()
    return {"points": int(record["point_count"]), "prepared_s": prepared_s, "first": first,
            "again": again, "after_open_mb": after_open, "flight": flight, "drive": drive,
            "page_errors": errors}  # fmt: skip
