"""PyVista front end: show exactly what our engine computes, per-structure lighting included.

* :func:`add_structures` / :func:`apply` put a volume with a
  :class:`~dvr_perception.structures.spec.StructureSpec` into a :class:`pyvista.Plotter` and
  update it in place (e.g. at every optimisation step);
* :func:`camera_from_plotter` / :func:`set_plotter_camera` exchange cameras;
* :func:`render_plotter` and :func:`before_after` return off-screen screenshots;
* :func:`add_quality_map` overlays a measure image;
* :func:`plot_visibility_histograms` and :func:`plot_convergence` draw matplotlib figures.

This package is a front end: unlike the core it imports ``pyvista`` and ``vtkmodules``
directly (lazily, inside the functions, except for type-free helpers).
"""

from dvr_perception.plotting._structure_volume import (
    MAX_MATERIALS,
    StructureVolume,
    add_structures,
    apply,
    material_groups,
)
from dvr_perception.plotting.camera import camera_from_plotter, set_plotter_camera
from dvr_perception.plotting.charts import plot_convergence, plot_visibility_histograms
from dvr_perception.plotting.overlay import QualityOverlay, add_quality_map
from dvr_perception.plotting.render import before_after, render_plotter

__all__ = [
    "MAX_MATERIALS",
    "QualityOverlay",
    "StructureVolume",
    "add_quality_map",
    "add_structures",
    "apply",
    "before_after",
    "camera_from_plotter",
    "material_groups",
    "plot_convergence",
    "plot_visibility_histograms",
    "render_plotter",
    "set_plotter_camera",
]
