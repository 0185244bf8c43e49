"""The memory limit every step stays under: its default, its setting and its parsing.

The ground floor of the memory accounting: the volume readers (:mod:`dvr_perception.volume`)
refuse a file larger than the limit before reading it, and the ray analysis
(:mod:`dvr_perception.rays.memory`) plans whole or bricked runs against it.

The limit is, in order: the ``value`` given to :func:`limit`, :func:`set_limit` (the command
line's ``--memory-limit``), the environment variable ``DVR_PERCEPTION_MEMORY_LIMIT``
(:data:`ENV`) and :data:`DEFAULT_FRACTION` of the machine's physical memory.  Sizes are binary
(GB = 2**30 bytes).

The default is a quarter of the machine: the limit bounds the arrays of the analysis (the
volume, its derived volumes, caches and the memos kept between analyses,
:func:`dvr_perception.rays.memory.plan`), while the process also holds Python, numba and
VTK, VTK's renderer runs with its own copy of the volume, and the machine runs other
programs.  On a 24 GB machine (a 5.9 GB limit) a 512 x 512 x 452 CT is analysed whole and a
1024 x 1024 x 904 one (1.8 GB) in bricks, within a peak of 6 GB (issue 31; ``dvr-perception
bench --json`` reports ``peak_rss_mb``).
"""

from __future__ import annotations

import math
import os
import re

from dvr_perception.errors import DVRInputError

__all__ = [
    "DEFAULT_FRACTION",
    "ENV",
    "human_bytes",
    "limit",
    "machine_memory",
    "parse_size",
    "set_limit",
]

#: Share of the machine's memory an analysis may use by default (see the module docstring).
DEFAULT_FRACTION = 0.25
#: The environment variable holding the limit (``--memory-limit`` sets it for child processes).
ENV = "DVR_PERCEPTION_MEMORY_LIMIT"
_LIMIT: list[int | None] = [None]
_UNITS = {"": 1, "K": 2**10, "M": 2**20, "G": 2**30, "T": 2**40}


def parse_size(text, name: str = "--memory-limit") -> int:
    """Bytes of ``"8G"``, ``"512M"``, ``"1.5GB"`` or a plain number of bytes.

    Examples
    --------
    >>> parse_size("1.5G"), parse_size("512MiB"), parse_size(2097152)
    (1610612736, 536870912, 2097152)
    """
    text = str(text)
    m = re.fullmatch(r"\s*([0-9]{1,15}(?:\.[0-9]{0,15})?)\s*([KMGT]?)(?:I?B)?\s*", text, re.I)
    value = float(m.group(1)) * _UNITS[m.group(2).upper()] if m else math.nan
    if not (math.isfinite(value) and value >= 2**20):
        shown = repr(text) if len(text) <= 40 else f"{text[:30]!r}... ({len(text)} characters)"
        raise DVRInputError(
            f"{name}: expected a memory size of at least 1M such as 8G or 512M, got {shown}"
        )
    return int(value)


def machine_memory() -> int:
    """Bytes of physical memory."""
    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):  # pragma: no cover - not POSIX
        return 8 * 2**30


def set_limit(value) -> None:
    """Set this process's limit (bytes, or a size text); ``None`` restores the default."""
    _LIMIT[0] = None if value is None else parse_size(value)


def limit(value=None) -> int:
    """Return the memory limit in bytes (see the module docstring for the order)."""
    if value is not None:
        return parse_size(value, "memory_limit")
    if _LIMIT[0] is not None:
        return _LIMIT[0]
    env = os.environ.get(ENV, "").strip()
    if env:
        return parse_size(env, ENV)
    return int(DEFAULT_FRACTION * machine_memory())


def human_bytes(n: float) -> str:
    """``n`` bytes as ``"1.50 GB"`` (from 1 GB) or ``"512 MB"``.

    Examples
    --------
    >>> human_bytes(1.5 * 2**30), human_bytes(3 * 2**20)
    ('1.50 GB', '3 MB')
    """
    return f"{n / 2**30:.2f} GB" if n >= 2**30 else f"{n / 2**20:.0f} MB"
