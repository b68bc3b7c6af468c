"""The dashboard (`/`, `frontend_assets/`) against a real `mmsclean serve` with the sample survey.

Plain tests check that the page and every asset it loads are served, and that nothing refers to
another host (no CDN: the app must work offline). Browser tests drive Debian's Chromium with
Playwright: log in, find the sample survey, start `run:phantom` from the survey page and watch
its progress bar reach 100 %, open its metrics (heat map cells = the job's confusion matrix),
cancel a running `run:guardrail` from the jobs page, upload and delete a survey, import one
from the server as a job, check what an annotator is not shown, log out.

Screenshots go to the test's tmp dir; `MMSCLEAN_UPDATE_SCREENSHOTS=1` (or a missing file) also
writes `docs/dashboard.png`, so ordinary runs leave the checkout clean.
"""

from __future__ import annotations

import os
import re
import time
from collections.abc import Iterator
from pathlib import Path
from urllib.parse import unquote

import httpx
import numpy as np
import pytest

from app.io.las import write_laz
from tests.api.server import ADMIN_PASSWORD, Server

ROOT = Path(__file__).resolve().parents[2]
ASSETS = ROOT / "frontend_assets"
DOCS_SCREENSHOT = ROOT / "docs" / "dashboard.png"
CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader"]
VIEWPORT = {"width": 1280, "height": 800}
# the only absolute URL the assets may hold: the SVG namespace, an identifier never fetched
ALLOWED_URLS = {"http://www.w3.org/2000/svg"}
JOB_TIMEOUT_S = 300  # run:phantom takes seconds alone, minutes on two busy cores


@pytest.fixture(scope="module")
def dashboard_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    """A server with the sample survey and one worker (the tests share two cores)."""
    data_dir = tmp_path_factory.mktemp("dashboard") / "var"
    running = Server(data_dir, env={"MMSCLEAN_WORKERS": "1"}).start()
    yield running
    running.stop()


# --- served files, no external URLs ---------------------------------------------------------


def module_imports(source: str) -> list[str]:
    """Relative module paths a JS file imports (static `import ... from "./x.js"`)."""
    return re.findall(r"""(?:import|from)\s*["'](\.{1,2}/[^"']+)["']""", source)


def served_assets(server: Server) -> dict[str, httpx.Response]:
    """Every file the page loads, following <script>/<link> tags and JS imports from `/`."""
    responses: dict[str, httpx.Response] = {}
    with httpx.Client(base_url=server.url) as client:
        index = client.get("/")
        responses["/"] = index
        todo = re.findall(r"""(?:src|href)=["'](/assets/[^"']+)["']""", index.text)
        while todo:
            url = todo.pop()
            if url in responses:
                continue
            response = client.get(url)
            responses[url] = response
            if url.endswith(".js") and response.status_code == 200:
                folder = url.rsplit("/", 1)[0]
                for rel in module_imports(response.text):
                    parts = f"{folder}/{rel}".split("/")
                    resolved: list[str] = []
                    for part in parts:
                        if part == "..":
                            resolved.pop()
                        elif part != ".":
                            resolved.append(part)
                    todo.append("/".join(resolved))
    return responses


def test_page_and_every_asset_it_loads_are_served(dashboard_server: Server) -> None:
    responses = served_assets(dashboard_server)
    index = responses["/"]
    assert index.status_code == 200
    assert index.headers["content-type"].startswith("text/html")
    csp = index.headers["content-security-policy"]
    assert "default-src 'self'" in csp and "script-src 'self'" in csp
    failed = {url: r.status_code for url, r in responses.items() if r.status_code != 200}
    assert not failed
    types = {url: r.headers["content-type"] for url, r in responses.items()}
    assert all(t.startswith("text/javascript") for u, t in types.items() if u.endswith(".js"))
    assert all(t.startswith("text/css") for u, t in types.items() if u.endswith(".css"))
    # every file in frontend_assets is reachable from the page (no dead files, no missing ones)
    on_disk = {
        f"/assets/{p.relative_to(ASSETS).as_posix()}"
        for p in ASSETS.rglob("*")
        if p.is_file() and not p.name.startswith(".")
    }
    assert on_disk - {"/assets/index.html"} == set(responses) - {"/"}
    for url in responses:
        if url != "/":
            body = (ASSETS / url.removeprefix("/assets/")).read_bytes()
            assert responses[url].content == body, url


def test_assets_do_not_leave_their_folder(dashboard_server: Server) -> None:
    with httpx.Client(base_url=dashboard_server.url) as client:
        for url in ("/assets/../pyproject.toml", "/assets/%2e%2e/pyproject.toml", "/assets/x.js"):
            response = client.get(url)
            assert response.status_code == 404, url
            assert "pyproject" not in response.text or "detail" in response.json()


def test_no_external_urls_in_the_page(dashboard_server: Server) -> None:
    responses = served_assets(dashboard_server)
    texts = {url: r.text for url, r in responses.items()}
    absolute = {
        match for text in texts.values() for match in re.findall(r"""https?://[^\s"'`)<>]+""", text)
    }
    assert absolute <= ALLOWED_URLS, absolute - ALLOWED_URLS
    # protocol-relative URLs (//cdn.example/x.js) in attributes, imports or CSS url()
    relative_to_host = [
        (url, m)
        for url, text in texts.items()
        for m in re.findall(r"""(?:src=|href=|url\(|from\s|import\s)\s*["']?//[^"'\s)]+""", text)
    ]
    assert not relative_to_host
    # what the page references is this server's own /assets/ or a route of the page itself
    index = texts["/"]
    refs = re.findall(r"""(?:src|href)=["']([^"']+)["']""", index)
    assert refs and all(r.startswith(("/assets/", "#/")) for r in refs), refs


def test_dashboard_routes_stay_out_of_the_api_schema(dashboard_server: Server) -> None:
    paths = httpx.get(f"{dashboard_server.url}/openapi.json").json()["paths"]
    assert "/" not in paths
    assert not [p for p in paths if p.startswith("/assets")]


# --- in the browser -------------------------------------------------------------------------


@pytest.fixture(scope="module")
def chromium() -> Iterator[object]:
    if not CHROMIUM.is_file():
        pytest.skip(
            f"Debian's Chromium is not installed at {CHROMIUM} (make system-deps installs it); "
            "browser tests need it and never download a browser"
        )
    sync_api = pytest.importorskip("playwright.sync_api", reason="the playwright package")
    with sync_api.sync_playwright() as playwright:
        browser = playwright.chromium.launch(
            executable_path=str(CHROMIUM), headless=True, args=CHROMIUM_ARGS
        )
        yield browser
        browser.close()


@pytest.fixture
def page(chromium, dashboard_server: Server, tmp_path: Path):
    """A fresh browser context (no cookie, empty sessionStorage) on the dashboard; any
    JavaScript error on the page fails the test."""
    context = chromium.new_context(viewport=VIEWPORT, base_url=dashboard_server.url)
    context.set_default_timeout(30_000)
    tab = context.new_page()
    errors: list[str] = []
    tab.on("pageerror", lambda exc: errors.append(str(exc)))
    tab.goto("/")
    yield tab
    tab.screenshot(path=str(tmp_path / "last-page.png"), full_page=True)
    context.close()
    assert not errors, errors


def log_in(page, username: str = "admin", password: str = ADMIN_PASSWORD) -> None:
    page.fill("#login-username", username)
    page.fill("#login-password", password)
    page.click("#login-form button[type=submit]")
    page.wait_for_selector("#surveys")


def bar_state(page, selector: str) -> tuple[str | None, float | None]:
    # both attributes from the same element in one call: the bar is rebuilt on every poll, and
    # two separate reads could take the status from one rendering and the value from another
    state = page.evaluate(
        """(selector) => {
            const bar = document.querySelector(selector);
            return bar ? [bar.dataset.status ?? null, bar.getAttribute("aria-valuenow")] : null;
        }""",
        selector,
    )
    if state is None:
        return None, None
    status, value = state
    return status, None if value is None else float(value)


def watch_bar(page, selector: str, until: set[str], timeout: float) -> list[tuple]:
    """(status, percent) of the progress bar, sampled until its status is in UNTIL."""
    seen: list[tuple] = []
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        state = bar_state(page, selector)
        if state != (None, None) and (not seen or seen[-1] != state):
            seen.append(state)
        if state[0] in until:
            return seen
        page.wait_for_timeout(100)
    raise AssertionError(f"{selector} did not reach {until} in {timeout} s: {seen}")


def save_screenshot(page, tmp_path: Path, name: str, docs: bool = False) -> None:
    page.screenshot(path=str(tmp_path / f"{name}.png"), full_page=True)
    if docs and (os.environ.get("MMSCLEAN_UPDATE_SCREENSHOTS") or not DOCS_SCREENSHOT.exists()):
        DOCS_SCREENSHOT.parent.mkdir(exist_ok=True)
        page.screenshot(path=str(DOCS_SCREENSHOT))


@pytest.mark.e2e
def test_wrong_password_shows_the_api_detail(page) -> None:
    page.fill("#login-username", "admin")
    page.fill("#login-password", "not-the-password")
    page.click("#login-form button[type=submit]")
    error = page.locator("#login-error")
    error.wait_for(state="visible")
    assert error.inner_text() == "wrong username or password"
    assert page.locator("#topbar").is_hidden()


@pytest.mark.e2e
def test_run_phantom_from_the_survey_page_and_read_its_metrics(
    page, dashboard_server: Server, tmp_path: Path
) -> None:
    log_in(page)
    row = page.locator("#surveys tr[data-survey]", has_text="sim-urban-60m")
    assert row.count() == 1
    assert "1,381,077" in row.inner_text()  # points of the sample survey
    save_screenshot(page, tmp_path, "surveys")
    row.locator("a.survey-link").click()
    page.wait_for_selector("form.pipeline[data-pipeline='run:phantom']")
    survey_id = int(page.url.rsplit("/", 1)[1])
    # a model is chosen by its registry id, never typed in as a file path
    assert page.locator("form.pipeline [name='model_path']").count() == 0
    model = page.locator("form.pipeline[data-pipeline='run:phantom'] select[name='model_id']")
    promoted = model.locator("option").first.inner_text()
    assert promoted == "promoted version for this survey's scanner"

    page.click("button[data-start='run:phantom']")
    bar = ".latest[data-kind='run:phantom'] .progress"
    page.wait_for_selector(bar)
    seen = watch_bar(page, bar, {"succeeded", "failed", "cancelled"}, JOB_TIMEOUT_S)
    assert seen[-1] == ("succeeded", 100.0), seen
    assert any(value < 100 for _, value in seen), f"the bar never moved: {seen}"
    with dashboard_server.client() as api:
        jobs = api.get("/jobs", params={"kind": "run:phantom", "survey_id": survey_id}).json()
    job = jobs[0]
    assert job["status"] == "succeeded" and job["created_by"] == 1  # started as admin
    # the review state below refreshes when the job ends: the model pre-labels are counted
    with dashboard_server.client() as api:
        model_labels = sum(api.get(f"/surveys/{survey_id}/pillars/stats").json()["model"])
    assert model_labels > 0
    total = page.locator("#pillar-stats tbody tr:last-child td:nth-child(3)")
    page.wait_for_function(
        "([el, want]) => el.textContent === want", arg=[total.element_handle(), f"{model_labels:,}"]
    )
    save_screenshot(page, tmp_path, "survey", docs=True)
    # a phantom run removes points: its cleaned map is exported (it waited for a clutter run)
    cleaned = page.locator("#exports li", has_text="cleaned map (LAZ)")
    cleaned.locator("a[data-export='cleaned.laz']").wait_for()
    assert f"run:phantom job {job['id']}" in cleaned.inner_text()
    # the combined maps wait for a clutter run too, and say so
    combined = page.locator("#exports li", has_text="cleaned map, clutter and phantom combined")
    assert combined.locator("span.disabled").count() == 1
    assert "needs a finished clutter run and a finished phantom run" in combined.inner_text()
    # the model picker names each version's scanner kind and held-out F (issue 20, defect 9)
    page.reload()
    versions = page.locator("#opt-run-phantom-model_id option[data-sensor]")
    versions.first.wait_for(state="attached")
    for text in versions.all_text_contents():
        assert re.search(r"\((rotating|profile) scanners", text), text

    # the job's metrics: confusion heat map cells hold the job's confusion matrix
    page.locator(".latest[data-kind='run:phantom'] a", has_text="results & metrics").click()
    page.wait_for_selector("#job-metrics [data-metric='phantom-pillar'] svg.heatmap")
    confusion = job["result"]["metrics"]["pillar"]["confusion"]
    counts = page.locator(
        "#job-metrics [data-metric='phantom-pillar'] svg.heatmap .cell-count"
    ).all_text_contents()  # SVG text has no innerText
    assert [int(c.replace(",", "")) for c in counts] == [v for row in confusion for v in row]
    titles_fit = page.eval_on_selector_all(
        "#job-metrics svg.heatmap",
        """svgs => svgs.every((svg) => {
            const title = svg.querySelector(".plot-title").getBBox();
            return title.x >= 0 && title.x + title.width <= svg.viewBox.baseVal.width;
        })""",
    )
    assert titles_fit  # a long matrix title was clipped at both ends (issue 20)
    phantom_f = job["result"]["metrics"]["pillar"]["classes"]["phantom"]["f1"]
    table = page.locator("#job-metrics [data-metric='phantom-pillar'] table").inner_text()
    assert f"{phantom_f:.1f}" in table
    assert page.locator("#job-files a", has_text="report.json").count() == 1
    page.wait_for_function("() => document.querySelector('#job-log').innerText.includes('job')")
    save_screenshot(page, tmp_path, "job")

    # the survey's metrics tab shows the same run
    page.goto(f"/#/surveys/{survey_id}/metrics")
    section = page.locator("[data-metrics='phantom']")
    section.locator("svg.heatmap").first.wait_for()
    assert f"job {job['id']}" in section.inner_text()
    save_screenshot(page, tmp_path, "metrics")


@pytest.mark.e2e
def test_cancel_a_running_job_from_the_jobs_page(
    page, dashboard_server: Server, tmp_path: Path
) -> None:
    log_in(page)
    page.locator("#surveys a.survey-link").first.click()
    # the classifier head is the model's default unless chosen; a choice is always sent, even
    # the one that used to be the form's default (a rotating card defaults to geometry)
    assert page.input_value("#opt-run-guardrail-head") == ""
    assert page.input_value("#opt-run-guardrail-threshold") == ""  # the model's, unless set
    page.select_option("#opt-run-guardrail-head", "image+geometry")
    page.click("button[data-start='run:guardrail']")
    page.wait_for_selector(".latest[data-kind='run:guardrail'] .progress")
    page.click("nav [data-nav='jobs']")
    row = page.locator("#jobs tr[data-job]", has_text="run:guardrail").first
    row.wait_for()
    job_id = int(row.get_attribute("data-job"))
    bar = f"#jobs tr[data-job='{job_id}'] .progress"
    # wait until a worker runs it and reports progress, so the cancel reaches a running job
    deadline = time.monotonic() + JOB_TIMEOUT_S
    while bar_state(page, bar)[0] != "running" or not bar_state(page, bar)[1]:
        assert time.monotonic() < deadline, bar_state(page, bar)
        page.wait_for_timeout(200)
    save_screenshot(page, tmp_path, "jobs-running")
    row.locator("button[data-action='cancel']").click()
    seen = watch_bar(page, bar, {"cancelled", "succeeded", "failed"}, JOB_TIMEOUT_S)
    assert seen[-1][0] == "cancelled", seen
    row.locator("button[data-action='resume']").wait_for()  # a cancelled job may be resumed
    with dashboard_server.client() as api:
        job = api.get(f"/jobs/{job_id}").json()
    assert job["status"] == "cancelled" and job["cancel_requested"]
    assert job["config"]["head"] == "image+geometry" and "threshold" not in job["config"]


@pytest.mark.e2e
def test_upload_a_survey_with_progress_then_delete_it(page, tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    xyz = rng.uniform([0, 0, 0], [40, 20, 3], size=(20_000, 3)) + [512_000.0, 5_400_000.0, 300]
    laz = write_laz(tmp_path / "street-upload.laz", xyz)
    log_in(page)
    page.set_input_files("#upload-file", str(laz))
    page.fill("#upload-name", "uploaded street")
    page.click("#upload-form button[type=submit]")
    row = page.locator("#surveys tr[data-survey]", has_text="uploaded street")
    row.wait_for()
    progress = page.locator("#upload-progress")
    assert progress.get_attribute("data-status") == "succeeded"
    assert progress.get_attribute("aria-valuenow") == "100"
    assert "20,000" in row.inner_text()

    page.once("dialog", lambda dialog: dialog.accept())  # the delete confirmation
    row.locator("button[data-action='delete']").click()
    row.wait_for(state="detached")
    assert page.locator("#surveys tr[data-survey]", has_text="sim-urban-60m").count() == 1


@pytest.mark.e2e
def test_a_viewer_link_opened_logged_out_returns_to_it_after_the_login(
    page, dashboard_server: Server
) -> None:
    """/viewer?survey=N&mode=qa without a login goes through the login page and back to that
    viewer and mode (issue 20), not to the surveys list; a `next` pointing elsewhere is not
    followed."""
    with dashboard_server.client() as admin:
        survey_id = admin.get("/surveys").json()[0]["id"]
    # the viser client itself is not what this checks: answer its page with a stand-in
    page.route("**/viewer?websocket=**", lambda route: route.fulfill(body="viewer stand-in"))
    page.goto(f"/viewer?survey={survey_id}&mode=qa")
    page.wait_for_selector("#login-form")
    page.fill("#login-username", "admin")
    page.fill("#login-password", ADMIN_PASSWORD)
    page.click("#login-form button[type=submit]")
    page.wait_for_url(re.compile(r".*/viewer\?websocket=.*"))
    assert f"/viewer/ws?survey={survey_id}&mode=qa" in unquote(page.url)
    page.evaluate("() => { sessionStorage.clear(); localStorage.clear(); }")  # logged out
    page.context.clear_cookies()
    page.goto("/?next=https://evil.example/viewer")
    log_in(page)  # lands on the surveys list
    assert page.url.startswith(dashboard_server.url)


@pytest.mark.e2e
def test_import_from_the_server_runs_as_a_job(page, dashboard_server: Server) -> None:
    """The import form names the server's import root, queues `import:survey`, follows the job
    under the form and lists the survey when it succeeds, with links to it from the form and from
    the job's page (issue 20); a path outside the import root is refused at once."""
    rng = np.random.default_rng(5)
    xyz = rng.uniform([0, 0, 0], [30, 10, 3], size=(5_000, 3)) + [512_000.0, 5_400_000.0, 300]
    (dashboard_server.data_dir / "imports").mkdir(exist_ok=True)
    write_laz(dashboard_server.data_dir / "imports" / "street-import.laz", xyz)
    log_in(page)
    root = str(dashboard_server.data_dir.resolve())
    page.wait_for_function(
        "root => document.querySelector('#import-root').textContent === root", arg=root
    )
    page.fill("#import-path", "/etc")
    page.click("#import-form button[type=submit]")
    page.wait_for_selector("#flash:not([hidden])")
    assert "import root" in page.locator("#flash").inner_text()
    assert page.locator("#import-status").is_hidden()

    page.fill("#import-path", "imports/street-import.laz")
    page.fill("#import-name", "imported street")
    page.click("#import-form button[type=submit]")
    page.wait_for_selector("#import-status:not([hidden]) a[href^='#/jobs/']")
    row = page.locator("#surveys tr[data-survey]", has_text="imported street")
    row.wait_for(timeout=JOB_TIMEOUT_S * 1000)
    assert "5,000" in row.inner_text()
    survey_id = row.get_attribute("data-survey")
    imported = page.locator("#import-status #imported-survey")
    assert imported.inner_text() == "imported street"
    assert imported.get_attribute("href") == f"#/surveys/{survey_id}"
    assert "Imported survey imported street" in page.locator("#flash").inner_text()
    page.locator("#import-status a[href^='#/jobs/']").click()
    job_survey = page.locator("#job-survey")
    job_survey.wait_for()
    assert job_survey.get_attribute("href") == f"#/surveys/{survey_id}"
    page.goto(f"{dashboard_server.url}/#/surveys")
    row.wait_for()
    page.once("dialog", lambda dialog: dialog.accept())
    row.locator("button[data-action='delete']").click()
    row.wait_for(state="detached")


@pytest.mark.e2e
def test_surveys_show_their_sensor_and_the_survey_page_declares_it(
    page, dashboard_server: Server, tmp_path: Path
) -> None:
    """The list shows each survey's sensor kind (how it was told as the title); a map without
    point times is unknown, its page says runs need the kind and an annotator declares it."""
    rng = np.random.default_rng(7)
    xyz = rng.uniform([0, 0, 0], [20, 10, 3], size=(2_000, 3)) + [512_000.0, 5_400_000.0, 300]
    laz = write_laz(tmp_path / "no-times.laz", xyz).read_bytes()
    with dashboard_server.client() as admin:
        params = {"filename": "no-times.laz", "name": "no times"}
        survey = admin.post("/surveys/upload", params=params, content=laz).json()
    log_in(page)
    assert "Sensor" in page.locator("#surveys thead").text_content()
    sample = page.locator("#surveys tr[data-survey]", has_text="sim-urban-60m")
    badge = sample.locator(".sensor-cell [data-sensor]")
    assert badge.inner_text() == "profile"
    assert badge.get_attribute("title") == "sim reader: scanner profile"
    assert page.locator("#import-sensor option").all_inner_texts() == [
        "Detect from the data",
        "Rotating (spinning multi-beam)",
        "Profile (MMS line scanner)",
    ]
    row = page.locator("#surveys tr[data-survey]", has_text="no times")
    assert row.locator("[data-sensor]").inner_text() == "unknown"

    row.locator("a.survey-link").click()
    page.wait_for_selector("#sensor-hint")
    page.select_option("#sensor-kind", "rotating")
    page.click("#sensor-save")
    page.wait_for_selector("#survey-sensor [data-sensor='rotating']")
    assert page.locator("#sensor-hint").count() == 0
    assert "declared by admin" in page.locator("#survey-sensor").inner_text()
    with dashboard_server.client() as admin:
        assert admin.get(f"/surveys/{survey['id']}").json()["sensor_kind"] == "rotating"
        assert admin.delete(f"/surveys/{survey['id']}").status_code == 204


@pytest.mark.e2e
def test_pillar_label_exports_wait_for_human_labels(page, dashboard_server: Server) -> None:
    """Without human pillar labels the CSV / NumPy exports are disabled with the reason (they
    answered 404 and the page showed nothing, issue 20) and no empty chart is drawn; with
    labels they download and the chart's count ticks are whole numbers, each once."""
    rng = np.random.default_rng(6)
    xyz = rng.uniform([0, 0, 0], [20, 10, 3], size=(2_000, 3)) + [512_000.0, 5_400_000.0, 300]
    (dashboard_server.data_dir / "imports").mkdir(exist_ok=True)
    write_laz(dashboard_server.data_dir / "imports" / "unlabelled.laz", xyz)
    with dashboard_server.client() as admin:
        answer = admin.post(
            "/surveys/import", json={"path": "imports/unlabelled.laz", "name": "unlabelled"}
        )
        survey_id = answer.json()["id"]
    log_in(page)
    page.goto(f"/#/surveys/{survey_id}")
    exports = page.locator("#exports")
    exports.locator("li", has_text="pillar labels (CSV)").wait_for()
    for text in ("pillar labels (CSV)", "pillar labels (NumPy)"):
        item = exports.locator("li", has_text=text)
        assert item.locator("a").count() == 0
        assert "needs human pillar labels" in item.inner_text()
    # the exports for mapping tools wait for the run they are made from (issue 20)
    for text, reason in (
        ("classified map, ASPRS classes (LAZ)", "needs a finished clutter or phantom run"),
        ("map with labels (PCD)", "needs a finished clutter or phantom run"),
        ("SemanticKITTI labels per frame (zip)", "needs a finished clutter run"),
    ):
        item = exports.locator("li", has_text=text)
        assert item.locator("a").count() == 0 and reason in item.inner_text(), text
    assert page.locator("#pillar-stats svg").count() == 0
    assert "No pillar labels yet" in page.locator("#pillar-stats-none").inner_text()
    with dashboard_server.client() as admin:
        labels = {"labels": [{"cell_id": 1, "label": 3}, {"cell_id": 2, "label": 1}]}
        assert admin.put(f"/surveys/{survey_id}/pillars/labels", json=labels).status_code == 200
        page.reload()
        link = page.locator("#exports a[data-export='pillars.csv']")
        link.wait_for()
        csv = admin.get(link.get_attribute("href"))
        assert csv.status_code == 200 and len(csv.text.splitlines()) == 3
        ticks = page.eval_on_selector_all(
            "#pillar-stats svg text.tick", "texts => texts.map((t) => t.textContent)"
        )
        numbers = [t for t in ticks if t.isdigit()]
        assert numbers == ["0", "1"]  # one label each: the most any class has is 1
        assert admin.delete(f"/surveys/{survey_id}").status_code == 204


@pytest.mark.e2e
def test_the_camera_option_says_when_the_weights_are_missing(
    page, dashboard_server: Server
) -> None:
    """Without the segmentation weights on the server the clutter form's camera option is
    unticked and says which file is missing and where to get it (issue 20); with them it stays
    ticked."""
    log_in(page)
    page.locator("#surveys a.survey-link").first.click()
    camera = page.locator("#opt-run-clutter-use_camera")
    camera.wait_for()
    page.wait_for_load_state("networkidle")
    with dashboard_server.client() as admin:
        present = admin.get("/models/segmentation").json()["available"]
    assert camera.is_checked() == present
    missing = {"available": False, "file": "/srv/weights/espnetv2_s_2.0_city_1024x512.pth",
               "upstream": "GitHub sacmehta/EdgeNets, model/segmentation/model_zoo/espnetv2/"
               "espnetv2_s_2.0_city_1024x512.pth"}  # fmt: skip
    page.route("**/models/segmentation", lambda route: route.fulfill(json=missing))
    page.reload()
    note = page.locator("#opt-run-clutter-use_camera-missing")
    note.wait_for()
    assert not page.locator("#opt-run-clutter-use_camera").is_checked()
    assert "/srv/weights/espnetv2_s_2.0_city_1024x512.pth" in note.inner_text()
    assert "sacmehta/EdgeNets" in note.inner_text()


@pytest.mark.e2e
def test_retraining_says_what_it_needs_and_how_the_last_one_ended(
    page, dashboard_server: Server
) -> None:
    """The retrain buttons state their prerequisites and stay disabled until the labels can
    train the model; a failed retraining shows where it was started (issue 20: the buttons
    queued jobs bound to fail, shown only on the Jobs page)."""
    log_in(page)
    page.click("nav [data-nav='models']")
    for pipeline, need in (("phantom", "retraining needs at least 50"), ("guardrail", "needs 20")):
        page.locator(f"[data-needs='{pipeline}']").wait_for()
        assert page.locator(f"button[data-retrain='{pipeline}']").is_disabled()
        assert need in page.locator(f"[data-needs='{pipeline}']").inner_text()
    with dashboard_server.client() as admin:  # a training queued past the dashboard
        failed = admin.post("/jobs", json={"kind": "train:guardrail", "config": {}}).json()
        deadline = time.monotonic() + JOB_TIMEOUT_S
        while admin.get(f"/jobs/{failed['id']}").json()["status"] != "failed":
            assert time.monotonic() < deadline
            time.sleep(0.5)
    shown = page.locator("[data-failed='guardrail']")
    shown.wait_for(timeout=15_000)
    assert f"job {failed['id']}" in shown.inner_text()
    assert "reviewed guardrail slices" in shown.inner_text()
    assert shown.locator("a").get_attribute("href") == f"#/jobs/{failed['id']}"


def log_out(page) -> None:
    page.click("#logout")
    page.wait_for_selector("#login-form")


@pytest.mark.e2e
def test_work_areas_are_assigned_labelled_signed_off_and_exports_warn(
    page, dashboard_server: Server, tmp_path: Path
) -> None:
    """The review workflow on the survey page (issue 20): a reviewer cuts the sample's drive
    into 20 m areas and assigns one, its annotator marks it labelled, its reviewer rejects it
    with a comment, then signs it off; the export links stay usable under a warning line that
    lists the areas not signed off."""
    dashboard_server.add_user("area-ann", "annotator", password="area-ann-pass-1")
    dashboard_server.add_user("area-rev", "reviewer", password="area-rev-pass-1")
    with dashboard_server.client() as admin:
        survey = next(s for s in admin.get("/surveys").json() if "urban-60m" in s["name"])
    url = f"/#/surveys/{survey['id']}"

    log_in(page)
    page.goto(url)
    page.locator("#areas-form").wait_for()
    page.fill("#areas-length", "20")
    page.click("#areas-create")
    rows = page.locator("#areas-table tr[data-area]")
    rows.nth(2).wait_for()
    assert rows.count() == 3
    first = page.locator("#areas-table tr[data-area='0']")
    assert "0 – 20 m" in first.inner_text()
    with dashboard_server.client() as admin:
        area_id = admin.get(f"/surveys/{survey['id']}/areas").json()[0]["id"]
    href = first.locator("[data-viewer-area='0']").get_attribute("href")
    assert href == f"/viewer?survey={survey['id']}&mode=pillars&area={area_id}"
    viewer = page.context.new_page()  # the link opens the viewer looking at the area
    viewer.goto(href if href.startswith("http") else page.url.split("/#")[0] + href)
    viewer.get_by_text("Work area 0", exact=True).wait_for(timeout=180_000)
    assert viewer.get_by_text("0-20 m along the drive, open.").count() == 1
    viewer.close()
    warning = page.locator("#export-warning")
    warning.wait_for()
    assert "3 of 3 work areas not signed off (0, 1, 2)" in warning.inner_text()
    assert page.locator("#exports a[data-export='qa-report.html']").count() == 1  # usable
    first.locator("select[data-assignee='0']").select_option(label="area-ann (annotator)")
    first.locator("select[data-reviewer='0']").select_option(label="area-rev (reviewer)")
    first.locator("button[data-action='assign']").click()
    page.wait_for_function(
        """() => document.querySelector("#areas-table tr[data-area='0'] td[data-col='assignee']")
            ?.textContent === "area-ann" """
    )
    log_out(page)

    log_in(page, "area-ann", "area-ann-pass-1")
    page.goto(url)
    first.locator("button[data-action='labelled']").click()
    page.locator("#areas-table tr[data-area='0'][data-state='labelled']").wait_for()
    unassigned = page.locator("#areas-table tr[data-area='1'] button[data-action='labelled']")
    assert unassigned.count() == 0
    assert page.locator("#areas-form").count() == 0  # annotators do not cut areas
    log_out(page)

    log_in(page, "area-rev", "area-rev-pass-1")
    page.goto(url)
    first.locator("input[data-comment='0']").fill("the kerb at 12 m is ground")
    first.locator("button[data-action='reject']").click()
    page.locator("#areas-table tr[data-area='0'][data-state='open']").wait_for()
    assert "rejected: the kerb at 12 m is ground" in first.inner_text()
    log_out(page)

    log_in(page, "area-ann", "area-ann-pass-1")
    page.goto(url)
    first.locator("button[data-action='labelled']").click()
    page.locator("#areas-table tr[data-area='0'][data-state='labelled']").wait_for()
    log_out(page)

    log_in(page, "area-rev", "area-rev-pass-1")
    page.goto(url)
    first.locator("button[data-action='sign-off']").click()
    page.locator("#areas-table tr[data-area='0'][data-state='signed_off']").wait_for()
    page.wait_for_function(
        """() => document.querySelector("#export-warning")?.textContent
            .includes("2 of 3 work areas not signed off (1, 2)")"""
    )
    assert page.locator("#exports a[data-export='qa-report.html']").count() == 1
    page.locator("#work-areas").screenshot(path=str(tmp_path / "work-areas.png"))
    with dashboard_server.client() as admin:
        ready = admin.get(f"/surveys/{survey['id']}/export-readiness").json()
        assert ready["warning"] in page.locator("#export-warning").inner_text()
        areas = admin.get(f"/surveys/{survey['id']}/areas").json()
    assert [a["state"] for a in areas] == ["signed_off", "open", "open"]


@pytest.mark.e2e
def test_an_annotator_sees_only_what_the_role_allows(page, dashboard_server: Server) -> None:
    dashboard_server.add_user("annie", "annotator", password="annotator-pass-1")
    log_in(page, "annie", "annotator-pass-1")
    assert page.locator("#who-role").inner_text() == "annotator"
    assert page.locator("button[data-action='delete']").count() == 0  # deleting: reviewers
    page.locator("#surveys a.survey-link").first.click()
    page.wait_for_selector("button[data-start='run:phantom']")  # annotators run pipelines
    assert page.locator("#exports").count() == 0  # exports: reviewers
    assert page.locator("a[data-mode='pillars']").get_attribute("href").startswith("/viewer?")
    page.click("nav [data-nav='models']")
    page.wait_for_selector("#models")
    assert page.locator("[data-retrain]").count() == 0  # retraining: admins
    assert page.locator("button[data-action='promote']").count() == 0


@pytest.mark.e2e
def test_log_out_ends_the_session(page) -> None:
    log_in(page)
    page.click("#logout")
    page.wait_for_selector("#login-form")
    assert page.evaluate("() => sessionStorage.length") == 0
    # the HttpOnly cookie went too: reads on the cookie alone are refused
    assert page.evaluate("async () => (await fetch('/auth/me')).status") == 401
    page.goto("/#/jobs")
    page.wait_for_selector("#login-form")  # every page needs a login again
