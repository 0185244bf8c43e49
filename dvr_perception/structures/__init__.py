"""Structures: spec data model and JSON, transfer functions, automatic proposal."""

from dvr_perception.structures.spec import Lighting, RenderSettings, Structure, StructureSpec

__all__ = ["Lighting", "RenderSettings", "Structure", "StructureSpec"]
