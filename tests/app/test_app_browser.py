"""Browser tests of the web app: a real server subprocess driven by headless Debian Chromium.

The server (``dvr-perception app``) serves a 40-voxel phantom on a free loopback port; the
page is loaded once and the tests run in file order on it.  Without Chromium or playwright the
tests skip, except under ``CI=true`` where they fail.
"""

from __future__ import annotations

import io
import json
import os
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]
IN_CI = os.environ.get("CI", "").lower() in ("1", "true", "yes")
START_TIMEOUT_S = 60
ACTION_TIMEOUT_MS = 60_000

pytestmark = [pytest.mark.vtk_render, pytest.mark.slow]


def _missing(reason: str) -> None:
    if IN_CI:
        pytest.fail(f"required under CI=true: {reason}")
    pytest.skip(reason)


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait_listening(port: int, proc: subprocess.Popen, log: Path) -> None:
    deadline = time.monotonic() + START_TIMEOUT_S
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            pytest.fail(f"app server exited ({proc.returncode}):\n{log.read_text()[-3000:]}")
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=1):
                return
        except OSError:
            time.sleep(0.3)
    pytest.fail(f"app server did not listen within {START_TIMEOUT_S} s:\n{log.read_text()[-3000:]}")


@pytest.fixture(scope="module")
def server(tmp_path_factory, vtk_can_render):
    root = tmp_path_factory.mktemp("app")
    data, exports = root / "data", root / "exports"
    data.mkdir()
    from dvr_perception.structures import save_spec
    from dvr_perception.volume import make_phantom

    _, spec = make_phantom(size=16)
    save_spec(spec.with_opacities([0.9] * len(spec.structures)), data / "opaque.json")
    (data / "bad.json").write_text('{"version": 1, "structures": [', encoding="utf-8")
    (root / "outside.json").write_text("{}", encoding="utf-8")
    port = _free_port()
    env = dict(os.environ)
    if not env.get("DISPLAY"):
        env["VTK_DEFAULT_OPENGL_WINDOW"] = "vtkEGLRenderWindow"
    cmd = [sys.executable, "-c", "from dvr_perception.cli import main; raise SystemExit(main())"]
    cmd += ["app", "--port", str(port), "--host", "127.0.0.1", "--data-dir", str(data)]
    cmd += ["--export-dir", str(exports), "--phantom-size", "40"]
    log = root / "server.log"
    with log.open("w") as out:
        proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, env=env, cwd=root)
    try:
        _wait_listening(port, proc, log)
        yield {"url": f"http://127.0.0.1:{port}/", "proc": proc, "exports": exports, "log": log}
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=10)


@pytest.fixture(scope="module")
def page(server):
    chromium = CHROMIUM if Path(CHROMIUM).is_file() else shutil.which("chromium")
    if chromium is None:
        _missing("Debian chromium not installed (apt-get install -y chromium)")
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        _missing("playwright not installed (pip install '.[app]')")
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=chromium, args=CHROMIUM_ARGS)
        try:
            pg = browser.new_page(viewport={"width": 1280, "height": 820})
            pg.set_default_timeout(ACTION_TIMEOUT_MS)
            pg.goto(server["url"])
            pg.wait_for_selector("#view img, #view canvas", state="attached")
            yield pg
        finally:
            browser.close()


def _value(page, key: str) -> float:
    return float(page.inner_text(f"#value-{key}"))


def _wait_value(page, key: str, *, not_equal: str | None = None) -> float:
    """Wait until the number is shown (and differs from ``not_equal``), return it."""
    page.wait_for_function(
        """([sel, old]) => {
            const el = document.querySelector(sel);
            if (!el) return false;
            const t = el.innerText.trim();
            return !isNaN(parseFloat(t)) && (old === null || t !== old);
        }""",
        arg=[f"#value-{key}", not_equal],
    )
    return _value(page, key)


def _view_image(page) -> np.ndarray:
    from PIL import Image

    png = page.locator("#view").screenshot()
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.float64) / 255.0


def _wait_image_change(page, before: np.ndarray, *, tries: int = 40) -> np.ndarray:
    for _ in range(tries):  # the pushed image arrives asynchronously
        img = _view_image(page)
        if img.shape == before.shape and np.abs(img - before).mean() > 1e-4:
            return img
        page.wait_for_timeout(250)
    return img


def _error_text(page) -> str:
    page.wait_for_selector("#error-message", state="visible")
    return page.inner_text("#error-message")


def test_page_shows_rendered_volume_and_measures(page):
    assert "Readable transparent volume rendering" in page.content()
    for key in ("E_v", "E_s", "E_t"):
        assert _wait_value(page, key) >= 0.0
    for _ in range(60):  # the first image arrives asynchronously
        img = _view_image(page)
        if img.std() > 0.02:
            break
        page.wait_for_timeout(250)
    assert img.std() > 0.02, "the view is blank"
    assert (img.max(axis=2) > 0.1).mean() > 0.05, "almost nothing rendered"
    assert page.locator("#structure-table tr").count() == 1 + 6


def _optimise(page, button: str) -> None:
    """Click an optimise button and wait until that run is done."""
    page.click(button)
    page.wait_for_selector("#cancel:not([disabled])")  # running
    page.wait_for_selector("#cancel[disabled]")  # finished
    assert page.inner_text("#progress-text").startswith("done")


def _load_spec(page, name: str) -> None:
    page.get_by_label("Spec file (in the data folder)").fill(name)
    page.click("#load-spec")


def test_optimise_opacity_lowers_visibility_error_and_changes_image(page):
    # start from a poor spec: every structure 90 % opaque, the outer layers hide the inner
    ev_text = page.inner_text("#value-E_v").strip()
    _load_spec(page, "opaque.json")
    _wait_value(page, "E_v", not_equal=ev_text)
    page.wait_for_selector("#measuring", state="hidden")
    ev_text = page.inner_text("#value-E_v").strip()
    ev0 = float(ev_text)
    before = _view_image(page)
    _optimise(page, "#optimise-opacity")
    ev1 = _wait_value(page, "E_v", not_equal=ev_text)
    assert ev1 < ev0
    after = _wait_image_change(page, before)
    assert np.abs(after - before).mean() > 1e-4, "the image did not change"
    # undo restores the previous spec and its error
    page.click("#undo")
    assert _wait_value(page, "E_v", not_equal=page.inner_text("#value-E_v").strip()) == ev0


def test_optimise_all_stages_and_quality_map(page, server):
    page.click("#show-map")
    _optimise(page, "#optimise-all")
    page.wait_for_selector("#measuring", state="hidden")
    assert _wait_value(page, "E_t") >= 0.0
    assert server["proc"].poll() is None
    page.click("#show-map")


def test_path_outside_data_folder_is_a_visible_error(page, server):
    _load_spec(page, "../outside.json")
    assert "outside the data folder" in _error_text(page)
    assert server["proc"].poll() is None


def test_malformed_spec_is_a_visible_error(page, server):
    _load_spec(page, "bad.json")
    page.wait_for_function(
        "() => document.querySelector('#error-message')?.innerText.includes('bad')"
    )
    assert "JSON" in _error_text(page) or "json" in _error_text(page)
    assert server["proc"].poll() is None
    assert _value(page, "E_v") >= 0.0  # the page still works


def test_export_writes_valid_files(page, server):
    page.click("#export")
    page.wait_for_function("() => document.querySelectorAll('#export-list').length === 4")
    files = {p.name: p for p in server["exports"].iterdir()}
    assert set(files) == {
        "phantom_view.png",
        "phantom_spec.json",
        "phantom_paraview.json",
        "phantom.vp.json",
    }
    assert files["phantom_view.png"].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    from dvr_perception.structures import load_spec

    assert len(load_spec(files["phantom_spec.json"]).structures) == 6
    json.loads(files["phantom_paraview.json"].read_text())
    json.loads(files["phantom.vp.json"].read_text())
    assert server["proc"].poll() is None
