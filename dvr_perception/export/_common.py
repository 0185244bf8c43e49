"""Shared helpers of the exporters: intensity-only check and VTK transfer-function nodes."""

from __future__ import annotations

from dvr_perception.errors import DVRInputError
from dvr_perception.export.vtk import to_vtk_transfer_functions
from dvr_perception.structures.spec import StructureSpec


def check_intensity_spec(spec, what: str) -> None:
    """Raise :class:`DVRInputError` unless ``spec`` is a spec of range structures only."""
    if not isinstance(spec, StructureSpec):
        raise DVRInputError(f"{what}: spec must be a StructureSpec, got {type(spec).__name__}")
    labels = [s.name for s in spec.structures if s.range is None]
    if labels:
        raise DVRInputError(
            f"{what}: structure(s) {', '.join(map(repr, labels))} are label structures; "
            "this format maps intensities to colour and opacity, so every structure needs an "
            "intensity 'range'"
        )


def transfer_nodes(
    spec, opacities, samples=None, scalar_range=None
) -> tuple[list[list[float]], list[list[float]]]:
    """Nodes of the VTK functions built by ``to_vtk_transfer_functions`` (with ``samples``).

    Returns
    -------
    color : list of [x, r, g, b, midpoint, sharpness]
    opacity : list of [x, y, midpoint, sharpness]
    """
    ctf, otf = to_vtk_transfer_functions(
        spec, opacities=opacities, samples=samples, scalar_range=scalar_range
    )
    color, opacity = [], []
    for i in range(ctf.GetSize()):
        node = [0.0] * 6
        ctf.GetNodeValue(i, node)
        color.append([float(v) for v in node])
    for i in range(otf.GetSize()):
        node = [0.0] * 4
        otf.GetNodeValue(i, node)
        opacity.append([float(v) for v in node])
    return color, opacity
