"""The optimised light in a ParaView render view (*Optimise this view*, *Undo*).

The engine shades with one white light, ``rendering.light_direction`` in camera coordinates
(``(0, 0, 1)``: the headlight), ambient = ``ambient`` x colour.  ParaView 5.11's render view
has its *Light Kit* (``UseLight``) and extra light proxies (``AdditionalLights``,
``paraview.simple.AddLight``; ``Coords`` ``"Headlight"``, ``"Camera"`` or ``"Scene"``).
:func:`apply_light` switches the kit off and gives the view one light of its own
(:data:`LIGHT_NAME`), either

* ``"headlight"``: ``Coords="Headlight"``; the GPU volume mapper's one-headlight shader adds
  ``ambient`` x colour as the engine does, but the light follows the view direction; or
* ``"optimised direction"``: ``Coords="Camera"`` at the optimised direction; exact direction,
  but with any light other than a single headlight the mapper's shader adds ``ambient`` x
  the lights' ambient colour (not x the colour; ParaView's light proxies have none: 0), so
  the ambient term is lost,

whichever renders closer to the engine's image (SSIM, measured by the caller), and with the
other extra lights switched off.  :func:`save_lights` / :func:`restore_lights` are *Undo*'s.
"""

__all__ = ["LIGHT_NAME", "apply_light", "restore_lights", "save_lights"]

LIGHT_NAME = "DVR Perception light"
_KEYS = ("Enable", "Coords", "Position", "FocalPoint", "Intensity", "Type")


def _values(light):
    return {k: light.GetPropertyValue(k) for k in _KEYS}


def save_lights(view):
    """The view's light set-up (kit switch, extra lights and their settings) for Undo."""
    lights = list(view.AdditionalLights)
    return {"UseLight": int(view.UseLight), "lights": lights,
            "values": [_values(light) for light in lights]}  # fmt: skip


def restore_lights(view, saved):
    """Put back what :func:`save_lights` saved; a light added since is removed."""
    from paraview import simple

    for light in list(view.AdditionalLights):
        if all(light != old for old in saved["lights"]):
            simple.RemoveLight(light)
    view.AdditionalLights = saved["lights"]
    for light, values in zip(saved["lights"], saved["values"], strict=True):
        for key, value in values.items():
            light.SetPropertyWithName(key, list(value) if isinstance(value, tuple) else value)
    view.UseLight = saved["UseLight"]


def _own_light(view):
    from paraview import simple

    for light in view.AdditionalLights:
        if light.Name == LIGHT_NAME:
            return light
    light = simple.AddLight(view=view)
    light.Name = LIGHT_NAME
    return light


def _set(light, kind, direction, intensity):
    light.Type = "Directional"
    light.Intensity = float(intensity)
    light.DiffuseColor = [1.0, 1.0, 1.0]
    if kind == "headlight":
        light.Coords = "Headlight"
    else:
        light.Coords = "Camera"
        light.Position = [float(c) for c in direction]
        light.FocalPoint = [0.0, 0.0, 0.0]


def apply_light(view, spec, measure):
    """Light ``view`` as the engine lights ``spec``; returns ``(kind, ssims)``.

    Parameters
    ----------
    view : proxy
        The render view.
    spec : StructureSpec
        The optimised spec (``rendering.light_direction``, ``light_intensity``).
    measure : callable
        ``measure()`` -> SSIM of the view's rendering now vs the engine's image.

    Returns
    -------
    tuple
        The kind kept (``"headlight"`` or ``"optimised direction"``) and the SSIM of each
        kind tried (the optimised direction is not tried when it is the headlight's).
    """
    import numpy as np

    direction = np.asarray(spec.rendering.light_direction, float)
    direction = direction / np.linalg.norm(direction)
    light = _own_light(view)
    for other in view.AdditionalLights:
        if other != light:
            other.Enable = 0
    light.Enable = 1
    view.UseLight = 0
    kinds = ["headlight"]
    if float(direction @ (0.0, 0.0, 1.0)) < 1.0 - 1e-9:
        kinds.append("optimised direction")
    ssims = {}
    for kind in kinds:
        _set(light, kind, direction, spec.rendering.light_intensity)
        ssims[kind] = measure()
    best = max(kinds, key=lambda k: ssims[k])
    if best != kinds[-1]:
        _set(light, best, direction, spec.rendering.light_intensity)
    return best, ssims
