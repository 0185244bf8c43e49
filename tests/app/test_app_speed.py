"""Speed of the web app on cthead, measured in the browser (issue 20).

'Optimise all' in the browser against ``dvr-perception optimize``, both timed here;
rotation at 512\u00b2 in the quick preview counted in painted frames per second.

The app serves cthead in one page whose view is :data:`VIEW_PX` pixels square, the issue's
512\u00b2.  The app measures and optimises on that view reduced to its sampling resolution
(:data:`~dvr_perception.app.session.MEASURE_SIZE`, 256\u00b2; the page names it).  "Optimise
all" is clicked and timed until the page says it is done and the result's 512\u00b2 image is
rendered; then ``dvr-perception optimize`` runs in a subprocess on the very camera the app's
optimiser used (the page exposes it) and is timed the same way.  The app may take at most
:data:`MAX_RATIO` times as long.  Both run :data:`ITERATIONS` iterations per stage (the CLI's
and the app's default is 10; fewer keep the test short).  The rotation test drags in the same
page (no second page to open and render).
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from dvr_perception.app.session import MEASURE_SIZE
from tests.conftest import _missing

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--no-first-run"]
VIEW_PX = 512
ITERATIONS = 3
MAX_RATIO = 1.5
DRAWER_PX, TOOLBAR_PX, FOOTER_PX = 470, 48, 20

pytestmark = [pytest.mark.vtk_render, pytest.mark.slow]


#: Counts, in the page, the frames in which the preview's WebGL canvas was drawn into with a
#: camera other than in the previous counted frame (wraps the context's draw calls).
FRAME_COUNTER = """
(() => {
  window.__draws = 0;
  const orig = HTMLCanvasElement.prototype.getContext;
  HTMLCanvasElement.prototype.getContext = function (type, attrs) {
    const ctx = orig.call(this, type, attrs);
    if (ctx && /webgl/.test(type) && !ctx.__counted) {
      ctx.__counted = true;
      for (const name of ['drawArrays', 'drawElements', 'drawArraysInstanced',
                          'drawElementsInstanced', 'drawRangeElements']) {
        const f = ctx[name];
        if (typeof f !== 'function') continue;
        ctx[name] = function (...a) { window.__draws += 1; return f.apply(this, a); };
      }
    }
    return ctx;
  };
  window.__frames = {on: false, n: 0, t0: 0, t1: 0, last: ''};
  const tick = () => {
    const F = window.__frames;
    if (F.on && window.__draws > 0) {
      const cam = window.trame?.refs?.local?.getCamera();
      const key = cam ? cam.position.map(v => v.toFixed(4)).join(',') : '';
      if (key !== F.last) { F.n += 1; F.last = key; }
    }
    window.__draws = 0;
    requestAnimationFrame(tick);
  };
  requestAnimationFrame(tick);
})();
"""


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
            "--verbose",  # the server logs how long each rendering and measurement took
        ],
    )
    try:
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=chromium, args=CHROMIUM_ARGS)
            try:
                size = {"width": DRAWER_PX + VIEW_PX, "height": TOOLBAR_PX + VIEW_PX + FOOTER_PX}
                pg = browser.new_page(viewport=size)
                pg.set_default_timeout(120_000)
                pg.add_init_script(FRAME_COUNTER)  # for the rotation test
                pg.goto(srv["url"])
                pg.wait_for_selector("#view img, #view canvas", state="attached")
                pg.wait_for_selector("#measuring", state="hidden")
                pg.server_log = srv["log"]
                yield pg, root, data
            finally:
                browser.close()
    finally:
        stop(srv["proc"])


#: Records every text the progress line shows (a MutationObserver on the page).
WATCH_PROGRESS = """() => {
  window.__progress = [];
  const el = document.querySelector('#progress-text');
  new MutationObserver(() => window.__progress.push(el.innerText))
    .observe(el, {childList: true, characterData: true, subtree: true});
}"""


def _run_all(page) -> tuple[float, list[str]]:
    """Click 'Optimise all'; return the seconds until the page says done, and the progress."""
    page.evaluate(WATCH_PROGRESS)
    t0 = time.monotonic()
    page.click("#optimise-all")
    page.wait_for_selector("#cancel:not([disabled])")
    page.wait_for_selector("#cancel[disabled]")
    seconds = time.monotonic() - t0
    assert page.inner_text("#progress-text").startswith("done")
    return seconds, page.evaluate("() => window.__progress")


#: The command line, as the test runs it (the pip environment's Python).
CLI = [sys.executable, "-c", "from dvr_perception.cli import main; raise SystemExit(main())"]


def _compile_optimiser_kernels(volume: Path, root: Path) -> None:
    """One tiny, untimed ``optimize`` of ``volume``: numba compiles (and caches on disk) the
    optimiser's kernels for its data type, so neither timed run pays that once-per-machine
    cost (on a fresh clone it was 25 s, all of it in the app's run, which came first)."""
    cmd = [*CLI, "optimize", str(volume), "--size", "128", "--max-iter", "1"]
    cmd += ["--out", str(root / "warm"), "--verbose"]  # -v: the progress path, as the app
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=600, cwd=root)
    assert done.returncode == 0, done.stderr[-2000:]


def test_optimise_all_is_as_fast_as_the_cli(cthead_page):
    page, root, data = cthead_page
    _compile_optimiser_kernels(data / "cthead.nhdr", root)
    page.click("#tab-optimise")
    page.wait_for_selector("#panel-optimise", state="visible")
    app_s, texts = _run_all(page)
    # progress before the first iteration (the library's progress= callback), then per stage
    # and iteration with the time left
    assert any(re.match(r"analysing the view before the first iteration: \d+ %", t) for t in texts)
    assert any(re.match(r"step \d of 3 \(\w+\): iteration \d+ of 3;.* s left$", t) for t in texts)
    camera = json.loads(page.get_attribute("#opt-camera", "data-camera"))
    # the app optimised the 512x512 view at its sampling resolution, and the page names it
    assert (camera["width"], camera["height"]) == (MEASURE_SIZE, MEASURE_SIZE), camera
    sampling = page.inner_text("#opt-sampling")
    px = f"{VIEW_PX}\u00d7{VIEW_PX} px view at {MEASURE_SIZE}\u00d7{MEASURE_SIZE} px"
    assert px in sampling, sampling
    (root / "camera.json").write_text(json.dumps(camera), encoding="utf-8")
    cmd = [*CLI, "optimize", str(data / "cthead.nhdr"), "--camera", str(root / "camera.json")]
    cmd += ["--max-iter", str(ITERATIONS), "--out", str(root / "cli"), "--json"]
    t0 = time.monotonic()
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=600, cwd=root)
    cli_s = time.monotonic() - t0
    assert done.returncode == 0, done.stderr[-2000:]
    report = json.loads(done.stdout)
    assert report["size"] == [camera["width"], camera["height"]]
    load = " ".join(f"{v:.2f}" for v in os.getloadavg())
    print(f"\nOptimise all, {VIEW_PX}x{VIEW_PX} view sampled at {camera['width']}x"
          f"{camera['height']}: app {app_s:.1f} s, CLI {cli_s:.1f} s (ratio "
          f"{app_s / cli_s:.2f}); load average {load}; page: {sampling!r}")  # fmt: skip
    assert app_s <= MAX_RATIO * cli_s, (app_s, cli_s)


#: The drag, in the page: a pointer move every MOVE_MS ms (a mouse's rate) for DRAG_MS ms,
#: to the right and up and down; the frame count runs meanwhile.  (Playwright's own moves wait
#: for a round trip each, which under load paces them slower than the page paints.)
DRAG = """
async ([x0, y0, ms, every]) => {
  const el = document.elementFromPoint(x0, y0);
  const F = Object.assign(window.__frames, {on: true, n: 0, t0: performance.now()});
  let k = 0, x = x0, y = y0;
  await new Promise(done => {
    const id = setInterval(() => {
      k += 1;
      x = x0 + 0.6 * k;
      y = y0 + 20 * Math.sin(k / 15);
      el.dispatchEvent(new PointerEvent('pointermove', {
        clientX: x, clientY: y, bubbles: true, cancelable: true, pointerId: 1,
        pointerType: 'mouse', isPrimary: true, buttons: 1}));
      if (performance.now() - F.t0 >= ms) { clearInterval(id); done(); }
    }, every);
  });
  F.on = false;
  F.t1 = performance.now();
  const label = document.querySelector('#view-mode');
  const canvas = document.querySelector('#local-view canvas');
  return {n: F.n, t0: F.t0, t1: F.t1, moves: k, x, y, mode: label.dataset.mode,
          label: label.innerText, canvas: [canvas.width, canvas.height], target: el.tagName};
}
"""
DRAG_MS, MOVE_MS = 2000, 8
#: The issue's 10 frames/s at 512x512.  The preview's canvas is half the view's size (stretched
#: to it) and vtk.js lowers the resolution further while moving: 31-35 frames/s at load 6 on the
#: shared 2-core machine, where the full-size canvas gave 9.5 (see dvr_perception.app.ui_preview).
MIN_FPS = 10.0
#: Seconds from the end of a drag until the numbers for the new view are on the page: the
#: issue's 2 s.  The server measures first and renders the exact image at 512x512 (which holds
#: its event loop) only once the numbers have been sent (``TFHandlers._image_after_numbers``).
#: Rendered first, the image had kept them back: 1.5-4.4 s at load 3.0-4.8 after 'Optimise
#: all' (render 1.2-3.8 s).  Since (2026-12-03, shared 2-core machine): 0.54-0.99 s in the
#: whole file (render 1.7-2.5 s, measure 0.3-0.6 s) at load 3.5-4.4, 0.2-0.7 s with
#: ``-k rotation`` at load 2.1-4.7; the test prints both timings (the server's --verbose log).
MAX_REMEASURE_S = 2.0


def _steps(log: Path, key: str) -> str:
    """The server's timings for the view and settings ``key`` (its ``--verbose`` log)."""
    text = log.read_text(errors="replace")
    found = [
        f"{what} {m.group(1)} s"
        for what, pattern in (
            ("VTK image rendered in", "image rendered in"),
            ("measured in", "measured in"),
        )
        for m in [re.search(rf"view\.settings {re.escape(key)}: {pattern} ([\d.]+) s", text)]
        if m
    ]
    return "; ".join(found) or "no timings in the server log"


#: The dimensions of the volume vtk.js holds in the page's preview (``null``: none yet).
PREVIEW_DIMS = """() => {
  const rw = window.trame?.refs?.local?.$?.provides?.view?.renderWindow;
  for (const ren of rw ? rw.getRenderers() : []) {
    for (const vol of ren.getVolumes()) {
      const data = vol.getMapper()?.getInputData();
      if (data) return data.getDimensions();
    }
  }
  return null;
}"""

#: Untimed drags at most before the timed one (until the preview paints).
WARM_DRAGS = 3


def _warm_drag(pg, cx: float, cy: float) -> dict:
    """An untimed drag of 0.6 s from ``(cx, cy)``; return its frame count once the view rests."""
    from playwright.sync_api import TimeoutError as PageTimeout

    key = pg.get_attribute("#now-key", "data-now")
    pg.mouse.move(cx, cy)
    pg.mouse.down()
    warm = pg.evaluate(DRAG, [cx, cy, 600, MOVE_MS])
    pg.mouse.move(warm["x"], warm["y"])
    pg.mouse.up()
    with contextlib.suppress(PageTimeout):  # no move got through: nothing to wait for
        pg.wait_for_function(
            "(old) => document.querySelector('#now-key').dataset.now !== old",
            arg=key,
            timeout=15_000,
        )
    pg.wait_for_function(
        "() => document.querySelector('#value-E_v').dataset.key === "
        "document.querySelector('#now-key').dataset.now && "
        "document.querySelector('#view-mode').dataset.mode === 'exact'",
        polling=50,
    )
    return warm


def test_rotation_in_the_preview_counts_frames_at_512(cthead_page):
    """A scripted drag of 2 s over the 512\u00b2 view: count the new frames painted.

    A frame counts when, in one animation frame of the page, the preview's WebGL context
    drew and the preview's camera differs from the last counted frame: frames the user sees
    change.  The exact image is hidden meanwhile (``#view-mode`` says which is shown).
    """
    pg, _, _ = cthead_page  # the module's page: the frame counter is in it from the start
    pg.wait_for_selector("#local-view canvas", state="attached")
    pg.wait_for_selector("#measuring", state="hidden")
    box = pg.locator("#view").bounding_box()
    assert (round(box["width"]), round(box["height"])) == (VIEW_PX, VIEW_PX)
    assert pg.get_attribute("#view-mode", "data-mode") == "exact"
    cx, cy = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    # untimed drags first: the preview's scene goes to the page when a drag starts (building
    # vtk.js's volume takes seconds on a loaded machine), then the view rests.  In a page just
    # opened (this test alone) the first drag can end before the preview paints: drag again.
    for _ in range(WARM_DRAGS):
        warm = _warm_drag(pg, cx, cy)
        if warm["n"] >= 3:  # the preview painted the moving camera
            break
    assert warm["n"] >= 3, warm
    # the preview is the whole volume, not a reduced copy (issue 30), and the label says so
    assert pg.evaluate(PREVIEW_DIMS) == [256, 256, 113]
    assert (
        pg.get_attribute("#view-mode", "data-detail") == "full volume, 256\u00d7256\u00d7113 voxels"
    )
    key = pg.get_attribute("#now-key", "data-now")
    pg.mouse.move(cx, cy)
    pg.mouse.down()
    frames = pg.evaluate(DRAG, [cx, cy, DRAG_MS, MOVE_MS])
    assert frames["mode"] == "preview", frames  # what was on screen during the drag
    # ... at half resolution, and the label says so
    assert frames["canvas"] == [VIEW_PX // 2, VIEW_PX // 2], frames
    assert "half resolution" in frames["label"], frames
    assert "full volume, 256\u00d7256\u00d7113 voxels" in frames["label"], frames
    pg.mouse.move(frames["x"], frames["y"])
    pg.mouse.up()
    t_up = time.monotonic()
    seconds = (frames["t1"] - frames["t0"]) / 1000.0
    fps = frames["n"] / seconds
    # the camera rests: the exact image and the numbers for the new view follow
    pg.wait_for_function("(old) => document.querySelector('#now-key').dataset.now !== old", arg=key)
    pg.wait_for_function(
        "() => document.querySelector('#value-E_v').dataset.key === "
        "document.querySelector('#now-key').dataset.now && "
        "!isNaN(parseFloat(document.querySelector('#value-E_v').innerText))",
        polling=50,
    )
    remeasure_s = time.monotonic() - t_up
    pg.wait_for_function("() => document.querySelector('#view-mode').dataset.mode === 'exact'")
    load = os.getloadavg()
    steps = _steps(pg.server_log, pg.get_attribute("#now-key", "data-now"))
    print(
        f"\npreview rotation at {VIEW_PX}x{VIEW_PX}: {frames['moves']} pointer moves, "
        f"{frames['n']} new frames in "
        f"{seconds:.2f} s = {fps:.1f} frames/s; numbers for the new view after "
        f"{remeasure_s:.2f} s ({steps}); load average {load[0]:.2f} {load[1]:.2f} "
        f"{load[2]:.2f}"
    )
    assert seconds >= 1.0  # the drag lasted (the count is over a real interval)
    assert fps >= MIN_FPS, (frames, seconds)
    assert remeasure_s <= MAX_REMEASURE_S, remeasure_s
