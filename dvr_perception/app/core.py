"""The trame web app: :class:`DVRApp` binds the page (:mod:`.ui`) to a :class:`.Session`.

Threading: VTK renders only in the server's event-loop thread (the EGL context lives there).
The optimiser and the measures run in a worker thread (``loop.run_in_executor``); the
optimiser's callback hands each intermediate spec to the loop with ``call_soon_threadsafe``,
where it is applied to the plotter (:func:`~dvr_perception.plotting.apply`) and the image is
pushed to the browser.  Cancel sets an event the callback turns into ``StopIteration``, so
the optimiser returns its best parameters so far.

State: trame keeps **one state per server process**, shared by every connected browser tab:
two tabs show the same volume, spec, camera, lens, calibration test and progress, and an edit
in one appears in the other (the tests check that two tabs stay consistent).  Run one server
per user (``dvr-perception app --port N``).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import threading
import time

from trame.app import TrameApp, asynchronous
from trame.decorators import change

from dvr_perception.app._guard import guard
from dvr_perception.app.lens import LensHandlers, lens_region
from dvr_perception.app.optimise_handlers import MAX_ITER, STAGE_SETS, OptimiseHandlers
from dvr_perception.app.page_input import PageInputGuard
from dvr_perception.app.plotter import new_plotter, show_spec
from dvr_perception.app.security import (
    FRAME_BYTES,
    ConnectionGuard,
    new_token,
    quiet_disconnects,
)
from dvr_perception.app.session import (
    MAX_UPLOAD_BYTES,
    MAX_VOLUME_BYTES,
    PHANTOM,
    UPLOADED,
    Session,
    measure_camera,
    orientation_choices,
    rgb_to_hex,
)
from dvr_perception.app.study import png_data_url
from dvr_perception.app.study_screens import RANKING_FILE, StudyHandlers
from dvr_perception.app.tf_handlers import TFHandlers
from dvr_perception.errors import DVRInputError

__all__ = ["MAX_ITER", "STAGE_SETS", "DVRApp", "lens_region"]

log = logging.getLogger("dvr_perception.app")

#: Seconds an info banner stays; an error banner stays until closed or for ERROR_S.
INFO_S = 5.0
ERROR_S = 30.0
#: Relative rise of the whole view's error with a lens result that warns before applying it.
LENS_WORSE = 0.10
#: Seconds after which a pushed image is pushed once more (see ``DVRApp._push_image``).
REPUSH_S = 0.8
#: Most seconds the exact image of a rested camera waits for its numbers' send to complete.
SEND_WAIT_S = 0.5
#: Colour range of the quality maps (deviations above 1 saturate).
MAP_CLIM = (0.0, 1.0)
#: Width of the before/after thumbnails.
THUMB_WIDTH = 210


def _style_bar(bar) -> None:
    """Plain, readable colour-bar text (no italics, title clear of the labels)."""
    bar.SetVerticalTitleSeparation(12)
    bar.SetPosition(0.88, 0.08)
    bar.SetWidth(0.1)
    bar.SetHeight(0.84)
    bar.SetBarRatio(0.45)
    bar.SetLabelFormat("%.1f")
    bar.SetUnconstrainedFontSize(True)
    for prop, size in ((bar.GetTitleTextProperty(), 20), (bar.GetLabelTextProperty(), 18)):
        prop.SetItalic(False)
        prop.SetShadow(True)
        prop.SetBold(prop is bar.GetTitleTextProperty())
        prop.SetFontSize(size)


class DVRApp(OptimiseHandlers, TFHandlers, LensHandlers, StudyHandlers, TrameApp):
    """Web app: choose a volume, edit structures, see the quality map, optimise, export.

    Parameters
    ----------
    server : trame server or str, optional
        Server (or its name) to attach to; default trame's default server.
    data_dir : str or Path, optional
        Folder of volumes and spec JSON files, only read; ``None`` offers the phantom and the
        app's own files only.
    volume : str, optional
        Volume shown first: ``"phantom"`` (default) or a file name in ``data_dir``.
    orientation : str, optional
        Orientation code of that first volume (``dvr-perception app --orientation CODE``).
    export_dir : str or Path, optional
        Folder the exports, calibration curves and ranking answers are written to (default
        ``exports`` in the state folder).
    state_dir : str or Path, optional
        Per-user folder the app writes uploads and saved settings to (default
        :func:`~dvr_perception.app.session.default_state_dir`).
    phantom_size : int
        Edge length of the built-in phantom.
    max_upload_bytes : int
        Largest volume file the upload field accepts.
    max_volume_bytes : int
        Largest voxel data (decompressed) an uploaded volume may hold.
    max_iter : int
        Optimiser iterations per stage.
    token : str, optional
        The secret a browser must present (default: a new random one, :attr:`token`).
    """

    def __init__(
        self,
        server=None,
        *,
        data_dir=None,
        volume=None,
        orientation=None,
        export_dir=None,
        state_dir=None,
        phantom_size=96,
        max_upload_bytes=MAX_UPLOAD_BYTES,
        max_volume_bytes=MAX_VOLUME_BYTES,
        max_iter=MAX_ITER,
        token=None,
    ):
        super().__init__(server)
        self.max_iter = int(max_iter)
        self.session = Session(
            data_dir,
            export_dir,
            state_dir=state_dir,
            phantom_size=phantom_size,
            max_volume_bytes=max_volume_bytes,
        )
        self.max_upload_bytes = int(max_upload_bytes)
        self.token = str(token) if token else new_token()
        # a websocket frame is read whole: bound it; an upload arrives in several frames,
        # re-assembled up to max_message_bytes (see dvr_perception.app.security)
        self.server.options["ws_max_msg_size"] = FRAME_BYTES
        self.max_message_bytes = self.max_upload_bytes + 2**20
        self.server.controller.on_server_bind.add(self._install_guard)
        self.calibration_test = None
        self.ranking = None
        self._curve = None
        self.plotter = new_plotter()
        self.handle = None
        self.measures = None
        self.view = None
        self._cancel = threading.Event()
        self._pending = None
        self._last_live = 0.0
        self._last_prep = 0.0  # when the preparation's progress was last handed on
        self._task_running = False
        self._measuring = False
        self._measure_again = False
        self._e_history: list[tuple] = []
        self._repush = None
        self._view_no = 0  # counts camera changes
        self._tf_no = 0  # counts changes of the transfer function (spec) shown
        self._tf_label = "as loaded"
        self._view_name = None  # the patient view chosen last (None: none, or another view)
        self._run = None  # the optimisation under way: start time, stages, camera, key
        self._banner_timer = None
        self._map_on = False
        self._init_state()
        self._show_volume(volume or PHANTOM, orientation=orientation)
        from dvr_perception.app.preview import Preview

        self.preview = Preview(self.session.volume, self.session.spec)
        self._sync_preview()
        self._preview_dirty = False  # the page gets the scene with its first state
        from dvr_perception.app.ui import build_ui

        self.ui = build_ui(self)

    def _install_guard(self, wslink_server, **_) -> None:
        """Put the token, origin, size and page-input checks into the server before it starts."""
        guard = ConnectionGuard(self.token, wslink_server.host, self.max_message_bytes)
        guard.install(wslink_server, self.server.protocol)
        page = PageInputGuard(self)
        for handler in wslink_server._ws_handlers:
            page.install(handler)
        quiet_disconnects()

    # -- helpers -----------------------------------------------------------------------------
    def _init_state(self) -> None:
        s = self.state
        s.volume_choices = self.session.volume_choices()
        s.volume_name = ""
        # the Data screen's Orientation field, shown for a file that records no orientation
        s.orientation_choices = orientation_choices()
        s.orientation_open = False
        s.orientation_code = ""
        # the folders are shown, never read back: the server alone chooses paths
        s.data_dir_label = str(self.session.data_dir or "")
        s.export_dir_label = str(self.session.export_dir)
        s.state_dir_label = str(self.session.state_dir)
        s.spec_name = "spec.json"
        s.spec_choices = self.session.spec_choices()
        s.spec_source = ""
        s.structures = []
        s.structure_names = []
        s.error = ""
        s.info = ""
        # the screen a banner appeared on, set by the page itself: the server's copy of ``tab``
        # may lag behind a click that follows a tab change at once
        s.banner_tab = "data"
        s.client_only("banner_tab")
        s.now_key = "0.0"  # view and transfer function shown: "VIEW.TF"
        s.measured_key = ""  # the view and transfer function the summary numbers are for
        s.measured_for = ""
        s.opt_key = ""  # the view and transfer function the optimisation results are for
        s.opt_for = ""
        s.opt_camera = None
        s.opt_sampling = ""  # the optimiser's sampling resolution, named in the page
        s.live_shares = []
        s.lens_whole_text = ""
        s.lens_worse = False
        s.show_map = False
        s.map_shown = ""  # the quality map in the pushed image ("": none)
        s.map_kind = "visibility"
        s.E_v = s.E_s = s.E_t = None
        s.measuring = False
        s.busy = False
        s.progress = 0
        s.progress_text = ""
        s.can_undo = False
        s.history = []
        s.exports = []
        s.tab = "data"
        s.map_opacity = 0.6
        s.shares = []
        s.error_history_svg = ""
        s.before_url = s.after_url = ""
        s.before_text = s.after_text = ""
        s.why_lines = []  # the optimiser's reason per structure (issue 16)
        # lens
        s.lens_shape = "rect"
        s.lens = None
        s.lens_text = ""
        s.lens_rows = []
        s.lens_drag = None
        s.client_only("lens_drag")
        # a lens result shown inside the lens, for the view and settings lens_result_key
        s.lens_result_key = s.lens_overlay_url = s.lens_whole_url = ""
        # calibration test
        s.cal_active = False
        s.cal_index = 0
        s.cal_total = 0
        s.cal_url = ""
        s.cal_rating = 0.5
        s.cal_name = "my_calibration.json"
        s.cal_svg = ""
        s.cal_saved = ""
        s.calibration_name = ""
        s.use_calibration = False
        s.has_calibration = False
        # ranking task
        s.rank_structure = 0
        s.rank_images = []
        s.rank_order = []
        s.rank_busy = False
        s.rank_result = ""
        s.rank_saved = False
        s.rank_file_label = str(self.session.export_dir / RANKING_FILE)
        # transfer-function view (geometry from dvr_perception.app.tf_view)
        s.tf = None
        s.tf_bar = []
        s.tf_value_range = [0, 1]
        s.tf_edit = None  # a dropped handle: {index, kind, fx, fy}
        s.tf_drag = None  # the handle being dragged (the page's own)
        s.client_only("tf_drag")
        s.show_legend = True
        s.view_mode = "exact"  # on screen: the engine's "exact" image or the vtk.js "preview"
        # upload
        s.upload = None
        s.max_upload_mb = round(self.max_upload_bytes / 1e6, 2)
        s.max_upload_bytes = self.max_upload_bytes

    def fail(self, message: str) -> None:
        """Show ``message`` as the page's error banner."""
        self.state.error = " ".join(str(message).split())
        self.state.info = ""

    @change("info", "error")
    def on_banner(self, info, error, **_):
        """Let a new banner time out (the page shows it only on the screen it appeared on)."""
        if not info and not error:
            return
        if self._banner_timer is not None:
            self._banner_timer.cancel()
        try:
            loop = asyncio.get_running_loop()
        except RuntimeError:
            return
        self._banner_timer = loop.call_later(ERROR_S if error else INFO_S, self._banner_out)

    def _banner_out(self) -> None:
        self._banner_timer = None
        with self.state:
            self.state.info = self.state.error = ""

    # -- what the numbers were measured for ---------------------------------------------------
    def _key(self) -> str:
        return f"{self._view_no}.{self._tf_no}"

    def _changed(self, *, view: bool = False, label: str = "") -> None:
        """Count a camera (``view``) or transfer-function change: older numbers go stale."""
        if view:
            self._view_no += 1
        else:
            self._tf_no += 1
            self._tf_label = label or "edited"
            self.state.lens_worse = False  # the lens result's cost was for the last settings
        self.state.now_key = self._key()

    def _describe(self, camera) -> str:
        """Return the view, size and settings numbers for a caption.

        After a patient-side button the view is named and its angles are from that view
        (``anterior, azimuth +30 deg, elevation -10 deg from it``: the CLI's ``--view
        anterior,30,-10``); otherwise azimuth and elevation are VTK's, with y up.
        """
        if self._view_name is not None:
            from dvr_perception.rays.camera import patient_angles

            az, el = patient_angles(self.session.volume, camera, self._view_name)
            where = (
                f"{self._view_name}, azimuth {round(az) + 0:+d} deg, elevation "
                f"{round(el) + 0:+d} deg from it"
            )
        else:
            d = [p - f for p, f in zip(camera.position, camera.focal_point, strict=True)]
            r = math.sqrt(sum(c * c for c in d)) or 1.0
            el = math.degrees(math.asin(max(-1.0, min(1.0, d[1] / r))))
            az = math.degrees(math.atan2(d[0], d[2]))
            where = f"azimuth {az:.0f} deg, elevation {el:.0f} deg"
        return (
            f"view {self._view_no} ({where}, {camera.width}\u00d7{camera.height} px), "
            f"settings {self._tf_no} ({self._tf_label})"
        )

    def _sync(self) -> None:
        """Copy the session's spec into the page state."""
        self.state.structures = self.session.structure_rows()
        self.state.spec_source = self.session.spec_source
        self.state.can_undo = bool(self.session.undo_stack)
        self.state.history = self.session.history_rows()
        self.state.structure_names = [
            {"title": s.name, "value": k} for k, s in enumerate(self.session.spec.structures)
        ]
        self._update_tf()
        self._sync_preview()

    def _render_rgb(self):
        """Render the view now and return it as an ``(H, W, 3)`` float image in [0, 1].

        The plotter's screenshot only reads the render window's last frame: a spec shown
        with :meth:`_render_spec` (no render) is not in it until rendered (issue 30: the
        "after" thumbnail was the "before" image).
        """
        self.plotter.ren_win.Render()
        return self.plotter.screenshot(None, return_img=True)[..., :3] / 255.0

    def _snapshot(self, img=None) -> str:
        """Return the view (rendered now) or ``img`` as a small PNG data URL (before/after)."""
        img = self._render_rgb() if img is None else img
        step = max(1, round(img.shape[1] / THUMB_WIDTH))
        return png_data_url(img[::step, ::step])

    def _push_image(self) -> None:
        """Send the view to the browser, and once more a little later.

        trame-vtk drops a push whose image is still being encoded when its retries run out
        (under load), which left the browser showing an older frame; the repeat makes sure
        the last state arrives (an unchanged frame is not sent again).  While the exact image
        of a rested camera waits for its numbers, pushes wait with it (``_show_exact``).
        """
        if self.view is None or self._image_due:
            return
        t0 = time.monotonic()
        self.view.update()
        log.info("view.settings %s: image rendered in %.2f s", self._key(), time.monotonic() - t0)
        try:
            loop = asyncio.get_running_loop()
        except RuntimeError:
            return
        if self._repush is None:
            self._repush = loop.call_later(REPUSH_S, self._push_again)

    def _push_again(self) -> None:
        self._repush = None
        if self.view is not None:
            self.view.update()

    def _show_volume(self, name: str, *, orientation=None) -> None:
        self.session.load_volume(name, orientation=orientation)
        self.state.volume_name = name
        self._show_loaded(f"loaded {name}", wait=True)

    def _show_loaded(self, label: str, *, view_name=None, wait: bool = False) -> None:
        """Show the session's newly loaded (or re-oriented) volume and spec, then re-measure.

        The camera is the patient view ``view_name``, or the spec's view, or (a spec without
        one) :func:`~dvr_perception.rays.camera.default_camera`: an oriented scan from the
        front, head up.
        """
        from dvr_perception.plotting import add_structures, set_plotter_camera
        from dvr_perception.rays.camera import default_camera, patient_view

        volume, spec = self.session.volume, self.session.spec
        self._tf_before = None
        self._view_name = view_name
        self.plotter.clear_actors()
        self.handle = add_structures(self.plotter, volume, spec)
        w, h = (int(v) for v in self.plotter.window_size)
        if view_name is not None:
            cam = patient_view(volume, view_name, width=w, height=h)
        else:  # the spec's view; else an oriented scan from the front, head up
            cam = default_camera(volume, spec.view, width=w, height=h)
        set_plotter_camera(self.plotter, cam, window_size=False)
        if self.preview is not None:
            self.preview.set_volume(volume, spec)
        self._changed(view=True)
        self._changed(label=label)
        self.state.opt_key = ""
        read = self.session.read_volume
        self.state.orientation_open = read is not None and not read.oriented
        self.state.orientation_code = self.session.orientation or ""
        self.state.lens = None
        self.state.lens_rows = []
        self.state.lens_text = ""
        self.state.rank_images = []
        self.state.rank_order = []
        self.state.before_url = self.state.after_url = ""
        self._sync()
        self._push_image()  # the new data (the map, if on, waits for fresh numbers)
        self.remeasure(wait=wait)

    def _show_spec(
        self, *, restructured: bool = False, label: str = "", measure: bool = True
    ) -> None:
        """Show the session's spec in the view and table, then re-measure (if ``measure``)."""
        if restructured:
            self.handle = None
        labels = self.session.undo_labels
        self._changed(label=label or (labels[-1] if labels else "edited"))
        self._render_spec(self.session.spec)
        self._sync()
        self._push_image()
        if measure:
            self.remeasure()

    def _render_spec(self, spec) -> None:
        """Show ``spec`` in the plotter (no render)."""
        self.handle = show_spec(self.plotter, self.handle, self.session.volume, spec)

    def current_camera(self):
        """Return the plotter's camera (the browser's view), reduced to the measure size."""
        from dvr_perception.plotting import camera_from_plotter

        return measure_camera(camera_from_plotter(self.plotter))

    # -- measures and quality map ------------------------------------------------------------
    def remeasure(self, *, wait: bool = False) -> None:
        """Measure the current view (in a worker thread unless ``wait``), update numbers and map.

        A request while a measurement runs is queued: one more measurement follows it.
        """
        if wait:
            cam = self.current_camera()
            self._set_measures(self.session.measure(cam), self._key(), self._describe(cam))
            return
        if self._measuring:
            self._measure_again = True
            return
        self._measuring = True
        self.state.measuring = True
        asynchronous.create_task(self._remeasure())

    async def _remeasure(self) -> None:
        loop = asyncio.get_running_loop()
        measures, error = None, ""
        while True:
            self._measure_again = False
            t0 = time.monotonic()
            key = self._key()
            try:  # whatever fails, the next request measures again (nothing stays stuck)
                cam = self.current_camera()
                described = self._describe(cam)
                measures = await loop.run_in_executor(None, self.session.measure, cam)
            except DVRInputError as exc:
                measures, error = None, f"measuring failed: {exc}"
            except Exception as exc:  # shown in the page; the server keeps running
                log.exception("measuring failed")
                measures, error = None, f"measuring failed: {exc}"
            log.info("view.settings %s: measured in %.2f s", key, time.monotonic() - t0)
            if not self._measure_again:
                break
        self._measuring = False
        with self.state:
            self.state.measuring = False
            if measures is None:
                self.fail(error)
            else:
                self._set_measures(measures, key, described)
        if self._image_due:  # now the image, once the numbers have gone out on the socket
            # (the block above only scheduled their send; a rendering would hold it back)
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(self.server.network_completion, SEND_WAIT_S)
            self._show_exact()

    def _set_measures(self, measures, key: str, described: str) -> None:
        self.measures = measures
        self.state.update(measures.as_state())
        self.state.measured_key = key
        self.state.measured_for = described
        self._set_shares({k: v["visible"] for k, v in measures.shares.items()})
        self._update_lens_rows()
        self._update_map()

    def _set_shares(self, visible: dict, name: str = "shares") -> None:
        """Per-structure bars: visible share now (``visible``) and wanted share."""
        wanted = self.measures.shares if self.measures is not None else {}
        rows = []
        for s in self.session.spec.structures:
            if s.name not in visible:
                continue
            rows.append(
                {
                    "name": s.name,
                    "color": rgb_to_hex(s.colour),
                    "visible": round(100 * float(visible[s.name]), 1),
                    "wanted": round(100 * float(wanted.get(s.name, {}).get("wanted", 0.0)), 1),
                }
            )
        self.state[name] = rows

    def _update_map(self, *, push: bool = True) -> None:
        """Show the quality map if it is on and the numbers are fresh; push the image (``push``)."""
        from dvr_perception.plotting import add_quality_map

        was_on = self._map_on
        for name in ("quality_image", "quality_bar"):
            self.plotter.remove_actor(name, render=False)
        fresh = self.state.measured_key == self.state.now_key
        self._map_on = bool(self.state.show_map and self.measures is not None and fresh)
        self.state.map_shown = self.state.map_kind if self._map_on else ""
        if not (self._map_on or was_on):
            return  # nothing shown before or now: no new image to push
        if self._map_on:
            kind = self.state.map_kind
            overlay = add_quality_map(
                self.plotter,
                self.measures.images[kind],
                title=f"{kind}\nproblem",
                clim=MAP_CLIM,
                opacity=min(max(float(self.state.map_opacity), 0.0), 1.0),
            )
            _style_bar(overlay.scalar_bar)
        if push:
            self._push_image()

    @change("show_map", "map_kind", "map_opacity")
    @guard
    def on_map_change(self, **_):
        """Toggle or switch the quality-map overlay."""
        self._update_map()

    # -- data --------------------------------------------------------------------------------
    @change("volume_name")
    @guard
    def on_volume_change(self, volume_name, **_):
        """Load the chosen volume with its preset (or proposed) structures."""
        if not volume_name or volume_name == self.session.volume_name or self._task_running:
            return
        self.state.error = ""
        self._show_volume(volume_name)

    @guard
    def set_importance(self, index, value):
        """Slider released: set a structure's importance."""
        self.session.set_structure(index, importance=value)
        self._show_spec()

    @guard
    def set_range(self, index, end, value):
        """Range field changed: set the low (``end`` 0) or high (1) value of a structure."""
        s = self.session.spec.structures[int(index)]
        if s.range is None:
            raise DVRInputError(f"{s.name}: a label structure has no value range")
        bounds = list(s.range)
        try:
            bounds[int(end)] = float(value)
        except (TypeError, ValueError):
            raise DVRInputError(f"range of {s.name}: {value!r} is not a number") from None
        self.state.error = ""
        self.session.set_structure(index, value_range=bounds)
        self._show_spec(restructured=True)

    @guard
    def set_colour(self, index, value):
        """Colour picked: set a structure's colour."""
        self.session.set_structure(index, colour=value)
        self._show_spec()

    @guard
    def load_spec(self, name=None):
        """Load the offered spec JSON named in the file field (data folder or ``saved/``)."""
        name = self.state.spec_name if name is None else name
        self.state.error = ""
        before = self.session.snapshot()
        self.session.load_spec_file(name)
        try:
            self._show_spec(restructured=True)
        except Exception:
            # the view could not show it: the session goes back to what is still shown
            self.session.restore(before)
            self._show_spec(restructured=True, measure=False)
            raise
        self.state.info = f"loaded {name}"

    @guard
    def save_spec(self, name=None):
        """Save the current spec as JSON into the app's settings folder."""
        self.state.error = ""
        saved = self.session.save_spec_file(self.state.spec_name if name is None else name)
        self.state.spec_choices = self.session.spec_choices()
        self.state.info = f"saved {saved} (in {self.session.settings_dir})"

    @guard
    def undo(self, steps=1):
        """Go back ``steps`` changes (1: the last one)."""
        if self._task_running or self.session.undo(int(steps)) is None:
            return
        self.state.error = ""
        self._show_spec(restructured=True, label=f"went back {int(steps)}")
        self.state.info = f"went back {int(steps)} step{'s' if int(steps) > 1 else ''}"

    @guard
    def export(self):
        """Write the PNG (with the legend), spec JSON, ParaView preset and Slicer file."""
        self.state.error = ""
        self.plotter.render()
        legend = None
        if self.state.show_legend:  # as on screen: the legend and colour bar beside the view
            legend = {
                "rows": self.session.structure_rows(),
                "bar": list(self.state.tf_bar or []),
                "value_range": tuple(self.state.tf_value_range),
            }
        self.state.exports = [p.name for p in self.session.export(self.plotter, legend=legend)]
        self.state.info = f"exported {len(self.state.exports)} files to {self.session.export_dir}"

    @guard
    def measure_view(self, *_):
        """Re-measure after the user rotated the view (the old numbers go stale at once)."""
        self._changed(view=True)
        if self.state.show_map:
            self._update_map()  # the old view's map is taken off until the new one is measured
        self.remeasure()

    def _lens_verdict(self, before, after) -> None:
        """Whole view before -> after the lens result; warn when it would get worse."""
        e0 = before.E_v + before.E_s + before.E_t
        e1 = after.E_v + after.E_s + after.E_t
        rise = (e1 - e0) / e0 if e0 > 0 else 0.0
        b, a = before.as_state(), after.as_state()
        parts = ", ".join(
            f"{name} {b[k]} -> {a[k]}"
            for k, name in (("E_v", "visibility"), ("E_s", "shape"), ("E_t", "transparency"))
        )
        self.state.lens_whole_text = (
            f"whole view: {parts}; total {e0:.3g} -> {e1:.3g} ({100 * rise:+.0f} %)"
        )
        self.state.lens_worse = rise > LENS_WORSE

    async def _after_text(self) -> None:
        """Fill the 'after' numbers once the new view is measured."""
        while self._measuring:
            await asyncio.sleep(0.1)
        with self.state:
            self.state.after_text = self._errors_text()

    # -- upload ------------------------------------------------------------------------------
    @change("upload")
    @guard
    def on_upload(self, upload, **_):
        """Check, store and show the volume file chosen in the upload field."""
        if not upload:
            return
        self.state.upload = None
        self.state.error = ""
        if self._task_running:
            raise DVRInputError("upload: wait until the optimisation has finished")
        f = upload  # one file {name, size, content: bytes}, checked by page_input.Upload
        content = f["content"]
        size = max(int(f["size"]), len(content))
        if size > self.max_upload_bytes:
            raise DVRInputError(
                f"upload {f.get('name')}: {size / 1e6:.2f} MB is larger than the limit of "
                f"{self.max_upload_bytes / 1e6:.2f} MB"
            )
        name = self.session.store_upload(
            f.get("name"), bytes(content), max_bytes=self.max_upload_bytes
        )
        self.state.volume_choices = self.session.volume_choices()
        self.state.volume_name = name
        stored = self.session.upload_dir / name.removeprefix(UPLOADED)
        self.state.info = f"uploaded {stored.name}: listed as {name}, stored as {stored}"
