"""The trame web app: :class:`DVRApp` binds the page (:mod:`.ui`) to a :class:`.Session`.

Threading: VTK renders only in the server's event-loop thread (the EGL context lives there).
The optimiser and the measures run in a worker thread (``loop.run_in_executor``); the
optimiser's callback hands each intermediate spec to the loop with ``call_soon_threadsafe``,
where it is applied to the plotter (:func:`~dvr_perception.plotting.apply`) and the image is
pushed to the browser.  Cancel sets an event the callback turns into ``StopIteration``, so
the optimiser returns its best parameters so far.

State: trame keeps **one state per server process**, shared by every connected browser tab:
two tabs show the same volume, spec, camera and progress, and an edit in one appears in the
other.  Run one server per user (``dvr-perception app --port N``).
"""

from __future__ import annotations

import asyncio
import functools
import logging
import threading
import warnings

from trame.app import TrameApp, asynchronous
from trame.decorators import change

from dvr_perception.app.scene import new_plotter, show_spec
from dvr_perception.app.session import PHANTOM, Session, measure_camera
from dvr_perception.errors import DVRInputError

__all__ = ["MAX_ITER", "STAGE_SETS", "DVRApp"]

log = logging.getLogger("dvr_perception.app")

#: Stages run by the two optimise buttons.
STAGE_SETS = {"opacity": ("opacity",), "all": ("opacity", "lighting", "colour")}
#: Optimiser iterations per stage.
MAX_ITER = 10
#: Least seconds between two live images while optimising (rendering blocks the optimiser).
LIVE_INTERVAL_S = 1.0
#: Colour range of the quality maps (deviations above 1 saturate).
MAP_CLIM = (0.0, 1.0)


def _guard(fn):
    """Show input errors (and unexpected ones) in the page instead of failing the handler."""

    @functools.wraps(fn)
    def wrapper(self, *args, **kwargs):
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                out = fn(self, *args, **kwargs)
            if caught:
                self.state.info = "; ".join(str(w.message) for w in caught[:3])
            return out
        except (DVRInputError, OSError, ValueError) as exc:
            self.fail(str(exc))
        except Exception as exc:
            log.exception("unexpected error in %s", fn.__name__)
            self.fail(f"unexpected {type(exc).__name__}: {exc}")
        return None

    return wrapper


class DVRApp(TrameApp):
    """Web app: choose a volume, edit structures, see the quality map, optimise, export.

    Parameters
    ----------
    server : trame server or str, optional
        Server (or its name) to attach to; default trame's default server.
    data_dir : str or Path, optional
        Folder of volumes and spec JSON files (the only folder specs are read from and saved
        to); ``None`` offers the phantom only.
    volume : str, optional
        Volume shown first: ``"phantom"`` (default) or a file name in ``data_dir``.
    export_dir : str or Path
        Folder the exports are written to.
    phantom_size : int
        Edge length of the built-in phantom.
    """

    def __init__(
        self,
        server=None,
        *,
        data_dir=None,
        volume=None,
        export_dir="dvr_exports",
        phantom_size=96,
    ):
        super().__init__(server)
        self.session = Session(data_dir, export_dir, phantom_size=phantom_size)
        self.plotter = new_plotter()
        self.handle = None
        self.measures = None
        self.view = None
        self._cancel = threading.Event()
        self._pending = None
        self._last_live = 0.0
        self._task_running = False
        self._measuring = False
        self._measure_again = False
        self._init_state()
        self._show_volume(volume or PHANTOM)
        from dvr_perception.app.ui import build_ui

        self.ui = build_ui(self)

    # -- helpers -----------------------------------------------------------------------------
    def _init_state(self) -> None:
        s = self.state
        s.volume_choices = self.session.volume_choices()
        s.volume_name = ""
        s.has_data_dir = self.session.data_dir is not None
        s.data_dir = str(self.session.data_dir or "")
        s.export_dir = str(self.session.export_dir)
        s.spec_path = "spec.json"
        s.spec_source = ""
        s.structures = []
        s.error = ""
        s.info = ""
        s.show_map = False
        s.map_kind = "visibility"
        s.E_v = s.E_s = s.E_t = None
        s.measuring = False
        s.busy = False
        s.progress = 0
        s.progress_text = ""
        s.can_undo = False
        s.exports = []

    def fail(self, message: str) -> None:
        """Show ``message`` as the page's error banner."""
        self.state.error = " ".join(str(message).split())
        self.state.info = ""

    def _sync(self) -> None:
        """Copy the session's spec into the page state."""
        self.state.structures = self.session.structure_rows()
        self.state.spec_source = self.session.spec_source
        self.state.can_undo = bool(self.session.undo_stack)

    def _push_image(self) -> None:
        if self.view is not None:
            self.view.update()

    def _show_volume(self, name: str) -> None:
        from dvr_perception.plotting import add_structures, set_plotter_camera
        from dvr_perception.rays import Camera

        volume, spec = self.session.load_volume(name)
        self.plotter.clear_actors()
        self.handle = add_structures(self.plotter, volume, spec)
        az, el, zoom = spec.view or (0.0, 0.0, 1.0)
        w, h = (int(v) for v in self.plotter.window_size)
        cam = Camera.from_view(
            volume.bounds, azimuth=az, elevation=el, zoom=zoom, width=w, height=h
        )
        set_plotter_camera(self.plotter, cam, window_size=False)
        self.state.volume_name = name
        self._sync()
        self.remeasure(wait=True)

    def _show_spec(self, *, restructured: bool = False) -> None:
        """Show the session's spec in the view and table, then re-measure."""
        if restructured:
            self.handle = None
        self._render_spec(self.session.spec)
        self._sync()
        self._push_image()
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
            self._set_measures(self.session.measure(self.current_camera()))
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
            try:
                measures = await loop.run_in_executor(
                    None, self.session.measure, self.current_camera()
                )
            except Exception as exc:  # shown in the page; the server keeps running
                log.exception("measuring failed")
                measures, error = None, f"measuring failed: {exc}"
            if not self._measure_again:
                break
        self._measuring = False
        with self.state:
            self.state.measuring = False
            if measures is None:
                self.fail(error)
            else:
                self._set_measures(measures)

    def _set_measures(self, measures) -> None:
        self.measures = measures
        self.state.update(measures.as_state())
        self._update_map()

    def _update_map(self) -> None:
        from dvr_perception.plotting import add_quality_map

        for name in ("quality_image", "quality_bar"):
            self.plotter.remove_actor(name, render=False)
        if self.state.show_map and self.measures is not None:
            kind = self.state.map_kind
            add_quality_map(
                self.plotter, self.measures.images[kind], title=f"{kind} error", clim=MAP_CLIM
            )
        self._push_image()

    @change("show_map", "map_kind")
    @_guard
    def on_map_change(self, **_):
        """Toggle or switch the quality-map overlay."""
        self._update_map()

    # -- data --------------------------------------------------------------------------------
    @change("volume_name")
    @_guard
    def on_volume_change(self, volume_name, **_):
        """Load the chosen volume with its preset (or proposed) structures."""
        if not volume_name or volume_name == self.session.volume_name or self._task_running:
            return
        self.state.error = ""
        self._show_volume(volume_name)

    @_guard
    def set_importance(self, index, value):
        """Slider released: set a structure's importance."""
        self.session.set_structure(index, importance=value)
        self._show_spec()

    @_guard
    def set_colour(self, index, value):
        """Colour picked: set a structure's colour."""
        self.session.set_structure(index, color=value)
        self._show_spec()

    @_guard
    def load_spec(self, path=None):
        """Load the spec JSON named in the file field (data folder only)."""
        path = self.state.spec_path if path is None else path
        self.state.error = ""
        self.session.load_spec_file(path)
        self._show_spec(restructured=True)
        self.state.info = f"loaded {path}"

    @_guard
    def save_spec(self, path=None):
        """Save the current spec as JSON into the data folder."""
        self.state.error = ""
        path = self.session.save_spec_file(self.state.spec_path if path is None else path)
        self.state.info = f"saved {path}"

    @_guard
    def undo(self):
        """Restore the previous spec."""
        if self._task_running or self.session.undo() is None:
            return
        self._show_spec(restructured=True)

    @_guard
    def export(self):
        """Write the PNG, spec JSON, ParaView preset and Slicer file to the export folder."""
        self.state.error = ""
        self.plotter.render()
        self.state.exports = [str(p) for p in self.session.export(self.plotter)]
        self.state.info = f"exported {len(self.state.exports)} files to {self.session.export_dir}"

    @_guard
    def measure_view(self, *_):
        """Re-measure after the user rotated the view."""
        self.remeasure()

    # -- optimisation ------------------------------------------------------------------------
    @_guard
    def optimise(self, which="opacity"):
        """Start optimising this view (``"opacity"`` or ``"all"`` stages) in the background."""
        if self._task_running:
            return
        if which not in STAGE_SETS:
            raise DVRInputError(f"optimise: unknown stage set {which!r}")
        self.state.error = ""
        self._task_running = True
        self._cancel.clear()
        self.state.busy = True
        self.state.progress = 0
        self.state.progress_text = "analysing the view..."
        asynchronous.create_task(self._optimise(STAGE_SETS[which]))

    @_guard
    def cancel(self):
        """Stop the running optimisation (it keeps the best result so far)."""
        if self._task_running:
            self._cancel.set()
            self.state.progress_text = "cancelling..."

    def _on_iteration(self, loop, stages, intermediate):
        """Optimiser callback (worker thread): hand the newest spec to the event loop."""
        if self._cancel.is_set():
            raise StopIteration
        first = self._pending is None
        self._pending = (stages, intermediate)
        if first:
            loop.call_soon_threadsafe(self._schedule_show, loop)

    def _schedule_show(self, loop) -> None:
        wait = self._last_live + LIVE_INTERVAL_S - loop.time()
        loop.call_later(max(0.0, wait), self._show_intermediate)

    def _show_intermediate(self) -> None:
        pending, self._pending = self._pending, None
        if pending is None or not self._task_running:
            return
        self._last_live = asyncio.get_running_loop().time()
        stages, r = pending
        done = stages.index(r.stage) * MAX_ITER + min(r.iteration, MAX_ITER)
        self._render_spec(r.spec)
        self._push_image()
        with self.state:
            self.state.progress = round(100 * done / (len(stages) * MAX_ITER))
            self.state.progress_text = (
                f"step {stages.index(r.stage) + 1} of {len(stages)} ({r.stage}): "
                f"iteration {r.iteration} of {MAX_ITER}"
            )

    async def _optimise(self, stages) -> None:
        from dvr_perception.optimize import optimize

        loop = asyncio.get_running_loop()
        spec, volume = self.session.spec, self.session.volume
        run = functools.partial(
            optimize,
            volume,
            spec,
            self.current_camera(),
            stages=stages,
            max_iter=MAX_ITER,
            seed=0,
            callback=functools.partial(self._on_iteration, loop, stages),
        )
        try:
            result = await loop.run_in_executor(None, run)
        except Exception as exc:  # shown in the page; the server keeps running
            log.exception("optimisation failed")
            result, error = None, f"optimisation failed: {exc}"
        self._task_running = False
        self._pending = None
        with self.state:
            self.state.busy = False
            if result is None:
                self.fail(error)
                self._show_spec()
                return
            self.session.push_undo()
            self.session.spec = result.spec
            cancelled = self._cancel.is_set()
            self.state.progress = 100
            self.state.progress_text = (
                f"{'cancelled, kept the best so far' if cancelled else 'done'}: total error "
                f"{result.initial['E']:.3g} -> {result.final['E']:.3g} ({result.nit} iterations)"
            )
            self._show_spec()
