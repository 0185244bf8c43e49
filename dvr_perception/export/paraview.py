"""ParaView colour-map + opacity preset (the JSON read by *Choose Preset -> Import*).

A ParaView preset file is a JSON list of preset objects.  Each object used here has

* ``"Name"``: the name shown in the preset dialog;
* ``"ColorSpace"``: ``"RGB"`` (interpolate colours linearly in RGB, as VTK does by default);
* ``"RGBPoints"``: flat ``[x0, r0, g0, b0, x1, r1, g1, b1, ...]``;
* ``"Points"``: flat ``[x0, o0, midpoint0, sharpness0, ...]``, the opacity function
  (ParaView's ``PiecewiseFunction`` node layout; its presence marks a preset with opacities);
* ``"Creator"``: ``"dvr_perception"`` (informational).

The points are the nodes of :func:`dvr_perception.export.vtk.to_vtk_transfer_functions`
for the same spec with ``samples=GPU_TABLE_SAMPLES`` (no two nodes closer than 1/4096 of their
span, so ParaView's GPU lookup texture fits OpenGL's limit without a VTK warning), so ParaView
reproduces its trapezoids to within that spacing.  ParaView rescales a preset
to the data range by default; keep the preset's own range (the dialog's option to use the preset
range) so that the structure boundaries stay at their intensities.
"""

from __future__ import annotations

from pathlib import Path

from dvr_perception._files import write_json
from dvr_perception.errors import DVRInputError
from dvr_perception.export._common import check_intensity_spec, transfer_nodes
from dvr_perception.export.vtk import GPU_TABLE_SAMPLES

__all__ = ["paraview_preset", "save_paraview_preset"]


def paraview_preset(spec, *, name: str | None = None, opacities=None, scalar_range=None) -> dict:
    """ParaView preset object (colour + opacity) equal to the spec's VTK transfer functions.

    Parameters
    ----------
    spec : StructureSpec
        Range structures only.
    name : str, optional
        Preset name (default ``"dvr_perception"``).
    opacities : array_like, optional
        One rendering opacity per structure (default: each structure's ``render_opacity``).
    scalar_range : (float, float), optional
        The data range the preset will be shown over; the nodes are kept 1/4096 of it apart
        too (``to_vtk_transfer_functions``' ``scalar_range``).

    Returns
    -------
    dict
        ``{"Name", "Creator", "ColorSpace", "RGBPoints", "Points"}`` (see the module docstring).

    Raises
    ------
    DVRInputError
        If ``spec`` has label structures, ``name`` is empty or an opacity is out of [0, 1].

    Examples
    --------
    >>> from dvr_perception.structures import Structure, StructureSpec
    >>> spec = StructureSpec((Structure("bone", 0.8, (1, 1, 1), range=(100, 200), edge=0.1),))
    >>> preset = paraview_preset(spec, name="bone")
    >>> preset["Points"][:8]
    [100.0, 0.0, 0.5, 0.0, 110.0, 0.8, 0.5, 0.0]
    """
    check_intensity_spec(spec, "ParaView preset")
    label = "dvr_perception" if name is None else name
    if not isinstance(label, str) or not label.strip():
        raise DVRInputError(f"name must be a non-empty string, got {name!r}")
    color, opacity = transfer_nodes(spec, opacities, GPU_TABLE_SAMPLES, scalar_range)
    return {
        "Name": label,
        "Creator": "dvr_perception",
        "ColorSpace": "RGB",
        "RGBPoints": [v for node in color for v in node[:4]],
        "Points": [v for node in opacity for v in node],
    }


def save_paraview_preset(
    spec, path, *, name: str | None = None, opacities=None, scalar_range=None
) -> Path:
    """Write :func:`paraview_preset` as a ParaView preset file (a one-element list, atomically).

    Parameters
    ----------
    spec : StructureSpec
        Range structures only.
    path : str or os.PathLike
        Output ``.json`` file; its directory must exist.
    name : str, optional
        Preset name (default: the file name without ``.json``).
    opacities : array_like, optional
        One rendering opacity per structure.
    scalar_range : (float, float), optional
        The data range the preset will be shown over (see :func:`paraview_preset`).

    Returns
    -------
    pathlib.Path
        The written path.

    Examples
    --------
    >>> import json, tempfile
    >>> from dvr_perception.structures import Structure, StructureSpec
    >>> spec = StructureSpec((Structure("bone", 0.8, (1, 1, 1), range=(100, 200)),))
    >>> out = save_paraview_preset(spec, Path(tempfile.mkdtemp()) / "bone.json")
    >>> json.loads(out.read_text())[0]["Name"]
    'bone'
    """
    label = Path(path).name.removesuffix(".json") if name is None else name
    preset = paraview_preset(spec, name=label, opacities=opacities, scalar_range=scalar_range)
    return write_json(path, [preset])
