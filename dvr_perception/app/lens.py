"""The lens (region refinement) of the web app: page fractions to pixels, and its handlers.

:class:`LensHandlers` is mixed into :class:`~dvr_perception.app.core.DVRApp`; it uses the
app's ``state``, ``session`` and ``measures``.
"""

from __future__ import annotations

import math

from trame.decorators import change

from dvr_perception.app._guard import guard
from dvr_perception.app.session import rgb_to_hex
from dvr_perception.errors import DVRInputError

__all__ = ["LensHandlers", "lens_region"]


def lens_region(lens, width: int, height: int):
    """Turn the page's lens (fractions of the view) into an optimiser region in pixels.

    ``lens`` is ``{"shape": "rect", "x0", "y0", "x1", "y1"}`` (corners) or
    ``{"shape": "circle", "x0", "y0", "r"}`` (centre, radius as a fraction of the width).

    Examples
    --------
    >>> lens_region({"shape": "rect", "x0": 0.5, "y0": 0.5, "x1": 0.25, "y1": 0.75}, 100, 80)
    ('rect', 25.0, 40.0, 50.0, 60.0)
    >>> lens_region({"shape": "circle", "x0": 0.5, "y0": 0.5, "r": 0.1}, 100, 80)
    ('circle', 50.0, 40.0, 10.0)
    """
    if not isinstance(lens, dict):
        raise DVRInputError("lens: draw a rectangle or a circle on the view first")
    try:
        if lens.get("shape") == "circle":
            cx, cy, r = (float(lens[k]) for k in ("x0", "y0", "r"))
            out = ("circle", cx * width, cy * height, r * width)
        elif lens.get("shape") == "rect":
            x0, y0, x1, y1 = (float(lens[k]) for k in ("x0", "y0", "x1", "y1"))
            out = (
                "rect",
                min(x0, x1) * width,
                min(y0, y1) * height,
                max(x0, x1) * width,
                max(y0, y1) * height,
            )
        else:
            raise DVRInputError(f"lens: unknown shape {lens.get('shape')!r}")
    except (KeyError, TypeError, ValueError):
        raise DVRInputError(f"lens: malformed region {lens!r}") from None
    if not all(math.isfinite(v) for v in out[1:]):
        raise DVRInputError(f"lens: malformed region {lens!r}")
    return out


class LensHandlers:
    """Page handlers of the Lens screen (draw, list the structures inside, set targets)."""

    @change("lens")
    @guard
    def on_lens_change(self, lens, **_):
        """List the structures inside a newly drawn lens with their targets (or clear it)."""
        if not lens:
            self.state.lens_rows = []
            self.state.lens_text = ""
            return
        self.state.error = ""
        self._update_lens_rows()

    def _update_lens_rows(self) -> None:
        from dvr_perception.optimize._region import parse_region

        lens = self.state.lens
        if not lens or self.measures is None or self.measures.present is None:
            return
        h, w = self.measures.present.shape
        region = lens_region(lens, w, h)
        try:
            mask = parse_region(region, h, w)
        except DVRInputError:
            self.state.lens_rows = []
            self.state.lens_text = "the region is too small or outside the image: draw again"
            return
        inside = self.session.region_structures(
            self.measures.present, mask, self.measures.share_images
        )
        old = {r["name"]: r for r in self.state.lens_rows or []}
        rows = []
        for r in inside:
            s = self.session.spec.structures[r["index"]]
            prev = old.get(r["name"], {})
            share = r["visible"] if r["visible"] is not None else 0.0
            rows.append(
                {
                    **r,
                    "color": rgb_to_hex(s.color),
                    "use_vis": prev.get("use_vis", False),
                    "vis": prev.get("vis", round(min(max(share, 0.05), 1.0), 2)),
                    "use_tr": prev.get("use_tr", False),
                    "tr": prev.get("tr", round(1.0 - float(s.render_opacity), 2)),
                }
            )
        self.state.lens_rows = rows
        kind = "circle" if lens.get("shape") == "circle" else "rectangle"
        pct = 100.0 * mask.mean()
        self.state.lens_text = (
            f"{kind} covering {pct:.0f} % of the image; {len(rows)} structure"
            f"{'' if len(rows) == 1 else 's'} inside"
        )

    @guard
    def set_lens_target(self, index, key, value):
        """Set a lens row's target field (``use_vis``, ``vis``, ``use_tr``, ``tr``)."""
        if key not in ("use_vis", "vis", "use_tr", "tr"):
            raise DVRInputError(f"lens target: unknown field {key!r}")
        rows = [dict(r) for r in self.state.lens_rows]
        for r in rows:
            if r["index"] == int(index):
                r[key] = bool(value) if key.startswith("use_") else float(value)
        self.state.lens_rows = rows

    def _lens_targets(self) -> dict:
        targets = {}
        for r in self.state.lens_rows or []:
            wanted = {}
            if r.get("use_vis"):
                wanted["visibility"] = float(r["vis"])
            if r.get("use_tr"):
                wanted["transparency"] = float(r["tr"])
            if wanted:
                targets[r["name"]] = wanted
        return targets

    @guard
    def clear_lens(self):
        """Remove the lens."""
        self.state.lens = None
        self.state.lens_rows = []
        self.state.lens_text = ""
