"""The dashboard in a real headless chromium (selenium): video, plots, ROI drag, screenshots."""

from __future__ import annotations

import asyncio
import re
import shutil
import time
from collections.abc import AsyncIterator, Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from dffd.web.server import DashboardServer, WebSettings
from tests.web_support import SyntheticDaemon

CHROMEDRIVER = "/usr/bin/chromedriver"
CHROMIUM = "/usr/bin/chromium"
# Page load, first frames and first plot points: a second or two on an idle machine; the
# shared 2-core CI box can be several times slower.
BROWSER_TIMEOUT_S = 20.0
_POLL_S = 0.1  # period at which a page condition is re-read (selenium has no push)

pytestmark = pytest.mark.skipif(
    not (Path(CHROMEDRIVER).exists() and Path(CHROMIUM).exists()),
    reason="needs Debian's chromium and chromium-driver",
)


def chrome_options(profile: Path) -> Any:
    """Headless chromium that touches nothing outside ``profile``."""
    from selenium.webdriver.chrome.options import Options

    options = Options()
    options.binary_location = CHROMIUM
    for arg in (
        "--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
        "--disable-background-networking", "--disable-component-update", "--disable-sync",
        "--no-first-run", f"--user-data-dir={profile}", "--window-size=1400,1400",
    ):  # fmt: skip
        options.add_argument(arg)
    return options


@pytest.fixture
def browser(tmp_path: Path) -> Iterator[Any]:
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    driver = webdriver.Chrome(
        service=Service(CHROMEDRIVER), options=chrome_options(tmp_path / "profile")
    )
    try:
        yield driver
    finally:
        driver.quit()
        shutil.rmtree(tmp_path / "profile", ignore_errors=True)


@pytest.fixture
async def served() -> AsyncIterator[tuple[SyntheticDaemon, DashboardServer]]:
    daemon = SyntheticDaemon(asyncio.get_running_loop())
    daemon.start()
    try:
        async with DashboardServer(WebSettings("127.0.0.1", 0), daemon, daemon.metrics) as srv:
            yield daemon, srv
    finally:
        daemon.stop()


async def wait_for(what: str, condition: Callable[[], Any]) -> Any:
    """Poll a blocking page condition in a thread (the server runs on this loop) until truthy."""
    deadline = time.monotonic() + BROWSER_TIMEOUT_S
    while True:
        value = await asyncio.to_thread(condition)
        if value:
            return value
        if time.monotonic() > deadline:
            raise TimeoutError(f"the page did not show {what} within {BROWSER_TIMEOUT_S} s")
        await asyncio.sleep(_POLL_S)


async def test_dashboard_video_plot_and_roi_drag(
    served: tuple[SyntheticDaemon, DashboardServer], browser: Any, tmp_path: Path
) -> None:
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By

    daemon, server = served
    await asyncio.to_thread(browser.get, server.url + "/")

    def attr(name: str) -> int:
        return int(browser.find_element(By.TAG_NAME, "body").get_attribute(f"data-{name}") or 0)

    def video_pixels() -> str:
        return str(browser.execute_script("return document.getElementById('video').toDataURL()"))

    await wait_for("video frames", lambda: attr("frames") >= 2)
    first = await asyncio.to_thread(video_pixels)
    frames = attr("frames")
    await wait_for("new video frames", lambda: attr("frames") >= frames + 3)
    assert await asyncio.to_thread(video_pixels) != first  # the picture changes, not only a count
    points = await wait_for("plot points", lambda: attr("points"))
    await wait_for("the plot growing", lambda: attr("points") > points + 5)
    await wait_for(
        "state tracking", lambda: browser.find_element(By.ID, "state").text == "TRACKING"
    )

    # An empty rejection list reads "none", not a numbered "1. none".
    empty = browser.execute_script(
        "showRejections([]); const li = document.querySelector('#rejections li');"
        "return [li.textContent, getComputedStyle(li).listStyleType];"
    )
    assert empty == ["none", "none"]

    # The 3D track: acceleration, angular speed, position σ and the model probabilities render.
    def text(element_id: str) -> str:
        return str(browser.find_element(By.ID, element_id).text)

    await wait_for("the 3D track", lambda: text("track-sigma") != "–")
    # docs/dashboard.png is this screenshot (pytest --basetemp=DIR, then copy it from there).
    await asyncio.to_thread(browser.save_screenshot, str(tmp_path / "dashboard.png"))
    numbers = r"-?\d+\.\d+"
    assert re.fullmatch(rf"{numbers}, {numbers}, {numbers}", text("track-acc"))
    assert re.fullmatch(rf"{numbers} rad/s \({numbers}°/s\)", text("track-omega"))
    sigma_mm = [float(v) for v in text("track-sigma").split(", ")]
    assert len(sigma_mm) == 3
    assert all(0.0 < v < 1000.0 for v in sigma_mm)
    bars = browser.find_elements(By.CSS_SELECTOR, "#track-probs .prob")
    assert [b.get_attribute("data-model") for b in bars] == ["cv", "ca", "ct"]
    probs = [float(b.find_element(By.CLASS_NAME, "value").text) for b in bars]
    assert sum(probs) == pytest.approx(1.0, abs=3e-3)  # three rounded to 3 digits

    # Drag a box around the disc (centre of the 320×240 frame, ~80 px wide at 5 m).
    canvas = browser.find_element(By.ID, "video")
    rect = browser.execute_script(
        "const r = arguments[0].getBoundingClientRect(); return [r.width, r.height];", canvas
    )
    sx, sy = rect[0] / 320, rect[1] / 240
    n_acquires = len(daemon.acquires)

    def drag() -> None:
        (
            ActionChains(browser)
            .move_to_element_with_offset(canvas, int(-60 * sx), int(-60 * sy))
            .click_and_hold()
            .move_by_offset(int(60 * sx), int(60 * sy))
            .move_by_offset(int(60 * sx), int(60 * sy))
            .release()
            .perform()
        )

    await asyncio.to_thread(drag)
    await wait_for("the acquire reply", lambda: "reply ok" in (
        browser.find_element(By.ID, "reply").get_attribute("class") or ""
    ))  # fmt: skip
    assert len(daemon.acquires) == n_acquires + 1
    x, y, w, h = daemon.acquires[-1]
    assert (x, y, w, h) == pytest.approx((100, 60, 120, 120), abs=4)
    reply = browser.find_element(By.ID, "reply").text
    assert '"cmd":"acquire"' in reply
    assert '"ok":true' in reply
    # The daemon re-acquires inside the box and estimates keep coming.
    seen = attr("points")
    await wait_for("estimates after the acquisition", lambda: attr("points") > seen + 5)
    await wait_for(
        "state tracking", lambda: browser.find_element(By.ID, "state").text == "TRACKING"
    )
    await asyncio.to_thread(browser.save_screenshot, str(tmp_path / "dashboard-after-roi.png"))
    for name in ("dashboard.png", "dashboard-after-roi.png"):
        assert (tmp_path / name).stat().st_size > 10_000
