"""The MPI driver: the measures and the optimiser over ParaView's MPI ranks.

Above the optimiser in the layering (it drives :func:`~dvr_perception.optimize.optimize` and
the measures); the ray walk over the ranks it builds on is :mod:`dvr_perception.rays.ranks`.
"""

from dvr_perception.distributed.ranks import RankCache, RankSession, optimize_in_threads, warm_up

__all__ = ["RankCache", "RankSession", "optimize_in_threads", "warm_up"]
