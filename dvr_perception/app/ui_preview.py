"""The view area of the page: the quick preview (vtk.js) under the VTK image, and its label.

While the camera moves, the browser draws the preview itself (:mod:`.preview`).  Its canvas
is :data:`PREVIEW_SCALE` of the view's pixels per side, stretched to the view (a script patches
trame-vtk's resize of the local view, then sets ``preview_scale``: the label names the
resolution only once the page really draws at it).  Within that canvas vtk.js lowers the
resolution further while the camera moves (its automatic image sample distance, aiming at 30
frames/s), so the label says "coarser while moving".

Measured on cthead at 512x512 in headless Chromium (software GL, SwiftShader), load average
5-6 on a shared 2-core machine: one full-quality frame of the 64-voxel copy the preview used
to be takes 4.7 s at 512x512, 0.96 s at 256x256, 0.26 s at 128x128 and 0.12 s at 64x64 (twice
the sample distance halves it), so only vtk.js's adaptive resolution makes a drag interactive;
with it, 9.5 frames/s with the canvas at full size (its full-size buffers and copies cost per
frame) and 31-35 frames/s at half size (50-56 at a third).  With the full volume (issue 30;
256x256x113 voxels, a sample every 2 voxels along the rays): 11.9-16.2 frames/s at load 6-8
(the page handled one pointer move per frame), and the one full-quality frame vtk.js draws
when the camera stops takes 1.0-1.3 s at 256x256 (1.4-1.7 s with a sample every voxel, which
delayed the numbers of the rested view to 1.7-3.2 s; now 0.4-1.3 s).
"""

from __future__ import annotations

from trame.widgets import client, html
from trame.widgets import vtk as vtk_widgets

__all__ = ["PREVIEW_SCALE", "view_area"]

#: Share of the view's pixels per side the preview is drawn at while the camera moves.
PREVIEW_SCALE = 0.5

#: Patches the local view (``trame.refs.local``) once it exists: its canvas gets
#: PREVIEW_SCALE of the size trame-vtk gives it (the canvas' CSS stretches it back).
_SCALE_SCRIPT = """
(() => {
  const scale = %(scale)s;
  const patch = () => {
    const view = window.trame?.refs?.local?.$?.provides?.view;
    if (!view || !view.openglRenderWindow || !view.container || !window.trame.state) {
      return false;
    }
    if (view.__dvrScale !== scale) {
      const resize = view.resize.bind(view);
      view.resize = () => {
        resize();
        const [w, h] = view.openglRenderWindow.getSize();
        view.openglRenderWindow.setSize(
          Math.max(10, Math.floor(w * scale)), Math.max(10, Math.floor(h * scale)));
      };
      view.__dvrScale = scale;
      view.resize();
    }
    window.trame.state.set('preview_scale', scale);
    return true;
  };
  const id = setInterval(() => { if (patch()) clearInterval(id); }, 200);
})();
"""

#: The label at the view's top right: which image is on screen.
LABEL = (
    "{{ view_mode !== 'exact' ? 'quick preview (vtk.js, ' + preview_detail + ', ' + "
    "(preview_scale === 1 ? 'full' : preview_scale === 0.5 ? 'half' : "
    "Math.round(100 * preview_scale) + ' %') + ' resolution, coarser while moving)' : "
    "(structures.some(r => r.label !== null && r.label !== undefined) ? "
    "'VTK label map (GPU ray caster, near the engine, one material)' : "
    "'VTK fixed-point ray caster (the engine\\'s model)') + "
    "(map_shown ? ' + ' + map_shown + ' quality map' : '') }}"
)


def view_area(app) -> None:
    """Add the quick preview (vtk.js, takes the mouse) under VTK's image of the server.

    A drag or a wheel turn in the preview shows the preview alone (``view_mode``
    ``"preview"``); when the camera rests the server measures that camera's view and, once
    the numbers are out, renders its image, which covers the preview again.
    """
    end = (app.local_camera, "[trame.refs.local.getCamera()]")
    app.state.preview_detail = app.preview.detail  # the volume's resolution in the preview
    app.state.preview_scale = 1  # each page says what it draws at (not synced back)
    app.state.client_only("preview_scale")
    client.Script(_SCALE_SCRIPT % {"scale": repr(float(PREVIEW_SCALE))})
    with html.Div(style="position: absolute; inset: 0; z-index: 0;", id="local-view"):
        app.local_view = vtk_widgets.VtkLocalView(
            app.preview.window,
            ref="local",
            interactor_events=(
                "local_events",
                ["StartAnimation", "EndAnimation", "StartMouseWheel", "EndMouseWheel"],
            ),
            StartAnimation=app.preview_start,
            StartMouseWheel=app.preview_start,
            EndAnimation=end,
            EndMouseWheel=end,
        )
    with html.Div(
        style=(
            "{position: 'absolute', inset: 0, zIndex: 1, pointerEvents: 'none', "
            "visibility: view_mode === 'exact' ? 'visible' : 'hidden'}",
        ),
        id="exact-view",
    ):
        app.view = vtk_widgets.VtkRemoteView(app.plotter.ren_win, ref="view", interactive_ratio=1)
    app.ctrl.view_update = app.view.update
    html.Div(
        LABEL,
        style="position: absolute; right: 8px; top: 8px; z-index: 4; pointer-events: none; "
        "color: #fff; background: rgba(0,0,0,0.55); padding: 2px 8px; border-radius: 4px;",
        classes="text-caption",
        raw_attrs=[
            ':data-mode="view_mode"',
            ':data-scale="preview_scale"',
            ':data-detail="preview_detail"',
            ':data-map="map_shown"',
        ],
        id="view-mode",
    )
