"""Apply the result of *Optimize Transfer Function* to a volume display in ParaView.

A helper for pvpython, pvbatch and the GUI's *Python Shell* (or as a macro: *Macros > Import
new macro...*, then select the optimiser's output and run it)::

    import sys; sys.path.insert(0, "/path/to/repo/plugin")
    from apply_result import apply_optimized
    opt = OptimizeTransferFunction(Input=reader, SpecFile="state_files/neghip.json")
    display = Show(reader, view); display.SetRepresentationType("Volume")
    apply_optimized(opt, display, preset_path="neghip_optimized.json")

**One material per representation.**  The optimiser gives every structure its own ambient,
diffuse, specular and specular power, but a ParaView volume representation has a single
material (``Ambient``, ``Diffuse``, ``Specular``, ``SpecularPower``).  ``apply_optimized``
uses the material of the *most important* structure (highest ``importance``; the first one
on ties) for the whole volume; the other structures' lighting and the optimised light
direction are not applied here (the toolbar's actions also set the view's light:
``view_light.py``).  The colour and opacity transfer functions are exact.
"""

import json
import os
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
if HERE not in sys.path:
    sys.path.insert(0, HERE)
import dvr_boot  # noqa: E402

dvr_boot.bind()  # the package holding this folder, its site-packages kept off the path

from dvr_perception._paraview_compat import setup as _setup  # noqa: E402

_setup()  # .pvdeps on sys.path and the numpy/inspect shims (idempotent)

__all__ = ["apply_optimized", "lighting_structure", "optimized_spec"]


def optimized_spec(source_or_spec):
    """The optimised ``StructureSpec`` of an optimiser output, or of a spec JSON/dict.

    ``source_or_spec`` is a ParaView proxy (the *Optimize Transfer Function* filter; its
    output is fetched), a VTK data object with the field data, a JSON string or a dict.
    """
    from dvr_perception.errors import DVRInputError
    from dvr_perception.structures.io import spec_from_dict

    obj = source_or_spec
    if isinstance(obj, str):
        try:
            obj = json.loads(obj)
        except ValueError as exc:
            raise DVRInputError(f"optimised spec: not valid JSON ({exc})") from None
    elif not isinstance(obj, dict):
        if not hasattr(obj, "GetFieldData"):  # a proxy: fetch its output
            from paraview import servermanager

            obj = servermanager.Fetch(obj)
        arr = obj.GetFieldData().GetAbstractArray("optimized_spec_json")
        if arr is None or arr.GetNumberOfValues() < 1:
            raise DVRInputError(
                "no 'optimized_spec_json' in the field data (is this the output of "
                "Optimize Transfer Function, and did it run without errors?)"
            )
        obj = json.loads(arr.GetValue(0))
    return spec_from_dict(obj, source="optimised spec")


def lighting_structure(spec):
    """The structure whose material the single ParaView material takes (most important)."""
    return max(spec.structures, key=lambda s: s.importance)  # max keeps the first on ties


def apply_optimized(source_or_spec_json, volume_display, *, preset_path=None, preset_name=None):
    """Set a volume display's transfer functions and material from an optimised spec.

    Parameters
    ----------
    source_or_spec_json
        The *Optimize Transfer Function* proxy (its field data's ``optimized_spec_json`` is
        read), its fetched output, or the spec as a JSON string or dict.
    volume_display
        A representation shown as ``"Volume"`` and coloured by the volume's scalar array
        (``ColorBy(display, ("POINTS", name))``).
    preset_path : str, optional
        Also write the transfer functions as a ParaView preset JSON
        (``dvr_perception.export.save_paraview_preset``; *Choose Preset > Import*).
    preset_name : str, optional
        The preset's name (default: the file name without ``.json``).

    The colour lookup table gets ``RGBPoints`` and the opacity function ``Points`` equal to
    ``to_vtk_transfer_functions`` of the spec (the LUT's range is fixed: no automatic
    rescaling).  ParaView has one material per representation, so ``Ambient``, ``Diffuse``,
    ``Specular`` and ``SpecularPower`` come from the most important structure
    (:func:`lighting_structure`); ``Shade`` follows the spec's ``rendering.shade``.

    Returns the applied ``StructureSpec``.
    """
    from batch_measure import data_range, set_transfer_functions
    from paraview import simple as pvs

    spec = optimized_spec(source_or_spec_json)
    array = volume_display.ColorArrayName[1]
    if not array:
        raise ValueError("the volume display is not coloured by an array (use ColorBy first)")
    set_transfer_functions(pvs, volume_display, array, spec)
    light = lighting_structure(spec).lighting
    volume_display.Ambient, volume_display.Diffuse = light.ambient, light.diffuse
    volume_display.Specular = light.specular
    volume_display.SpecularPower = light.specular_power
    volume_display.Shade = int(bool(spec.rendering.shade))
    if preset_path is not None:
        from dvr_perception.export import save_paraview_preset

        save_paraview_preset(
            spec, preset_path, name=preset_name, scalar_range=data_range(volume_display, array)
        )
    return spec
