"""The page of the web app (Vuetify 3): tabs for the seven screens, a side panel and the view.

Screens (tabs in the top bar):

1. **Data** -- volume (list of the data folder, upload), structure table (colour, importance,
   current opacity), spec JSON load/save;
2. **Quality map** -- what the three errors mean, the map overlay (kind, strength) and the
   visible share of every structure against the wanted share;
3. **Optimise** -- opacity only or all stages, live progress, cancel, before/after, history
   with undo to any earlier step;
4. **Lens** -- draw a rectangle or circle on the view, set targets for the structures
   inside, refine only that region;
5. **Calibration** -- rate test images of known see-through, fit and save your curve;
6. **Ranking study** -- order images by how see-through a structure looks; answers saved;
7. **Export** -- PNG, spec JSON, ParaView preset, Slicer file.

The three error numbers, the progress bar and Cancel stay visible on the view screens.
Elements the browser tests use carry ``id`` attributes.
"""

from __future__ import annotations

from trame.ui.vuetify3 import SinglePageWithDrawerLayout
from trame.widgets import html
from trame.widgets import vtk as vtk_widgets
from trame.widgets import vuetify3 as v3

__all__ = ["TABS", "build_ui"]

TITLE = "Readable transparent volume rendering"

#: (value, label) of the screens.
TABS = (
    ("data", "1 Data"),
    ("quality", "2 Quality map"),
    ("optimise", "3 Optimise"),
    ("lens", "4 Lens"),
    ("calibration", "5 Calibration"),
    ("ranking", "6 Ranking study"),
    ("export", "7 Export"),
)
STUDY_TABS = "['calibration', 'ranking'].includes(tab)"

ERRORS = (
    ("E_v", "Visibility", "Is each structure as visible as its importance asks?"),
    ("E_s", "Shape", "Are the surface shapes readable (shading matches curvature)?"),
    ("E_t", "Transparency", "Does each layer look as see-through as intended?"),
)


def _heading(title: str, hint: str = "") -> None:
    html.Div(title, classes="text-subtitle-1 font-weight-bold mt-2")
    if hint:
        html.Div(hint, classes="text-body-2 text-medium-emphasis mb-1")


# -- always visible on the view screens --------------------------------------------------------
def _summary(app) -> None:
    with v3.VCard(variant="outlined", classes="pa-2 mb-2", v_show=f"!{STUDY_TABS}"):
        html.Div(
            "Image quality of this view (errors: 0 is perfect, lower is better)",
            classes="text-body-2 font-weight-bold",
        )
        with v3.VRow(dense=True, classes="mt-1"):
            for key, name, help_text in ERRORS:
                with v3.VCol(cols=4, classes="text-center", title=help_text):
                    html.Div(f"{name} error", classes="text-caption")
                    html.Div(
                        f"{{{{ {key} === null ? '-' : {key} }}}}",
                        classes="text-h6",
                        id=f"value-{key}",
                    )
        html.Div("measuring...", v_show="measuring", classes="text-caption", id="measuring")
        html.Div(
            "Transparency judged with your calibration ({{ calibration_name }})",
            v_show="use_calibration && calibration_name",
            classes="text-caption text-primary",
            id="calibration-active",
        )
        with html.Div(v_show="busy || progress_text", classes="mt-1"):
            v3.VProgressLinear(model_value=("progress",), height=6, v_show="busy")
            with v3.VRow(dense=True, align="center", classes="mt-1"):
                with v3.VCol(cols=9):
                    html.Div("{{ progress_text }}", classes="text-caption", id="progress-text")
                with v3.VCol(cols=3):
                    v3.VBtn(
                        "Cancel",
                        click=app.cancel,
                        block=True,
                        size="small",
                        color="error",
                        variant="tonal",
                        disabled=("!busy",),
                        id="cancel",
                    )


# -- 1 data --------------------------------------------------------------------------------
def _data_panel(app) -> None:
    _heading(
        "Volume and structures",
        "Choose a scan; each structure is a range of values shown in one colour.",
    )
    v3.VSelect(
        label="Volume",
        v_model=("volume_name",),
        items=("volume_choices",),
        density="compact",
        hide_details=True,
        disabled=("busy",),
        id="volume-select",
    )
    v3.VFileInput(
        v_if="has_data_dir",
        model_value=("upload",),
        # refuse oversized files in the browser already (they would not fit a message)
        update_modelValue=(
            "(f => f && f.size > max_upload_bytes"
            " ? (error = 'upload ' + f.name + ': ' + (f.size / 1e6).toFixed(2)"
            " + ' MB is larger than the limit of ' + (max_upload_bytes / 1e6).toFixed(2)"
            " + ' MB') : (upload = $event))([].concat($event || [])[0])"
        ),
        label=("`Upload a volume file (at most ${max_upload_mb} MB)`",),
        title=".nrrd, .mha, .mhd, .vti, .nii or .nii.gz",
        density="compact",
        hide_details=True,
        show_size=True,
        disabled=("busy",),
        classes="mt-2",
        id="upload",
    )
    html.Div("Structures from: {{ spec_source }}", classes="text-caption mt-2")
    with html.Table(classes="w-100 text-body-2", id="structure-table"):
        with html.Tr():
            html.Th("Colour", classes="text-left")
            html.Th("Structure and value range", classes="text-left")
            html.Th("Importance", classes="text-left", title="how visible it should be")
            html.Th("Opacity now", classes="text-right")
        with html.Tr(v_for="row in structures", key="row.index"):
            with html.Td():
                html.Input(
                    type="color",
                    value=("row.color",),
                    disabled=("busy",),
                    change=(app.set_colour, "[row.index, $event.target.value]"),
                    style="width: 32px; height: 24px; border: none; padding: 0;",
                )
            with html.Td():
                html.Div("{{ row.name }}")
                with html.Div(v_if="row.range", classes="text-caption d-flex align-center"):
                    for end in (0, 1):
                        html.Input(
                            type="number",
                            value=(f"row.range[{end}]",),
                            disabled=("busy",),
                            change=(app.set_range, f"[row.index, {end}, $event.target.value]"),
                            title="lowest value" if end == 0 else "highest value",
                            classes=f"range-{'lo' if end == 0 else 'hi'}",
                            style="width: 52px; border: 1px solid #bdbdbd; border-radius: 3px; "
                            "padding: 0 3px;",
                        )
                        if end == 0:
                            html.Span("to", classes="mx-1")
            with html.Td(style="min-width: 140px"):
                v3.VSlider(
                    model_value=("row.importance",),
                    min=0,
                    max=1,
                    step=0.05,
                    thumb_label=True,
                    hide_details=True,
                    density="compact",
                    disabled=("busy",),
                    end=(app.set_importance, "[row.index, $event]"),
                )
            html.Td("{{ row.opacity.toFixed(2) }}", classes="text-right")
    html.Div("Importance: 0 = may vanish, 1 = must stay clearly visible.", classes="text-caption")
    with v3.VRow(dense=True, classes="mt-2", align="center", v_if="has_data_dir"):
        with v3.VCol(cols=6):
            v3.VTextField(
                label="Settings file (.json)",
                v_model=("spec_path",),
                density="compact",
                hide_details=True,
                id="spec-path",
            )
        with v3.VCol(cols=3):
            v3.VBtn(
                "Load",
                click=(app.load_spec, "[spec_path]"),
                block=True,
                disabled=("busy",),
                id="load-spec",
            )
        with v3.VCol(cols=3):
            v3.VBtn("Save", click=(app.save_spec, "[spec_path]"), block=True, id="save-spec")
    html.Div(
        "Settings files are read from and saved to the data folder: {{ data_dir }}",
        v_if="has_data_dir",
        classes="text-caption",
    )


# -- 2 quality map ---------------------------------------------------------------------------
def _quality_panel(app) -> None:
    _heading("What the three errors mean")
    with html.Table(classes="w-100 text-body-2"):
        for _key, name, help_text in ERRORS:
            with html.Tr():
                html.Td(name, classes="font-weight-medium pr-2", style="vertical-align: top")
                html.Td(help_text)
    _heading("Quality map", "Colours the image where it is hard to read (yellow = problem).")
    v3.VSwitch(
        label="Show the quality map over the image",
        v_model=("show_map",),
        color="primary",
        density="compact",
        hide_details=True,
        id="show-map",
    )
    with v3.VBtnToggle(
        v_model=("map_kind",),
        mandatory=True,
        density="compact",
        divided=True,
        variant="outlined",
        disabled=("!show_map",),
        id="map-kind",
    ):
        v3.VBtn("Visibility", value="visibility", size="small")
        v3.VBtn("Shape", value="shape", size="small")
        v3.VBtn("Transparency", value="transparency", size="small")
    with html.Div(id="map-opacity"):
        v3.VSlider(
            label="Map strength",
            v_model=("map_opacity",),
            min=0.1,
            max=1.0,
            step=0.1,
            thumb_label=True,
            hide_details=True,
            density="compact",
            disabled=("!show_map",),
            classes="mt-2",
        )
    _heading(
        "How much of the picture each structure takes",
        "Bar = share of what you see now; black mark = share its importance asks for.",
    )
    _share_chart("share-chart")


def _share_chart(element_id: str, *, compact: bool = False) -> None:
    """Bars: each structure's visible share now, with a mark at the share wanted."""
    text = "text-caption" if compact else "text-body-2"
    with (
        html.Div(id=element_id),
        html.Div(
            v_for="row in shares",
            key="row.name",
            classes="d-flex align-center" + ("" if compact else " mb-1"),
        ),
    ):
        html.Div("{{ row.name }}", classes=text, style="width: 110px; line-height: 1.4")
        with html.Div(
            style="position: relative; flex: 1; background: #eeeeee; "
            f"height: {10 if compact else 14}px;",
        ):
            html.Div(
                style=(
                    "{position: 'absolute', left: 0, top: 0, bottom: 0, "
                    "width: row.visible + '%', background: row.color, "
                    "border: '1px solid #757575'}",
                ),
            )
            html.Div(
                style=(
                    "{position: 'absolute', top: '-2px', bottom: '-2px', width: '3px', "
                    "left: 'calc(' + row.wanted + '% - 1px)', background: '#000'}",
                ),
            )
        html.Div(
            "{{ row.visible.toFixed(0) }} %",
            classes="text-caption text-right share-value",
            style="width: 48px",
        )


# -- 3 optimise ------------------------------------------------------------------------------
def _optimise_panel(app) -> None:
    _heading(
        "Optimise this view",
        "Adjusts the rendering for the view as it is now (rotate it first: drag; the wheel "
        "zooms). Cancel keeps the best result so far.",
    )
    with v3.VRow(dense=True):
        with v3.VCol(cols=6):
            v3.VBtn(
                "Optimise opacity",
                click=(app.optimise, "['opacity']"),
                color="primary",
                block=True,
                disabled=("busy",),
                id="optimise-opacity",
            )
        with v3.VCol(cols=6):
            v3.VBtn(
                "Optimise all",
                title="opacity, then lighting, then colour",
                click=(app.optimise, "['all']"),
                color="primary",
                variant="outlined",
                block=True,
                disabled=("busy",),
                id="optimise-all",
            )
    html.Div("'Optimise all' also adjusts lighting and colours.", classes="text-caption")
    with html.Div(v_show="error_history_svg", classes="mt-2"):
        html.Div(
            "Errors at each iteration (quick preview resolution)",
            classes="text-body-2 font-weight-bold",
        )
        html.Div(v_html=("error_history_svg",), id="error-history")
        html.Div("Visible share of each structure (mark: wanted)", classes="text-caption")
        _share_chart("share-chart-live", compact=True)
    with html.Div(v_if="before_url", classes="mt-2", id="before-after"):
        html.Div("Before and after", classes="text-body-2 font-weight-bold")
        with v3.VRow(dense=True):
            with v3.VCol(cols=6):
                html.Img(
                    src=("before_url",),
                    style="width: 100%; height: 120px; object-fit: contain; background: #000;",
                    id="before-image",
                )
                html.Div("before: {{ before_text }}", classes="text-caption")
            with v3.VCol(cols=6, v_if="after_url"):
                html.Img(
                    src=("after_url",),
                    style="width: 100%; height: 120px; object-fit: contain; background: #000;",
                    id="after-image",
                )
                html.Div("after: {{ after_text }}", classes="text-caption")
    with html.Div(classes="d-flex align-center mt-2"):
        html.Div("History of changes", classes="text-subtitle-1 font-weight-bold flex-grow-1")
        v3.VBtn(
            "Undo last change",
            click=app.undo,
            size="small",
            disabled=("busy || !can_undo",),
            id="undo",
        )
    with (
        html.Div(id="history-list", classes="mt-1"),
        html.Div(v_for="h in history", key="h.steps", classes="d-flex align-center"),
    ):
        html.Div("{{ h.label }}", classes="text-body-2 flex-grow-1")
        v3.VBtn(
            "Go back to before this",
            click=(app.undo, "[h.steps]"),
            size="x-small",
            variant="text",
            color="primary",
            disabled=("busy",),
        )


# -- 4 lens --------------------------------------------------------------------------------
def _lens_panel(app) -> None:
    _heading(
        "Lens: improve one region",
        "Choose a shape, then drag on the image to mark the region to improve. Only that "
        "region is optimised; you can ask for how visible or how see-through each structure "
        "inside it should be.",
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
                    "in {{ (100 * row.fraction).toFixed(0) }} % of the region",
                    classes="text-caption",
                )
            for use, key in (("use_vis", "vis"), ("use_tr", "tr")):
                with (
                    html.Td(style="min-width: 120px"),
                    html.Div(classes="d-flex align-center"),
                ):
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
                        disabled=(f"!row.{use}",),
                        end=(app.set_lens_target, f"[row.index, '{key}', $event]"),
                    )
                    html.Span(
                        f"{{{{ row.{key}.toFixed(2) }}}}",
                        classes="text-caption ml-1",
                        style=(f"{{opacity: row.{use} ? 1 : 0.4}}",),
                    )
    html.Div(
        "Tick a box to set a target. Visible share: how much of what you see in the region "
        "should be this structure. See-through: 0 = solid, 1 = invisible.",
        classes="text-caption",
        v_if="lens_rows.length",
    )
    with v3.VRow(dense=True, classes="mt-2"):
        with v3.VCol(cols=6):
            v3.VBtn(
                "Refine region",
                title="optimise opacity inside the lens",
                click=(app.optimise, "['opacity', true]"),
                color="primary",
                block=True,
                disabled=("busy || !lens_rows.length",),
                id="refine-lens",
            )
        with v3.VCol(cols=6):
            v3.VBtn(
                "Clear region",
                click=app.clear_lens,
                block=True,
                disabled=("busy || !lens",),
                id="clear-lens",
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


def _lens_pad(app) -> None:
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


# -- 5 calibration ---------------------------------------------------------------------------
def _calibration_panel(app) -> None:
    _heading(
        "Calibrate how you see transparency",
        "People judge see-through layers a little differently. You will see 8 test images: "
        "a grey square lying over a background. Say how much of the background you can see "
        "through the square. From your answers a personal curve is fitted and saved; the "
        "transparency error then uses it.",
    )
    v3.VTextField(
        label="Calibration file (saved in the export folder)",
        v_model=("cal_file",),
        density="compact",
        hide_details=True,
        id="cal-file",
    )
    with v3.VRow(dense=True, classes="mt-2"):
        with v3.VCol(cols=6):
            v3.VBtn(
                "Start the test",
                click=app.start_calibration,
                color="primary",
                block=True,
                id="cal-start",
            )
        with v3.VCol(cols=6):
            v3.VBtn(
                "Load saved curve",
                click=app.load_calibration_file,
                block=True,
                id="cal-load",
            )
    v3.VSwitch(
        label="Use my calibration in the measures",
        v_model=("use_calibration",),
        disabled=("!has_calibration",),
        color="primary",
        density="compact",
        hide_details=True,
        id="use-calibration",
    )
    html.Div("Saved: {{ cal_saved }}", v_if="cal_saved", classes="text-caption", id="cal-saved")


def _calibration_screen(app) -> None:
    with html.Div(v_if="tab === 'calibration'", classes="pa-6", id="calibration-screen"):
        with html.Div(v_if="cal_active"):
            html.Div(
                "Test image {{ cal_index }} of {{ cal_total }}",
                classes="text-h6",
                id="cal-progress",
            )
            html.Div(
                "How much of the background can you see through the grey square in the middle?",
                classes="text-body-1 mb-3",
            )
            html.Img(
                src=("cal_url",),
                style="width: 256px; height: 256px; image-rendering: pixelated; "
                "border: 1px solid #9e9e9e;",
                id="cal-image",
            )
            with html.Div(style="max-width: 420px", classes="mt-4"):
                v3.VSlider(
                    v_model=("cal_rating",),
                    min=0,
                    max=1,
                    step=0.05,
                    thumb_label="always",
                    hide_details=True,
                    classes="cal-rating",
                )
                with html.Div(classes="d-flex justify-space-between text-caption"):
                    html.Span("0: nothing (solid square)")
                    html.Span("1: everything (no square)")
                v3.VBtn(
                    "Next image",
                    click=app.rate_stimulus,
                    color="primary",
                    classes="mt-3",
                    id="cal-next",
                )
        with html.Div(v_if="!cal_active"):
            html.Div("Your calibration curve", classes="text-h6")
            html.Div(
                "Press 'Start the test' on the left to (re)do the test. The chart shows your "
                "answers (dots), the fitted curve (blue line) and, dashed, what the measure "
                "assumes without calibration.",
                classes="text-body-1 mb-3",
                style="max-width: 640px",
            )
            html.Div(v_html=("cal_svg",), id="cal-chart")


# -- 6 ranking -------------------------------------------------------------------------------
def _ranking_panel(app) -> None:
    _heading(
        "Ranking study",
        "As in the paper's user study: you see the same view four times; only the colour "
        "brightness of one structure differs. Click the images in order, from the one where "
        "that structure looks most see-through to the one where it looks least "
        "see-through, then save. Your answer and the measured order are added to a file.",
    )
    v3.VSelect(
        label="Structure whose colour changes",
        v_model=("rank_structure",),
        items=("structure_names",),
        density="compact",
        hide_details=True,
        id="rank-structure",
    )
    v3.VBtn(
        "New set of images",
        click=app.new_ranking,
        color="primary",
        block=True,
        loading=("rank_busy",),
        classes="mt-2",
        id="rank-new",
    )
    html.Div("Answers file: {{ rank_file }}", classes="text-caption mt-2")
    html.Div("{{ rank_result }}", classes="text-body-2 mt-2", id="rank-result")


def _ranking_screen(app) -> None:
    with html.Div(v_if="tab === 'ranking'", classes="pa-6", id="ranking-screen"):
        html.Div(
            "Click the images from MOST see-through to LEAST see-through",
            classes="text-h6",
        )
        html.Div(
            "Press 'New set of images' on the left to begin.",
            v_if="!rank_images.length",
            classes="text-body-1",
        )
        with (
            html.Div(classes="d-flex flex-wrap", style="gap: 16px", v_if="rank_images.length"),
            html.Div(
                v_for="img in rank_images",
                key="img.id",
                classes="rank-card",
                style="position: relative; cursor: pointer; text-align: center;",
                click="rank_saved || rank_order.includes(img.id) || "
                "(rank_order = [...rank_order, img.id])",
                id=("'rank-' + img.label",),
            ),
        ):
            html.Img(
                src=("img.url",),
                style=(
                    "{width: '200px', border: rank_order.includes(img.id) ? "
                    "'4px solid #1565c0' : '4px solid transparent'}",
                ),
            )
            html.Div("Image {{ img.label }}", classes="text-body-1")
            html.Div(
                "{{ rank_order.indexOf(img.id) + 1 }}",
                v_if="rank_order.includes(img.id)",
                classes="text-h5",
                style="position: absolute; top: 8px; left: 8px; width: 40px; "
                "height: 40px; line-height: 40px; border-radius: 50%; color: #fff; "
                "background: #1565c0;",
            )
        with html.Div(classes="mt-4", v_if="rank_images.length"):
            html.Div(
                "Your order: {{ rank_order.map(i => rank_images.find(r => r.id === i).label)"
                ".join(' > ') || '(none yet)' }}",
                classes="text-body-1 mb-2",
            )
            v3.VBtn(
                "Start over",
                click="rank_order = []",
                disabled=("rank_saved",),
                classes="mr-2",
                id="rank-reset",
            )
            v3.VBtn(
                "Save my answer",
                click=app.save_ranking,
                color="primary",
                disabled=("rank_saved || rank_order.length !== rank_images.length",),
                id="rank-save",
            )
            html.Div(
                "{{ rank_result }} Press 'New set of images' for the next set.",
                v_if="rank_saved",
                classes="text-body-1 mt-3",
                style="max-width: 900px",
            )


# -- 7 export --------------------------------------------------------------------------------
def _export_panel(app) -> None:
    _heading(
        "Export",
        "Saves the image and settings to use in other programs: PNG image, settings (JSON), "
        "ParaView colour/opacity preset and 3D Slicer volume property (.vp.json).",
    )
    v3.VBtn("Export view and settings", click=app.export, block=True, color="primary", id="export")
    html.Div("Export folder: {{ export_dir }}", classes="text-caption mt-1")
    html.Div("Written:", v_if="exports.length", classes="text-body-2 mt-2")
    html.Div("{{ name }}", v_for="name in exports", classes="text-body-2 ml-2", id="export-list")


def build_ui(app):
    """Build the page of ``app`` (a :class:`~dvr_perception.app.core.DVRApp`).

    Returns
    -------
    SinglePageWithDrawerLayout
        The layout (trame serves it as the page).
    """
    with SinglePageWithDrawerLayout(app.server, full_height=True) as layout:
        app.state.trame__title = TITLE
        layout.title.set_text("Readable volume rendering")
        layout.title.style = "flex: none; font-size: 1.05rem; font-weight: 600;"
        layout.toolbar.density = "compact"
        with layout.toolbar:
            with v3.VTabs(
                v_model=("tab",),
                density="compact",
                color="primary",
                classes="ml-4",
                id="tabs",
            ):
                for value, label in TABS:
                    v3.VTab(label, value=value, id=f"tab-{value}")
            v3.VSpacer()
            html.Div("{{ volume_name }}", classes="text-body-2 mr-4")
        layout.drawer.width = 470
        with layout.drawer, html.Div(classes="pa-3"):
            v3.VAlert(
                v_if="error",
                text=("error",),
                type="error",
                density="compact",
                closable=True,
                click_close="error = ''",
                id="error-message",
            )
            v3.VAlert(
                v_if="info && !error",
                text=("info",),
                type="info",
                density="compact",
                variant="tonal",
                closable=True,
                click_close="info = ''",
                id="info-message",
            )
            _summary(app)
            for value, build in (
                ("data", _data_panel),
                ("quality", _quality_panel),
                ("optimise", _optimise_panel),
                ("lens", _lens_panel),
                ("calibration", _calibration_panel),
                ("ranking", _ranking_panel),
                ("export", _export_panel),
            ):
                with html.Div(v_show=f"tab === '{value}'", id=f"panel-{value}"):
                    build(app)
        with (
            layout.content,
            v3.VContainer(
                fluid=True, classes="pa-0 fill-height", style="position: relative;", id="view"
            ),
        ):
            app.view = vtk_widgets.VtkRemoteView(
                app.plotter.ren_win,
                ref="view",
                interactive_ratio=1,
                interactor_events=("view_events", ["EndAnimation"]),
                EndAnimation=app.measure_view,
            )
            app.ctrl.view_update = app.view.update
            _lens_pad(app)
            with html.Div(
                v_if=STUDY_TABS,
                style="position: absolute; inset: 0; z-index: 6; background: #fff; overflow: auto;",
                id="study-screen",
            ):
                _calibration_screen(app)
                _ranking_screen(app)
    return layout
