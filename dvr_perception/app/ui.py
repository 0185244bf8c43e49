"""The page of the web app (Vuetify 3): a side panel with four numbered steps and the 3D view.

1. **Data** -- volume, structure table (colour, importance slider, current opacity), spec
   JSON load/save;
2. **Optimise this view** -- opacity only or all stages, progress, cancel, undo;
3. **Image quality** -- E_v, E_s, E_t and the quality-map overlay;
4. **Export** -- PNG, spec JSON, ParaView preset, Slicer file.

Elements the browser tests use carry ``id`` attributes.
"""

from __future__ import annotations

from trame.ui.vuetify3 import SinglePageWithDrawerLayout
from trame.widgets import html
from trame.widgets import vtk as vtk_widgets
from trame.widgets import vuetify3 as v3

__all__ = ["build_ui"]

TITLE = "Readable transparent volume rendering"

ERRORS = (
    ("E_v", "Visibility error", "Is each structure as visible as its importance asks?"),
    ("E_s", "Shape error", "Are the surface shapes readable (shading matches curvature)?"),
    ("E_t", "Transparency error", "Does each layer look as transparent as intended?"),
)


def _section(number: int, title: str):
    v3.VDivider(classes="my-2")
    html.Div(f"{number}. {title}", classes="text-subtitle-1 font-weight-bold mt-1")


def _data_panel(app) -> None:
    _section(1, "Data")
    v3.VSelect(
        label="Volume",
        v_model=("volume_name",),
        items=("volume_choices",),
        density="compact",
        hide_details=True,
        disabled=("busy",),
        id="volume-select",
    )
    html.Div("Structures: {{ spec_source }}", classes="text-caption mt-1")
    with html.Table(classes="w-100 text-body-2", id="structure-table"):
        with html.Tr():
            html.Th("Colour", classes="text-left")
            html.Th("Structure", classes="text-left")
            html.Th("Importance (how visible it should be)", classes="text-left")
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
            html.Td("{{ row.name }}")
            with html.Td(style="min-width: 150px"):
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
    with v3.VRow(dense=True, classes="mt-1", align="center", v_if="has_data_dir"):
        with v3.VCol(cols=6):
            v3.VTextField(
                label="Spec file (in the data folder)",
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
    html.Div("Data folder: {{ data_dir }}", v_if="has_data_dir", classes="text-caption")


def _optimise_panel(app) -> None:
    _section(2, "Optimise this view")
    html.Div(
        "Rotate the view (drag; wheel zooms), then optimise the rendering for that view.",
        classes="text-caption",
    )
    with v3.VRow(dense=True, classes="mt-1"):
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
        with v3.VCol(cols=6):
            v3.VBtn("Cancel", click=app.cancel, block=True, disabled=("!busy",), id="cancel")
        with v3.VCol(cols=6):
            v3.VBtn(
                "Undo",
                click=app.undo,
                block=True,
                disabled=("busy || !can_undo",),
                id="undo",
            )
    v3.VProgressLinear(model_value=("progress",), height=6, classes="mt-2", v_show="busy")
    html.Div("{{ progress_text }}", classes="text-caption", id="progress-text")


def _quality_panel(app) -> None:
    _section(3, "Image quality of this view")
    html.Div("0 is perfect; lower is better.", classes="text-caption")
    with html.Table(classes="w-100 text-body-2"):
        for key, name, help_text in ERRORS:
            with html.Tr(title=help_text):
                html.Td(f"{name} ({key.replace('_', '')})")
                html.Td(
                    f"{{{{ {key} === null ? '-' : {key} }}}}",
                    classes="text-right font-weight-bold",
                    id=f"value-{key}",
                )
            with html.Tr():
                html.Td(help_text, colspan=2, classes="text-caption pb-1")
    html.Div("measuring...", v_show="measuring", classes="text-caption", id="measuring")
    v3.VSwitch(
        label="Show quality map over the image (yellow = problem)",
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
        disabled=("!show_map",),
    ):
        v3.VBtn("Visibility", value="visibility", size="small")
        v3.VBtn("Shape", value="shape", size="small")
        v3.VBtn("Transparency", value="transparency", size="small")


def _export_panel(app) -> None:
    _section(4, "Export")
    v3.VBtn("Export view and settings", click=app.export, block=True, id="export")
    html.Div(
        "PNG image, spec JSON, ParaView preset and 3D Slicer .vp.json into {{ export_dir }}",
        classes="text-caption",
    )
    html.Div("{{ name }}", v_for="name in exports", classes="text-caption", id="export-list")


def build_ui(app):
    """Build the page of ``app`` (a :class:`~dvr_perception.app.core.DVRApp`).

    Returns
    -------
    SinglePageWithDrawerLayout
        The layout (trame serves it as the page).
    """
    with SinglePageWithDrawerLayout(app.server, full_height=True) as layout:
        layout.title.set_text(TITLE)
        layout.toolbar.density = "compact"
        with layout.toolbar:
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
            _data_panel(app)
            _optimise_panel(app)
            _quality_panel(app)
            _export_panel(app)
        with layout.content, v3.VContainer(fluid=True, classes="pa-0 fill-height", id="view"):
            app.view = vtk_widgets.VtkRemoteView(
                app.plotter.ren_win,
                ref="view",
                interactive_ratio=1,
                interactor_events=("view_events", ["EndAnimation"]),
                EndAnimation=app.measure_view,
            )
            app.ctrl.view_update = app.view.update
    return layout
