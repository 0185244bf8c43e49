"""The page of the web app (Vuetify 3): tabs for the seven screens, a side panel and the view.

Screens (tabs in the top bar):

1. **Data** -- volume (list of the data folder, upload), structure table (colour, importance,
   current opacity), the transfer-function view (histogram with each structure's range and
   opacity, draggable), spec JSON load/save;
2. **Quality map** -- what the three errors mean, the map overlay (kind, strength) and the
   visible share of every structure against the wanted share;
3. **Optimise** -- opacity only or all stages, live progress, cancel, before/after, history
   with undo to any earlier step;
4. **Lens** -- draw a rectangle or circle on the view, set targets for the structures
   inside, refine from that region: the result is shown inside the lens over the current
   rendering, with the whole view's change and cost, and applied to the whole view on request;
5. **Calibration** -- rate test images of known see-through, fit and save your curve;
6. **Ranking study** -- order images by how see-through a structure looks; answers saved;
7. **Export** -- PNG, spec JSON, ParaView preset, Slicer file.

The three error numbers, the progress bar and Cancel stay visible on the view screens.
Over the view: a legend with the structures' colours and opacities and a colour bar of the
value range (:mod:`.ui_tf`), and buttons for the reset and the six axis views.
Elements the browser tests use carry ``id`` attributes.
"""

from __future__ import annotations

from trame.ui.vuetify3 import SinglePageWithDrawerLayout
from trame.widgets import client, html
from trame.widgets import vuetify3 as v3

from dvr_perception.app._widgets import half_button, heading
from dvr_perception.app.ui_lens import lens_pad, lens_panel
from dvr_perception.app.ui_preview import view_area
from dvr_perception.app.ui_study import (
    calibration_panel,
    calibration_screen,
    ranking_panel,
    ranking_screen,
)
from dvr_perception.app.ui_tf import tf_editor, view_overlay

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
#: The summary numbers are for the view and transfer function shown.
FRESH = "measured_key === now_key"
#: The optimisation's results are for the view and transfer function shown.
OPT_FRESH = "opt_key === now_key"

ERRORS = (
    ("E_v", "Visibility", "Is each structure as visible as its importance asks?"),
    ("E_s", "Shape", "Are the surface shapes readable (shading matches curvature)?"),
    ("E_t", "Transparency", "Does each layer look as see-through as intended?"),
)


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
                        f"{{{{ {key} === null || !({FRESH}) ? '-' : {key} }}}}",
                        classes="text-h6 measured",
                        raw_attrs=[':data-key="measured_key"'],
                        id=f"value-{key}",
                    )
        html.Div(
            f"{{{{ {FRESH} ? 'for ' + measured_for "
            ": 'the view or settings changed: re-measuring' }}",
            classes="text-caption measured",
            raw_attrs=[':data-key="measured_key"'],
            id="measured-for",
        )
        html.Div("measuring...", v_show="measuring", classes="text-caption", id="measuring")
        html.Div(raw_attrs=[':data-now="now_key"'], id="now-key", style="display: none")
        html.Div(
            raw_attrs=[':data-camera="JSON.stringify(opt_camera)"'],
            id="opt-camera",
            style="display: none",
        )
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
                    html.Div(
                        f"{{{{ busy || {OPT_FRESH} ? progress_text : 'the last optimisation was "
                        "for an earlier view or settings' }}",
                        classes="text-caption measured",
                        raw_attrs=[':data-key="busy ? now_key : opt_key"'],
                        id="progress-text",
                    )
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
    heading(
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
    # only for a file that records no patient orientation (its axes were taken as L, P, S)
    v3.VSelect(
        label="Orientation (the file records none)",
        v_model=("orientation_code",),
        items=("orientation_choices",),
        v_if="orientation_open",
        title="where the file's index axes x, y, z point; the patient views (Anterior ...) "
        "follow it",
        density="compact",
        hide_details=True,
        disabled=("busy",),
        classes="mt-2",
        id="orientation-select",
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
                html.Div(
                    "label {{ row.label }} (segmentation)",
                    v_if="row.label !== null && row.label !== undefined",
                    classes="text-caption label-id",
                )
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
    heading("Transfer function", "Each structure's value range and opacity over the histogram.")
    tf_editor(app)
    with v3.VRow(dense=True, classes="mt-2", align="center"):
        with v3.VCol(cols=6):
            v3.VTextField(
                label="Settings file (.json or Slicer .seg.nrrd)",
                v_model=("spec_name",),
                density="compact",
                hide_details=True,
                id="spec-path",
            )
        with v3.VCol(cols=3):
            v3.VBtn(
                "Load",
                click=(app.load_spec, "[spec_name]"),
                block=True,
                disabled=("busy",),
                id="load-spec",
            )
        with v3.VCol(cols=3):
            v3.VBtn("Save", click=(app.save_spec, "[spec_name]"), block=True, id="save-spec")
    html.Div(
        "Settings files and 3D Slicer segmentations (.seg.nrrd) to load: "
        "{{ spec_choices.join(', ') || 'none yet' }}. "
        "Load reads them from the data folder ({{ data_dir_label || 'none' }}; saved/...: "
        "the app's folder); Save writes a plain name into the app's folder "
        "{{ state_dir_label }}/settings.",
        classes="text-caption",
        id="spec-choices",
    )


# -- 2 quality map ---------------------------------------------------------------------------
def _quality_panel(app) -> None:
    heading("What the three errors mean")
    with html.Table(classes="w-100 text-body-2"):
        for _key, name, help_text in ERRORS:
            with html.Tr():
                html.Td(name, classes="font-weight-medium pr-2", style="vertical-align: top")
                html.Td(help_text)
    heading("Quality map", "Colours the image where it is hard to read (yellow = problem).")
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
    heading(
        "How much of the picture each structure takes",
        "Bar = share of what you see now; black mark = share its importance asks for.",
    )
    _share_chart("share-chart")


def _share_chart(
    element_id: str,
    *,
    compact: bool = False,
    rows: str = "shares",
    key: str = "measured_key",
) -> None:
    """Bars: each structure's visible share (``rows``, measured for ``key``) and the wanted one.

    When ``key`` is not the view and settings shown, the bars and numbers are hidden.
    """
    text = "text-caption" if compact else "text-body-2"
    with (
        html.Div(id=element_id, classes="measured", raw_attrs=[f':data-key="{key}"']),
        html.Div(
            v_for=f"row in ({key} === now_key ? {rows} : [])",
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
    heading(
        "Optimise this view",
        "Adjusts the rendering for the view as it is now (rotate it first: drag; the wheel "
        "zooms). Cancel keeps the best result so far.",
    )
    with v3.VRow(dense=True):
        half_button(
            "Optimise opacity",
            click=(app.optimise, "['opacity']"),
            color="primary",
            disabled=("busy",),
            id="optimise-opacity",
        )
        half_button(
            "Optimise all",
            title="opacity, then lighting, then colour",
            click=(app.optimise, "['all']"),
            color="primary",
            variant="outlined",
            disabled=("busy",),
            id="optimise-all",
        )
    html.Div("'Optimise all' also adjusts lighting and colours.", classes="text-caption")
    html.Div(
        f"{{{{ busy || {OPT_FRESH} ? opt_sampling : '' }}}}",
        v_show="opt_sampling",
        classes="text-caption measured",
        raw_attrs=[':data-key="busy ? now_key : opt_key"'],
        id="opt-sampling",
    )
    with html.Div(v_show="error_history_svg", classes="mt-2"):
        html.Div(
            "Errors at each iteration (the optimiser's sampling resolution)",
            classes="text-body-2 font-weight-bold",
        )
        html.Div(
            v_html=(f"{OPT_FRESH} ? error_history_svg : ''",),
            classes="measured",
            raw_attrs=[':data-key="opt_key"'],
            id="error-history",
        )
        html.Div("Visible share of each structure (mark: its target share)", classes="text-caption")
        _share_chart("share-chart-live", compact=True, rows="live_shares", key="opt_key")
    with html.Div(v_if="before_url", classes="mt-2", id="before-after"):
        html.Div("Before and after", classes="text-body-2 font-weight-bold")
        html.Div(
            f"{{{{ {OPT_FRESH} ? 'for ' + opt_for : 'for an earlier view or settings: "
            "optimise again for the numbers of this one' }}",
            classes="text-caption measured",
            raw_attrs=[':data-key="opt_key"'],
            id="opt-for",
        )
        with v3.VRow(dense=True):
            with v3.VCol(cols=6):
                html.Img(
                    src=("before_url",),
                    style="width: 100%; height: 120px; object-fit: contain; background: #000;",
                    id="before-image",
                )
                html.Div(
                    f"before: {{{{ {OPT_FRESH} ? before_text : '-' }}}}",
                    classes="text-caption measured",
                    raw_attrs=[':data-key="opt_key"'],
                    id="before-text",
                )
            with v3.VCol(cols=6, v_if="after_url"):
                html.Img(
                    src=("after_url",),
                    style="width: 100%; height: 120px; object-fit: contain; background: #000;",
                    id="after-image",
                )
                html.Div(
                    f"after: {{{{ {OPT_FRESH} ? after_text : '-' }}}}",
                    classes="text-caption measured",
                    raw_attrs=[':data-key="opt_key"'],
                    id="after-text",
                )
    with html.Div(v_if="before_url", classes="mt-2"):
        html.Div(
            "Transfer function: now (solid) and before the optimisation (dashed)",
            classes="text-body-2 font-weight-bold",
        )
        tf_editor(app, element_id="tf-optimise", editable=False)
    with html.Div(
        v_if=f"why_lines.length && {OPT_FRESH}",
        classes="mt-2 measured",
        raw_attrs=[':data-key="opt_key"'],
        id="why",
    ):
        html.Div("What changed and why", classes="text-body-2 font-weight-bold")
        html.Div("{{ line }}", v_for="line in why_lines", key="line", classes="text-caption")
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


# -- 7 export --------------------------------------------------------------------------------
def _export_panel(app) -> None:
    heading(
        "Export",
        "Saves the image and settings to use in other programs: PNG image, settings (JSON), "
        "ParaView colour/opacity preset and 3D Slicer volume property (.vp.json).",
    )
    v3.VBtn("Export view and settings", click=app.export, block=True, color="primary", id="export")
    html.Div("Export folder: {{ export_dir_label }}", classes="text-caption mt-1")
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
            # a new banner belongs to the screen shown when it arrives
            client.ClientStateChange(value="info + '|' + error", change="banner_tab = tab")
            v3.VAlert(
                v_if="error && banner_tab === tab",
                text=("error",),
                type="error",
                density="compact",
                closable=True,
                click_close="error = ''",
                id="error-message",
            )
            v3.VAlert(
                v_if="info && !error && banner_tab === tab",
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
                ("lens", lens_panel),
                ("calibration", calibration_panel),
                ("ranking", ranking_panel),
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
            view_area(app)
            lens_pad(app)
            view_overlay(app)
            with html.Div(
                v_if=STUDY_TABS,
                style="position: absolute; inset: 0; z-index: 6; background: #fff; overflow: auto;",
                id="study-screen",
            ):
                calibration_screen(app)
                ranking_screen(app)
    return layout
