"""Shared helpers of the exporters: intensity-only check and VTK transfer-function nodes.

The nodes are computed without VTK (importing VTK's rendering module costs about a tenth of a
second, which ``optimize`` need not pay to write its presets): :func:`transfer_nodes` adds the
points of :func:`~dvr_perception.export.vtk.transfer_points` the way VTK's ``AddPoint`` and
``AddRGBPoint`` do, so the lists equal what ``GetNodeValue`` reads from the VTK functions.
"""

from __future__ import annotations

from dvr_perception.errors import DVRInputError
from dvr_perception.export.vtk import transfer_points
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
    color, opacity = transfer_points(
        spec, opacities=opacities, samples=samples, scalar_range=scalar_range
    )
    return _vtk_nodes(color), _vtk_nodes(opacity)


#: The midpoint and sharpness VTK gives a point added without them.
_MIDPOINT, _SHARPNESS = 0.5, 0.0


def _vtk_nodes(points) -> list[list[float]]:
    """Return the nodes a VTK function holds after adding ``points`` in turn.

    As VTK does (duplicate scalars not allowed, its default): a point replaces the node
    already at its ``x``, then the nodes are sorted by ``x``; each node is the point followed
    by the default midpoint and sharpness.

    Examples
    --------
    >>> _vtk_nodes([(2.0, 0.5), (1.0, 0.0), (2.0, 1.0)])
    [[1.0, 0.0, 0.5, 0.0], [2.0, 1.0, 0.5, 0.0]]
    """
    nodes: list[list[float]] = []
    for point in points:
        x = float(point[0])
        nodes = [n for n in nodes if n[0] != x]
        nodes.append([x, *(float(v) for v in point[1:]), _MIDPOINT, _SHARPNESS])
        nodes.sort(key=lambda n: n[0])
    return nodes
