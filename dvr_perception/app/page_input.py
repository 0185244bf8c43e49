"""What the page may send the web app's server, checked by type and range before any handler.

Everything a browser tab sends arrives in two wslink calls: ``trame.state.update`` (state
variables the page set: a field, a switch, a dropped handle, an upload) and ``trame.trigger``
(a button or an event calling a handler with arguments).  :class:`PageInputGuard` sits in
front of both (installed by :class:`~dvr_perception.app.core.DVRApp` when its server binds)
and checks every value against one table:

* :data:`STATE`: each state variable the page may set, with its rule (type, range, choices);
* :data:`TRIGGERS`: each page handler, with the rules of its arguments;
* every other variable the server created (:meth:`PageInputGuard.server_owned`) is the server's
  alone: the page cannot set it.

A value that breaks its rule never reaches the state nor a handler: the page gets one message
in its error banner, the variable goes back to the server's value in every tab, the log gets
one line and the app goes on as before.  The handlers themselves only call the library.

Examples
--------
>>> STATE["map_kind"].check("shape", None)
'shape'
>>> STATE["map_kind"].check("../../etc", None)
Traceback (most recent call last):
...
dvr_perception.app.page_input.Refused: map kind '../../etc': expected one of visibility, \
shape, transparency
>>> STATE["map_opacity"].check(float("nan"), None)
Traceback (most recent call last):
...
dvr_perception.app.page_input.Refused: map strength nan: expected a number from 0 to 1
"""

from __future__ import annotations

import logging
import math
import re

from dvr_perception.errors import DVRInputError

__all__ = ["STATE", "TRIGGERS", "PageInputGuard", "Refused", "rules_table"]

log = logging.getLogger("dvr_perception.app")

#: Longest text the page may send in a name field (a file name, a volume or settings choice).
NAME_CHARS = 255
#: Longest banner text the page may set (its own upload-size message).
BANNER_CHARS = 1000
#: Farthest a camera may be from the volume's centre, in volume diagonals.
CAMERA_DIAGONALS = 1000.0
#: Largest fraction of the view (or chart) a lens or a dropped handle may reach: the pointer
#: may leave the view while it draws (the handlers clamp what lies outside).
FRACTION_SPAN = 10.0
#: Most items in a list the page sends (the ranking order).
LIST_ITEMS = 16
#: Most keys in a dict the page sends (a lens, a camera, a dropped handle, an upload).
DICT_KEYS = 16
#: The three quality maps.
MAP_KINDS = ("visibility", "shape", "transparency")
#: The page's screens (:data:`dvr_perception.app.ui.TABS`).
TAB_NAMES = ("data", "quality", "optimise", "lens", "calibration", "ranking", "export")
#: The lifecycle events trame's page reports (``trame.lifecycle.update``).
LIFECYCLE = ("client_connected", "client_exited", "client_unmounted")


class Refused(DVRInputError):
    """A value from the page that breaks its rule (the message names it and the rule)."""


def _shown(value) -> str:
    """Return a short, printable rendering of a value from the page (for the message)."""
    if isinstance(value, (bytes, bytearray)):
        return f"<{len(value)} bytes>"
    if isinstance(value, dict):
        return f"<a dict of {len(value)} keys>"
    if isinstance(value, (list, tuple)):
        return f"<a list of {len(value)} items>"
    text = repr(value)
    text = "".join(c if c.isprintable() else "?" for c in text)
    return text if len(text) <= 60 else text[:57] + "..."


class Rule:
    """A check of one value from the page: :meth:`check` returns it (normalised) or refuses.

    Parameters
    ----------
    label : str
        How the message names the value (``"map kind"``).
    """

    expected = "a value"

    def __init__(self, label: str = "") -> None:
        self.label = label

    def named(self, label: str) -> Rule:
        """Set the name the message uses; return the rule."""
        self.label = label
        return self

    def refuse(self, value, expected: str | None = None):
        """Raise :class:`Refused` for ``value``."""
        raise Refused(f"{self.label} {_shown(value)}: expected {expected or self.expected}")

    def check(self, value, ctx):
        """Return ``value`` if it meets the rule (``ctx``: the app, for live ranges)."""
        raise NotImplementedError

    def describe(self) -> str:
        """Return the rule in words (for the README and the report)."""
        return self.expected


class Flag(Rule):
    """``true`` or ``false`` (no 0/1, no strings)."""

    expected = "true or false"

    def check(self, value, ctx):
        if not isinstance(value, bool):
            self.refuse(value)
        return value


class Number(Rule):
    """A finite number from ``lo`` to ``hi`` (an integer if ``integer``).

    ``text``: a number written as text is taken too (an HTML number field sends text).

    Examples
    --------
    >>> Number(0, 1, label="importance").check(0.25, None)
    0.25
    >>> Number(1, 50, integer=True, label="steps").check(True, None)
    Traceback (most recent call last):
    ...
    dvr_perception.app.page_input.Refused: steps True: expected an integer from 1 to 50
    """

    def __init__(self, lo, hi, *, integer=False, text=False, label=""):
        super().__init__(label)
        self.lo, self.hi, self.integer, self.text = lo, hi, integer, text

    @property
    def expected(self) -> str:
        kind = "an integer" if self.integer else "a number"
        return f"{kind} from {self.lo:g} to {self.hi:g}"

    def bounds(self, ctx):
        """Return the range ``(lo, hi)`` (fixed here; live in subclasses)."""
        return self.lo, self.hi

    def check(self, value, ctx):
        raw = value
        if self.text and isinstance(value, str) and len(value) <= 40:
            try:
                value = float(value.strip())
            except ValueError:
                self.refuse(raw)
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            self.refuse(raw)
        if not math.isfinite(value):
            self.refuse(raw)
        if self.integer:
            if value != int(value):
                self.refuse(raw)
            value = int(value)
        lo, hi = self.bounds(ctx)
        if not lo <= value <= hi:
            self.refuse(raw, self._expected_in(lo, hi))
        return value

    def _expected_in(self, lo, hi) -> str:
        kind = "an integer" if self.integer else "a number"
        return f"{kind} from {lo:g} to {hi:g}"


class StructureIndex(Number):
    """The index of one of the current spec's structures (``0`` to ``K - 1``)."""

    expected = "the index of a structure (0 to the number of structures - 1)"

    def __init__(self, label: str = "structure"):
        super().__init__(0, 0, integer=True, label=label)

    def bounds(self, ctx):
        n = len(ctx.session.spec.structures) if ctx is not None else 1
        return 0, n - 1


class RangeValue(Number):
    """A structure's range end: a number within the volume's values widened by their span."""

    expected = "a number within the volume's values widened by their span on each side"

    def __init__(self, label: str = "range value"):
        super().__init__(-math.inf, math.inf, text=True, label=label)

    def bounds(self, ctx):
        if ctx is None:
            return -1e12, 1e12
        hist = ctx._histogram()
        lo, hi = float(hist["lo"]), float(hist["hi"])
        span = max(hi - lo, 1.0)
        return lo - span, hi + span


class Choice(Rule):
    """One of a fixed list of values (compared by type too: ``1`` is not ``"1"``)."""

    def __init__(self, values, label: str = ""):
        super().__init__(label)
        self.values = tuple(values)

    @property
    def expected(self) -> str:
        return "one of " + ", ".join(str(v) for v in self.values)

    def check(self, value, ctx):
        if isinstance(value, (str, int)) and not isinstance(value, bool):
            for v in self.values:
                if type(v) is type(value) and v == value:
                    return value
        self.refuse(value)
        return None


class Text(Rule):
    """A text of at most ``max_chars`` characters, no control characters."""

    def __init__(self, max_chars: int = NAME_CHARS, label: str = ""):
        super().__init__(label)
        self.max_chars = max_chars

    @property
    def expected(self) -> str:
        return f"a text of at most {self.max_chars} characters"

    def check(self, value, ctx):
        if not isinstance(value, str) or len(value) > self.max_chars:
            self.refuse(value)
        if any(ord(c) < 32 or ord(c) == 127 for c in value):
            self.refuse(value, "a text without control characters")
        return value


class RankingImage(Rule):
    """The id of one of the ranking task's images (``img1`` ...; those shown, once shown)."""

    expected = "the id of a ranking image (img1, img2, ...)"
    _ID = re.compile(r"img[0-9]{1,2}")

    def check(self, value, ctx):
        if not isinstance(value, str) or not self._ID.fullmatch(value):
            self.refuse(value)
        ranking = getattr(ctx, "ranking", None)
        if ranking is not None and value not in ranking.ids:
            self.refuse(value, "the id of an image shown: " + ", ".join(ranking.ids))
        return value


class Colour(Rule):
    """A colour ``#rrggbb`` (what the page's colour field sends)."""

    expected = "a colour #rrggbb"
    _HEX = re.compile(r"#[0-9a-fA-F]{6}")

    def check(self, value, ctx):
        if not isinstance(value, str) or not self._HEX.fullmatch(value):
            self.refuse(value)
        return value


class Maybe(Rule):
    """Nothing (``null``), or a value meeting ``rule``."""

    def __init__(self, rule: Rule):
        super().__init__(rule.label)
        self.rule = rule

    def named(self, label: str) -> Rule:
        self.label = label
        self.rule.named(label)
        return self

    @property
    def expected(self) -> str:
        return f"nothing or {self.rule.expected}"

    def check(self, value, ctx):
        return None if value is None else self.rule.check(value, ctx)


class ListOf(Rule):
    """A list of at most ``max_items`` values, each meeting ``item``, none repeated."""

    def __init__(self, item: Rule, max_items: int = LIST_ITEMS, label: str = ""):
        super().__init__(label)
        self.item, self.max_items = item, max_items

    @property
    def expected(self) -> str:
        return f"a list of at most {self.max_items} distinct items, each {self.item.expected}"

    def check(self, value, ctx):
        if not isinstance(value, list) or len(value) > self.max_items:
            self.refuse(value)
        self.item.label = f"{self.label} item"
        out = [self.item.check(v, ctx) for v in value]
        if len(set(out)) != len(out):
            self.refuse(value, "distinct items")
        return out


class Record(Rule):
    """A dict with the keys ``fields`` (each meeting its rule); ``optional`` ones may be absent.

    Other keys (at most :data:`DICT_KEYS` in all) are dropped.
    """

    def __init__(self, fields: dict, optional=(), label: str = ""):
        super().__init__(label)
        self.fields, self.optional = fields, frozenset(optional)

    @property
    def expected(self) -> str:
        keys = ", ".join(f"{k}: {r.expected}" for k, r in self.fields.items())
        return f"a dict {{{keys}}}"

    def check(self, value, ctx):
        if not isinstance(value, dict) or len(value) > DICT_KEYS:
            self.refuse(value, f"a dict with the keys {', '.join(self.fields)}")
        out = {}
        for key, rule in self.fields.items():
            if key not in value:
                if key in self.optional:
                    continue
                self.refuse(value, f"a dict with the keys {', '.join(self.fields)}")
            rule.label = f"{self.label}.{key}"
            out[key] = rule.check(value[key], ctx)
        return out


class Lens(Rule):
    """The lens drawn on the view: a rectangle (corners) or circle, in fractions of the view."""

    expected = (
        "nothing, {shape: 'rect', x0, y0, x1, y1} or {shape: 'circle', x0, y0, r} (fractions "
        f"of the view from {-FRACTION_SPAN:g} to {FRACTION_SPAN:g}; r from 0 to "
        f"{FRACTION_SPAN:g}), with the view's w and h in pixels"
    )

    def check(self, value, ctx):
        if value is None:
            return None
        if not isinstance(value, dict):
            self.refuse(value)
        frac = Number(-FRACTION_SPAN, FRACTION_SPAN)
        fields = {"shape": Choice(("rect", "circle")), "x0": frac, "y0": frac}
        if value.get("shape") == "circle":
            fields["r"] = Number(0.0, FRACTION_SPAN)
        else:
            fields["x1"] = frac
            fields["y1"] = frac
        fields["w"] = fields["h"] = Number(1, 100_000)
        return Record(fields, optional=("w", "h"), label=self.label).check(value, ctx)


class Camera(Rule):
    """The preview's camera after a drag: ``position``, ``focalPoint``, ``viewUp``.

    Each three finite numbers; position and focal point within :data:`CAMERA_DIAGONALS`
    volume diagonals of the volume's centre and apart; the view-up direction neither zero nor
    along the view direction.  Other keys of vtk.js's camera (at most :data:`DICT_KEYS`) are
    dropped.
    """

    expected = (
        "a camera {position, focalPoint, viewUp}: three finite numbers each, within "
        f"{CAMERA_DIAGONALS:g} volume diagonals of the volume, position apart from the focal "
        "point, view-up not along the view direction"
    )

    def _three(self, value, key, ctx):
        v = value.get(key)
        if not isinstance(v, list) or len(v) != 3:
            self.refuse(value, f"{key}: three numbers")
        return [Number(-math.inf, math.inf, label=f"{self.label}.{key}").check(c, ctx) for c in v]

    def check(self, value, ctx):
        if not isinstance(value, dict) or len(value) > DICT_KEYS:
            self.refuse(value)
        pos, focal, up = (self._three(value, k, ctx) for k in ("position", "focalPoint", "viewUp"))
        b = ctx.session.volume.bounds if ctx is not None else (0.0, 1.0) * 3
        centre = [(b[2 * i] + b[2 * i + 1]) / 2 for i in range(3)]
        diag = math.dist(b[0::2], b[1::2]) or 1.0
        far = CAMERA_DIAGONALS * diag
        for key, p in (("position", pos), ("focalPoint", focal)):
            if math.dist(p, centre) > far:
                self.refuse(p, f"{key} within {far:.3g} of the volume's centre")
        direction = [f - p for p, f in zip(pos, focal, strict=True)]
        dist = math.hypot(*direction)
        if dist < 1e-6 * diag:
            self.refuse(value, "a position apart from the focal point")
        up_norm = math.hypot(*up)
        cross = (
            up[1] * direction[2] - up[2] * direction[1],
            up[2] * direction[0] - up[0] * direction[2],
            up[0] * direction[1] - up[1] * direction[0],
        )
        if up_norm == 0 or math.hypot(*cross) < 1e-6 * up_norm * dist:
            self.refuse(up, "viewUp not zero and not along the view direction")
        return {"position": pos, "focalPoint": focal, "viewUp": up}


class Upload(Rule):
    """The upload field's file(s): ``{name, size, content}`` (the first of a list is used).

    ``name`` a text, ``size`` an integer from 0 to the upload limit, ``content`` bytes or a
    list of bytes (trame sends a large file in parts), joined here.  The file itself is then
    checked by :meth:`~dvr_perception.app.session.Session.store_upload`.
    """

    expected = (
        "nothing or a file {name, size, content}: name a text, size a whole number of bytes "
        "within the upload limit, content bytes or a list of bytes"
    )

    def check(self, value, ctx):
        if value is None:
            return None
        if isinstance(value, list):
            if not 1 <= len(value) <= LIST_ITEMS:
                self.refuse(value)
            value = value[0]
        if not isinstance(value, dict) or len(value) > DICT_KEYS:
            self.refuse(value)
        limit = ctx.max_upload_bytes if ctx is not None else 2**31
        name = Text(NAME_CHARS, label=f"{self.label}.name").check(value.get("name"), ctx)
        content = value.get("content")
        if isinstance(content, list) and len(content) <= 100_000:
            if not all(isinstance(c, (bytes, bytearray)) for c in content):
                self.refuse(content, "upload content as bytes or a list of bytes")
            if sum(len(c) for c in content) > limit:
                self.refuse(content, f"at most {limit} bytes")
            content = b"".join(content)
        if not isinstance(content, (bytes, bytearray)):
            self.refuse(content, "upload content as bytes or a list of bytes")
        size = value.get("size", len(content))
        size = Number(0, limit, integer=True, label=f"{self.label}.size").check(size, ctx)
        if len(content) > limit:
            self.refuse(content, f"at most {limit} bytes")
        return {"name": name, "size": size, "content": bytes(content)}


class LensTarget(Rule):
    """The arguments of a lens row's target field: structure, field, value."""

    expected = "[structure index, 'use_vis' or 'use_tr' with true/false, or 'vis' or 'tr' 0 to 1]"

    def check(self, value, ctx):
        index, key, v = value
        index = StructureIndex(f"{self.label} structure").check(index, ctx)
        key = Choice(("use_vis", "vis", "use_tr", "tr"), f"{self.label} field").check(key, ctx)
        if key.startswith("use_"):
            v = Flag(f"{self.label} {key}").check(v, ctx)
        else:
            v = Number(0.0, 1.0, label=f"{self.label} {key}").check(v, ctx)
        return [index, key, v]


class Args:
    """The positional arguments of a page handler: ``rules`` (the last ``optional`` may lack).

    ``whole``: one rule over the whole argument list instead (:class:`LensTarget`).
    """

    def __init__(self, *rules: Rule, optional: int = 0, whole: Rule | None = None):
        self.rules, self.optional, self.whole = rules, optional, whole

    def check(self, name: str, args, kwargs, ctx) -> list:
        """Return the checked arguments of handler ``name``, or refuse them."""
        lo, hi = len(self.rules) - self.optional, len(self.rules)
        if kwargs or not lo <= len(args) <= hi:
            raise Refused(
                f"page action {name}: expected {lo if lo == hi else f'{lo} to {hi}'} "
                f"argument{'' if hi == 1 else 's'}, got {len(args) + len(kwargs)}"
            )
        if self.whole is not None:
            self.whole.label = self.whole.label or name
            return self.whole.check(list(args), ctx)
        out = []
        for k, (rule, value) in enumerate(zip(self.rules, args, strict=False)):
            rule.label = rule.label or f"{name} argument {k + 1}"
            out.append(rule.check(value, ctx))
        return out

    def describe(self) -> str:
        """Return the arguments in words."""
        if self.whole is not None:
            return self.whole.expected
        if not self.rules:
            return "no arguments"
        parts = [r.expected for r in self.rules]
        if self.optional:
            parts[-self.optional :] = [f"optional: {p}" for p in parts[-self.optional :]]
        return "; ".join(parts)


def _stage_sets():
    from dvr_perception.app.optimise_handlers import STAGE_SETS

    return tuple(STAGE_SETS)


def _orientation_codes():
    from dvr_perception.app.session import ORIENTATION_CODES

    return ("", *ORIENTATION_CODES)


def _undo_depth() -> int:
    from dvr_perception.app.session import UNDO_DEPTH

    return UNDO_DEPTH


def _axes():
    from dvr_perception.app.tf_view import AXES

    return tuple(AXES)


def _patient_views():
    from dvr_perception.rays.camera import PATIENT_VIEWS

    return tuple(PATIENT_VIEWS)


#: Every state variable the page may set, with its rule (checked before the state takes it).
STATE: dict[str, Rule] = {
    name: rule.named(label)
    for name, label, rule in (
        ("volume_name", "volume", Text()),
        ("upload", "upload", Upload()),
        ("orientation_code", "orientation", Choice(_orientation_codes())),
        ("spec_name", "settings file", Text()),
        ("show_map", "show map", Flag()),
        ("map_kind", "map kind", Choice(MAP_KINDS)),
        ("map_opacity", "map strength", Number(0.0, 1.0)),
        ("tab", "screen", Choice(TAB_NAMES)),
        ("lens_shape", "lens shape", Choice(("rect", "circle"))),
        ("lens", "lens", Lens()),
        ("cal_name", "calibration file", Text()),
        ("use_calibration", "use calibration", Flag()),
        ("cal_rating", "rating", Number(0.0, 1.0)),
        ("rank_structure", "ranking structure", StructureIndex()),
        ("rank_order", "ranking order", ListOf(RankingImage())),
        (
            "tf_edit",
            "transfer-function edit",
            Maybe(
                Record(
                    {
                        "index": StructureIndex(),
                        "kind": Choice(("lo", "hi", "opacity")),
                        "fx": Number(-FRACTION_SPAN, FRACTION_SPAN),
                        "fy": Number(-FRACTION_SPAN, FRACTION_SPAN),
                    }
                )
            ),
        ),
        ("show_legend", "show legend", Flag()),
        ("error", "error banner", Text(BANNER_CHARS)),
        ("info", "info banner", Text(BANNER_CHARS)),
    )
}

#: Every page handler the page may call, with the rules of its arguments.
TRIGGERS: dict[str, Args] = {
    "set_importance": Args(StructureIndex(), Number(0.0, 1.0, label="importance")),
    "set_range": Args(StructureIndex(), Choice((0, 1), "range end"), RangeValue()),
    "set_colour": Args(StructureIndex(), Colour("colour")),
    "load_spec": Args(Maybe(Text(label="settings file")), optional=1),
    "save_spec": Args(Maybe(Text(label="settings file")), optional=1),
    "undo": Args(Number(1, _undo_depth(), integer=True, label="undo steps"), optional=1),
    "optimise": Args(
        Choice(_stage_sets(), "optimise stages"), Flag("optimise in lens"), optional=2
    ),
    "cancel": Args(),
    "export": Args(),
    "lens_apply": Args(),
    "lens_discard": Args(),
    "clear_lens": Args(),
    "set_lens_target": Args(Rule(), Rule(), Rule(), whole=LensTarget("lens target")),
    "start_calibration": Args(),
    "rate_stimulus": Args(Maybe(Number(0.0, 1.0, label="rating")), optional=1),
    "load_calibration_file": Args(),
    "new_ranking": Args(),
    "save_ranking": Args(Maybe(ListOf(RankingImage(), label="ranking order")), optional=1),
    "preview_start": Args(),
    "local_camera": Args(Camera("camera")),
    "view_axis": Args(Choice(_axes(), "view direction")),
    "view_patient": Args(Choice(_patient_views(), "patient view")),
    "reset_view": Args(),
}


def rules_table() -> list[tuple[str, str, str]]:
    """Return ``(kind, name, rule)`` rows of every checked state variable and handler."""
    rows = [("state", name, rule.describe()) for name, rule in STATE.items()]
    rows += [("action", name, args.describe()) for name, args in TRIGGERS.items()]
    return rows


class PageInputGuard:
    """Check every state change and handler call from the page of ``app`` before it is used.

    Parameters
    ----------
    app : DVRApp
        The app (its ``state``, ``session``, ``fail`` and the live ranges).
    """

    def __init__(self, app) -> None:
        self.app = app
        self._owned: frozenset[str] | None = None

    def server_owned(self) -> frozenset[str]:
        """Return the state variables the server created and the page may not set."""
        if self._owned is None:
            state = self.app.state
            names = set(state.to_dict())
            client = set(state["trame__client_only"] or [])
            self._owned = frozenset(names - set(STATE) - client)
        return self._owned

    # -- the checks ------------------------------------------------------------------------
    def check_changes(self, changes) -> tuple[list, list[str], list[str]]:
        """Split ``trame.state.update``'s changes into those kept and the reasons refused.

        Returns ``(kept, reasons, names)``: the changes to apply (values normalised), one
        reason per refused change and the names of the variables refused (to be sent back).
        """
        if not isinstance(changes, list):
            return [], [f"state update: expected a list of changes, got {_shown(changes)}"], []
        kept, reasons, names = [], [], []
        owned = self.server_owned()
        for change in changes:
            key = change.get("key") if isinstance(change, dict) else None
            if not isinstance(key, str) or len(key) > 200:
                reasons.append(f"state update: malformed change {_shown(change)}")
                continue
            value = change.get("value")
            rule = STATE.get(key)
            try:
                if rule is not None:
                    value = rule.check(value, self.app)
                elif key in owned:
                    raise Refused(f"{key}: set by the server, not by the page")
            except Refused as exc:
                reasons.append(str(exc))
                if key in owned or key in STATE:
                    names.append(key)
                continue
            kept.append({"key": key, "value": value})
        return kept, reasons, names

    def check_trigger(self, fn, args, kwargs):
        """Return the checked ``(args, kwargs)`` for the page handler ``fn``, or refuse them."""
        args = [] if args is None else args
        kwargs = {} if kwargs is None else kwargs
        if not isinstance(args, list) or not isinstance(kwargs, dict):
            raise Refused("page action: malformed arguments")
        if getattr(fn, "__self__", None) is not self.app:
            return args, kwargs  # not one of the app's handlers (a widget's own)
        name = getattr(fn, "__name__", "")
        spec = TRIGGERS.get(name)
        if spec is None:
            raise Refused(f"page action {name}: not an action of the page")
        return spec.check(name, args, kwargs, self.app), {}

    def refused(self, reasons: list[str], names=()) -> None:
        """Show ``reasons`` as one message, log one line, give every tab the server's values."""
        text = "; ".join(reasons[:3]) + (
            f" (and {len(reasons) - 3} more)" if len(reasons) > 3 else ""
        )
        log.warning("page input refused: %s", text)
        state = self.app.state
        with state:
            self.app.fail(f"refused: {text}")
        protocol = self.app.server.protocol
        names = [n for n in names if n in state.to_dict()]
        if names and protocol is not None:
            protocol.publish("trame.state.topic", {n: state[n] for n in names})

    # -- wslink ----------------------------------------------------------------------------
    def install(self, handler) -> None:
        """Wrap the state-update and trigger calls of wslink's ``handler``."""
        fmap = handler.functionMap
        if "trame.state.update" not in fmap or "trame.trigger" not in fmap:
            msg = "trame protocol without state update or trigger: cannot check page input"
            raise RuntimeError(msg)
        update_obj, update = fmap["trame.state.update"]
        trigger_obj, trigger = fmap["trame.trigger"]
        life_obj, life = fmap.get("trame.lifecycle.update", (None, None))
        guard = self

        def checked_update(obj, changes):
            kept, reasons, names = guard.check_changes(changes)
            result = update(obj, kept) if kept else None
            if reasons:
                guard.refused(reasons, names)
            return result

        async def checked_trigger(obj, name, args, kwargs):
            fn = guard.app.server.controller.trigger_fn(name) if isinstance(name, str) else None
            if fn is None:
                guard.refused([f"page action {_shown(name)}: no such action"])
                return None
            try:
                args, kwargs = guard.check_trigger(fn, args, kwargs)
            except Refused as exc:
                guard.refused([str(exc)])
                return None
            return await trigger(obj, name, args, kwargs)

        def checked_lifecycle(obj, name):
            if name not in LIFECYCLE:
                log.warning("page input refused: lifecycle event %s", _shown(name))
                return None
            return life(obj, name)

        fmap["trame.state.update"] = (update_obj, checked_update)
        fmap["trame.trigger"] = (trigger_obj, checked_trigger)
        if life is not None:
            fmap["trame.lifecycle.update"] = (life_obj, checked_lifecycle)
