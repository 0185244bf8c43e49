"""The Calibration and Ranking screens of the web app (side panels and full screens)."""

from __future__ import annotations

from trame.widgets import html
from trame.widgets import vuetify3 as v3

from dvr_perception.app._widgets import half_button, heading

__all__ = ["calibration_panel", "calibration_screen", "ranking_panel", "ranking_screen"]


# -- 5 calibration ---------------------------------------------------------------------------
def calibration_panel(app) -> None:
    """Side panel of the Calibration screen: file name, start, load, use the curve."""
    heading(
        "Calibrate how you see transparency",
        "People judge see-through layers a little differently. You will see 8 test images: "
        "a grey square lying over a background. Say how much of the background you can see "
        "through the square. From your answers a personal curve is fitted and saved; the "
        "transparency error then uses it.",
    )
    v3.VTextField(
        label="Calibration file (saved in the export folder)",
        v_model=("cal_name",),
        density="compact",
        hide_details=True,
        id="cal-file",
    )
    with v3.VRow(dense=True, classes="mt-2"):
        half_button(
            "Start the test",
            click=app.start_calibration,
            color="primary",
            id="cal-start",
        )
        half_button(
            "Load saved curve",
            click=app.load_calibration_file,
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


def calibration_screen(app) -> None:
    """Full screen of the calibration test: the stimulus, the rating slider, the curve."""
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
                    # the value on screen, not a later state sync
                    click=(app.rate_stimulus, "[cal_rating]"),
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
def ranking_panel(app) -> None:
    """Side panel of the Ranking study: structure, answers file, new set of images."""
    heading(
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
    html.Div("Answers file: {{ rank_file_label }}", classes="text-caption mt-2")
    html.Div("{{ rank_result }}", classes="text-body-2 mt-2", id="rank-result")


def ranking_screen(app) -> None:
    """Full screen of the ranking task: the images to order and the result."""
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
                # the order goes with the click: no race with the state sync of rank_order
                click=(app.save_ranking, "[rank_order]"),
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
