"""Handlers of the transfer-function view and the view-direction buttons (a DVRApp mixin).

They only call the library (:mod:`dvr_perception.app.tf_view` and the session) and show the
result: the page reports a dropped handle in ``tf_edit``; the histogram is counted once per
volume.
"""

from __future__ import annotations

import warnings

from trame.decorators import change

from dvr_perception.app._guard import guard
from dvr_perception.app.tf_view import (
    axis_camera,
    colour_bar_stops,
    dropped_edit,
    tf_chart,
    value_histogram,
)

__all__ = ["TFHandlers"]

#: Seconds after which the exact image has been pushed (see ``DVRApp._push_image``).
REPUSH_S = 0.8
#: Seconds between a change of the transfer function or camera and sending the preview's scene.
PREVIEW_SEND_S = 0.1
#: Most seconds the exact image waits for the numbers after the camera rests (see
#: ``TFHandlers._image_after_numbers``).
EXACT_WAIT_S = 1.5


def _three(camera, key: str) -> tuple[float, float, float]:
    """Three finite numbers ``camera[key]`` from the page, or one clear error."""
    import math

    from dvr_perception.errors import DVRInputError

    try:
        v = tuple(float(c) for c in camera[key])
    except (TypeError, ValueError, KeyError):
        raise DVRInputError(f"camera from the page: {key} missing or not numbers") from None
    if len(v) != 3 or not all(math.isfinite(c) for c in v):
        raise DVRInputError(f"camera from the page: {key} must be three finite numbers")
    return v


class TFHandlers:
    """Transfer-function editor and standard views of :class:`~dvr_perception.app.core.DVRApp`."""

    _tf_hist = (None, None)  # (volume id, histogram)
    _tf_before = None  # the spec before the last optimisation
    preview = None  # the quick preview (dvr_perception.app.preview.Preview)
    local_view = None  # its view in the page
    _preview_dirty = False  # the preview changed since its scene was last sent
    _preview_timer = None  # the pending _send_preview
    _view_name = None  # the patient view chosen last (named in the captions)
    _exact_timer = None  # the pending switch back to the exact image after a drag
    _image_due = False  # the exact image waits for the numbers of the rested camera
    _image_timer = None  # the pending _show_exact if the numbers take longer

    def _histogram(self) -> dict:
        volume = self.session.volume
        if self._tf_hist[0] != id(volume):
            self._tf_hist = (id(volume), value_histogram(volume))
        return self._tf_hist[1]

    def _update_tf(self) -> None:
        """Put the editor's geometry, the colour bar and the legend into the page state."""
        spec = self.session.spec
        if spec is None or self.session.volume is None:
            return
        hist = self._histogram()
        self.state.tf = tf_chart(hist, spec, before=self._tf_before)
        self.state.tf_bar = colour_bar_stops(spec, hist)
        self.state.tf_value_range = [round(hist["lo"], 1), round(hist["hi"], 1)]

    @change("tf_edit")
    @guard
    def on_tf_edit(self, tf_edit, **_):
        """Set the range end or opacity of a dropped handle's structure, render, measure."""
        if not tf_edit:
            return
        self.state.tf_edit = None
        if self._task_running:
            self._update_tf()  # the handle goes back where it was
            return
        edit = dropped_edit(
            self._histogram(),
            self.session.spec,
            index=tf_edit.get("index"),
            kind=tf_edit.get("kind"),
            fx=tf_edit.get("fx"),
            fy=tf_edit.get("fy"),
        )
        self.state.error = ""
        before = self.session.spec
        self.session.set_structure(tf_edit["index"], **edit)
        if self.session.spec is before:
            self._update_tf()
            return
        self._show_spec(restructured="value_range" in edit)

    def _sync_preview(self) -> None:
        """Give the browser's quick preview the current spec and camera, sent a moment later.

        Publishing the new scene in the same event-loop tick as the state of a change made the
        page drop that state (a banner vanished at once); waiting for the next drag to send it
        showed the previous transfer function in the drag's first frames.  So the scene goes
        out :data:`PREVIEW_SEND_S` after the change, once the state is flushed
        (:meth:`_send_preview`), and at a drag's start if it is still unsent.  Not after a
        drag: the page's preview has that camera already, and a scene arriving in the next
        drag kept the page busy rebuilding it (half the frames).
        """
        if self.preview is None:
            return
        import asyncio

        self.preview.set_spec(self.session.spec)
        self.state.preview_detail = self.preview.detail  # named in the view's label
        self.preview.set_camera(self.plotter.camera, self.plotter.window_size)
        self._preview_dirty = True
        try:
            loop = asyncio.get_running_loop()
        except RuntimeError:
            return  # no server yet: the page gets the scene with its first state
        if self._preview_timer is None:
            self._preview_timer = loop.call_later(PREVIEW_SEND_S, self._send_preview)

    def _send_preview(self) -> None:
        """Publish the preview's scene to the page if it changed since it was last sent."""
        self._preview_timer = None
        protocol = self.server.protocol
        if not self._preview_dirty or protocol is None or self.local_view is None:
            return
        self._preview_dirty = False
        delta = self.local_view._helper.scene(self.preview.window, new_state=False, widgets=[])
        protocol.publish("trame.vtk.delta", delta)

    @guard
    def preview_start(self):
        """Mark the preview as shown at a drag's start; send its scene if still unsent."""
        self.state.view_mode = "preview"
        if self._exact_timer is not None:  # the last drag's "exact" must not end this one
            self._exact_timer.cancel()
            self._exact_timer = None
        self._image_due = False  # nor its exact image, still waiting for its numbers
        if self._image_timer is not None:
            self._image_timer.cancel()
            self._image_timer = None
        self._send_preview()

    @guard
    def local_camera(self, camera):
        """Show the exact image for the camera the preview rests at after a drag or zoom."""
        self.plotter.camera.SetPosition(*_three(camera, "position"))
        self.plotter.camera.SetFocalPoint(*_three(camera, "focalPoint"))
        self.plotter.camera.SetViewUp(*_three(camera, "viewUp"))
        self.plotter.renderer.ResetCameraClippingRange()
        if self.preview is not None:  # the page's preview has this camera: nothing to send
            self.preview.set_camera(self.plotter.camera, self.plotter.window_size)
        self._changed(view=True)
        self._image_after_numbers()

    def _image_after_numbers(self) -> None:
        """Measure the rested camera's view, and render its exact image once the numbers are out.

        Rendering the exact image holds the event loop (and the GIL) for its whole duration:
        1.2-3.8 s for cthead at 512\u00b2 at load 3-5 with optimised, transparent settings,
        against 0.1-0.5 s for the measurement in its worker thread.  Rendered first, it kept
        the numbers back for that long (issue 20: numbers within 2 s of the rest).  So the
        measurement starts first and :meth:`_show_exact` follows its numbers; meanwhile the
        page shows the preview, and says so.  If the numbers take more than
        :data:`EXACT_WAIT_S`, the image is rendered without them.
        """
        import asyncio

        self._image_due = True  # DVRApp._push_image holds every push until _show_exact
        self.remeasure()
        try:
            loop = asyncio.get_running_loop()
        except RuntimeError:
            self._show_exact()
            return
        if self._image_timer is not None:
            self._image_timer.cancel()
        self._image_timer = loop.call_later(EXACT_WAIT_S, self._show_exact)

    def _show_exact(self) -> None:
        """Render and push the exact image that waited for the numbers, with its map."""
        if self._image_timer is not None:
            self._image_timer.cancel()
            self._image_timer = None
        if not self._image_due:
            return
        self._image_due = False
        self._update_map(push=False)  # the fresh numbers' map, or no stale one
        self._push_image()
        self._exact_shown()

    def _exact_shown(self) -> None:
        """Say the exact image is on screen once its (repeated) push has gone out."""
        import asyncio

        try:
            loop = asyncio.get_running_loop()
        except RuntimeError:
            self.state.view_mode = "exact"
            return

        def done():
            self._exact_timer = None
            with self.state:
                self.state.view_mode = "exact"

        if self._exact_timer is not None:
            self._exact_timer.cancel()
        self._exact_timer = loop.call_later(REPUSH_S, done)

    def _set_camera(self, camera) -> None:
        from dvr_perception.plotting import set_plotter_camera

        set_plotter_camera(self.plotter, camera, window_size=False)
        self._sync_preview()
        self._changed(view=True)
        if self.state.show_map:
            self._update_map()
        self._push_image()
        self.remeasure()

    @guard
    def view_axis(self, axis):
        """Look at the volume along ``axis`` (``"+X"`` ... ``"-Z"``)."""
        w, h = (int(v) for v in self.plotter.window_size)
        self._view_name = None
        self._set_camera(axis_camera(self.session.volume.bounds, axis, width=w, height=h))

    @guard
    def view_patient(self, name):
        """Look at the volume from a patient side (``"anterior"`` ... ``"inferior"``).

        :func:`~dvr_perception.rays.camera.patient_view`: in the volume's patient (LPS) frame,
        e.g. ``"anterior"`` looks at the face from in front, head up.
        """
        from dvr_perception.errors import DVRInputError, DVRWarning
        from dvr_perception.rays.camera import PATIENT_VIEWS, patient_view

        if name not in PATIENT_VIEWS:
            raise DVRInputError(
                f"view {str(name)[:40]!r}: expected one of {', '.join(PATIENT_VIEWS)}"
            )
        w, h = (int(v) for v in self.plotter.window_size)
        self._view_name = name  # the captions name it; later rotations are relative to it
        self._set_camera(patient_view(self.session.volume, name, width=w, height=h))
        note = self.session.patient_view_note()  # names the Data screen's Orientation field
        if note is not None:  # the guard shows it on the page's message line
            warnings.warn(note, DVRWarning, stacklevel=2)

    @change("orientation_code")
    @guard
    def on_orientation_change(self, orientation_code, **_):
        """Orientation chosen on the Data screen (a file without one): re-order and show it.

        Only the session re-orders (:meth:`~dvr_perception.app.session.Session.set_orientation`);
        a patient view shown stays that patient side, now the right way round.
        """
        code = orientation_code or None
        read = self.session.read_volume
        if read is None or read.oriented or code == self.session.orientation:
            return
        if self._task_running:
            self.state.orientation_code = self.session.orientation or ""
            return
        self.state.error = ""
        try:
            self.session.set_orientation(code)
        except Exception:
            self.state.orientation_code = self.session.orientation or ""  # as still shown
            raise
        self._show_loaded(f"orientation {code or 'as stored'}", view_name=self._view_name)

    @guard
    def reset_view(self):
        """Go back to the spec's view (or the default view), the whole volume in sight.

        Without a view in the spec, an oriented scan is seen from the front, head up
        (:func:`~dvr_perception.rays.camera.default_camera`), as on loading.
        """
        from dvr_perception.rays.camera import default_camera

        w, h = (int(v) for v in self.plotter.window_size)
        self._view_name = None
        self._set_camera(default_camera(self.session.volume, self.session.spec.view, width=w,
                                        height=h))  # fmt: skip
