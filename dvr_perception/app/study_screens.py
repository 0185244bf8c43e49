"""Handlers of the web app's two study screens: the calibration test and the ranking task.

:class:`StudyHandlers` is mixed into :class:`~dvr_perception.app.core.DVRApp`; it uses the
app's ``state``, ``session``, ``remeasure`` and ``current_camera``.  The studies themselves
(stimuli, fitting, ranking images) live in :mod:`.study`.
"""

from __future__ import annotations

import asyncio
import functools
import logging
import time
from pathlib import Path

from trame.app import asynchronous
from trame.decorators import change

from dvr_perception.app._guard import guard
from dvr_perception.app.charts import calibration_svg
from dvr_perception.app.session import measure_camera, plain_name
from dvr_perception.app.study import CalibrationTest, RankingTask
from dvr_perception.errors import DVRInputError

__all__ = ["RANKING_FILE", "RANKING_SIZE", "StudyHandlers"]

log = logging.getLogger("dvr_perception.app")

#: File (in the export folder) the ranking answers are appended to.
RANKING_FILE = "ranking_answers.csv"
#: Long side of the ranking images.
RANKING_SIZE = 160


class StudyHandlers:
    """Page handlers of the Calibration and Ranking screens."""

    # -- calibration test --------------------------------------------------------------------
    @guard
    def start_calibration(self):
        """Start a new calibration test (stimuli in a new random order)."""
        self.state.error = ""
        self.calibration_test = CalibrationTest(seed=int(time.time()) % 100_000)
        self.state.cal_active = True
        self.state.cal_saved = ""
        self.state.cal_svg = ""
        self.state.cal_rating = 0.5
        self._show_stimulus()

    def _show_stimulus(self) -> None:
        t = self.calibration_test
        self.state.cal_total = len(t.stimuli)
        self.state.cal_index = len(t.ratings) + 1
        self.state.cal_url = t.image_url()

    @guard
    def rate_stimulus(self, value=None):
        """Record the rating of the shown stimulus; after the last one fit and save the curve."""
        t = self.calibration_test
        if t is None:
            raise DVRInputError("calibration: press 'Start the test' first")
        t.rate(self.state.cal_rating if value is None else value)
        self.state.cal_rating = 0.5
        if not t.done:
            self._show_stimulus()
            return
        self.state.cal_active = False
        path = self._results_path(self.state.cal_name, ".json")
        path, curve = t.save(path)
        self._curve = curve
        self.session.use_calibration(curve, path.name)
        self.state.cal_saved = str(path)
        self.state.cal_svg = calibration_svg(curve, t.measured, t.ratings)
        self.state.has_calibration = True
        self.state.use_calibration = True
        self.state.calibration_name = path.name
        self.state.info = (
            f"saved your calibration curve to {path} (your answers: "
            f"{t.ratings_path(path).name}); the measures now use it"
        )
        self.remeasure()

    @guard
    def load_calibration_file(self):
        """Load a saved calibration curve (from the export folder) and use it."""
        from dvr_perception.calibration import load_calibration

        self.state.error = ""
        path = self._results_path(self.state.cal_name, ".json", must_exist=True)
        curve = load_calibration(path)
        self._curve = curve
        self.session.use_calibration(curve, path.name)
        self.state.cal_svg = calibration_svg(curve)
        self.state.has_calibration = True
        self.state.use_calibration = True
        self.state.calibration_name = path.name
        self.state.info = f"loaded {path.name}; the measures now use it"
        self.remeasure()

    @change("use_calibration")
    @guard
    def on_use_calibration(self, use_calibration, **_):
        """Switch the personal calibration on or off for the measures and the optimiser."""
        want = bool(use_calibration) and self._curve is not None
        current = self.session.calibration is not None
        if want == current:
            return
        name = self.state.calibration_name if want else ""
        self.session.use_calibration(self._curve if want else None, name)
        self.remeasure()

    def _results_path(self, text, suffix: str, *, must_exist: bool = False) -> Path:
        """Resolve a plain file name inside the export folder (no folders, given suffix)."""
        name = plain_name(text, "calibration file", (suffix,))
        folder = self.session.export_dir
        if must_exist:
            if not (folder / name).is_file():
                raise DVRInputError(f"{name}: no such file in {folder}")
            return folder / name
        return self.session.writable_dir(folder) / name

    # -- ranking task ------------------------------------------------------------------------
    @guard
    def new_ranking(self):
        """Render a new set of ranking images (in the background)."""
        if self.state.rank_busy:
            return
        self.state.error = ""
        self.state.rank_busy = True
        self.state.rank_result = ""
        self.state.rank_saved = False
        self.state.rank_order = []
        asynchronous.create_task(self._new_ranking(int(self.state.rank_structure or 0)))

    async def _new_ranking(self, structure: int) -> None:
        loop = asyncio.get_running_loop()
        camera = measure_camera(self.current_camera(), RANKING_SIZE)
        run = functools.partial(
            RankingTask.make,
            self.session.volume,
            self.session.spec,
            camera,
            structure,
            seed=int(time.time() * 1000) % 100_000,
        )
        try:
            task, error = await loop.run_in_executor(None, run), ""
        except Exception as exc:  # shown in the page; the server keeps running
            log.exception("ranking images failed")
            task, error = None, f"ranking images failed: {exc}"
        with self.state:
            self.state.rank_busy = False
            if task is None:
                self.fail(error)
                return
            self.ranking = task
            letters = "ABCDEFGH"
            self.state.rank_images = [
                {"id": i, "label": letters[k], "url": task.urls[i]}
                for k, i in enumerate(task.shown)
            ]
            self.state.rank_order = []

    @guard
    def save_ranking(self, order=None):
        """Append the viewer's order (most see-through first) to the answers file."""
        if self.ranking is None:
            raise DVRInputError("ranking: press 'New set of images' first")
        if self.state.rank_saved:
            raise DVRInputError("ranking: this answer is already saved; press 'New set of images'")
        order = list(self.state.rank_order if order is None else order)
        path = self.session.writable_dir(self.session.export_dir) / RANKING_FILE
        row = self.ranking.record(order, path)
        labels = {r["id"]: r["label"] for r in self.state.rank_images}
        measured = " > ".join(labels[i] for i in row["measured_order"].split())
        self.state.rank_result = (
            f"saved to {path.name}. Most to least see-through by the measure: {measured}; "
            f"your order agrees on {row['pairs_agreeing']} of {row['pairs_total']} pairs."
        )
        self.state.rank_saved = True
        self.state.info = f"answer saved to {path}"
