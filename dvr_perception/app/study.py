"""The app's calibration test and ranking task (paper, Sec. 6 and 7.3), without a web framework.

:class:`CalibrationTest` shows calibration stimuli of known transmittance
(:func:`dvr_perception.calibration.calibration_stimuli`) one after another, records how
see-through the viewer finds each, fits the viewer's monotone curve
(:func:`~dvr_perception.calibration.fit_calibration`) and saves it as JSON
(:func:`~dvr_perception.calibration.save_calibration`).  The measured transmittance of a
stimulus uses the same contrast as the app's transparency measure (Michelson).

:class:`RankingTask` is the user study's ranking task: images of the current view in which the
colour of one structure differs, shown in random order; the viewer orders them from most to
least see-through, and the answer, with the measured order, is appended to a CSV file.
"""

from __future__ import annotations

import base64
import csv
import io
import itertools
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from dvr_perception.errors import DVRInputError

__all__ = [
    "CALIBRATION_TRANSMITTANCES",
    "RANKING_FIELDS",
    "CalibrationTest",
    "RankingTask",
    "kendall_agreement",
    "png_data_url",
]

#: Transmittances of the calibration stimuli (each on a plain and a textured background).
CALIBRATION_TRANSMITTANCES = (0.15, 0.35, 0.55, 0.75)
#: Colour brightness factors of the ranking images.
RANKING_LEVELS = (0.25, 0.5, 0.75, 1.0)
#: Columns of the ranking answers file.
RANKING_FIELDS = (
    "timestamp",
    "set_id",
    "volume",
    "structure",
    "image_ids",
    "user_order",
    "measured_order",
    "measured_transparency",
    "pairs_agreeing",
    "pairs_total",
)


def png_data_url(image, *, scale: int = 1) -> str:
    """Encode an ``(H, W, 3)`` float image in [0, 1] as a ``data:image/png`` URL.

    Examples
    --------
    >>> png_data_url(np.zeros((2, 2, 3)))[:22]
    'data:image/png;base64,'
    """
    from PIL import Image

    arr = np.clip(np.nan_to_num(np.asarray(image, dtype=np.float64)), 0.0, 1.0)
    img = Image.fromarray(np.round(arr * 255).astype(np.uint8), mode="RGB")
    if scale > 1:
        img = img.resize((img.width * scale, img.height * scale), Image.NEAREST)
    buf = io.BytesIO()
    img.save(buf, format="PNG")
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def kendall_agreement(order_a, order_b) -> tuple[int, int]:
    """Return ``(agreeing pairs, all pairs)`` of two orders of the same items.

    Examples
    --------
    >>> kendall_agreement(["a", "b", "c"], ["a", "c", "b"])
    (2, 3)
    """
    pos_b = {item: k for k, item in enumerate(order_b)}
    if sorted(pos_b) != sorted(order_a):
        raise DVRInputError(f"ranking: orders hold different items: {order_a} vs {order_b}")
    pairs = list(itertools.combinations(order_a, 2))
    agree = sum(1 for x, y in pairs if pos_b[x] < pos_b[y])
    return agree, len(pairs)


@dataclass
class CalibrationTest:
    """A viewer's calibration run: stimuli in random order, one rating per stimulus.

    Parameters
    ----------
    seed : int
        Shuffles the stimuli (and draws the textures).
    size : int
        Stimulus edge in pixels (a multiple of 8).
    """

    seed: int = 0
    size: int = 128
    stimuli: list = field(default_factory=list, repr=False)
    measured: list = field(default_factory=list)
    ratings: list = field(default_factory=list)

    def __post_init__(self) -> None:
        from dvr_perception.calibration import calibration_stimuli, measured_transmittance

        stims = calibration_stimuli(
            transmittances=CALIBRATION_TRANSMITTANCES,
            backgrounds=("light",),
            textures=("plain", "textured"),
            size=self.size,
            seed=self.seed,
        )
        order = np.random.default_rng(self.seed).permutation(len(stims))
        self.stimuli = [stims[k] for k in order]
        self.measured = [measured_transmittance(s, contrast="michelson") for s in self.stimuli]

    @property
    def done(self) -> bool:
        """Whether every stimulus has been rated."""
        return len(self.ratings) >= len(self.stimuli)

    @property
    def current(self) -> int:
        """Index of the stimulus to rate next."""
        return min(len(self.ratings), len(self.stimuli) - 1)

    def image_url(self, k: int | None = None) -> str:
        """PNG data URL of stimulus ``k`` (default: the current one)."""
        s = self.stimuli[self.current if k is None else int(k)]
        return png_data_url(s.image, scale=2)

    def rate(self, value) -> None:
        """Record the current stimulus' rating: how see-through it looks, 0 to 1."""
        if self.done:
            raise DVRInputError("calibration: every image is already rated; save the curve")
        try:
            v = float(value)
        except (TypeError, ValueError):
            v = float("nan")
        if not 0.0 <= v <= 1.0:
            raise DVRInputError(f"calibration rating: expected 0 to 1, got {value}")
        self.ratings.append(v)

    def fit(self):
        """Fit the viewer's curve to the ratings so far (at least two distinct stimuli)."""
        from dvr_perception.calibration import fit_calibration

        n = len(self.ratings)
        if n < 2:
            raise DVRInputError("calibration: rate at least two images before fitting a curve")
        return fit_calibration(self.measured[:n], self.ratings)

    def save(self, path) -> tuple[Path, object]:
        """Fit and save the curve as JSON at ``path``; return the path and the curve.

        The ratings themselves go next to it, to ``<stem>.ratings.csv`` (one row per rated
        image: time, texture, background, composited and measured transmittance, rating).
        """
        from dvr_perception.calibration import save_calibration

        curve = self.fit()
        out = Path(save_calibration(curve, path))
        stamp = time.strftime("%Y-%m-%dT%H:%M:%S%z")
        with self.ratings_path(out).open("w", newline="", encoding="utf-8") as fh:
            writer = csv.writer(fh)
            writer.writerow(
                (
                    "timestamp",
                    "image",
                    "texture",
                    "background",
                    "transmittance",
                    "measured",
                    "rating",
                )
            )
            for k, rating in enumerate(self.ratings):
                st = self.stimuli[k]
                writer.writerow(
                    (
                        stamp,
                        k + 1,
                        st.texture,
                        st.background,
                        f"{st.transmittance:.4f}",
                        f"{self.measured[k]:.4f}",
                        f"{rating:.4f}",
                    )
                )
        return out, curve

    @staticmethod
    def ratings_path(curve_path) -> Path:
        """Where :meth:`save` writes the ratings for a curve file."""
        p = Path(curve_path)
        stem = p.name[: -len(".json")] if p.name.endswith(".json") else p.name
        return p.with_name(stem + ".ratings.csv")


def _brighter(color, factor: float) -> tuple[float, float, float]:
    """Scale a colour's brightness (HSV value) to ``factor`` of full, keeping its hue."""
    import colorsys

    h, s, _ = colorsys.rgb_to_hsv(*(float(c) for c in color))
    return colorsys.hsv_to_rgb(h, s, float(factor))


@dataclass
class RankingTask:
    """One set of the ranking task: the same view with one structure's colour varied.

    Build it with :meth:`make`; :attr:`images` are shown in :attr:`shown` order (random).
    """

    set_id: str
    volume: str
    structure: str
    ids: list
    urls: dict
    measured: dict
    shown: list

    @classmethod
    def make(cls, volume, spec, camera, structure: int, *, seed=None, curvature=None):
        """Render and measure the variants of ``spec`` for structure index ``structure``."""
        from dvr_perception.measures import transparency
        from dvr_perception.rays.engine import analyze

        k = int(structure)
        if not 0 <= k < len(spec.structures):
            raise DVRInputError(f"ranking: no structure {structure}")
        target = spec.structures[k]
        rng = np.random.default_rng(seed)
        ids, urls, measured = [], {}, {}
        for n, level in enumerate(RANKING_LEVELS):
            structures = list(spec.structures)
            structures[k] = replace(target, colour=_brighter(target.colour, level))
            variant = replace(spec, structures=tuple(structures))
            analysis = analyze(volume, variant, camera, curvature=curvature)
            t = transparency(analysis, variant).per_structure.get(target.name, {})
            value = t.get("perceived_transparency")
            image_id = f"img{n + 1}"
            ids.append(image_id)
            urls[image_id] = png_data_url(analysis.image)
            measured[image_id] = None if value is None else float(value)
        shown = [ids[j] for j in rng.permutation(len(ids))]
        set_id = time.strftime("%Y%m%dT%H%M%S") + f"-{int(rng.integers(1000)):03d}"
        return cls(set_id, volume.name, target.name, ids, urls, measured, shown)

    def measured_order(self) -> list[str]:
        """Image ids from most to least see-through by the measure (unmeasured last)."""
        return sorted(
            self.ids, key=lambda i: (self.measured[i] is None, -(self.measured[i] or 0.0))
        )

    def record(self, user_order, path) -> dict:
        """Append the viewer's order (most see-through first) to the CSV file ``path``.

        Returns the written row.
        """
        order = [str(i) for i in user_order]
        if sorted(order) != sorted(self.ids):
            raise DVRInputError(
                f"ranking: put all {len(self.ids)} images in order first (got {len(order)})"
            )
        measured = self.measured_order()
        agree, total = kendall_agreement(order, measured)
        row = {
            "timestamp": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "set_id": self.set_id,
            "volume": self.volume,
            "structure": self.structure,
            "image_ids": " ".join(self.shown),
            "user_order": " ".join(order),
            "measured_order": " ".join(measured),
            "measured_transparency": " ".join(
                f"{i}={'nan' if self.measured[i] is None else f'{self.measured[i]:.3f}'}"
                for i in self.ids
            ),
            "pairs_agreeing": agree,
            "pairs_total": total,
        }
        p = Path(path)
        p.parent.mkdir(parents=True, exist_ok=True)
        new = not p.is_file() or p.stat().st_size == 0
        with p.open("a", newline="", encoding="utf-8") as fh:
            writer = csv.DictWriter(fh, fieldnames=RANKING_FIELDS)
            if new:
                writer.writeheader()
            writer.writerow(row)
        return row
