"""``--backend``: which ray-analysis back end the commands that analyse use."""

from __future__ import annotations

__all__ = ["BACKENDS", "add_backend_arg"]

#: As :data:`dvr_perception.rays.engine.BACKENDS` (tested equal; not imported here, so that
#: ``--help`` does not load the engine).
BACKENDS = ("auto", "numba", "numpy", "cuda")


def add_backend_arg(parser) -> None:
    """Declare ``--backend {auto,numba,numpy,cuda}`` (default ``auto``)."""
    parser.add_argument(
        "--backend",
        choices=BACKENDS,
        default="auto",
        help="ray-analysis back end: auto (the GPU when numba finds a CUDA device, else numba "
        "on the CPU), numba, numpy, or cuda (needs the gpu extra and an NVIDIA GPU) "
        "(default auto)",
    )
