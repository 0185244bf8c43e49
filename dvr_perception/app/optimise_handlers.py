"""The optimise buttons of the web app: run the optimiser in a worker thread, show its progress.

:class:`OptimiseHandlers` is mixed into :class:`~dvr_perception.app.core.DVRApp`; it uses the
app's ``state``, ``session``, ``plotter`` and the view helpers (``current_camera``,
``_show_spec``, ``_set_measures``, ...).  The optimiser's callback (worker thread) hands each
intermediate result to the event loop with ``call_soon_threadsafe``; only numbers and the
chart are pushed while it runs, the new rendering once it is done.  Cancel sets an event the
callback turns into ``StopIteration``, so the optimiser returns its best parameters so far.
"""

from __future__ import annotations

import asyncio
import functools
import logging
import time

from trame.app import asynchronous

from dvr_perception.app._guard import guard
from dvr_perception.app.charts import lines_svg
from dvr_perception.app.lens import lens_region
from dvr_perception.errors import DVRCancelled, DVRInputError

__all__ = ["LIVE_INTERVAL_S", "MAX_ITER", "PREP_SHARE", "STAGE_SETS", "TERMS", "OptimiseHandlers"]

log = logging.getLogger("dvr_perception.app")

#: Stages run by the two optimise buttons.
STAGE_SETS = {"opacity": ("opacity",), "all": ("opacity", "lighting", "colour")}
#: Optimiser iterations per stage.
MAX_ITER = 10
#: Least seconds between two progress updates while optimising.  Only numbers and the chart
#: are pushed: a VTK rendering holds the GIL for its whole duration (2-3 s for cthead at
#: 512\u00b2 in software GL), and one per second starved the optimiser's thread (issue 20).
LIVE_INTERVAL_S = 0.25
#: Share of the progress bar for the analysis before the optimiser's first iteration.
PREP_SHARE = 0.1
#: The error terms charted per iteration: key, label, colour.
TERMS = ("E_v", "E_s", "E_t")
_TERM_STYLE = (("visibility", "#1565c0"), ("shape", "#2e7d32"), ("transparency", "#ef6c00"))


def _history_chart(history) -> str:
    """SVG of the three errors per iteration (empty string without iterations)."""
    if not history:
        return ""
    cols = list(zip(*history, strict=True))
    return lines_svg([(label, color, cols[k]) for k, (label, color) in enumerate(_TERM_STYLE)])


def _why_lines(result) -> list[str]:
    """One line per structure: opacity and share of the picture before -> target -> after."""
    from dvr_perception.optimize.explain import explanation_line

    return [explanation_line(n, e) for n, e in result.structures.items()]


class OptimiseHandlers:
    """Page handlers of the optimise buttons (opacity, all stages, in the lens) and Cancel."""

    @guard
    def optimise(self, which="opacity", in_lens=False):
        """Start optimising this view (``"opacity"`` or ``"all"`` stages) in the background.

        With ``in_lens`` only the lens region drives the optimisation, with the targets set
        for the structures inside it.  Its result is not applied: it is shown inside the lens
        over the current rendering, with the whole view's change and cost beside it, and one
        click applies it to the whole view (:meth:`~.LensHandlers.lens_apply`).
        """
        if self._task_running:
            return
        if which not in STAGE_SETS:
            raise DVRInputError(f"optimise: unknown stage set {which!r}")
        camera = self.current_camera()
        region = targets = None
        if in_lens:
            region = lens_region(self.state.lens, camera.width, camera.height)
            targets = self._lens_targets()
        s = self.state
        s.error = ""
        self._task_running = True
        self._cancel.clear()
        stages = STAGE_SETS[which]
        self._run = {
            "t0": time.monotonic(),
            "stages": stages,
            "view": self._view_no,
            "tf": self._tf_no,
        }
        s.busy = True
        s.progress = 0
        s.progress_text = "analysing the view..."
        s.opt_key = self._key()
        s.opt_for = self._describe(camera)
        s.opt_camera = camera.to_dict()  # the optimiser's camera, for the CLI to redo it
        s.opt_sampling = self._sampling_text(camera)
        s.before_url = self._snapshot()  # rendered now: what is on screen for this camera
        s.before_text = self._errors_text() if s.measured_key == s.now_key else ""
        s.after_url = s.after_text = ""
        self._drop_lens_result()
        s.live_shares = []
        s.why_lines = []
        self._e_history = []
        s.error_history_svg = ""
        label = f"optimise {which}" + (" in lens" if in_lens else "")
        asynchronous.create_task(self._optimise(stages, camera, region, targets, label))

    def _sampling_text(self, camera) -> str:
        """Name the optimiser's sampling resolutions for ``camera`` (the reduced view)."""
        from dvr_perception.optimize.core import DEFAULT_RESOLUTION

        w, h = (int(v) for v in self.plotter.window_size)
        return (
            f"The optimiser samples this {w}\u00d7{h} px view at {camera.width}\u00d7"
            f"{camera.height} px (its before and after errors) and iterates at "
            f"{DEFAULT_RESOLUTION} px on the long side."
        )

    def _errors_text(self, m=None) -> str:
        """Return the three errors of ``m`` (default: the summary's) as a caption."""
        if m is not None:
            m = m.as_state()
            return f"visibility {m['E_v']}, shape {m['E_s']}, transparency {m['E_t']}"
        s = self.state
        if s.E_v is None:
            return ""
        return f"visibility {s.E_v}, shape {s.E_s}, transparency {s.E_t}"

    @guard
    def cancel(self):
        """Stop the running optimisation (it keeps the best result so far)."""
        if self._task_running:
            self._cancel.set()
            self.state.progress_text = "cancelling..."

    def _on_iteration(self, loop, stages, intermediate):
        """Optimiser callback (worker thread): hand the newest numbers to the event loop."""
        if self._cancel.is_set():
            raise StopIteration
        self._e_history.append(tuple(float(intermediate.terms[k]) for k in TERMS))
        first = self._pending is None
        self._pending = (stages, intermediate)
        if first:
            loop.call_soon_threadsafe(self._schedule_show, loop)

    def _on_prep(self, loop, fraction) -> None:
        """Optimiser's preparation progress (worker thread; the library's ``progress=``)."""
        if self._cancel.is_set():
            raise StopIteration("cancelled in the page")
        now = time.monotonic()
        if fraction < 1.0 and now - self._last_prep < LIVE_INTERVAL_S:
            return
        self._last_prep = now
        loop.call_soon_threadsafe(self._show_prep, float(fraction))

    def _show_prep(self, fraction: float) -> None:
        """Progress of the analysis before the first iteration (the bar's first PREP_SHARE)."""
        if not self._task_running or self._cancel.is_set() or self._e_history:
            return  # the iterations report from now on
        elapsed = time.monotonic() - self._run["t0"]
        left = elapsed / fraction * (1.0 - fraction) if fraction > 0 else 0.0
        with self.state:
            self.state.progress = round(100 * PREP_SHARE * fraction)
            self.state.progress_text = (
                f"analysing the view before the first iteration: {100 * fraction:.0f} %; "
                f"{elapsed:.0f} s so far"
                + (f", about {left:.0f} s left for this step" if fraction > 0 else "")
            )

    def _schedule_show(self, loop) -> None:
        wait = self._last_live + LIVE_INTERVAL_S - loop.time()
        loop.call_later(max(0.0, wait), self._show_intermediate)

    def _show_intermediate(self) -> None:
        """Progress, errors and shares of the newest iteration (numbers only: no rendering)."""
        from dvr_perception.optimize.core import DEFAULT_RESOLUTION

        pending, self._pending = self._pending, None
        if pending is None or not self._task_running or self._cancel.is_set():
            return
        self._last_live = asyncio.get_running_loop().time()
        stages, r = pending
        n = self.max_iter
        done = stages.index(r.stage) * n + min(r.iteration, n)
        total = len(stages) * n
        elapsed = time.monotonic() - self._run["t0"]
        left = elapsed / max(done, 1) * (total - done)
        e = sum(float(r.terms[k]) for k in TERMS)
        with self.state:
            self.state.error_history_svg = _history_chart(list(self._e_history))
            self._set_shares(r.terms.get("visible_share", {}), "live_shares")
            self.state.progress = round(100 * (PREP_SHARE + (1 - PREP_SHARE) * done / total))
            self.state.progress_text = (
                f"step {stages.index(r.stage) + 1} of {len(stages)} ({r.stage}): "
                f"iteration {r.iteration} of {n}; total error {e:.3g} at the optimiser's "
                f"{DEFAULT_RESOLUTION} px sampling; {elapsed:.0f} s so far, at most about "
                f"{left:.0f} s left"
            )

    def _optimise_in_worker(self, stages, camera, region, targets, callback, progress=None):
        """Run the optimiser (worker thread); return the result and the whole view's measures.

        The measures before and after come from the optimiser's own analyses of ``camera``
        (no second rendering), so the whole view's numbers appear with the result.
        """
        from dvr_perception.optimize import optimize

        session = self.session
        spec = session.spec
        result = optimize(
            session.volume,
            spec,
            camera,
            stages=stages,
            region=region,
            targets=targets,
            calibration=session.calibration,
            max_iter=self.max_iter,
            seed=0,
            callback=callback,
            curvature=session.curvature(spec),
            progress=progress,
        )
        first, last = result.analyses or (None, None)
        if first is None:
            return result, None, None
        return result, session.measures_of(first, spec), session.measures_of(last, result.spec)

    async def _optimise(self, stages, camera, region, targets, label) -> None:
        loop = asyncio.get_running_loop()
        callback = functools.partial(self._on_iteration, loop, stages)
        progress = functools.partial(self._on_prep, loop)
        self._last_prep = 0.0
        work = (stages, camera, region, targets, callback, progress)
        error = ""
        try:
            result, before, after = await loop.run_in_executor(
                None, self._optimise_in_worker, *work
            )
        except DVRCancelled:  # cancelled before the first iteration: nothing to keep
            result = None
        except Exception as exc:  # shown in the page; the server keeps running
            log.exception("optimisation failed")
            result, error = None, f"optimisation failed: {exc}"
        run, self._run = self._run, None
        self._task_running = False
        self._pending = None
        with self.state:
            self.state.error_history_svg = _history_chart(list(self._e_history))
            if result is None:
                self.state.busy = False
                if error:
                    self.fail(error)
                else:
                    self.state.progress_text = "cancelled before the first iteration: unchanged"
                self._show_spec()
                return
            cancelled = self._cancel.is_set()
            where = " in the lens" if region is not None else ""
            self.state.progress = 100
            same = result.final["E"] >= result.initial["E"]
            self.state.progress_text = (
                f"{'cancelled, kept the best so far' if cancelled else 'done'}: total error"
                f"{where} {result.initial['E']:.3g} -> {result.final['E']:.3g} "
                f"({result.nit} iterations, {time.monotonic() - run['t0']:.0f} s)"
                + ("; no better setting found, rendering unchanged" if same else "")
            )
        # the outcome is on the page before the new view is rendered (seconds for a large view)
        await asyncio.sleep(0.05)
        label += " (cancelled)" if cancelled else ""
        if region is not None:  # shown inside the lens, applied to the whole view on request
            with self.state:
                self.state.busy = False
                self._show_lens_result(result, before, after, label, run["tf"])
            return
        with self.state:
            self.state.busy = False
            self.session.push_undo(label)
            self._tf_before = self.session.spec  # drawn dashed in the transfer-function view
            self.session.spec = result.spec
            self.state.why_lines = _why_lines(result)
            self._render_spec(result.spec)
            self.state.after_url = self._snapshot()  # rendered with the result (issue 30)
            fresh = after is not None and run["view"] == self._view_no
            self._show_spec(label=label, measure=not fresh)
            self.state.opt_key = self._key()
            self.state.opt_for = self._describe(camera)
            if before is not None:
                self.state.before_text = self._errors_text(before)
            if fresh:
                self._set_measures(after, self._key(), self.state.opt_for)
                self.state.after_text = self._errors_text(after)
            else:
                asynchronous.create_task(self._after_text())
