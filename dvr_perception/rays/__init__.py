"""Rays: cameras and the ray-analysis engine."""

from dvr_perception.rays.camera import Camera, parse_view

__all__ = ["Camera", "parse_view"]
