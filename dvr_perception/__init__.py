"""dvr_perception: perception-based transparency optimisation for direct volume rendering.

The pipeline reads as the sub-packages: :mod:`~dvr_perception.volume` (I/O, phantom) →
:mod:`~dvr_perception.structures` (spec, transfer functions) → :mod:`~dvr_perception.rays`
(camera, ray-analysis engine) → :mod:`~dvr_perception.measures` → optimisation → front ends
(:mod:`~dvr_perception.cli`, plotting, web app, ParaView plugin).
"""

__version__ = "0.1.0"
