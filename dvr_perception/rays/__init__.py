"""Rays: cameras and the ray-analysis engine."""

from dvr_perception.rays.camera import Camera, parse_view
from dvr_perception.rays.engine import RayAnalysis, RayCache, analyze, reevaluate

__all__ = ["Camera", "RayAnalysis", "RayCache", "analyze", "parse_view", "reevaluate"]
