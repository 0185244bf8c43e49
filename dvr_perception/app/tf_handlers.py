"""Handlers of the transfer-function view and the view-direction buttons (a DVRApp mixin).

They only call the library (:mod:`dvr_perception.app.tf_view` and the session) and show the
result: the page reports a dropped handle in ``tf_edit``; the histogram is counted once per
volume.
"""

from __future__ import annotations

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


class TFHandlers:
    """Transfer-function editor and standard views of :class:`~dvr_perception.app.core.DVRApp`."""

    _tf_hist = (None, None)  # (volume id, histogram)
    _tf_before = None  # the spec before the last optimisation

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

    def _set_camera(self, camera) -> None:
        from dvr_perception.plotting import set_plotter_camera

        set_plotter_camera(self.plotter, camera, window_size=False)
        self._changed(view=True)
        if self.state.show_map:
            self._update_map()
        self._push_image()
        self.remeasure()

    @guard
    def view_axis(self, axis):
        """Look at the volume along ``axis`` (``"+X"`` ... ``"-Z"``)."""
        w, h = (int(v) for v in self.plotter.window_size)
        self._set_camera(axis_camera(self.session.volume.bounds, axis, width=w, height=h))

    @guard
    def reset_view(self):
        """Go back to the spec's view (or the default front view), the whole volume in sight."""
        from dvr_perception.rays import Camera

        az, el, zoom = self.session.spec.view or (0.0, 0.0, 1.0)
        w, h = (int(v) for v in self.plotter.window_size)
        self._set_camera(
            Camera.from_view(
                self.session.volume.bounds, azimuth=az, elevation=el, zoom=zoom, width=w, height=h
            )
        )
