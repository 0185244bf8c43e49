"""The Lens screen of the web app: its side panel and the drawing pad over the view."""

from __future__ import annotations

from trame.widgets import html
from trame.widgets import vuetify3 as v3

from dvr_perception.app._widgets import half_button, heading

__all__ = ["lens_pad", "lens_panel"]


# -- 4 lens --------------------------------------------------------------------------------
def lens_panel(app) -> None:
    """Side panel of the Lens screen: shape, drawing hint, targets per structure, refine."""
    heading(
        "Lens: improve one region",
        "Choose a shape, then drag on the image to mark the region to improve. The "
        "settings are optimised for that region (you can ask how visible or how see-through "
        "each structure inside it should be); the result is shown inside the region over the "
        "current rendering, and applied to the whole view only when you click Apply.",
    )
    with v3.VBtnToggle(
        v_model=("lens_shape",),
        mandatory=True,
        density="compact",
        divided=True,
        variant="outlined",
        color="primary",
        id="lens-shape",
    ):
        v3.VBtn("Rectangle", value="rect", size="small", id="lens-rect")
        v3.VBtn("Circle", value="circle", size="small", id="lens-circle")
    html.Div(
        "{{ lens_text || 'No region yet: drag on the image.' }}",
        classes="text-body-2 mt-2",
        id="lens-text",
    )
    with html.Table(classes="w-100 text-body-2 mt-1", v_if="lens_rows.length", id="lens-table"):
        with html.Tr():
            html.Th("Structure in region", classes="text-left")
            html.Th("Visible share wanted", classes="text-left")
            html.Th("See-through wanted", classes="text-left")
        with html.Tr(v_for="row in lens_rows", key="row.index"):
            with html.Td():
                html.Span(
                    style=(
                        "{display: 'inline-block', width: '12px', height: '12px', "
                        "background: row.color, border: '1px solid #757575', "
                        "marginRight: '4px'}",
                    )
                )
                html.Span("{{ row.name }}")
                html.Div(
                    "{{ measured_key === now_key ? 'in ' + (100 * row.fraction).toFixed(0) "
                    "+ ' % of the region' : 're-measuring' }}",
                    classes="text-caption measured",
                    raw_attrs=[':data-key="measured_key"'],
                )
            for use, key in (("use_vis", "vis"), ("use_tr", "tr")):
                with html.Td(style="min-width: 120px"):
                    with html.Div(classes="d-flex align-center"):
                        v3.VCheckboxBtn(
                            model_value=(f"row.{use}",),
                            density="compact",
                            update_modelValue=(
                                app.set_lens_target,
                                f"[row.index, '{use}', $event]",
                            ),
                            classes=f"lens-{use}",
                        )
                        v3.VSlider(
                            model_value=(f"row.{key}",),
                            min=0,
                            max=1,
                            step=0.05,
                            thumb_label=True,
                            hide_details=True,
                            density="compact",
                            end=(app.set_lens_target, f"[row.index, '{key}', $event]"),
                        )
                        html.Span(
                            f"{{{{ row.{key}.toFixed(2) }}}}",
                            classes="text-caption ml-1",
                            style=(f"{{opacity: row.{use} && row.set_{key} ? 1 : 0.4}}",),
                        )
                    html.Div(
                        "move the slider to set a target",
                        v_if=f"row.{use} && !row.set_{key}",
                        classes=f"text-caption text-medium-emphasis lens-unset-{key}",
                    )
    html.Div(
        "Move a slider to set a target (its box ticks; untick it to drop the target). "
        "Visible share: how much of what you see in the region should be this structure. "
        "See-through: 0 = solid, 1 = invisible.",
        classes="text-caption",
        v_if="lens_rows.length",
    )
    with v3.VRow(dense=True, classes="mt-2"):
        half_button(
            "Refine region",
            title="optimise opacity inside the lens",
            click=(app.optimise, "['opacity', true]"),
            color="primary",
            disabled=("busy || !lens_rows.length",),
            id="refine-lens",
        )
        half_button(
            "Clear region",
            click=app.clear_lens,
            disabled=("busy || !lens",),
            id="clear-lens",
        )
    with html.Div(
        v_if="lens_result_key && lens_result_key === now_key",
        classes="mt-3",
        id="lens-result",
    ):
        html.Div("The refined setting", classes="text-body-2 font-weight-bold")
        html.Div(
            "Inside the lens on the view: the refined setting; around it: the current one "
            "(nothing is applied yet). It changes the transfer function, so it changes the "
            "whole view, as here:",
            classes="text-caption",
        )
        html.Img(
            src=("lens_whole_url",),
            style="width: 100%; height: 120px; object-fit: contain; background: #000;",
            id="lens-whole-image",
        )
        html.Div(
            "{{ opt_key === now_key ? lens_whole_text : '' }}",
            v_show="lens_whole_text",
            classes="text-body-2 mt-1 measured",
            raw_attrs=[':data-key="opt_key"'],
            id="lens-whole",
        )
        with v3.VAlert(
            v_if="lens_worse",
            type="warning",
            density="compact",
            variant="tonal",
            classes="mt-2",
            id="lens-prompt",
        ):
            html.Div(
                "Applied to the whole view, this setting makes the whole view worse by more "
                "than 10 %.",
                classes="text-body-2",
            )
        with v3.VRow(dense=True, classes="mt-1"):
            half_button(
                "Apply to whole view",
                title="use the refined setting everywhere (one step in the history)",
                click=app.lens_apply,
                color="primary",
                disabled=("busy",),
                id="lens-apply",
            )
            half_button(
                "Discard",
                title="forget the refined setting",
                click=app.lens_discard,
                disabled=("busy",),
                id="lens-discard",
            )


def _outline_style(x0, y0, x1, y1, circle) -> str:
    """Vue style object of a lens outline from pixel expressions."""
    r = f"Math.hypot(({x1}) - ({x0}), ({y1}) - ({y0}))"
    return (
        f"({circle}) ? {{left: (({x0}) - {r}) + 'px', top: (({y0}) - {r}) + 'px', "
        f"width: (2 * {r}) + 'px', height: (2 * {r}) + 'px', borderRadius: '50%'}} : "
        f"{{left: Math.min({x0}, {x1}) + 'px', top: Math.min({y0}, {y1}) + 'px', "
        f"width: Math.abs(({x1}) - ({x0})) + 'px', height: Math.abs(({y1}) - ({y0})) + 'px'}}"
    )


def lens_pad(app) -> None:
    """Transparent layer over the view that turns mouse drags into the lens (Lens tab)."""
    d = "lens_drag"
    down = (
        f"{d} = {{x0: $event.offsetX, y0: $event.offsetY, x1: $event.offsetX, "
        "y1: $event.offsetY, w: $event.currentTarget.clientWidth, "
        "h: $event.currentTarget.clientHeight}; "
        "$event.currentTarget.setPointerCapture($event.pointerId)"
    )
    move = f"{d} && ({d} = {{...{d}, x1: $event.offsetX, y1: $event.offsetY}})"
    up = (
        f"{d} && (lens = lens_shape === 'circle' ? "
        f"{{shape: 'circle', x0: {d}.x0 / {d}.w, y0: {d}.y0 / {d}.h, "
        f"r: Math.hypot({d}.x1 - {d}.x0, {d}.y1 - {d}.y0) / {d}.w, w: {d}.w, h: {d}.h}} : "
        f"{{shape: 'rect', x0: {d}.x0 / {d}.w, y0: {d}.y0 / {d}.h, x1: {d}.x1 / {d}.w, "
        f"y1: {d}.y1 / {d}.h, w: {d}.w, h: {d}.h}}); {d} = null"
    )
    with html.Div(
        v_if="tab === 'lens'",
        id="lens-pad",
        style="position: absolute; inset: 0; z-index: 5; cursor: crosshair; touch-action: none;",
        pointerdown=down,
        pointermove=move,
        pointerup=up,
        __events=["pointerdown", "pointermove", "pointerup"],
    ):
        outline = (
            "{position: 'absolute', pointerEvents: 'none', border: '3px dashed #ffeb3b', "
            "boxShadow: '0 0 0 1px #000'}"
        )
        drawing = _outline_style(
            f"{d}.x0", f"{d}.y0", f"{d}.x1", f"{d}.y1", "lens_shape === 'circle'"
        )
        # the lens result inside the lens over the current rendering (transparent outside)
        html.Img(
            v_if="lens_overlay_url && lens_result_key === now_key && view_mode === 'exact'",
            src=("lens_overlay_url",),
            style="position: absolute; inset: 0; width: 100%; height: 100%; pointer-events: none",
            id="lens-result-overlay",
        )
        html.Div(v_if=d, style=(f"[{outline}, {drawing}]",), id="lens-drawing")
        c = "lens"
        html.Div(
            v_if=f"!{d} && {c}",
            style=(
                f"[{outline}, {c}.shape === 'circle' ? {{left: ({c}.x0 - {c}.r) * {c}.w + 'px', "
                f"top: ({c}.y0 * {c}.h - {c}.r * {c}.w) + 'px', width: 2 * {c}.r * {c}.w + 'px', "
                f"height: 2 * {c}.r * {c}.w + 'px', borderRadius: '50%'}} : "
                f"{{left: Math.min({c}.x0, {c}.x1) * {c}.w + 'px', "
                f"top: Math.min({c}.y0, {c}.y1) * {c}.h + 'px', "
                f"width: Math.abs({c}.x1 - {c}.x0) * {c}.w + 'px', "
                f"height: Math.abs({c}.y1 - {c}.y0) * {c}.h + 'px'}}]",
            ),
            id="lens-outline",
        )
        html.Div(
            "Drag to draw the region; switch to another screen to rotate the view.",
            style="position: absolute; left: 8px; top: 8px; color: #fff; "
            "background: rgba(0,0,0,0.55); padding: 2px 8px; border-radius: 4px; "
            "pointer-events: none;",
            classes="text-body-2",
        )
