"""The quality maps beside the volume: 2-D views with a legend each and the structure table.

Used by :mod:`dvr_view` (the toolbar's actions): :func:`show_quality` puts the measure images
of a DVR Perception filter's output in 2-D render views next to the 3-D view (never in it)
and its per-structure field data in a spreadsheet view.
"""

__all__ = ["QUALITY_MAPS", "QUALITY_PREFIX", "TABLE_VIEW", "open_quality_views", "show_quality"]

#: The measure images shown in the quality views: (point array, legend title).
QUALITY_MAPS = (
    ("visibility_deviation", "Visibility deviation"),
    ("shape_deviation", "Shape deviation"),
    ("transparency_deviation", "Transparency deviation"),
)
QUALITY_PREFIX = "DVR quality: "
TABLE_VIEW = "DVR structures"


def _simple():
    from paraview import simple

    return simple


def _field_names(data):
    """The names of the field arrays of ``data`` that are *not* one tuple per structure."""
    fd = data.GetFieldData()
    names = fd.GetAbstractArray("structure_names")
    count = names.GetNumberOfValues() if names is not None else 0
    return [
        fd.GetAbstractArray(i).GetName()
        for i in range(fd.GetNumberOfArrays())
        if fd.GetAbstractArray(i).GetNumberOfTuples() != count
    ]


def show_quality(proxy, view, data=None):
    """The measure maps of ``proxy`` in 2-D views beside ``view``, the table below them.

    The first call splits ``view``'s layout cell: the right half becomes a 2 x 2 grid of one
    2-D render view per map of :data:`QUALITY_MAPS` (a scalar bar each) and a spreadsheet of
    the per-structure field data; later calls reuse those views.  Returns ``{title: view}``.
    """
    simple = _simple()
    views = open_quality_views(view)
    for qview in views:  # one filter's output at a time
        for rep in qview.Representations:
            shown = rep.GetProperty("Input") is not None and rep.Visibility
            if shown and rep.Input != proxy:
                rep.Visibility = 0
    for (array, title), qview in zip(QUALITY_MAPS, views[:-1], strict=True):
        rep = simple.Show(proxy, qview)
        rep.Representation = "Slice"
        simple.ColorBy(rep, ("POINTS", array))
        lut = simple.GetColorTransferFunction(array)
        lut.ApplyPreset("Viridis (matplotlib)", True)
        rep.RescaleTransferFunctionToDataRange(False, True)
        rep.SetScalarBarVisibility(qview, True)
        bar = simple.GetScalarBar(lut, qview)
        bar.Title, bar.ComponentTitle = title, ""
        bar.Orientation, bar.WindowLocation = "Horizontal", "Lower Center"
        bar.ScalarBarLength, bar.TitleFontSize, bar.LabelFontSize = 0.6, 12, 11
        bar.RangeLabelFormat = "%-#.2g"
        qview.InteractionMode = "2D"
        qview.OrientationAxesVisibility = 0
        _frame_above_legend(qview)
        simple.Render(qview)
    table = views[-1]
    simple.Show(proxy, table)
    table.FieldAssociation = "Field Data"
    if data is not None:  # only the per-structure columns
        table.HiddenColumnLabels = _field_names(data)
    return {title: v for (_, title), v in zip(QUALITY_MAPS, views, strict=False)}


def open_quality_views(view):
    """The 2-D views and the spreadsheet beside ``view``: its layout cell is split on first use.

    The actions call this before they copy the view's camera and aspect ratio into a filter:
    the split halves the 3-D view's width (at once in the GUI), and the filter's image must
    have the aspect the view has when the maps are beside it.
    """
    return _quality_views(_simple().GetLayout(view), view)


def _frame_above_legend(view):
    """Fit the map in the upper part of a 2-D view, clear of the legend at the bottom."""
    _simple().ResetCamera(view)
    camera = view.GetActiveCamera()
    scale = camera.GetParallelScale() * 1.3
    (fx, fy, fz), (px, py, pz) = camera.GetFocalPoint(), camera.GetPosition()
    shift = 0.3 * scale  # the camera down: the map up
    camera.SetFocalPoint(fx, fy - shift, fz)
    camera.SetPosition(px, py - shift, pz)
    camera.SetParallelScale(scale)


def _quality_views(layout, view):
    """The 2-D views and the spreadsheet beside ``view`` (created and placed on first use)."""
    simple = _simple()
    names = [QUALITY_PREFIX + title for _, title in QUALITY_MAPS] + [TABLE_VIEW]
    found = [simple.FindView(n) for n in names]
    if all(v is not None for v in found):
        return found
    # the right half of the view's cell, as a 2 x 2 grid: the three maps, then the table
    cell = layout.GetViewLocation(view)
    layout.SplitHorizontal(cell, 0.5)
    right = 2 * cell + 2
    layout.SplitVertical(right, 0.5)
    cells = []
    for row in (2 * right + 1, 2 * right + 2):
        layout.SplitHorizontal(row, 0.5)
        cells += [2 * row + 1, 2 * row + 2]
    views = []
    for name, where in zip(names, cells, strict=True):
        kind = "SpreadSheetView" if name == TABLE_VIEW else "RenderView"
        v = simple.CreateView(kind)
        simple.RenameView(name, v)
        simple.AssignViewToLayout(view=v, layout=layout, hint=where)
        views.append(v)
    return views
