"""Structures, lighting and rendering settings: the data model behind a spec JSON file.

Transfer-function semantics (shared by our engine and the VTK converters):

* A range structure ``[lo, hi]`` with edge fraction ``e`` has a trapezoidal **membership**
  ``m(v)``: 0 at ``lo``, rising linearly to 1 at ``lo + e*(hi-lo)``, 1 up to ``hi - e*(hi-lo)``,
  falling to 0 at ``hi``; 0 outside.  Ranges of different structures may touch but not overlap,
  so every intensity belongs to at most one structure.
* A label structure has ``m = 1`` on voxels whose label equals its id (nearest lookup).
* The scalar opacity of a sample of structure ``s`` is ``opacity_s * m(v)``, where the rendering
  opacity ``opacity_s`` starts at the importance and is what the optimiser changes.  Opacity is
  per ``opacity_unit_distance`` of ray length and corrected for the sample distance as VTK's
  ``ScalarOpacityUnitDistance`` does: ``a = 1 - (1 - opacity*m) ** (step / unit)``.
* The colour of a sample of ``s`` is ``colour_s``; shading is Phong with the structure's lighting.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field, replace

from dvr_perception._deprecation import renamed_keyword
from dvr_perception.errors import DVRInputError

__all__ = [
    "MAX_NAME_LENGTH",
    "MAX_STRUCTURES",
    "Lighting",
    "RenderSettings",
    "Structure",
    "StructureSpec",
    "name_problem",
    "printable",
]

SPEC_VERSION = 1
#: Most structures a spec may hold (the engine keeps one bit per structure in 32 bits); checked
#: before any per-structure or pairwise work.
MAX_STRUCTURES = 32
#: Longest structure name (characters).  A name labels table rows, plot titles and legends;
#: without a bound one long name makes every figure take unbounded time and memory.
MAX_NAME_LENGTH = 64
#: Label ids are 32-bit signed integers.
_LABEL_RANGE = (-(2**31), 2**31 - 1)


def printable(text, limit: int | None = None) -> str:
    r"""Return ``text`` with every non-printable character escaped, cut to ``limit`` characters.

    Control, format and separator characters (everything :meth:`str.isprintable` refuses,
    e.g. ESC, newline, the right-to-left override) are written as Python escapes
    (``\x1b``, ``\n``, ``\u202e``), so a name can never drive a terminal; with ``limit``
    a longer result is cut and ends with ``…``.

    Examples
    --------
    >>> print(printable("bone\x1b[2J"))
    bone\x1b[2J
    >>> printable("a" * 10, limit=5)
    'aaaa…'
    """
    text = str(text)
    if limit is not None and len(text) > 4 * limit:
        text = text[: 4 * limit]  # enough to cut from: escapes only lengthen the text
    if not text.isprintable():
        text = "".join(ch if ch.isprintable() else ascii(ch)[1:-1] for ch in text)
    if limit is not None and len(text) > limit:
        text = text[: max(limit - 1, 0)] + "…"
    return text


def name_problem(name) -> str | None:
    r"""Why ``name`` cannot be a structure name, or ``None`` when it can.

    A name is a non-empty string of at most :data:`MAX_NAME_LENGTH` printable characters
    (:meth:`str.isprintable`: no control, format or line/paragraph separator characters).

    Examples
    --------
    >>> name_problem("brain and soft tissue") is None
    True
    >>> print(name_problem("bone\x1b[31m"))
    must hold printable characters only, got '\x1b' at position 4
    """
    if not isinstance(name, str) or not name.strip():
        return "must be a non-empty string"
    if len(name) > MAX_NAME_LENGTH:
        return f"must be at most {MAX_NAME_LENGTH} characters, got {len(name)} characters"
    if not name.isprintable():
        i = next(i for i, ch in enumerate(name) if not ch.isprintable())
        return f"must hold printable characters only, got {name[i]!a} at position {i}"
    return None


@dataclass(frozen=True)
class Lighting:
    """Per-structure Phong material (VTK volume-property conventions)."""

    ambient: float = 0.2
    diffuse: float = 0.8
    specular: float = 0.2
    specular_power: float = 16.0


@dataclass(frozen=True)
class Structure:
    """One structure: an intensity range *or* a label id, with importance, colour and lighting.

    ``opacity`` is the rendering opacity; ``None`` means "equal to ``importance``".
    ``expected_opacity`` is the perceived opacity the transparency measure aims for; ``None``
    means "equal to ``importance``".  ``colour`` is RGB in [0, 1]; the keyword and attribute
    ``color`` are deprecated aliases of it.
    """

    name: str
    importance: float
    colour: tuple[float, float, float]
    range: tuple[float, float] | None = None
    label: int | None = None
    edge: float = 0.1
    lighting: Lighting = field(default_factory=Lighting)
    opacity: float | None = None
    expected_opacity: float | None = None

    def __post_init__(self) -> None:
        """Refuse a name that is too long or not printable (:func:`name_problem`)."""
        problem = name_problem(self.name)
        if problem is not None:
            shown = printable(self.name, 40) if isinstance(self.name, str) else type(self.name)
            raise DVRInputError(f"structure name {shown!r}: {problem}")

    @property
    def color(self) -> tuple[float, float, float]:
        """Deprecated alias of :attr:`colour`."""
        warnings.warn(
            "Structure.color is deprecated; use Structure.colour", DeprecationWarning, stacklevel=2
        )
        return self.colour

    @property
    def render_opacity(self) -> float:
        """The opacity used for rendering (``opacity`` or, if unset, ``importance``)."""
        return self.importance if self.opacity is None else self.opacity

    @property
    def target_opacity(self) -> float:
        """The opacity the transparency measure expects (``expected_opacity`` or importance)."""
        return self.importance if self.expected_opacity is None else self.expected_opacity


# ``Structure(color=...)`` keeps working for one release (a DeprecationWarning).
Structure.__init__ = renamed_keyword("color", "colour", name="Structure")(Structure.__init__)


@dataclass(frozen=True)
class RenderSettings:
    """How the volume is rendered; ``None`` distances default to the smallest voxel spacing.

    ``light_direction`` is given in camera coordinates (x right, y up, z towards the viewer);
    ``(0, 0, 1)`` is VTK's default headlight.
    """

    shade: bool = True
    sample_distance: float | None = None
    opacity_unit_distance: float | None = None
    light_direction: tuple[float, float, float] = (0.0, 0.0, 1.0)
    light_intensity: float = 1.0


@dataclass(frozen=True)
class StructureSpec:
    """A versioned list of structures plus background colour and render settings."""

    structures: tuple[Structure, ...]
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rendering: RenderSettings = field(default_factory=RenderSettings)
    view: tuple[float, float, float] | None = None
    labels_file: str | None = None
    version: int = SPEC_VERSION

    @property
    def names(self) -> tuple[str, ...]:
        """Structure names in order (the index is the structure id used by the engine)."""
        return tuple(s.name for s in self.structures)

    def with_opacities(self, opacities) -> StructureSpec:
        """Return a copy whose structures have the given rendering opacities."""
        new = tuple(
            replace(s, opacity=float(o)) for s, o in zip(self.structures, opacities, strict=True)
        )
        return replace(self, structures=new)


# -- validation helpers (used by dvr_perception.structures.io) ---------------------------------
_LIGHTING_KEYS = ("ambient", "diffuse", "specular", "specular_power")
_RENDER_KEYS = (
    "shade",
    "sample_distance",
    "opacity_unit_distance",
    "light_direction",
    "light_intensity",
)
_STRUCTURE_KEYS = (
    "name",
    "range",
    "label",
    "importance",
    "colour",
    "color",  # read as "colour" (files written by 0.1 spell it so)
    "lighting",
    "expected_opacity",
    "opacity",
    "edge",
)
_TOP_KEYS = ("version", "background", "structures", "rendering", "view", "labels")


def _shown(value, limit: int = 80) -> str:
    """``repr(value)`` cut to about ``limit`` characters (huge integers cannot be printed)."""
    try:
        text = repr(value)
    except ValueError:  # an integer of more than 4300 digits
        return "a number too large to print"
    return text if len(text) <= limit else f"{text[: limit - 3]}..."


class _Checker:
    """Field validation that raises one DVRInputError naming ``source`` and the field path."""

    def __init__(self, source: str) -> None:
        self.source = source
        self.unknown: list[str] = []

    def fail(self, path: str, expected: str, got=None, *, show_got: bool = True):
        tail = f", got {_shown(got)}" if show_got else ""
        raise DVRInputError(f"{self.source}: {path} {expected}{tail}")

    def scan_nonfinite(self, value, path: str) -> None:
        """Reject NaN/inf anywhere (also in unknown fields), naming the first one found."""
        if isinstance(value, float) and not math.isfinite(value):
            self.fail(path or "value", "must be a finite number", value)
        elif isinstance(value, dict):
            for k, v in value.items():
                self.scan_nonfinite(v, f"{path}.{k}" if path else str(k))
        elif isinstance(value, list):
            for i, v in enumerate(value):
                self.scan_nonfinite(v, f"{path}[{i}]")

    def obj(self, value, path: str, known) -> dict:
        if not isinstance(value, dict):
            self.fail(path, "must be a JSON object", type(value).__name__, show_got=True)
        prefix = f"{path}." if path else ""
        self.unknown += [f"{prefix}{k}" for k in value if k not in known]
        return value

    def number(self, value, path: str, lo=None, hi=None, *, lo_open=False, hi_open=False):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            self.fail(path, "must be a number", value)
        try:
            v = float(value)
        except OverflowError:
            self.fail(path, "must be a finite number", value)
        if lo is not None or hi is not None:
            below = lo is not None and (v <= lo if lo_open else v < lo)
            above = hi is not None and (v >= hi if hi_open else v > hi)
            if below or above:
                left = "(" if lo_open else "["
                right = ")" if hi_open or hi is None else "]"
                lo_s = "-inf" if lo is None else f"{lo:g}"
                hi_s = "inf" if hi is None else f"{hi:g}"
                self.fail(path, f"must be in {left}{lo_s}, {hi_s}{right}", value)
        return v

    def vector(self, value, path: str, n, lo=None, hi=None, what: str = "numbers"):
        sizes = n if isinstance(n, tuple) else (n,)
        if not isinstance(value, list) or len(value) not in sizes:
            count = " or ".join(str(s) for s in sizes)
            self.fail(path, f"must be a list of {count} {what}", value)
        return tuple(self.number(v, f"{path}[{i}]", lo, hi) for i, v in enumerate(value))

    def optional(self, d: dict, key: str, path: str, lo, hi, **kw):
        if d.get(key) is None:
            return None
        return self.number(d[key], f"{path}.{key}", lo, hi, **kw)


def _parse_structure(c: _Checker, d, path: str, has_labels: bool) -> Structure:
    d = c.obj(d, path, _STRUCTURE_KEYS)
    name = d.get("name")
    problem = name_problem(name)
    if problem is not None:
        c.fail(f"{path}.name", problem, name, show_got=not isinstance(name, str) or not name)
    has_range, has_label = d.get("range") is not None, d.get("label") is not None
    if has_range == has_label:
        which = "both" if has_range else "neither"
        c.fail(
            path,
            f"must have exactly one of 'range' [lo, hi] or 'label' (got {which})",
            show_got=False,
        )
    rng = label = None
    if has_range:
        lo, hi = c.vector(d["range"], f"{path}.range", 2)
        if not lo < hi:
            c.fail(f"{path}.range", "must be [lo, hi] with lo < hi", d["range"])
        rng = (lo, hi)
    else:
        label = d["label"]
        if isinstance(label, bool) or not isinstance(label, int):
            c.fail(f"{path}.label", "must be an integer label id", label)
        if not _LABEL_RANGE[0] <= label <= _LABEL_RANGE[1]:
            c.fail(f"{path}.label", "must be a 32-bit integer label id", label)
        if not has_labels:
            c.fail(
                f"{path}.label",
                "needs a 'labels' file at the top level of the spec",
                show_got=False,
            )
    if "importance" not in d:
        c.fail(f"{path}.importance", "is missing; expected a number in (0, 1]", show_got=False)
    importance = c.number(d["importance"], f"{path}.importance", 0, 1, lo_open=True)
    if "colour" in d and "color" in d:
        c.fail(f"{path}", f"({name!r}) gives both 'colour' and 'color'; give one", show_got=False)
    key = "color" if "color" in d else "colour"
    if key not in d:
        c.fail(f"{path}.colour", "is missing; expected [r, g, b] in [0, 1]", show_got=False)
    colour = c.vector(d[key], f"{path}.{key}", 3, 0, 1, "numbers in [0, 1]")
    light = Lighting()
    if d.get("lighting") is not None:
        ld = c.obj(d["lighting"], f"{path}.lighting", _LIGHTING_KEYS)
        vals = {}
        for k in _LIGHTING_KEYS[:3]:
            if k in ld:
                vals[k] = c.number(ld[k], f"{path}.lighting.{k}", 0, 1)
        if "specular_power" in ld:
            vals["specular_power"] = c.number(
                ld["specular_power"], f"{path}.lighting.specular_power", 0, 128, lo_open=True
            )
        light = Lighting(**vals)
    edge = c.optional(d, "edge", path, 0, 0.5)
    return Structure(
        name=name,
        importance=importance,
        colour=colour,
        range=rng,
        label=label,
        edge=0.1 if edge is None else edge,
        lighting=light,
        opacity=c.optional(d, "opacity", path, 0, 1),
        expected_opacity=c.optional(d, "expected_opacity", path, 0, 1),
    )


def _parse_rendering(c: _Checker, d) -> RenderSettings:
    d = c.obj(d, "rendering", _RENDER_KEYS)
    kw: dict = {}
    if d.get("shade") is not None:
        if not isinstance(d["shade"], bool):
            c.fail("rendering.shade", "must be true or false", d["shade"])
        kw["shade"] = d["shade"]
    for key in ("sample_distance", "opacity_unit_distance"):
        kw[key] = c.optional(d, key, "rendering", 0, None, lo_open=True)
    if d.get("light_direction") is not None:
        v = c.vector(d["light_direction"], "rendering.light_direction", 3)
        if not any(v):
            c.fail("rendering.light_direction", "must be a non-zero vector", d["light_direction"])
        kw["light_direction"] = v
    if d.get("light_intensity") is not None:
        kw["light_intensity"] = c.number(d["light_intensity"], "rendering.light_intensity", 0)
    return RenderSettings(**kw)


def parse_spec_dict(d, source: str = "spec") -> tuple[StructureSpec, list[str]]:
    """Validate a parsed spec JSON object; return the spec and the unknown field paths.

    Raises :class:`~dvr_perception.errors.DVRInputError` (one message naming ``source`` and the
    field path) on the first violation.  See :mod:`dvr_perception.structures.io`.
    """
    c = _Checker(source)
    if not isinstance(d, dict):
        c.fail("top level", "must be a JSON object", type(d).__name__)
    c.scan_nonfinite(d, "")
    c.obj(d, "", _TOP_KEYS)
    if "version" not in d:
        c.fail("version", f"is missing; expected {SPEC_VERSION}", show_got=False)
    if isinstance(d["version"], bool) or d["version"] != SPEC_VERSION:
        c.fail("version", f"must be {SPEC_VERSION}", d["version"])
    labels = d.get("labels")
    if labels is not None and (not isinstance(labels, str) or not labels.strip()):
        c.fail("labels", "must be a non-empty path string", labels)
    items = d.get("structures")
    if not isinstance(items, list) or not items:
        c.fail("structures", "must be a non-empty list of structures", items)
    if len(items) > MAX_STRUCTURES:
        c.fail(
            "structures",
            f"must hold at most {MAX_STRUCTURES} structures, got {len(items)}",
            show_got=False,
        )
    structures = [
        _parse_structure(c, s, f"structures[{i}]", labels is not None) for i, s in enumerate(items)
    ]
    seen: dict = {}
    for i, s in enumerate(structures):
        key = ("name", s.name)
        if key in seen:
            c.fail(f"structures[{i}].name", f"duplicates structures[{seen[key]}].name", s.name)
        seen[key] = i
        if s.label is not None:
            if ("label", s.label) in seen:
                j = seen[("label", s.label)]
                c.fail(f"structures[{i}].label", f"duplicates structures[{j}].label", s.label)
            seen[("label", s.label)] = i
    ranged = sorted((s.range, i) for i, s in enumerate(structures) if s.range is not None)
    for n in range(1, len(ranged)):
        (lo, _), i = ranged[n]
        (plo, phi), j = ranged[n - 1]  # sorted by lo: an overlap shows in neighbours first
        if lo < phi:
            a, b = structures[j], structures[i]
            c.fail(
                f"structures[{i}].range",
                f"[{lo:g}, {b.range[1]:g}] of {b.name!r} overlaps structures[{j}].range "
                f"[{plo:g}, {phi:g}] of {a.name!r}; ranges may touch but not overlap",
                show_got=False,
            )
    background = (0.0, 0.0, 0.0)
    if d.get("background") is not None:
        background = c.vector(d["background"], "background", 3, 0, 1, "numbers in [0, 1]")
    rendering = (
        RenderSettings() if d.get("rendering") is None else _parse_rendering(c, d["rendering"])
    )
    view = None
    if d.get("view") is not None:
        v = c.vector(d["view"], "view", (2, 3), what="numbers [azimuth, elevation, zoom]")
        if len(v) == 3 and v[2] <= 0:
            c.fail("view[2]", "(zoom) must be positive", d["view"][2])
        view = (v[0], v[1], v[2] if len(v) == 3 else 1.0)
    spec = StructureSpec(
        structures=tuple(structures),
        background=background,
        rendering=rendering,
        view=view,
        labels_file=labels,
        version=SPEC_VERSION,
    )
    return spec, c.unknown
