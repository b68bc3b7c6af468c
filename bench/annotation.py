"""A timed labelling session in a real browser (issue 20): a scripted annotator labels a 100 m
street of a real SemanticKITTI sequence with the viewer's tools, as a person would.

A real `mmsclean serve` on loopback with the sequence imported; Debian's Chromium (headless,
software WebGL) driven by Playwright, logged in as an annotator. The page's websocket frames are
watched both ways: the camera it sends (so the script knows where every pillar is on screen,
projected as the server projects it: `app.viewer.picking.ScreenCamera`) and the colour updates
it receives. The annotator's answers are the sequence's reference pillar classes
(`bench.labelling_loop.reference_answers`: SemanticKITTI labels through the shared pillar rule).

The street: the pillars within 50 m along and 15 m across the drive of the sequence's middle
pose. The camera: the top view (T) zoomed (mouse wheel) until it is about 80 m above the street.
The session, in the order an annotator works (label broadly, then carve out and correct what the
colours show wrong):

1. Fill (G, a click on the road, Enter): the ground.
2. With "Apply to: unlabelled only", the objects of the minority classes (every non-ground
   class but the street's most common one): per connected group of one class (30 pillars or
   more, largest first) a rectangle (shift-drag round its box) where the group fills most of
   its box or where no other pillar the lock lets through lies in it (what the colours show an
   annotator), else a lasso (a Ctrl-drag round its convex hull, at a hand's pace); Enter
   where the selection is previewed.
3. The majority class in one rectangle over the whole street (unlabelled only), with the
   height slice's lower end dragged to 0.5 m above the ground (so the road the fill did not
   reach is not shown and not selected); then the slice back.
4. Corrections, in two passes: the non-ground pillars still unlabelled first (what no
   selection saw, under a canopy: outlined with "select hidden points too" ticked), so the
   street is complete first; then the wrong labels. Per pass, per connected group of pillars
   with one wrong label (or none) that should be one class, largest first: "Apply to" locked
   to that label (its neighbours keep theirs) and the group outlined as in 2 (8 pillars or
   more); then the brush (B, radius 0.4 m) on each such pillar left.

It stops when the corrections are done or after 10 minutes of interaction (the height slice's
drags count). Per tool: interactions, pillars labelled (given a label or another one), seconds
of interaction (from the first input event to the colours received and drawn) and pillars per
minute; the latency from the committing input (the click, or Enter) to the colours received
in the page, p50 / p90; the server's own time to answer each message of the session, from its
log (`MMSCLEAN_VIEWER_LOG_SLOWER_MS=0` logs every one); the share of non-ground pillars
labelled and when all of them were; the class accuracy of the labels against the reference
and their confusion.

The annotator's side (this script, Playwright's driver, the browser) runs at a lower priority
(nice 10), the server it starts first at the normal one: the browser's software WebGL takes
both cores of this machine while it draws, this script decodes every colour update it watches,
and an operator's browser runs on the operator's machine, not the server's.

    MMSCLEAN_REAL_DATA=../shared/data .venv/bin/python -m bench.annotation [--sequence 08]
"""

from __future__ import annotations

import argparse
import os
import re
import statistics
import sys
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

import msgspec
import numpy as np
import psutil
from scipy import ndimage
from scipy.spatial import ConvexHull, QhullError, cKDTree

from app.core.labels import PillarClass
from app.io import open_survey
from app.io.accumulate import accumulate
from app.store.pillar_labels import STORE_GRID
from app.viewer.modes.pillars import APPLY_TO, HEIGHT_SLICE
from app.viewer.picking import ScreenCamera
from app.viewer.pillar_colors import DISPLAY_NAMES
from bench.common import append_results, markdown_table
from bench.labelling_loop import reference_answers
from bench.viewer import login
from bench.viewer_browser import AFTER_DRAWING, CHROMIUM, CHROMIUM_ARGS, VIEWPORT
from tests.api.server import Server
from tests.viewer.wire import decode_frame, is_color_update, is_point_cloud

STREET_ALONG, STREET_ACROSS = 50.0, 15.0  # metres each way from the middle pose
CAMERA_HEIGHT = 80.0  # metres above the street, top view
BUDGET_S = 600.0  # seconds of interaction
GROUP_MIN = 30  # pillars: smaller objects of the minority classes are left to the corrections
LASSO_STEP_PX = 12.0  # pixels between the pointer's positions along a lasso
LASSO_STEP_MS = 40  # between them (a 100-pixel loop is drawn in about a second)
LASSO_OUT_PX = 4.0  # the lasso runs this far outside the group's hull
CORRECT_MIN = 8  # pillars: a wrong group this large is outlined, smaller ones are brushed
SLICE_LOW = 0.5  # metres above the ground: the height slice's lower end for the majority class
APPLY_ALL, APPLY_UNLABELLED = APPLY_TO[:2]
RECT_FILL = 0.6  # a group filling this share of its box gets a rectangle, else a lasso
SAFE_PX = 6  # pixels round a rectangle where no pillar the lock lets through may be harmed
BRUSH_RADIUS = 0.4
PANEL_X = 0.72  # share of the canvas width left of the GUI panel (clicks stay left of it)
ANSWER_TIMEOUT_S = 15.0  # the longest wait for an interaction's colours
BRUSH_TIMEOUT_S = 3.0  # ... for a brush's (its answer may repeat the status line before it)
DEAD_ENDS = ("Nothing to label", "No visible points", "no shown pillar", "met no point")
CLASS_KEYS = {0: "1", 1: "2", 2: "3", 3: "4"}  # PillarClass -> hotkey
PASSWORD = "password-123"
CLIENT_NICE = 10  # the annotator's side (this script, the browser) yields the cores to the
# server: on this 2-core machine the browser's software WebGL takes both while it draws, and
# an operator's browser runs on the operator's machine, not the server's
OVERVIEW_POINTS = 500_000  # the default: every pillar of a ten-frame sequence is shown
TILE_POINTS = 100_000  # the tile in focus, kept small for software WebGL


CLASS_LABELS = tuple(DISPLAY_NAMES[int(c)].lower() for c in PillarClass)  # the viewer's names
MAP_CLOUDS = ("/pillars/overview", "/pillars/tile")  # the labelling view's point clouds
PARAGRAPHS = "() => Array.from(document.querySelectorAll('p'), p => p.innerText)"


class Page:
    """The viewer tab: the camera it last sent and the colour updates it received."""

    def __init__(self, browser, server: Server, token: str, survey_id: int):
        self.context = browser.new_context(viewport=VIEWPORT)
        self.context.add_cookies([{"name": "mmsclean_token", "value": token, "url": server.url}])
        self.page = self.context.new_page()
        self.camera: dict | None = None
        self.colours: list[float] = []  # arrival of each frame with new colours (or points)
        self.clouds: list[float] = []  # of each frame with a point cloud
        self.errors: list[str] = []
        self.page.on("pageerror", lambda exc: self.errors.append(str(exc)))
        self.page.on("websocket", self._watch)
        self.page.goto(f"{server.url}/viewer?survey={survey_id}")

    def _watch(self, ws) -> None:
        def received(payload) -> None:
            if not isinstance(payload, bytes):
                return
            messages = decode_frame(payload)
            clouds = [m for m in messages if is_point_cloud(m)]
            map_clouds = any(m["name"] in MAP_CLOUDS for m in clouds)  # not the preview's
            if map_clouds or any(is_color_update(m) for m in messages):  # classes hidden:
                self.colours.append(time.perf_counter())  # a write resends the cloud whole
            if clouds:
                self.clouds.append(time.perf_counter())

        def sent(payload) -> None:
            if not isinstance(payload, bytes):
                return
            try:
                message = msgspec.msgpack.decode(payload)
            except msgspec.DecodeError:
                return
            if isinstance(message, dict) and message.get("type") == "ViewerCameraMessage":
                self.camera = message

        ws.on("framereceived", received)
        ws.on("framesent", sent)

    def screen(self) -> ScreenCamera:
        """The camera the page last sent, as the server projects with it."""
        fields = ("wxyz", "position", "fov", "image_width", "image_height")
        return ScreenCamera.of(SimpleNamespace(**{k: self.camera[k] for k in fields}))

    def canvas(self) -> dict:
        return self.page.locator("canvas").first.bounding_box()

    def settle(self, quiet_s: float = 0.3) -> None:
        """Wait until no colour update has arrived for `quiet_s` (one write recolours the
        overview and the tile in focus: the second may come after the first is counted)."""
        while True:
            count = len(self.colours)
            self.page.wait_for_timeout(quiet_s * 1000)
            if len(self.colours) == count:
                return

    def texts(self) -> set[str]:
        """The page's text lines (one script in the page: a locator query per line costs a
        round trip each, and the script polls this while timing)."""
        return set(self.page.evaluate(PARAGRAPHS))

    def colours_after(
        self, since: int, shown: set[str], preview_ok: bool = False,
        timeout: float = ANSWER_TIMEOUT_S,
    ) -> float | None:  # fmt: skip
        """When the first colour update after the `since`-th arrived, once drawn; None: none
        came (a new status line says nothing was labelled or a preview waits for Enter, or
        time ran out). `shown`: the page's text lines before the interaction."""
        deadline = time.perf_counter() + timeout
        while len(self.colours) <= since:
            if time.perf_counter() > deadline:
                return None
            new = " ".join(self.texts() - shown)
            if any(t in new for t in DEAD_ENDS):
                return None
            if not preview_ok and "pillars selected" in new:
                return None
            self.page.wait_for_timeout(40)
        self.page.evaluate(AFTER_DRAWING)
        return self.colours[since]


class Tally:
    def __init__(self) -> None:
        self.rows: dict[str, dict] = {}
        self.latency: list[float] = []  # seconds from the committing input to the colours
        self.complete_at: tuple[float, float] | None = None  # (seconds, accuracy) when every
        # non-ground pillar first held a label

    def add(self, tool: str, seconds: float, pillars: int, latency: float | None) -> None:
        """One interaction; latency: from its committing input to the colours received."""
        row = self.rows.setdefault(tool, {"n": 0, "s": 0.0, "pillars": 0})
        row["n"] += 1
        row["s"] += seconds
        row["pillars"] += pillars
        if latency is not None:
            self.latency.append(latency)

    @property
    def seconds(self) -> float:
        return sum(r["s"] for r in self.rows.values())


def street_pillars(sequence: Path, origin: np.ndarray) -> dict:
    """The street's pillars: store ids, reference class, local centre and top."""
    answers = reference_answers(sequence)
    survey = open_survey(sequence, "semantickitti")
    poses = survey.poses()
    middle = poses[len(poses) // 2]
    heading = poses[-1][:2, 3] - poses[0][:2, 3]
    heading = heading / max(np.linalg.norm(heading), 1e-9)
    amap = accumulate(survey, origin=origin)
    world_xy = np.asarray(amap.world_xy, dtype=np.float64)
    cells = STORE_GRID.point_cell_ids(world_xy)
    uniq, inverse = np.unique(cells, return_inverse=True)
    top = np.full(len(uniq), -np.inf)
    np.maximum.at(top, inverse.ravel(), np.asarray(amap.xyz[:, 2], dtype=np.float64))
    centre = STORE_GRID.cell_center(*STORE_GRID.decode(uniq))
    rel = centre - middle[:2, 3]
    along = rel @ heading
    across = rel @ np.array([-heading[1], heading[0]])
    street = (np.abs(along) <= STREET_ALONG) & (np.abs(across) <= STREET_ACROSS)
    pos, found = answers.index(uniq)
    keep = street & found
    return {
        "cells": uniq[keep], "klass": answers.classes[pos[keep]],
        "local": np.column_stack([centre[keep] - origin[:2], top[keep]]),
        "middle": middle[:3, 3] - origin,
    }  # fmt: skip


def labelled(api, survey_id: int, cells: np.ndarray) -> dict[int, int]:
    """cell id -> human label of the street's pillars."""
    x, y = STORE_GRID.cell_center(*STORE_GRID.decode(cells)).T
    tile = api.get(
        f"/surveys/{survey_id}/pillars/labels",
        params={"x0": x.min() - 1, "y0": y.min() - 1, "x1": x.max() + 1, "y1": y.max() + 1,
                "source": "human"},
    ).json()  # fmt: skip
    return dict(zip(tile["cell_id"], tile["label"], strict=True))


def lasso_path(hull: np.ndarray) -> np.ndarray:
    """(n, 2) page pixels a hand follows round a convex hull (its vertices in order): the hull
    pushed LASSO_OUT_PX outwards from its centre, walked every LASSO_STEP_PX, closed."""
    centre = hull.mean(axis=0)
    away = hull - centre
    length = np.maximum(np.linalg.norm(away, axis=1, keepdims=True), 1e-9)
    pushed = hull + away / length * LASSO_OUT_PX
    ring = np.vstack([pushed, pushed[:1]])
    steps = [
        np.linspace(a, b, max(int(np.linalg.norm(b - a) // LASSO_STEP_PX), 1), endpoint=False)
        for a, b in zip(ring[:-1], ring[1:], strict=True)
    ]
    return np.vstack([*steps, ring[-1:]])


def run_session(view: Page, api, survey_id: int, street: dict) -> Tally:
    page, tally = view.page, Tally()
    box = view.canvas()
    cells, klass = street["cells"], street["klass"]
    state = {"labels": {}, "apply_to": APPLY_ALL}

    def to_page(local: np.ndarray) -> np.ndarray:
        """Page pixels of local points (the camera reports its render size, which may differ
        from the canvas's CSS box)."""
        screen = view.screen()
        px, _ = screen.project(np.atleast_2d(local))
        scale = np.array([box["width"] / screen.width, box["height"] / screen.height])
        return px * scale + [box["x"], box["y"]]

    canvas_lo = np.array([box["x"] + 6, box["y"] + 6])
    canvas_hi = np.array([box["x"] + box["width"] * PANEL_X, box["y"] + box["height"] - 6])

    def on_canvas(p: np.ndarray) -> bool:
        return bool((p > canvas_lo).all() and (p < canvas_hi).all())

    def labelled_count() -> int:
        state["labels"] = labelled(api, survey_id, cells)
        return len(state["labels"])

    def current() -> np.ndarray:
        """Each street pillar's human label now (-1: none)."""
        return np.array([state["labels"].get(c, -1) for c in cells.tolist()], dtype=np.int64)

    def act(tool: str, inputs, commit) -> None:
        """Inputs, then the committing input; timed to the colours drawn."""
        view.settle()  # the previous interaction's colours all in, outside the timing
        labelled_count()
        before = dict(state["labels"])
        mark = len(view.colours)
        started = time.perf_counter()
        if inputs() is False:  # the page did not take the inputs: nothing to commit
            page.keyboard.press("Escape")
            tally.add(tool, time.perf_counter() - started, 0, None)
            print(f"{tally.seconds:7.1f} s  {tool:12s} dropped (an input was not taken)")
            return
        shown = view.texts()
        committed = time.perf_counter()
        commit()
        answered = view.colours_after(
            mark, shown, timeout=BRUSH_TIMEOUT_S if tool == "brush" else ANSWER_TIMEOUT_S
        )
        if answered is None and "pillars selected" in " ".join(view.texts() - shown):
            mark = len(view.colours)  # the preview's own colours are not the answer
            page.keyboard.press("Enter")  # a large selection is previewed: apply it
            committed = time.perf_counter()
            answered = view.colours_after(mark, shown, preview_ok=True)
        if answered is not None:  # the colours come before the store's write: wait for it
            deadline = time.perf_counter() + ANSWER_TIMEOUT_S
            while time.perf_counter() < deadline and "batch" not in " ".join(view.texts() - shown):
                page.wait_for_timeout(20)
        done = time.perf_counter()
        if answered is None:
            print("    no colours; the page said:", " / ".join(sorted(view.texts() - shown)))
        latency = None if answered is None else answered - committed
        labelled_count()
        gained = sum(1 for c, v in state["labels"].items() if before.get(c) != v)
        tally.add(tool, done - started, gained, latency)
        now = current()
        if tally.complete_at is None and (now[klass != 0] >= 0).all():
            given = now >= 0
            tally.complete_at = tally.seconds, float((now[given] == klass[given]).mean())
        print(f"{tally.seconds:7.1f} s  {tool:12s} {gained:6d} pillars labelled "
              f"({'no answer' if latency is None else f'{latency * 1000:.0f} ms'})",
              flush=True)  # fmt: skip

    def apply_to(choice: str) -> None:
        """The "Apply to" lock (its clicks are counted in the next interaction's time only
        when they happen inside it: here they are not timed, as a hotkey would not be)."""
        if state["apply_to"] == choice:
            return
        page.locator(f"input:not([type=hidden])[value='{state['apply_to']}']").click()
        page.get_by_role("option", name=choice, exact=True).click()
        page.evaluate("document.activeElement && document.activeElement.blur()")
        state["apply_to"] = choice

    def held_drag(tool: str, key: str, path: np.ndarray, steps: int = 1, pause_ms: int = 0):
        """A drag along `path` (page pixels) with `key` held, committed by its release."""

        def drag() -> None:
            page.keyboard.down(key)
            page.mouse.move(*path[0])
            page.mouse.down()
            for p in path[1:]:
                page.mouse.move(*p, steps=steps)
                if pause_ms:
                    page.wait_for_timeout(pause_ms)

        def release() -> None:
            page.mouse.up()
            page.keyboard.up(key)

        act(tool, drag, release)

    def rectangle(tool: str, lo: np.ndarray, hi: np.ndarray) -> None:
        held_drag(tool, "Shift", np.array([lo, hi]), steps=4)

    def outline(group: np.ndarray, k: int, lock: int) -> None:
        """A group of pillars (to become class k) by a rectangle where one is safe (no other
        pillar in its box that "Apply to" lets through, `lock`: the label it reaches, -1 for
        unlabelled ones, should become something else) or the group fills most of its box,
        else a lasso round its convex hull."""
        corners = to_page(street["local"][group])
        lo, hi = corners.min(axis=0) - 2, corners.max(axis=0) + 2
        try:
            hull = ConvexHull(corners) if len(corners) >= 3 else None
        except QhullError:  # the pillars in a line
            hull = None
        if (
            hull is None
            or hull.volume >= RECT_FILL * float(np.prod(hi - lo))
            or safe(lo, hi, group, k, lock)
        ):
            rectangle("rectangle", lo, hi)
            return
        # Ctrl held, round the group at a hand's pace (the page reports the pointer at 20 Hz)
        held_drag("lasso", "Control", lasso_path(corners[hull.vertices]), pause_ms=LASSO_STEP_MS)

    def safe(lo: np.ndarray, hi: np.ndarray, group: np.ndarray, k: int, lock: int) -> bool:
        """No pillar outside the group within SAFE_PX of the box that the lock lets through
        and that should not become class k (what an annotator sees from the colours)."""
        px = to_page(street["local"])
        near = ((px > lo - SAFE_PX) & (px < hi + SAFE_PX)).all(axis=1)
        near[group] = False
        now = current()
        return not (near & (now == lock) & (klass != k)).any()

    def fits(group: np.ndarray) -> bool:
        corners = to_page(street["local"][group])
        return on_canvas(corners.min(axis=0)) and on_canvas(corners.max(axis=0))

    def whole_street() -> tuple[np.ndarray, np.ndarray]:
        corners = to_page(street["local"])
        return np.maximum(corners.min(axis=0), canvas_lo), np.minimum(
            corners.max(axis=0), canvas_hi
        )

    # 1. fill: the road from the ground pillar near the middle pose with the most ground round it
    ground = np.flatnonzero(klass == 0)
    xy = street["local"][ground, :2]
    close = ground[np.hypot(*(xy - street["middle"][:2]).T) < 15.0]
    tree = cKDTree(xy)
    crowd = np.array([len(n) for n in tree.query_ball_point(street["local"][close, :2], 1.0)])
    seed = close[int(np.argmax(crowd))]
    page.keyboard.press(CLASS_KEYS[0])
    page.keyboard.press("g")
    p = to_page(street["local"][seed])[0]
    act("fill", lambda: None, lambda: page.mouse.click(*p))
    labelled_count()

    # 2. the minority classes' objects, one by one (unlabelled only: the fill's road is kept)
    counts = np.bincount(klass[klass != 0], minlength=4)
    major = int(np.argmax(counts))
    apply_to(APPLY_UNLABELLED)
    minority = np.flatnonzero((klass != 0) & (klass != major) & (current() < 0))
    for k, group in groups(cells, klass, minority, GROUP_MIN):
        if tally.seconds > BUDGET_S:
            break
        if fits(group):
            page.keyboard.press(CLASS_KEYS[k])
            outline(group, k, -1)

    # 3. the majority class: one rectangle over the street with the points near the ground
    #    hidden by the height slice (unlabelled only), then the slice back
    if tally.seconds <= BUDGET_S:
        height_slice(view, SLICE_LOW, tally)
        page.keyboard.press(CLASS_KEYS[major])
        rectangle("rectangle", *whole_street())
        height_slice(view, HEIGHT_SLICE[0], tally)

    # 4. corrections, as the colours show them, in two passes: first the non-ground pillars
    #    still unlabelled (those no selection saw, under a canopy: outlined with "select
    #    hidden points too", the lock keeping the labelled ones), so the street is complete
    #    first; then the wrong labels. Per pass, groups of pillars of one wrong label (or none)
    #    that should be one class, with "Apply to" locked to that label (the neighbours keep
    #    theirs), largest first; then the brush on each such pillar left
    labelled_count()
    print("after the broad strokes:", confusion(klass, current()).tolist(), flush=True)
    radius = page.locator(
        'xpath=//label[normalize-space(.)="Brush radius (m)"]'
        '/ancestor::div[contains(@class,"mantine-Flex-root")][1]//input[not(@type="hidden")]'
    ).last
    radius.fill(str(BRUSH_RADIUS))
    radius.press("Enter")
    page.evaluate("document.activeElement && document.activeElement.blur()")

    def to_correct(unlabelled: bool) -> np.ndarray:
        now = current()
        wrong = (now != klass) & ((klass != 0) | (now >= 0))
        return np.flatnonzero(wrong & ((now < 0) == unlabelled))

    for unlabelled in (True, False):
        if unlabelled:  # only the unlabelled points shown: what lies under a canopy too
            hide_labelled(view, True, tally)
        hidden_too(page, unlabelled)
        for k, was, group in wrong_groups(cells, klass, current(), to_correct(unlabelled)):
            if tally.seconds > BUDGET_S:
                break
            if len(group) >= CORRECT_MIN and fits(group):
                apply_to(APPLY_UNLABELLED if was < 0 else APPLY_TO[2 + was])
                page.keyboard.press(CLASS_KEYS[k])
                outline(group, k, was)
        hidden_too(page, False)
        labelled_count()
        page.keyboard.press("b")
        for i in to_correct(unlabelled):
            if tally.seconds > BUDGET_S:
                break
            was = int(current_label(state, cells[i]))
            if was == klass[i]:
                continue
            p = to_page(street["local"][i])[0]
            if not on_canvas(p):
                continue
            apply_to(APPLY_UNLABELLED if was < 0 else APPLY_TO[2 + was])
            page.keyboard.press(CLASS_KEYS[int(klass[i])])
            act("brush", lambda: None, lambda p=p: page.mouse.click(*p))
        if unlabelled:
            hide_labelled(view, False, tally)
    labelled_count()
    return tally


def hidden_too(page, on: bool) -> None:
    """Tick or untick "Select hidden points too" (the Rectangle folder opened first); not
    timed, as a setting is not an interaction."""
    box = page.get_by_label("Select hidden points too")
    if not box.is_visible():
        page.get_by_text("Rectangle", exact=True).click()
        box.wait_for(state="visible", timeout=5000)
    if box.is_checked() != on:
        box.set_checked(on)
        page.evaluate("document.activeElement && document.activeElement.blur()")


def hide_labelled(view: Page, on: bool, tally: Tally) -> None:
    """Tick (or untick) "Hide <class>" for every pillar class, so that only the unlabelled
    points are shown (the Display folder opened first; the ground, the most points, hidden
    first and shown last), timed until the redrawn points have come."""
    page = view.page
    boxes = [page.get_by_label(f"Hide {name}") for name in CLASS_LABELS]
    if not boxes[0].is_visible():
        page.get_by_text("Display", exact=True).click()
        boxes[0].wait_for(state="visible", timeout=5000)
    view.settle()
    started = time.perf_counter()
    first = len(view.clouds)
    for box in boxes if on else boxes[::-1]:
        if box.is_checked() != on:
            box.set_checked(on)
    page.evaluate("document.activeElement && document.activeElement.blur()")
    deadline = time.perf_counter() + ANSWER_TIMEOUT_S
    while len(view.clouds) == first and time.perf_counter() < deadline:
        page.wait_for_timeout(40)
    while True:  # the last redraw's clouds in (one per toggle the server did not fold)
        count = len(view.clouds)
        page.wait_for_timeout(1000)
        if len(view.clouds) == count:
            break
    page.evaluate(AFTER_DRAWING)
    seconds = time.perf_counter() - started - 1.0  # the last quiet second is not its work
    tally.add("hide classes", seconds, 0, None)
    print(f"{tally.seconds:7.1f} s  {'labelled classes ' + ('hidden' if on else 'shown')}",
          flush=True)  # fmt: skip


def current_label(state: dict, cell: int) -> int:
    return int(state["labels"].get(int(cell), -1))


def height_slice(view: Page, low: float, tally: Tally) -> None:
    """Drag the height slice's lower end to `low` metres above the ground (the Display folder
    opened first), timed until the redrawn points arrive."""
    page = view.page
    track = page.locator(
        'xpath=//label[normalize-space(.)="Height slice (m)"]'
        '/ancestor::div[contains(@class,"mantine-Flex-root")][1]'
        '//div[contains(@class,"multi-slider-track-container")]'
    ).first
    if not track.is_visible():
        page.get_by_text("Display", exact=True).click()
        track.wait_for(state="visible", timeout=5000)
    view.settle()
    started = time.perf_counter()
    clouds = len(view.clouds)
    lane = track.bounding_box()
    thumb = track.locator(".multi-slider-thumb").first.bounding_box()
    lo, hi = HEIGHT_SLICE
    x = lane["x"] + lane["width"] * (low - lo) / (hi - lo)
    page.mouse.move(thumb["x"] + thumb["width"] / 2, thumb["y"] + thumb["height"] / 2)
    page.mouse.down()
    page.mouse.move(x, thumb["y"] + thumb["height"] / 2, steps=2)
    page.mouse.up()
    deadline = time.perf_counter() + ANSWER_TIMEOUT_S
    while len(view.clouds) == clouds and time.perf_counter() < deadline:
        page.wait_for_timeout(40)
    page.evaluate(AFTER_DRAWING)
    tally.add("height slice", time.perf_counter() - started, 0, None)
    print(f"{tally.seconds:7.1f} s  height slice from {low:g} m", flush=True)


def wrong_groups(cells: np.ndarray, klass: np.ndarray, now: np.ndarray, wrong: np.ndarray):
    """(right class, wrong label, indices) of connected groups of wrongly labelled pillars
    sharing both: unlabelled ones first (the street complete first), then largest first."""
    pair = klass[wrong] * 8 + (now[wrong] + 1)  # one code per (right, wrong) pair
    found = [
        (len(g), int(code) // 8, int(code) % 8 - 1, g)
        for code in np.unique(pair).tolist()
        for _, g in groups(cells, np.zeros(len(cells), np.int64), wrong[pair == code], 1)
    ]
    for _, k, was, g in sorted(found, key=lambda f: (f[2] >= 0, -f[0])):
        yield k, was, g


def groups(cells: np.ndarray, klass: np.ndarray, todo: np.ndarray, least: int):
    """(class, indices) of connected groups (8-neighbours) of `todo` pillars of one class,
    `least` or more, largest first: each class's pillars rasterised and labelled."""
    ix, iy = (np.asarray(a, dtype=np.int64) for a in STORE_GRID.decode(cells[todo]))
    ix, iy = ix - ix.min(), iy - iy.min()
    found = []
    for k in np.unique(klass[todo]).tolist():
        raster = np.zeros((ix.max() + 1, iy.max() + 1), dtype=bool)
        mine = klass[todo] == k
        raster[ix[mine], iy[mine]] = True
        component, _ = ndimage.label(raster, structure=np.ones((3, 3)))
        ids = component[ix[mine], iy[mine]]
        sizes = np.bincount(ids)
        for c in np.flatnonzero(sizes >= least):
            if c:
                found.append((int(sizes[c]), k, todo[mine][ids == c]))
    for _, k, members in sorted(found, key=lambda g: -g[0]):
        yield k, members


def zoom_to(view: Page, height: float) -> None:
    """Mouse-wheel steps over the canvas until the camera is about `height` above its focus."""
    box = view.canvas()
    view.page.mouse.move(box["x"] + box["width"] * 0.4, box["y"] + box["height"] / 2)
    for _ in range(60):
        c = view.camera
        distance = float(np.linalg.norm(np.subtract(c["position"], c["look_at"])))
        if abs(distance - height) < 0.08 * height:
            return
        view.page.mouse.wheel(0, 120 if distance < height else -120)
        view.page.wait_for_timeout(300)


def measure(sequence: Path) -> dict:
    from playwright.sync_api import sync_playwright

    if not CHROMIUM.is_file():
        raise SystemExit(f"Debian's Chromium is not installed at {CHROMIUM} (make system-deps)")
    with tempfile.TemporaryDirectory() as tmp:
        env = {"MMSCLEAN_SAMPLE_DIR": "", "MMSCLEAN_IMPORT_ROOT": str(sequence.parent),
               "MMSCLEAN_RETRAIN_EVERY": "0", "MMSCLEAN_WORKERS": "1",
               "MMSCLEAN_VIEWER_OVERVIEW_POINTS": str(OVERVIEW_POINTS),
               "MMSCLEAN_VIEWER_TILE_POINTS": str(TILE_POINTS),
               "MMSCLEAN_VIEWER_LOG_SLOWER_MS": "0"}  # fmt: skip
        server = Server(Path(tmp) / "var", env=env).start()
        os.nice(CLIENT_NICE)  # this script, Playwright's driver and the browser started next
        try:
            admin = server.client()
            record = admin.post(
                "/surveys/import",
                json={"path": str(sequence), "format": "semantickitti", "name": sequence.name},
            )
            record.raise_for_status()
            survey_id = record.json()["id"]
            origin = np.asarray(admin.get(f"/surveys/{survey_id}").json()["origin"], float)
            street = street_pillars(sequence, origin)
            annotator = server.add_user("annotator", "annotator", PASSWORD)
            token = login(server, "annotator", PASSWORD)
            with sync_playwright() as playwright:
                browser = playwright.chromium.launch(
                    executable_path=str(CHROMIUM), headless=True, args=CHROMIUM_ARGS
                )
                view = Page(browser, server, token, survey_id)
                browser_yields()
                view.page.get_by_text("Click: brush. Shift-drag: rectangle.").wait_for(
                    timeout=600_000
                )
                view.page.wait_for_timeout(3000)
                view.page.keyboard.press("t")
                view.page.wait_for_timeout(1500)
                zoom_to(view, CAMERA_HEIGHT)
                view.page.wait_for_timeout(2000)
                before = len(server.log())
                tally = run_session(view, annotator, survey_id, street)
                answers = server_answers(server.log()[before:])
                errors = view.errors
                browser.close()
            labels = labelled(annotator, survey_id, street["cells"])
        finally:
            server.stop()
    non_ground = street["klass"] != 0
    have = np.array([c in labels for c in street["cells"].tolist()])
    given = np.array([labels.get(c, -1) for c in street["cells"].tolist()])
    return {"tally": tally, "pillars": len(street["cells"]), "non_ground": int(non_ground.sum()),
            "non_ground_labelled": int((have & non_ground).sum()),
            "accuracy": float((given[have] == street["klass"][have]).mean()) if have.any() else 0.0,
            "confusion": confusion(street["klass"], given),
            "errors": errors, "answers": answers}  # fmt: skip


ANSWER_LINE = re.compile(r"viewer client \S+: (\w+) answered in (\d+) ms \((\d+) ms of it wait")
NOT_INTERACTIONS = {"_camera_settled", "_recolor", "_review_changed", "_draw_due_views", "_start"}


def server_answers(log: str) -> list[tuple[str, float, float]]:
    """(action, seconds, of them waiting for earlier work) of each interaction the server
    answered, from its log (every one logged: MMSCLEAN_VIEWER_LOG_SLOWER_MS=0): from its
    message's arrival to its answer (a label write's colours, else the end of its work).
    Camera moves and the server's own follow-up work (the label feed, the views' redraw) are
    not interactions."""
    return [
        (m.group(1), int(m.group(2)) / 1000.0, int(m.group(3)) / 1000.0)
        for m in ANSWER_LINE.finditer(log)
        if m.group(1) not in NOT_INTERACTIONS
    ]


def confusion(klass: np.ndarray, given: np.ndarray) -> np.ndarray:
    """(4, 5) pillar counts: reference class (rows) by the label given (columns, the last:
    none)."""
    table = np.zeros((4, 5), dtype=np.int64)
    np.add.at(table, (klass, np.where(given < 0, 4, given)), 1)
    return table


def confusion_rows(table: np.ndarray) -> list[list[str]]:
    return [[CLASS_LABELS[r]] + [f"{v:,}" for v in table[r]] for r in range(len(table))]


def browser_yields() -> None:
    """Chromium sets its own processes' priorities (its GPU process above normal): put them
    all at CLIENT_NICE with the rest of the annotator's side."""
    for child in psutil.Process().children(recursive=True):
        try:
            if "chrom" in child.name():
                child.nice(CLIENT_NICE)
        except psutil.Error:  # gone meanwhile
            continue


def percentiles_ms(values: list[float]) -> tuple[float, float]:
    """(p50, p90) in milliseconds; NaN without values."""
    if not values:
        return float("nan"), float("nan")
    p90 = statistics.quantiles(values, n=10)[-1] if len(values) > 1 else values[0]
    return statistics.median(values) * 1000.0, p90 * 1000.0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sequence", default="08")
    parser.add_argument("--no-record", action="store_true")
    args = parser.parse_args(argv)
    real = os.environ.get("MMSCLEAN_REAL_DATA")
    if not real:
        raise SystemExit("MMSCLEAN_REAL_DATA is not set (the real SemanticKITTI sample)")
    sequence = Path(real).resolve() / "semantickitti" / "sequences" / args.sequence
    result = measure(sequence)
    tally: Tally = result["tally"]
    rows = [
        [tool, str(r["n"]), f"{r['pillars']:,}", f"{r['s']:.1f}",
         f"{60.0 * r['pillars'] / r['s']:,.0f}" if r["s"] else "-"]
        for tool, r in tally.rows.items()
    ]  # fmt: skip
    total = sum(r["pillars"] for r in tally.rows.values())
    per_minute = 60.0 * total / max(tally.seconds, 1e-9)
    interactions = sum(r["n"] for r in tally.rows.values())
    rows.append(
        ["all", str(interactions), f"{total:,}", f"{tally.seconds:.1f}", f"{per_minute:,.0f}"]
    )
    table = markdown_table(
        ["tool", "interactions", "pillars labelled", "seconds", "pillars / min"], rows
    )
    p50, p90 = percentiles_ms(tally.latency)
    answers = [seconds for _, seconds, _ in result["answers"]]
    s50, s90 = percentiles_ms(answers)
    slow = [
        f"{a} {1000 * t:.0f} ms, {1000 * w:.0f} ms of it waiting"
        for a, t, w in result["answers"]
        if t > 0.2
    ]
    share = 100.0 * result["non_ground_labelled"] / max(result["non_ground"], 1)
    complete = (
        "Not every non-ground pillar was labelled."
        if tally.complete_at is None
        else f"Every non-ground pillar held a label after {tally.complete_at[0]:.0f} s "
        f"(accuracy then {100.0 * tally.complete_at[1]:.1f} %)."
    )
    summary = (
        f"Street (SemanticKITTI {args.sequence}, real, 100 m x 30 m): {result['pillars']:,} "
        f"pillars with points, {result['non_ground']:,} non-ground; labelled "
        f"{result['non_ground_labelled']:,} of them ({share:.1f} %) "
        f"in {tally.seconds / 60.0:.1f} min of interaction; class accuracy of the labels "
        f"{100.0 * result['accuracy']:.1f} %. {complete} Latency from the committing input "
        f"(click or key) to the colours received in the page: p50 {p50:.0f} ms, p90 {p90:.0f} "
        f"ms. The server's own time to answer (its log: from a message's arrival to the colours "
        f"sent, or the end of the work), over all {len(answers)} messages of the session "
        f"(vertex clicks, keys, settings too): p50 {s50:.0f} ms, p90 {s90:.0f} ms, max "
        f"{1000 * max(answers, default=0):.0f} ms; over 200 ms: {len(slow)}"
        f"{' (' + '; '.join(slow) + ')' if slow else ''}. Page errors: {len(result['errors'])}."
    )
    wrong = markdown_table(
        ["reference \\ labelled", *CLASS_LABELS, "none"],
        confusion_rows(result["confusion"]),
    )
    table = (
        f"{table}\n\nThe street's pillars by reference class (rows) and the label they ended "
        f"with:\n\n{wrong}"
    )
    print(table)
    print(summary)
    if not args.no_record:
        append_results(
            "Timed labelling session in the browser (issue 20)",
            "MMSCLEAN_REAL_DATA=../shared/data python -m bench.annotation "
            f"--sequence {args.sequence}",
            table, summary,
        )  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
