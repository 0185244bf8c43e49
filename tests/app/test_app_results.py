"""What the web app shows after an optimisation, checked in the server's own images (issue 30).

The app runs in this process (no browser): its handlers are called as the page calls them,
inside an event loop, and the thumbnails, the lens overlay and the view are compared pixel by
pixel with renderings of the specs they claim to show.
"""

from __future__ import annotations

import asyncio
import base64
import io

import numpy as np
import pytest

pytestmark = [pytest.mark.vtk_render, pytest.mark.slow]

#: Grey levels one 8-bit PNG step apart count as equal.
PNG_STEP = 1.5 / 255


def _decode(url: str) -> np.ndarray:
    """A PNG data URL as an ``(H, W, C)`` float image in [0, 1] (RGB or RGBA)."""
    from PIL import Image

    assert url.startswith("data:image/png;base64,"), url[:40]
    img = Image.open(io.BytesIO(base64.b64decode(url.split(",", 1)[1])))
    return np.asarray(img, dtype=np.float64) / 255.0


async def _idle(app) -> None:
    """Wait until no optimisation or measurement of ``app`` runs."""
    await asyncio.sleep(0.05)
    while app._task_running or app._measuring:
        await asyncio.sleep(0.05)
    await asyncio.sleep(0.1)


def _run(app, action) -> None:
    async def go():
        action()
        await _idle(app)

    asyncio.run(go())


def _thumb(app, img: np.ndarray) -> np.ndarray:
    """``img`` subsampled as the app's thumbnails are."""
    from dvr_perception.app.core import THUMB_WIDTH

    step = max(1, round(img.shape[1] / THUMB_WIDTH))
    return img[::step, ::step]


def _render(app, spec) -> np.ndarray:
    """The view rendered with ``spec`` (the app's spec is shown again afterwards)."""
    app._render_spec(spec)
    try:
        return app._render_rgb()
    finally:
        app._render_spec(app.session.spec)


@pytest.fixture(scope="module")
def app(tmp_path_factory, vtk_can_render):
    from trame.app import get_server

    from dvr_perception.app.core import DVRApp

    root = tmp_path_factory.mktemp("results")
    app = DVRApp(
        get_server("test_app_results", client_type="vue3"),
        state_dir=root / "state",
        export_dir=root / "exports",
        phantom_size=40,
        max_iter=3,
    )
    # a poor spec: the outer layers too opaque, the inner ones too faint
    app.session.spec = app.session.spec.with_opacities([0.6, 0.6, 0.6, 0.2, 0.2, 0.2])
    _run(app, lambda: app._show_spec(label="poor"))
    return app


def test_after_thumbnail_shows_the_result(app):
    """Today's code read the render window's last frame: after == before (issue 30)."""
    spec0 = app.session.spec
    _run(app, lambda: app.optimise("opacity"))
    assert app.state.progress_text.startswith("done"), app.state.progress_text
    assert app.session.spec is not spec0
    before, after = _decode(app.state.before_url), _decode(app.state.after_url)
    assert before.shape == after.shape
    assert np.abs(after - before).mean() > 1e-3, "the after thumbnail is the before image"
    # each thumbnail is the view rendered with its spec
    assert np.abs(before - _thumb(app, _render(app, spec0))).max() <= PNG_STEP
    assert np.abs(after - _thumb(app, _render(app, app.session.spec))).max() <= PNG_STEP
    _run(app, lambda: app.undo(1))
    assert app.session.spec == spec0


def _lens_rows(app, lens) -> list[dict]:
    app.state.lens = lens
    app._drop_lens_result()
    app._update_lens_rows()
    rows = app.state.lens_rows
    assert rows, app.state.lens_text
    return rows


def test_a_ticked_box_without_a_set_slider_is_no_target(app):
    rows = _lens_rows(app, {"shape": "rect", "x0": 0.3, "y0": 0.3, "x1": 0.7, "y1": 0.7})
    k = rows[-1]["index"]
    app.set_lens_target(k, "use_vis", True)
    assert app._lens_targets() == {}
    app.set_lens_target(k, "vis", 0.8)  # the slider: its box ticks, its value is the target
    assert app._lens_targets() == {rows[-1]["name"]: {"visibility": 0.8}}
    app.set_lens_target(k, "use_vis", False)
    assert app._lens_targets() == {}


def test_lens_result_is_shown_inside_the_lens_and_applied_on_request(app):
    from dvr_perception.app.lens import lens_mask

    lens = {"shape": "rect", "x0": 0.3, "y0": 0.3, "x1": 0.6, "y1": 0.65}
    rows = _lens_rows(app, lens)
    inner = max(rows, key=lambda r: app.session.spec.structures[r["index"]].importance)
    app.set_lens_target(inner["index"], "vis", 0.8)
    spec0 = app.session.spec
    n_undo = len(app.session.undo_stack)
    view0 = app._render_rgb()
    _run(app, lambda: app.optimise("opacity", in_lens=True))
    assert "in the lens" in app.state.progress_text, app.state.progress_text
    # nothing applied: the settings, the history and the view are as before
    assert app.session.spec is spec0
    assert len(app.session.undo_stack) == n_undo
    assert np.abs(app._render_rgb() - view0).max() == 0.0
    pending = app._lens_pending[0].spec
    whole = _render(app, pending)
    h, w = view0.shape[:2]
    mask = lens_mask(lens, w, h)
    assert np.abs(whole - view0)[mask].mean() > 1e-3, "the lens result changed nothing inside"
    assert np.abs(whole - view0)[~mask].mean() > 1e-4, "the result leaves the rest unchanged"
    # the overlay over the view: the result inside the lens, transparent outside
    overlay = _decode(app.state.lens_overlay_url)
    assert overlay.shape == (h, w, 4)
    assert np.array_equal(overlay[..., 3] > 0.5, mask)
    assert np.abs(overlay[..., :3] - whole)[mask].max() <= PNG_STEP
    assert app.state.lens_result_key == app._key()
    # the after thumbnail: focus (the result) inside, context (the view now) outside
    after, before = _decode(app.state.after_url), _decode(app.state.before_url)
    small = _thumb(app, mask)
    assert np.abs(after - _thumb(app, view0))[~small].max() <= PNG_STEP
    assert np.abs(after - _thumb(app, whole))[small].max() <= PNG_STEP
    assert np.abs(after - before)[small].mean() > 1e-3
    assert np.abs(_decode(app.state.lens_whole_url) - _thumb(app, whole)).max() <= PNG_STEP
    # the whole view's cost is named
    assert "whole view" in app.state.lens_whole_text
    assert "total" in app.state.lens_whole_text
    assert app.state.after_text.startswith("inside the lens")
    assert all(line.startswith("if applied: ") for line in app.state.why_lines)
    # one click applies it to the whole view: the whole image changes, one undo step
    _run(app, app.lens_apply)
    assert app.session.spec == pending
    assert len(app.session.undo_stack) == n_undo + 1
    assert "applied to the whole view" in app.session.undo_labels[-1]
    applied = app._render_rgb()
    assert np.abs(applied - whole).max() <= 1e-12
    assert np.abs(applied - view0)[~mask].mean() > 1e-4
    # the Optimise screen's "after" is now the whole view with the result, and its errors
    assert np.abs(_decode(app.state.after_url) - _thumb(app, applied)).max() <= PNG_STEP
    assert app.state.after_text.startswith("visibility")
    assert not app.state.why_lines[0].startswith("if applied")
    assert app.state.lens_result_key == ""
    assert app._lens_pending is None
    _run(app, lambda: app.undo(1))
    assert app.session.spec == spec0


def test_a_discarded_or_moved_lens_drops_its_result(app):
    lens = {"shape": "circle", "x0": 0.5, "y0": 0.5, "r": 0.15}
    _lens_rows(app, lens)
    _run(app, lambda: app.optimise("opacity", in_lens=True))
    assert app._lens_pending is not None
    assert app.state.lens_overlay_url
    app.lens_discard()
    assert app._lens_pending is None
    assert not app.state.lens_overlay_url
    app.lens_apply()  # nothing to apply: a message in the page, nothing changes
    assert "no lens result" in app.state.error
    # a new lens drops the result of the last one
    _run(app, lambda: app.optimise("opacity", in_lens=True))
    assert app._lens_pending is not None
    app.on_lens_change({"shape": "rect", "x0": 0.1, "y0": 0.1, "x1": 0.4, "y1": 0.4})
    assert app._lens_pending is None
    assert not app.state.lens_overlay_url
