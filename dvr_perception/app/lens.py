"""The lens (region refinement) of the web app: page fractions to pixels, and its handlers.

:class:`LensHandlers` is mixed into :class:`~dvr_perception.app.core.DVRApp`; it uses the
app's ``state``, ``session``, ``plotter`` and ``measures``.

A lens refinement optimises the whole transfer function from the region, so its result
changes the whole image.  It is therefore not applied at once: the page shows it inside the
lens over the current rendering (focus + context, :func:`composite`), the whole view with it
as a thumbnail with the whole view's errors before -> after (its cost), and one click applies
it to the whole view (:meth:`LensHandlers.lens_apply`).
"""

from __future__ import annotations

import base64
import io
import math

import numpy as np
from trame.decorators import change

from dvr_perception.app._guard import guard
from dvr_perception.app.session import rgb_to_hex
from dvr_perception.errors import DVRInputError

__all__ = ["LensHandlers", "composite", "lens_mask", "lens_region", "overlay_data_url"]


def _why_lines(result) -> list[str]:
    from dvr_perception.app.optimise_handlers import _why_lines as lines

    return lines(result)


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


def lens_mask(lens, width: int, height: int) -> np.ndarray:
    """Return the lens as a boolean ``(height, width)`` mask of an image of that size.

    The pixels whose centre lies inside the lens (as the optimiser's region,
    :func:`~dvr_perception.optimize._region.parse_region`).

    Examples
    --------
    >>> m = lens_mask({"shape": "rect", "x0": 0.25, "y0": 0.0, "x1": 0.75, "y1": 0.5}, 4, 4)
    >>> m.astype(int)
    array([[0, 1, 1, 0],
           [0, 1, 1, 0],
           [0, 0, 0, 0],
           [0, 0, 0, 0]])
    """
    from dvr_perception.optimize._region import parse_region

    return parse_region(lens_region(lens, width, height), int(height), int(width))


def composite(context: np.ndarray, focus: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Return ``focus`` inside ``mask`` and ``context`` outside it (images ``(H, W, C)``).

    Examples
    --------
    >>> out = composite(np.zeros((2, 2, 3)), np.ones((2, 2, 3)), np.eye(2, dtype=bool))
    >>> out[..., 0]
    array([[1., 0.],
           [0., 1.]])
    """
    context, focus = np.asarray(context), np.asarray(focus)
    if context.shape != focus.shape or context.shape[:2] != np.shape(mask):
        raise DVRInputError(
            f"lens composite: images {context.shape} and {focus.shape} and mask "
            f"{np.shape(mask)} differ in size"
        )
    return np.where(np.asarray(mask, bool)[..., None], focus, context)


def overlay_data_url(image: np.ndarray, mask: np.ndarray) -> str:
    """Encode ``image`` (``(H, W, 3)`` in [0, 1]) inside ``mask`` as a transparent PNG data URL.

    Outside the mask the PNG is fully transparent: laid over the view, it shows the lens
    result inside the lens and leaves the current rendering around it.

    Examples
    --------
    >>> overlay_data_url(np.ones((2, 2, 3)), np.eye(2, dtype=bool))[:22]
    'data:image/png;base64,'
    """
    from PIL import Image

    rgb = np.round(np.clip(np.nan_to_num(np.asarray(image, float)), 0, 1) * 255).astype(np.uint8)
    alpha = np.where(np.asarray(mask, bool), 255, 0).astype(np.uint8)[..., None]
    buf = io.BytesIO()
    Image.fromarray(np.concatenate([rgb, alpha], axis=2), mode="RGBA").save(buf, format="PNG")
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


class LensHandlers:
    """Page handlers of the Lens screen (draw, list the structures inside, set targets)."""

    @change("lens")
    @guard
    def on_lens_change(self, lens, **_):
        """List the structures inside a newly drawn lens with their targets (or clear it)."""
        self._drop_lens_result()  # it was for the previous lens
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
                    "color": rgb_to_hex(s.colour),
                    "use_vis": prev.get("use_vis", False),
                    "vis": prev.get("vis", round(min(max(share, 0.05), 1.0), 2)),
                    "use_tr": prev.get("use_tr", False),
                    "tr": prev.get("tr", round(1.0 - float(s.render_opacity), 2)),
                    # a slider the user set: a ticked box alone (the value as it is now)
                    # is no target (issue 30)
                    "set_vis": prev.get("set_vis", False),
                    "set_tr": prev.get("set_tr", False),
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
        """Set a lens row's target field (``use_vis``, ``vis``, ``use_tr``, ``tr``).

        Setting a slider (``vis``, ``tr``) also ticks its box: that value is the target.
        A ticked box whose slider was never set is no target.
        """
        if key not in ("use_vis", "vis", "use_tr", "tr"):
            raise DVRInputError(f"lens target: unknown field {key!r}")
        rows = [dict(r) for r in self.state.lens_rows]
        for r in rows:
            if r["index"] == int(index):
                r[key] = bool(value) if key.startswith("use_") else float(value)
                if not key.startswith("use_"):
                    r[f"use_{key}"] = r[f"set_{key}"] = True
        self.state.lens_rows = rows

    def _lens_targets(self) -> dict:
        targets = {}
        for r in self.state.lens_rows or []:
            wanted = {}
            if r.get("use_vis") and r.get("set_vis"):
                wanted["visibility"] = float(r["vis"])
            if r.get("use_tr") and r.get("set_tr"):
                wanted["transparency"] = float(r["tr"])
            if wanted:
                targets[r["name"]] = wanted
        return targets

    @guard
    def clear_lens(self):
        """Remove the lens (and a lens result not applied)."""
        self._drop_lens_result()
        self.state.lens = None
        self.state.lens_rows = []
        self.state.lens_text = ""

    # -- the lens result: shown inside the lens, applied on request ---------------------------
    _lens_pending = None  # (result, label, settings number) of the lens result shown

    def _drop_lens_result(self) -> None:
        """Forget the lens result shown (a new run, a new lens, applied or discarded)."""
        self._lens_pending = None
        s = self.state
        s.lens_result_key = s.lens_overlay_url = s.lens_whole_url = ""
        s.lens_whole_text = ""
        s.lens_worse = False

    def _show_lens_result(self, result, before, after, label: str, tf_no: int) -> None:
        """Show a lens refinement's result inside the lens over the current rendering.

        Renders the view with the result's spec (the whole view as it would be) and with the
        current one, composites the result inside the lens over the current rendering (the
        "after" thumbnail and the overlay over the view), and shows the whole view's errors
        before -> after (``before``, ``after``: measures of the optimiser's camera, or
        ``None``).  The session's spec is not changed: :meth:`lens_apply` does that.
        """
        s = self.state
        current = self.session.spec
        if self._tf_no != tf_no or self.state.lens is None:
            s.progress_text += "; the settings or the lens changed meanwhile: result dropped"
            return
        if result.spec == current:
            return  # no better setting found: nothing to show or apply
        try:
            self._render_spec(result.spec)
            whole = self._render_rgb()
        finally:
            self._render_spec(current)
        now = self._render_rgb()
        mask = lens_mask(self.state.lens, now.shape[1], now.shape[0])
        s.after_url = self._snapshot(composite(now, whole, mask))
        s.lens_whole_url = self._snapshot(whole)
        s.lens_overlay_url = overlay_data_url(whole, mask)
        s.lens_result_key = self._key()
        s.opt_key = self._key()  # the settings shown are still those optimised from
        s.why_lines = [f"if applied: {line}" for line in _why_lines(result)]
        s.after_text = (
            f"inside the lens: the refined setting (total error in the lens "
            f"{result.initial['E']:.3g} -> {result.final['E']:.3g}); outside: unchanged"
        )
        if before is not None:
            s.before_text = self._errors_text(before)
        if before is not None and after is not None:
            self._lens_verdict(before, after)
        self._lens_pending = (result, label, self._tf_no, after, s.lens_whole_url)

    @guard
    def lens_apply(self):
        """Apply the lens result shown to the whole view (one step in the history)."""
        if self._task_running:
            return
        pending = self._lens_pending
        if pending is None:
            raise DVRInputError("lens: no lens result to apply: refine a region first")
        result, label, tf_no, after, whole_url = pending
        if tf_no != self._tf_no:
            self._drop_lens_result()
            raise DVRInputError("lens: the settings changed since the refinement: refine again")
        self.session.push_undo(f"{label}, applied to the whole view")
        self._tf_before = self.session.spec  # drawn dashed in the transfer-function view
        self.session.spec = result.spec
        self._drop_lens_result()
        self._show_spec(label=f"{label}, applied to the whole view")
        # the Optimise screen's "after": now the whole view with the result
        self.state.after_url = whole_url
        self.state.after_text = self._errors_text(after) if after is not None else ""
        self.state.why_lines = _why_lines(result)
        self.state.opt_key = self._key()

    @guard
    def lens_discard(self):
        """Forget the lens result shown (the view stays as it is)."""
        self._drop_lens_result()
