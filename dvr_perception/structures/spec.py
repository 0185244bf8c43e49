"""Structures, lighting and rendering settings: the data model behind a spec JSON file.

Transfer-function semantics (shared by our engine and the VTK converters):

* A range structure ``[lo, hi]`` with edge fraction ``e`` has a trapezoidal **membership**
  ``m(v)``: 0 at ``lo``, rising linearly to 1 at ``lo + e*(hi-lo)``, 1 up to ``hi - e*(hi-lo)``,
  falling to 0 at ``hi``; 0 outside.  Ranges of different structures may touch but not overlap,
  so every intensity belongs to at most one structure.
* A label structure has ``m = 1`` on voxels whose label equals its id (nearest lookup).
* The scalar opacity of a sample of structure ``s`` is ``opacity_s * m(v)``, where the rendering
  opacity ``opacity_s`` starts at the importance and is what the optimiser changes.  Opacity is
  per ``opacity_unit_distance`` of ray length and corrected for the sample distance as VTK's
  ``ScalarOpacityUnitDistance`` does: ``a = 1 - (1 - opacity*m) ** (step / unit)``.
* The colour of a sample of ``s`` is ``color_s``; shading is Phong with the structure's lighting.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

__all__ = ["Lighting", "RenderSettings", "Structure", "StructureSpec"]

SPEC_VERSION = 1


@dataclass(frozen=True)
class Lighting:
    """Per-structure Phong material (VTK volume-property conventions)."""

    ambient: float = 0.2
    diffuse: float = 0.8
    specular: float = 0.2
    specular_power: float = 16.0


@dataclass(frozen=True)
class Structure:
    """One structure: an intensity range *or* a label id, with importance, colour and lighting.

    ``opacity`` is the rendering opacity; ``None`` means "equal to ``importance``".
    ``expected_opacity`` is the perceived opacity the transparency measure aims for; ``None``
    means "equal to ``importance``".
    """

    name: str
    importance: float
    color: tuple[float, float, float]
    range: tuple[float, float] | None = None
    label: int | None = None
    edge: float = 0.1
    lighting: Lighting = field(default_factory=Lighting)
    opacity: float | None = None
    expected_opacity: float | None = None

    @property
    def render_opacity(self) -> float:
        """The opacity used for rendering (``opacity`` or, if unset, ``importance``)."""
        return self.importance if self.opacity is None else self.opacity

    @property
    def target_opacity(self) -> float:
        """The opacity the transparency measure expects (``expected_opacity`` or importance)."""
        return self.importance if self.expected_opacity is None else self.expected_opacity


@dataclass(frozen=True)
class RenderSettings:
    """How the volume is rendered; ``None`` distances default to the smallest voxel spacing.

    ``light_direction`` is given in camera coordinates (x right, y up, z towards the viewer);
    ``(0, 0, 1)`` is VTK's default headlight.
    """

    shade: bool = True
    sample_distance: float | None = None
    opacity_unit_distance: float | None = None
    light_direction: tuple[float, float, float] = (0.0, 0.0, 1.0)
    light_intensity: float = 1.0


@dataclass(frozen=True)
class StructureSpec:
    """A versioned list of structures plus background colour and render settings."""

    structures: tuple[Structure, ...]
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rendering: RenderSettings = field(default_factory=RenderSettings)
    view: tuple[float, float, float] | None = None
    labels_file: str | None = None
    version: int = SPEC_VERSION

    @property
    def names(self) -> tuple[str, ...]:
        """Structure names in order (the index is the structure id used by the engine)."""
        return tuple(s.name for s in self.structures)

    def with_opacities(self, opacities) -> StructureSpec:
        """Return a copy whose structures have the given rendering opacities."""
        new = tuple(
            replace(s, opacity=float(o)) for s, o in zip(self.structures, opacities, strict=True)
        )
        return replace(self, structures=new)
