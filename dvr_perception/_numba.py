"""Where the numba kernels come from: numba when it can be imported and is not switched off."""

from __future__ import annotations

import importlib
import os


def kernels(module: str):
    """Return the kernel module ``module`` (imported), or None without numba.

    None when numba cannot be imported or the environment variable
    ``DVR_PERCEPTION_NO_NUMBA`` is set to anything but ``""`` or ``"0"``; the callers then
    use their numpy code.
    """
    if os.environ.get("DVR_PERCEPTION_NO_NUMBA", "").strip() not in ("", "0"):
        return None
    try:
        return importlib.import_module(module)
    except ImportError:
        return None
