"""The CUDA back end's host side: is it usable, device copies of the volumes, the walk.

Nothing here imports ``numba.cuda`` until a CUDA analysis is asked for (or ``auto`` looks for
a device once per process).  ``backend="cuda"`` needs numba's CUDA target (the ``gpu`` extra,
``numba-cuda``) and a CUDA device, or numba's CUDA simulator (``NUMBA_ENABLE_CUDASIM=1``,
tests only: every thread runs in Python); ``auto`` takes it only with a real device, never
under the simulator, and not with ``DVR_PERCEPTION_NO_CUDA`` set.
"""

from __future__ import annotations

import contextlib
import os
import sys
import threading
import warnings
import weakref

import numpy as np

from dvr_perception.errors import DVRInputError

__all__ = ["auto_usable", "kernels", "numpy_for_numba_cuda", "to_device"]

_INSTALL = "pip install 'dvr-perception[gpu]'"
_LOCK = threading.Lock()
_AUTO: list = []  # [bool] once looked up
_DEVICE: dict = {}  # id(host array) -> (weakref, pointer, shape, dtype, device array)
#: Host arrays kept on the device between analyses (the derived volumes of the last volumes).
_KEEP = 12


def numpy_for_numba_cuda() -> None:
    """Give numpy back ``row_stack`` (removed in numpy 2.5), which numba.cuda still uses.

    Called before ``numba.cuda`` is imported; an alias of :func:`numpy.vstack`, only where
    the attribute is missing.
    """
    if "row_stack" not in vars(np):
        setattr(np, "row_stack", np.vstack)  # noqa: B010


def _simulated() -> bool:
    from numba.core import config

    return bool(config.ENABLE_CUDASIM)


def kernels():
    """Return :mod:`dvr_perception.rays._cuda_kernels` for ``backend="cuda"``.

    Raises
    ------
    DVRInputError
        numba's CUDA target cannot be imported, or no CUDA device (nor the simulator) is
        available: one line saying what to install or check.
    """
    if os.environ.get("DVR_PERCEPTION_NO_NUMBA", "").strip() not in ("", "0"):
        raise DVRInputError(
            "backend: 'cuda' was requested but DVR_PERCEPTION_NO_NUMBA is set (the CUDA back "
            "end compiles with numba); unset it or use backend='numpy'"
        )
    numpy_for_numba_cuda()
    try:
        from numba import cuda

        from dvr_perception.rays import _cuda_kernels as ck
    except ImportError as exc:
        raise DVRInputError(
            f"backend: 'cuda' was requested but numba's CUDA target cannot be imported ({exc}); "
            f"install the GPU extra ({_INSTALL}) or use backend='auto'"
        ) from None
    if not _simulated() and getattr(cuda, "implementation", "") != "NVIDIA":
        raise DVRInputError(
            "backend: 'cuda' needs the numba-cuda package (numba's built-in CUDA target cannot "
            f"compile the walk); install the GPU extra ({_INSTALL}) or use backend='auto'"
        )
    try:
        ok = bool(cuda.is_available())
    except Exception:  # a broken driver installation: the same answer as no device
        ok = False
    if not ok:
        raise DVRInputError(
            "backend: 'cuda' was requested but no CUDA device is available "
            f"(numba.cuda.is_available() is False: no NVIDIA GPU, driver or CUDA libraries; "
            f"{_INSTALL} installs the libraries); use backend='auto' or 'numba'"
        )
    return ck


def auto_usable() -> bool:
    """Whether ``backend="auto"`` takes the CUDA back end (a real device; looked up once)."""
    if os.environ.get("DVR_PERCEPTION_NO_CUDA", "").strip() not in ("", "0"):
        return False
    if os.environ.get("DVR_PERCEPTION_NO_NUMBA", "").strip() not in ("", "0"):
        return False
    with _LOCK:
        if not _AUTO:
            _AUTO.append(_look_for_device())
        return _AUTO[0]


def _no_nvidia_driver() -> bool:
    """Return True where the platform shows no NVIDIA driver (Linux: no ``/dev/nvidiactl``).

    Saves importing ``numba.cuda`` (0.1-0.2 s) on machines without a GPU; elsewhere numba
    asks the driver.
    """
    if not sys.platform.startswith("linux"):
        return False
    return not (os.path.exists("/dev/nvidiactl") or os.path.exists("/proc/driver/nvidia"))


def _look_for_device() -> bool:
    try:
        if _no_nvidia_driver() or _simulated():
            return False
        numpy_for_numba_cuda()
        from numba import cuda

        if getattr(cuda, "implementation", "") != "NVIDIA" or not cuda.is_available():
            return False
        import dvr_perception.rays._cuda_kernels  # noqa: F401  (importable, e.g. numba-cuda)
    except Exception:  # no CUDA target, no driver: the CPU it is
        return False
    return True


def to_device(a: np.ndarray, keep: bool = False):
    """Return a device copy of ``a``; ``keep``: reuse it while ``a`` lives (read-only volumes).

    The derived volumes of :mod:`~dvr_perception.rays._grid` are memoised per volume, so the
    same host array comes back analysis after analysis: it is copied to the device once.
    """
    from numba import cuda

    a = np.ascontiguousarray(a)
    if not keep:
        return cuda.to_device(a)
    key = id(a)
    with _LOCK:
        hit = _DEVICE.get(key)
        if hit is not None and hit[0]() is a and hit[1:4] == (a.ctypes.data, a.shape, a.dtype.str):
            return hit[4]
    dev = cuda.to_device(a)
    with _LOCK:
        for k in [k for k, v in _DEVICE.items() if v[0]() is None]:
            _DEVICE.pop(k, None)
        while len(_DEVICE) >= _KEEP:
            _DEVICE.pop(next(iter(_DEVICE)))
        _DEVICE[key] = (weakref.ref(a), a.ctypes.data, a.shape, a.dtype.str, dev)
    return dev


@contextlib.contextmanager
def quiet_launch():
    """Launch kernels without numba's performance warnings (low occupancy on small images).

    A 12 x 10 image is a grid of two blocks: numba-cuda warns that the GPU is under-used,
    which is true and not the user's concern (and an error where warnings are errors).
    """
    from numba.core.errors import NumbaPerformanceWarning

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NumbaPerformanceWarning)
        yield


def free_bytes() -> int | None:
    """Free memory of the current CUDA device in bytes (None where it cannot be asked)."""
    try:
        from numba import cuda

        return int(cuda.current_context().get_memory_info()[0])
    except Exception:
        return None


def check_fits(need: int) -> None:
    """Raise :class:`DVRInputError` when ``need`` bytes exceed the device's free memory."""
    free = free_bytes()
    if free is not None and need > free:
        raise DVRInputError(
            f"backend: the cuda analysis needs {need / 2**30:.2f} GiB on the GPU but "
            f"{free / 2**30:.2f} GiB are free; use backend='numba' (bricked), build_cache=False "
            "or a smaller image"
        )
