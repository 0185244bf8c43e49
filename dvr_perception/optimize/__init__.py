"""Perception-driven optimisation of the rendering parameters (paper, Sec. 5-6).

:func:`optimize` is the front door: it minimises ``E = w_v E_v + w_s E_s + w_t E_t`` (Eq. 12) over
the rendering parameters in stages -- opacity (visibility leads; SLSQP on exact gradients of ``E_v``
and coverage, with annealing restarts), lighting (shape leads), colour (transparency leads) -- with
conjugate gradients on finite-difference gradients and simulated-annealing moves, optionally inside
a region (the lens of Sec. 6) and over several views. It returns an
:class:`~.results.OptimizationResult`; callbacks receive :class:`~.results.IntermediateResult`
copies. Stages are classes in the :data:`~.stages.STAGES` registry
(:func:`~.stages.register_stage`).
"""

from dvr_perception.optimize.core import DEFAULT_RESOLUTION, optimize
from dvr_perception.optimize.results import (
    STATUS_MESSAGES,
    IntermediateResult,
    OptimizationResult,
    StageRecord,
)
from dvr_perception.optimize.stages import (
    STAGES,
    ColourStage,
    LightingStage,
    OpacityStage,
    Stage,
    register_stage,
)

__all__ = [
    "DEFAULT_RESOLUTION",
    "STAGES",
    "STATUS_MESSAGES",
    "ColourStage",
    "IntermediateResult",
    "LightingStage",
    "OpacityStage",
    "OptimizationResult",
    "Stage",
    "StageRecord",
    "optimize",
    "register_stage",
]

# ``dvr_perception.optimize(volume, spec, camera)`` calls :func:`optimize` (the top-level API)
import sys

from dvr_perception import _CallableModule

sys.modules[__name__].__class__ = _CallableModule
