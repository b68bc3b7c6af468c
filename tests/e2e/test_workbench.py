"""The labelling workbench in a real browser (issue 20, "what users of the anchor tools
expect"): standard views, colour modes, the top and side views beside the 3D view, the click
tools (fill, polygon, measure, inspect), the free-hand lasso, class locks and the shortcut
sheet on the sample survey; the multi-view layout and colour modes on a real SemanticKITTI
sequence. Screenshots go to docs/ (see conftest)."""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from tests.api.server import ADMIN_PASSWORD, Server
from tests.e2e.conftest import (
    VIEWER_OVERVIEW_POINTS,
    VIEWER_TILE_POINTS,
    VIEWER_VIEWPORT,
    api_login,
    close_notifications,
    save_screenshot,
    wait_until,
)
from tests.e2e.pixels import canvas_pixels

PASSWORD = "password-123"
REAL_SEQUENCE = "08"


def blur(page) -> None:
    """Keys go to the page, not to the GUI input clicked last."""
    page.evaluate("document.activeElement && document.activeElement.blur()")


def pick_option(page, current: str, option: str) -> None:
    page.locator(f"input:not([type=hidden])[value='{current}']").click()
    page.get_by_role("option", name=option, exact=True).click()
    blur(page)


def canvas_point(page, fx: float, fy: float) -> tuple[float, float]:
    box = page.locator("canvas").first.bounding_box()
    assert box is not None
    return box["x"] + box["width"] * fx, box["y"] + box["height"] * fy


def colourful_share(page) -> float:
    """Share of canvas pixels that are clearly coloured (not grey, not white)."""
    rgb = canvas_pixels(page).astype(np.int32)
    spread = rgb.max(axis=2) - rgb.min(axis=2)
    return float((spread > 60).mean())


def status_text(page, fragment: str) -> str:
    locator = page.get_by_text(fragment).first
    locator.wait_for()
    return locator.inner_text()


@pytest.mark.e2e
def test_views_colours_and_click_tools_on_the_sample(
    open_viewer, viewer_server: Server, artefacts
) -> None:
    viewer_server.add_user("workbench", "annotator", PASSWORD)
    page = open_viewer("workbench", PASSWORD, survey_id=1)
    page.get_by_text("Click: brush. Shift-drag: rectangle.").wait_for()
    page.wait_for_timeout(3000)
    # the top and side views beside the 3D view: two images in the panel
    assert page.locator("img").count() >= 2
    grey = colourful_share(page)

    # colour by height: the grey unlabelled street turns into a colour ramp
    page.get_by_text("Display", exact=True).click()
    pick_option(page, "Label", "Height above ground")
    page.wait_for_timeout(2500)
    assert colourful_share(page) > grey + 0.02
    close_notifications(page)
    save_screenshot(page, artefacts, "height", docs="viewer_colour_height.png")

    # standard views: T looks down on the street
    page.keyboard.press("t")
    page.wait_for_timeout(2500)
    save_screenshot(page, artefacts, "top", docs="viewer_top_view.png")

    # measure: two clicks
    page.keyboard.press("m")
    page.mouse.click(*canvas_point(page, 0.4, 0.5))
    page.get_by_text("Measure: click the second point.").wait_for()
    page.mouse.click(*canvas_point(page, 0.5, 0.5))
    assert "Distance" in status_text(page, "Distance")

    # inspect: the point's coordinates and labels
    page.keyboard.press("i")
    page.mouse.click(*canvas_point(page, 0.45, 0.5))
    assert "above the ground" in status_text(page, "Point x")

    # fill from the road (the focus is on the drive), applied on Enter when large
    page.keyboard.press("g")
    page.mouse.click(*canvas_point(page, 0.45, 0.5))
    text = wait_until(
        "the fill",
        lambda: page.get_by_text("(fill").count() and page.get_by_text("(fill").first.inner_text(),
    )
    if "selected" in text:
        page.keyboard.press("Enter")
    page.get_by_text("pillars: Ground (fill").wait_for()

    # polygon: three clicks and Enter, only where nothing is labelled yet (coloured by label)
    pick_option(page, "Height above ground", "Label")
    pick_option(page, "All pillars", "Unlabelled only")
    page.keyboard.press("4")
    page.keyboard.press("p")
    for fx, fy in ((0.3, 0.3), (0.6, 0.3), (0.45, 0.7)):
        page.mouse.click(*canvas_point(page, fx, fy))
    page.get_by_text("Polygon: 3 vertices").wait_for()
    page.keyboard.press("Enter")
    text = wait_until(
        "the polygon",
        lambda: (
            page.get_by_text("(polygon").count() and page.get_by_text("(polygon").first.inner_text()
        ),
    )
    if "selected" in text:
        page.keyboard.press("Enter")
    page.get_by_text("pillars: Phantom (polygon").wait_for()

    # lasso: a free-hand Ctrl-drag round another stretch, its path drawn while it grows
    pick_option(page, "Unlabelled only", "All pillars")
    page.keyboard.press("3")
    page.keyboard.down("Control")
    loop = [(0.55 + 0.12 * np.cos(a), 0.5 + 0.15 * np.sin(a)) for a in np.linspace(0, 6.0, 13)]
    page.mouse.move(*canvas_point(page, *loop[0]))
    page.mouse.down()
    for fx, fy in loop[1:]:
        page.mouse.move(*canvas_point(page, fx, fy))
        page.wait_for_timeout(60)  # the page reports the pointer at about 20 Hz
    save_screenshot(page, artefacts, "lasso-drawn", docs="viewer_lasso.png")
    page.mouse.up()
    page.keyboard.up("Control")
    lassoed = page.get_by_text("(lasso")
    text = wait_until("the lasso", lambda: lassoed.count() and lassoed.first.inner_text())
    if "selected" in text:
        page.keyboard.press("Enter")
    page.get_by_text("pillars: Short object (lasso").wait_for()
    page.wait_for_timeout(2000)
    close_notifications(page)
    save_screenshot(page, artefacts, "tools", docs="viewer_tools.png")

    # the shortcut sheet
    page.keyboard.press("h")
    page.get_by_text("this sheet").wait_for()
    save_screenshot(page, artefacts, "shortcuts", docs="viewer_shortcuts.png")
    page.get_by_role("button", name="Close").click()


@pytest.fixture(scope="module")
def real_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    """A server whose import root is the real KITTI / SemanticKITTI sample."""
    real = os.environ.get("MMSCLEAN_REAL_DATA")
    if not real or not Path(real).is_dir():
        pytest.skip("MMSCLEAN_REAL_DATA is not set (real SemanticKITTI sample)")
    data_dir = tmp_path_factory.mktemp("workbench-real") / "var"
    env = {
        "MMSCLEAN_VIEWER_OVERVIEW_POINTS": str(VIEWER_OVERVIEW_POINTS),
        "MMSCLEAN_VIEWER_TILE_POINTS": str(VIEWER_TILE_POINTS),
        "MMSCLEAN_RETRAIN_EVERY": "0",
        "MMSCLEAN_WORKERS": "1",
        "MMSCLEAN_IMPORT_ROOT": str(Path(real).resolve()),
    }
    running = Server(data_dir, env=env).start()
    yield running
    running.stop()


@pytest.mark.e2e
def test_multi_view_and_colour_modes_on_real_semantickitti(
    viewer_browser, real_server: Server, artefacts
) -> None:
    """Real data (SemanticKITTI 08, ten HDL-64E frames): the 3D view with the top and side
    views, coloured by intensity, by height and by the camera's colour."""
    api = real_server.client()
    path = Path(os.environ["MMSCLEAN_REAL_DATA"]) / "semantickitti" / "sequences" / REAL_SEQUENCE
    imported = api.post(
        "/surveys/import",
        json={"path": str(path), "format": "semantickitti", "name": f"real-{REAL_SEQUENCE}"},
    )
    assert imported.status_code == 201, imported.text
    survey_id = imported.json()["id"]
    token = api_login(real_server, "admin", ADMIN_PASSWORD)
    context = viewer_browser.new_context(viewport=VIEWER_VIEWPORT)
    errors: list[str] = []
    try:
        context.add_cookies([{"name": "mmsclean_token", "value": token, "url": real_server.url}])
        page = context.new_page()
        page.on("pageerror", lambda exc: errors.append(str(exc)))
        page.goto(f"{real_server.url}/viewer?survey={survey_id}")
        page.get_by_text("Click: brush. Shift-drag: rectangle.").wait_for(timeout=300_000)
        page.wait_for_timeout(4000)
        assert page.locator("img").count() >= 2  # top and side views
        page.get_by_text("Display", exact=True).click()
        pick_option(page, "Label", "Intensity")
        page.wait_for_timeout(3000)
        close_notifications(page)
        save_screenshot(page, artefacts, "real-intensity", docs="viewer_real_08_intensity.png")
        pick_option(page, "Intensity", "Height above ground")
        page.wait_for_timeout(3000)
        assert colourful_share(page) > 0.02
        save_screenshot(page, artefacts, "real-height", docs="viewer_real_08_height.png")
        pick_option(page, "Height above ground", "Camera colour")  # image_2's colours
        page.wait_for_timeout(3000)
        save_screenshot(page, artefacts, "real-camera", docs="viewer_real_08_camera.png")
    finally:
        context.close()
    assert not errors, errors
