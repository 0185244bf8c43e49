"""'Optimise all' in the browser against ``dvr-perception optimize``, both timed here (issue 20).

The app serves cthead; the page is sized so that the view is about :data:`VIEW_PX` pixels
square (smaller than the issue's 512\u00b2 to fit the CI budget).  "Optimise all" is clicked and
timed until the page says it is done; then ``dvr-perception optimize`` runs in a subprocess on
the very camera the app's optimiser used (the page exposes it) and is timed the same way.  The
app may take at most :data:`MAX_RATIO` times as long.  Both run :data:`ITERATIONS` iterations
per stage (the CLI's and the app's default is 10; fewer keep the test short).
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.conftest import _missing

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--no-first-run"]
VIEW_PX = 128
ITERATIONS = 3
MAX_RATIO = 1.5
DRAWER_PX, TOOLBAR_PX = 470, 48

pytestmark = [pytest.mark.vtk_render, pytest.mark.slow]


@pytest.fixture(scope="module")
def cthead_page(tmp_path_factory, vtk_can_render, app_server, shared_data):
    data = shared_data
    chromium = CHROMIUM if Path(CHROMIUM).is_file() else shutil.which("chromium")
    if chromium is None:
        _missing("Debian chromium not installed (apt-get install -y chromium)")
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        _missing("playwright not installed (pip install '.[app]')")
    root = tmp_path_factory.mktemp("speed")
    start, stop = app_server
    srv = start(
        root,
        [
            "--data-dir",
            str(data),
            "--state-dir",
            str(root / "state"),
            "cthead.nhdr",
            "--iterations",
            str(ITERATIONS),
        ],
    )
    try:
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=chromium, args=CHROMIUM_ARGS)
            try:
                size = {"width": DRAWER_PX + VIEW_PX, "height": TOOLBAR_PX + VIEW_PX}
                pg = browser.new_page(viewport=size)
                pg.set_default_timeout(120_000)
                pg.goto(srv["url"])
                pg.wait_for_selector("#view img, #view canvas", state="attached")
                pg.wait_for_selector("#measuring", state="hidden")
                yield pg, root, data
            finally:
                browser.close()
    finally:
        stop(srv["proc"])


def _run_all(page) -> float:
    """Click 'Optimise all', return the seconds until the page says it is done."""
    t0 = time.monotonic()
    page.click("#optimise-all")
    page.wait_for_selector("#cancel:not([disabled])")
    page.wait_for_selector("#cancel[disabled]")
    seconds = time.monotonic() - t0
    assert page.inner_text("#progress-text").startswith("done")
    return seconds


def test_optimise_all_is_as_fast_as_the_cli(cthead_page):
    page, root, data = cthead_page
    page.click("#tab-optimise")
    page.wait_for_selector("#panel-optimise", state="visible")
    app_s = _run_all(page)
    camera = json.loads(page.get_attribute("#opt-camera", "data-camera"))
    (root / "camera.json").write_text(json.dumps(camera), encoding="utf-8")
    cmd = [sys.executable, "-c", "from dvr_perception.cli import main; raise SystemExit(main())"]
    cmd += ["optimize", str(data / "cthead.nhdr"), "--camera", str(root / "camera.json")]
    cmd += ["--max-iter", str(ITERATIONS), "--out", str(root / "cli"), "--json"]
    t0 = time.monotonic()
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=600, cwd=root)
    cli_s = time.monotonic() - t0
    assert done.returncode == 0, done.stderr[-2000:]
    report = json.loads(done.stdout)
    assert report["size"] == [camera["width"], camera["height"]]
    print(f"\nOptimise all at {camera['width']}x{camera['height']}: app {app_s:.1f} s, "
          f"CLI {cli_s:.1f} s")  # fmt: skip
    assert app_s <= MAX_RATIO * cli_s, (app_s, cli_s)
