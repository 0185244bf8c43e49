"""The transfer-function view of the web app, and the legend, colour bar and view buttons.

The chart is an SVG whose geometry comes ready-made from the server (``tf``, computed by
:func:`dvr_perception.app.tf_view.tf_chart`): the log-scaled histogram, each structure's
trapezoid, its handles (range ends on the axis, opacity on the top) and, after an
optimisation, the previous curves dashed.  Dragging a handle moves it on the page alone
(``tf_drag``); dropping it sends its position in ``tf_edit`` and the server does the rest.
"""

from __future__ import annotations

from trame.widgets import html
from trame.widgets import vuetify3 as v3
from trame_client.widgets.html import HtmlElement

from dvr_perception.app.tf_view import AXES, HEIGHT, WIDTH

#: Patient-side view buttons (:data:`dvr_perception.rays.camera.PATIENT_VIEWS`), by initial.
PATIENT_BUTTONS = ("anterior", "posterior", "left", "right", "superior", "inferior")

__all__ = ["tf_editor", "view_overlay"]

#: Pointer position in viewBox units (the event's element is the chart's ``svg``).
_BOX = "$event.currentTarget.getBoundingClientRect()"
_VX = f"(($event.clientX - {_BOX}.left) / {_BOX}.width * {WIDTH:g})"
_VY = f"(($event.clientY - {_BOX}.top) / {_BOX}.height * {HEIGHT:g})"

_DOWN = (
    "!busy && $event.target.dataset.kind && (tf_drag = {index: "
    "Number($event.target.dataset.index), kind: $event.target.dataset.kind, "
    f"x: {_VX}, y: {_VY}}}, $event.currentTarget.setPointerCapture($event.pointerId))"
)
_MOVE = f"tf_drag && (tf_drag = {{...tf_drag, x: {_VX}, y: {_VY}}})"
_UP = (
    "tf_drag && (tf_edit = {index: tf_drag.index, kind: tf_drag.kind, "
    f"fx: {_VX} / {WIDTH:g}, fy: {_VY} / {HEIGHT:g}}}, tf_drag = null)"
)


def _dragged(kind: str, axis: str, default: str) -> str:
    """Vue expression: the handle's coordinate, following the pointer while it is dragged."""
    return (
        f"tf_drag && tf_drag.index === row.index && tf_drag.kind === '{kind}' "
        f"? tf_drag.{axis} : {default}"
    )


def _el(tag: str, *attrs: str, **kw):
    """Add an SVG element with bound attributes (``attrs`` are raw Vue attributes)."""
    return HtmlElement(tag, raw_attrs=list(attrs), **kw)


def tf_editor(app, *, element_id: str = "tf-editor", editable: bool = True) -> None:
    """Add the chart (and, when ``editable``, its drag handles and colour swatches)."""
    with html.Div(v_if="tf", id=element_id, classes="tf-editor"):
        events = {}
        if editable:
            events = {
                "pointerdown": _DOWN,
                "pointermove": _MOVE,
                "pointerup": _UP,
                "__events": ["pointerdown", "pointermove", "pointerup"],
            }
        with html.Svg(
            raw_attrs=[f'viewBox="0 0 {WIDTH:g} {HEIGHT:g}"', 'width="100%"'],
            style="display: block; touch-action: none; user-select: none; background: #fff; "
            "border: 1px solid #e0e0e0;",
            classes="tf-chart",
            **events,
        ):
            _el("path", ':d="tf.bars"', 'fill="#cfd8dc"', classes="tf-histogram")
            _el(
                "line",
                'x1="0"',
                f'x2="{WIDTH:g}"',
                ':y1="tf.base"',
                ':y2="tf.base"',
                'stroke="#9e9e9e"',
            )
            _el(
                "polyline",
                ':points="old.points"',
                'fill="none"',
                ':stroke="old.color"',
                'stroke-width="1.5"',
                'stroke-dasharray="4 3"',
                v_for="(old, k) in (opt_key === now_key ? tf.before : [])",
                key="'b' + k",
                classes="tf-before",
            )
            with HtmlElement("g", v_for="row in tf.structures", key="row.index"):
                _el(
                    "polygon",
                    ':points="row.points"',
                    ':fill="row.color"',
                    'fill-opacity="0.3"',
                    ':stroke="row.color"',
                    'stroke-width="2"',
                    ':data-index="row.index"',
                    classes="tf-curve",
                )
                if editable:
                    for kind, x, y in (
                        ("lo", "row.x_lo", "tf.y_lo"),
                        ("hi", "row.x_hi", "tf.y_hi"),
                        ("opacity", "row.x_mid", "row.y_top"),
                    ):
                        cx = _dragged(kind, "x", x) if kind != "opacity" else x
                        cy = _dragged(kind, "y", y) if kind == "opacity" else y
                        _el(
                            "circle",
                            f':cx="{cx}"',
                            f':cy="{cy}"',
                            'r="5"',
                            ':fill="row.color"',
                            'stroke="#212121"',
                            'stroke-width="1.5"',
                            ':data-index="row.index"',
                            f'data-kind="{kind}"',
                            ':data-name="row.name"',
                            style=f"cursor: {'ns' if kind == 'opacity' else 'ew'}-resize;",
                            classes=f"tf-handle tf-{kind}",
                        )
            _el(
                "text",
                ':x="t.x"',
                f'y="{HEIGHT - 6:g}"',
                ':text-anchor="t.anchor"',
                'font-size="11"',
                'font-family="sans-serif"',
                'fill="#616161"',
                v_for="t in tf.ticks",
                key="t.x",
                children=["{{ t.label }}"],
            )
        html.Div(
            "Grey: how many voxels have each value (log scale). Drag a dot on the axis to move a "
            "range end, the dot on top to set the opacity; dashed: before the last "
            "optimisation.",
            classes="text-caption",
        )
        if editable:
            with (
                html.Div(classes="d-flex flex-wrap", id=f"{element_id}-legend"),
                html.Div(
                    v_for="row in tf.structures",
                    key="row.index",
                    classes="d-flex align-center mr-3 text-caption",
                ),
            ):
                html.Input(
                    type="color",
                    value=("row.color",),
                    disabled=("busy",),
                    change=(app.set_colour, "[row.index, $event.target.value]"),
                    title="colour",
                    classes="tf-swatch",
                    style="width: 22px; height: 18px; border: none; padding: 0;",
                )
                html.Span(
                    "{{ row.name }} {{ row.range[0] }}-{{ row.range[1] }}, "
                    "opacity {{ row.opacity.toFixed(2) }}",
                    classes="ml-1 tf-row",
                )


def view_overlay(app) -> None:
    """Legend and colour bar over the rendering, and the reset and axis-view buttons."""
    with html.Div(
        v_if="show_legend && tf && !['calibration', 'ranking', 'lens'].includes(tab)",
        id="view-legend",
        style="position: absolute; left: 8px; top: 8px; z-index: 4; pointer-events: none; "
        "background: rgba(0,0,0,0.55); color: #fff; padding: 4px 8px; border-radius: 4px; "
        "width: 220px;",
        classes="text-caption",
    ):
        with html.Div(v_for="row in structures", key="row.index", classes="d-flex align-center"):
            html.Span(
                style=(
                    "{display: 'inline-block', width: '12px', height: '12px', "
                    "background: row.color, border: '1px solid #fff', marginRight: '6px'}",
                ),
            )
            html.Span("{{ row.name }}", classes="flex-grow-1 legend-name")
            html.Span("{{ row.opacity.toFixed(2) }}")
        with html.Div(
            style="position: relative; height: 10px; background: #424242; margin-top: 4px;",
            id="colour-bar",
        ):
            html.Div(
                v_for="b in tf_bar",
                key="b.name",
                style=(
                    "{position: 'absolute', top: 0, bottom: 0, left: b.start + '%', "
                    "width: Math.max(b.end - b.start, 0.5) + '%', background: b.color}",
                ),
                title=("b.name",),
            )
        with html.Div(classes="d-flex"):
            html.Span("{{ tf_value_range[0] }}", classes="flex-grow-1")
            html.Span("value", classes="flex-grow-1")
            html.Span("{{ tf_value_range[1] }}")
    with html.Div(
        v_if="!['calibration', 'ranking'].includes(tab)",
        id="view-buttons",
        style="position: absolute; left: 8px; bottom: 8px; z-index: 7;",
        classes="d-flex",
    ):
        v3.VBtn(
            "Reset",
            click=app.reset_view,
            size="x-small",
            disabled=("busy",),
            id="view-reset",
            classes="mr-1",
        )
        for axis in AXES:
            v3.VBtn(
                axis,
                click=(app.view_axis, f"['{axis}']"),
                size="x-small",
                disabled=("busy",),
                id=f"view-{'p' if axis[0] == '+' else 'm'}{axis[1].lower()}",
                classes="mr-1",
                title=f"look along {axis}",
            )
        for name in PATIENT_BUTTONS:
            v3.VBtn(
                name[0].upper(),
                click=(app.view_patient, f"['{name}']"),
                size="x-small",
                disabled=("busy",),
                id=f"view-{name}",
                classes="mr-1" + (" ml-2" if name == PATIENT_BUTTONS[0] else ""),
                title=f"{name} view (patient frame)",
            )
