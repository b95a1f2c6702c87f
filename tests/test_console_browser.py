"""The operator console in a real browser: Playwright drives the distribution's Chromium
through `rigctl serve` on the simulated rig. Screenshots go to test-artifacts/console/
(RIGCTL_ARTIFACTS overrides the directory)."""

from __future__ import annotations

import os
import re
import shutil
from pathlib import Path

import pytest

from tests.mockproc import ROOT
from tests.service_stack import TOKEN, Stack, get, post, wait_for

pytestmark = pytest.mark.integration

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
INSTALL = "apt-get install chromium (Debian/Ubuntu), then pip install playwright"
# what Chromium needs on a closed network and as root (see the machine's notes)
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update",
                 "--disable-sync", "--disable-dev-shm-usage"]
WAIT_MS = 240_000  # a run on a busy host; the waits are on conditions


def _playwright():
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        pytest.skip(f"no Playwright for Python: {INSTALL}")
    if CHROMIUM is None:
        pytest.skip(f"no Chromium on this machine: {INSTALL}")
    return sync_playwright


@pytest.fixture(scope="module")
def artifacts() -> Path:
    path = Path(os.environ.get("RIGCTL_ARTIFACTS", ROOT / "test-artifacts")) / "console"
    path.mkdir(parents=True, exist_ok=True)
    return path


@pytest.fixture(scope="module")
def browser():
    sync_playwright = _playwright()
    with sync_playwright() as p:
        chromium = p.chromium.launch(executable_path=CHROMIUM, headless=True,
                                     args=CHROMIUM_ARGS)
        try:
            yield chromium
        finally:
            chromium.close()


@pytest.fixture(scope="module")
def stack(tmp_path_factory, browser):
    s = Stack(tmp_path_factory.mktemp("console"))
    yield s
    s.stop()


@pytest.fixture
def page(browser, stack):
    context = browser.new_context(viewport={"width": 1280, "height": 900})
    page = context.new_page()
    page.set_default_timeout(60_000)
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.on("dialog", lambda dialog: dialog.accept())
    yield page
    context.close()
    assert not errors, f"JavaScript errors in the console: {errors}"


def _fits_width(page) -> bool:
    return page.evaluate("document.documentElement.scrollWidth <= window.innerWidth + 1")


def _start(page, stack, procedure: str, values: dict[str, str]) -> None:
    page.goto(f"{stack.base}/console/start?procedure={procedure}")
    for name, value in values.items():
        page.fill(f"#f-{name}", value)
    page.click("#start-form button[type=submit]")


@pytest.mark.timeout(900)
def test_console_end_to_end(page, stack, artifacts):
    base = stack.base
    # 1. every page opens, at desktop width, without script errors
    for path, heading in (("/console/", f"Rig {stack.rig_name}"), ("/console/runs", "Runs"),
                          ("/console/history", "Calibration history"),
                          ("/console/start", "Start a procedure")):
        page.goto(base + path)
        assert page.locator("h2").first.inner_text() == heading
        assert _fits_width(page), f"{path} overflows 1280 px"
    page.goto(base + "/console/")
    assert "head" in page.locator("details").first.inner_text()
    page.screenshot(path=artifacts / "rig-idle.png", full_page=True)

    # a refusal without the token shows the server's message and asks for the token
    _start(page, stack, "capture-survey", {"views": "1"})
    page.wait_for_selector("#message.error")
    assert "missing or wrong bearer token" in page.inner_text("#message")
    page.fill("#token", TOKEN)
    page.click("#token-form button")
    assert page.inner_text("#token-state").strip() == "set"

    # 2-3. a capture-survey from the form; its progress reaches the end over /events
    _start(page, stack, "capture-survey", {"pan_deg": "-5, 5", "tilt_deg": "0",
                                           "views": "2", "settle_s": "0.05"})
    page.wait_for_selector("#started:not([hidden])")
    run_id = page.inner_text("#started-link").strip()
    assert re.fullmatch(r"\d{8}T\d{6}-capture-survey-[0-9a-f]+", run_id)
    page.wait_for_function(
        "document.getElementById('started-text').textContent.startsWith('finished')",
        timeout=WAIT_MS)
    assert page.inner_text("#started-text") == "finished: succeeded"
    done = page.evaluate("[document.getElementById('started-progress').value,"
                         " document.getElementById('started-progress').max]")
    assert done[0] == done[1] > 1
    page.screenshot(path=artifacts / "start-finished.png", full_page=True)

    # 4. the run's page: parameters, log and four captures as thumbnails that load
    page.click("#started-link")
    page.wait_for_url(f"**/console/runs/{run_id}")
    assert page.inner_text("#run-status") == "succeeded"
    thumbs = page.locator(".thumb img")
    assert thumbs.count() == 4  # 2 pan x 1 tilt + 2 arm views
    page.wait_for_function("[...document.querySelectorAll('.thumb img')]"
                           ".every(i => i.complete && i.naturalWidth === 320)")
    full = page.locator(".thumb").first.get_attribute("href")
    assert get(base + full).headers["content-type"] == "image/png"
    assert '"views": 2' in page.inner_text("pre")
    page.screenshot(path=artifacts / "run-capture-survey.png", full_page=True)

    # 5. a calibration from the form, followed live on the rig page; a second run queued
    # behind it is aborted from the rig page's queue
    _start(page, stack, "active-camera", {"pan_deg": "5", "tilt_deg": "5"})
    page.wait_for_selector("#started:not([hidden])")
    camera_run = page.inner_text("#started-link").strip()
    queued = post(stack, "/runs", {"procedure": "capture-survey",
                                   "params": {"views": 1}}).json()["run_id"]
    page.goto(base + "/console/")
    page.wait_for_selector(f"#queue button[data-abort='{queued}']")
    page.click(f"#queue button[data-abort='{queued}']")
    page.wait_for_selector("#message.info")
    assert wait_for(stack, queued, statuses=("aborted",))["status"] == "aborted"
    page.wait_for_selector(f"#current-run a[href='/console/runs/{camera_run}']",
                           timeout=WAIT_MS)
    page.wait_for_function("document.getElementById('progress')"
                           " && document.getElementById('progress').value > 0",
                           timeout=WAIT_MS)
    page.screenshot(path=artifacts / "rig-running.png", full_page=True)
    assert wait_for(stack, camera_run, timeout=WAIT_MS // 1000)["status"] == "succeeded"
    page.wait_for_function("document.querySelector('#current-run .muted')", timeout=WAIT_MS)

    # accept it with a comment; the history shows the decision and the comment
    page.goto(base + "/console/history?procedure=active-camera")
    row = page.locator(f"tr:has(a[href='/console/runs/{camera_run}'])")
    assert row.locator(".badge").inner_text() == "pending"
    page.goto(f"{base}/console/runs/{camera_run}")
    assert float(page.locator("table.result tr:has-text('fx') td.num").first.inner_text()) \
        == pytest.approx(900.0, rel=0.005)  # the ideal world's focal length
    page.fill("#decision-form textarea", "lens refocused, checked by hand")
    page.click("#decision-form button[value=accept]")
    page.wait_for_selector("#run-decision.accepted")
    page.goto(base + "/console/history?procedure=active-camera")
    row = page.locator(f"tr:has(a[href='/console/runs/{camera_run}'])")
    assert row.locator(".badge").inner_text() == "accepted"
    assert "lens refocused, checked by hand" in row.inner_text()
    page.wait_for_function("document.querySelector('img.plot').naturalWidth > 0")
    page.screenshot(path=artifacts / "history.png", full_page=True)

    # 6. bad parameters show the server's refusal, and nothing is queued
    before = len(get(base + "/runs?limit=1000").json())
    _start(page, stack, "capture-survey", {"views": "500"})
    page.wait_for_selector("#message.error")
    assert "views" in page.inner_text("#message")
    assert "less than or equal to 50" in page.inner_text("#message")
    _start(page, stack, "capture-survey", {"pan_deg": "500", "views": "0"})
    page.wait_for_selector("#message.error")
    refusal = post(stack, "/runs", {"procedure": "capture-survey",
                                    "params": {"pan_deg": [500], "views": 0}}).json()["detail"]
    assert refusal in page.inner_text("#message")  # the same text the CLI prints
    page.screenshot(path=artifacts / "start-refused.png", full_page=True)
    assert len(get(base + "/runs?limit=1000").json()) == before


@pytest.mark.timeout(300)
def test_console_fits_a_tablet(browser, stack, artifacts):
    context = browser.new_context(viewport={"width": 820, "height": 1180}, has_touch=True)
    page = context.new_page()
    try:
        for name, path in (("rig", "/console/"), ("runs", "/console/runs"),
                           ("history", "/console/history"), ("start", "/console/start")):
            page.goto(stack.base + path)
            assert _fits_width(page), f"{path} overflows a tablet's width"
            page.screenshot(path=artifacts / f"tablet-{name}.png", full_page=True)
    finally:
        context.close()
