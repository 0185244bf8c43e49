"""Per-viewer calibration of perceived transparency (paper, Sec. 6 and Fig. 6(b)(c)).

:mod:`~.stimuli` makes test images of a transparent layer of known transmittance over plain
(bipartite) and textured backgrounds and measures them with Metelli / TAP; :mod:`~.curve` fits a
monotone curve from the measured to the viewer-perceived transmittance and stores it as JSON.
The curve is what :func:`dvr_perception.measures.transparency` takes as ``calibration``.
"""

from dvr_perception.calibration.curve import (
    CalibrationCurve,
    fit_calibration,
    load_calibration,
    save_calibration,
)
from dvr_perception.calibration.stimuli import (
    Stimulus,
    calibration_stimuli,
    measured_transmittance,
)

__all__ = [
    "CalibrationCurve",
    "Stimulus",
    "calibration_stimuli",
    "fit_calibration",
    "load_calibration",
    "measured_transmittance",
    "save_calibration",
]
