"""The CUDA back end's host side: is it usable, device copies of the volumes, the walk.

Nothing here imports ``numba.cuda`` until a CUDA analysis is asked for (or ``auto`` looks for
a device once per process).  ``backend="cuda"`` needs numba's CUDA target (the ``gpu`` extra,
``numba-cuda``) and a CUDA device, or numba's CUDA simulator (``NUMBA_ENABLE_CUDASIM=1``,
tests only: every thread runs in Python); ``auto`` takes it only with a real device, never
under the simulator, and not with ``DVR_PERCEPTION_NO_CUDA`` set.

What does not change between analyses stays on the device, so that an analysis pays for its
walk and its outputs only: the derived volumes while the volume lives (:func:`to_device`),
the rays of the last cameras (:func:`rays_for`), the small tables by content (:func:`table`)
and the per-ray work arrays of the last analysis (:func:`scratch`).
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

__all__ = [
    "WORK_LOCK",
    "auto_usable",
    "kernels",
    "numpy_for_numba_cuda",
    "rays_for",
    "scratch",
    "table",
    "to_device",
]

_INSTALL = "pip install 'dvr-perception[gpu]'"
_LOCK = threading.Lock()
_AUTO: list = []  # [bool] once looked up
#: pool -> {id(host array): (weakref, pointer, shape, dtype, device array)}, least recent first
_DEVICE: dict = {"volume": {}, "rays": {}}
#: Host arrays kept on the device between analyses, per pool: the derived volumes of the last
#: volumes, and the rays of the last cameras (:func:`rays_for`).
_KEEP = {"volume": 12, "rays": 20}
_TABLES: dict = {}  # (dtype, shape, bytes) -> device array: small read-only tables
_KEEP_TABLES = 64
_RAYS: dict = {}  # camera_pack bytes -> ray set (engine._segments' dict), least recent first
_KEEP_RAYS = 4
_KEEP_RAYS_BYTES = 1 << 29  # and at most 512 MiB of them (2048^2 rays are 280 MB)
_SCRATCH: dict = {}  # name -> device array reused by the analysis holding WORK_LOCK
#: Held by the analysis whose outputs live in :func:`scratch` arrays until they are copied back.
WORK_LOCK = threading.Lock()


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


def to_device(a: np.ndarray, keep: bool = False, pool: str = "volume"):
    """Return a device copy of ``a``; ``keep``: reuse it while ``a`` lives (read-only arrays).

    The derived volumes of :mod:`~dvr_perception.rays._grid` are memoised per volume, and the
    rays per camera (:func:`rays_for`), so the same host array comes back analysis after
    analysis: it is copied to the device once.  ``pool`` (``"volume"`` or ``"rays"``): which
    of the two least-recently-used stores keeps it, so that new cameras do not push the
    volumes off the device.
    """
    from numba import cuda

    a = np.ascontiguousarray(a)
    if not keep:
        return cuda.to_device(a)
    key = id(a)
    store = _DEVICE[pool]
    with _LOCK:
        hit = store.pop(key, None)
        if hit is not None and hit[0]() is a and hit[1:4] == (a.ctypes.data, a.shape, a.dtype.str):
            store[key] = hit  # most recent last
            return hit[4]
    dev = cuda.to_device(a)
    with _LOCK:
        for k in [k for k, v in store.items() if v[0]() is None]:
            store.pop(k, None)
        while len(store) >= _KEEP[pool]:
            store.pop(next(iter(store)))
        store[key] = (weakref.ref(a), a.ctypes.data, a.shape, a.dtype.str, dev)
    return dev


def table(a: np.ndarray):
    """Return a device copy of the small read-only table ``a``, reused while its bytes recur.

    The per-analysis tables (opacities, colours, light, shading table, ...) are a few
    kilobytes: keyed by their content, an optimisation that changes one opacity uploads only
    the tables that changed.  Kernels never write them.
    """
    from numba import cuda

    a = np.ascontiguousarray(a)
    key = (a.dtype.str, a.shape, a.tobytes())
    with _LOCK:
        hit = _TABLES.pop(key, None)
        if hit is not None:
            _TABLES[key] = hit
            return hit
    dev = cuda.to_device(a)
    with _LOCK:
        while len(_TABLES) >= _KEEP_TABLES:
            _TABLES.pop(next(iter(_TABLES)))
        _TABLES[key] = dev
    return dev


def rays_for(pack: np.ndarray, make):
    """Return the ray set of camera pack ``pack``, made by ``make()`` once per camera.

    ``pack`` (:func:`~dvr_perception.rays._grid.camera_pack`) determines the rays entirely
    (camera, volume geometry, sample distance), so an analysis with the same camera (every
    evaluation of an optimisation, every frame of a benchmark) reuses the rays and their device
    copies (:func:`to_device` with ``pool="rays"``).  The arrays are shared: not to be written.
    ``total`` is added (the sum of the sample counts), and the first analysis that builds a
    cache adds ``base`` (their exclusive sum: where each ray's entries start on the device).
    """
    key = np.ascontiguousarray(pack, np.float64).tobytes()
    with _LOCK:
        hit = _RAYS.pop(key, None)
        if hit is not None:
            _RAYS[key] = hit
            return hit
    seg = make()
    seg["total"] = int(seg["n"].sum())
    size = sum(seg[q].nbytes for q in ("a", "b", "t", "n"))
    with _LOCK:
        held = sum(v["a"].nbytes * 2 + v["t"].nbytes + v["n"].nbytes for v in _RAYS.values())
        while _RAYS and (len(_RAYS) >= _KEEP_RAYS or held + size > _KEEP_RAYS_BYTES):
            old = _RAYS.pop(next(iter(_RAYS)))
            held -= old["a"].nbytes * 2 + old["t"].nbytes + old["n"].nbytes
        _RAYS[key] = seg
    return seg


def scratch(name: str, shape, dtype, mine: bool):
    """Return a device array of ``shape`` and ``dtype`` (contents undefined).

    ``mine`` (the caller holds :data:`WORK_LOCK`): the array of the last analysis under
    ``name`` when its shape and type match (no allocation, no free per analysis), else a new
    one kept for the next; otherwise always a new one.
    """
    from numba import cuda

    shape = tuple(int(v) for v in (shape if isinstance(shape, tuple) else (shape,)))
    dtype = np.dtype(dtype)
    if not mine:
        return cuda.device_array(shape, dtype)
    hit = _SCRATCH.get(name)
    if hit is not None and hit.shape == shape and hit.dtype == dtype:
        return hit
    _SCRATCH.pop(name, None)  # freed before the new one is made
    dev = cuda.device_array(shape, dtype)
    _SCRATCH[name] = dev
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
    """Raise :class:`DVRInputError` when ``need`` bytes exceed the device's free memory.

    The work arrays kept from the last analysis (:func:`scratch`) count as free: they are
    reused or replaced.
    """
    free = free_bytes()
    if free is not None:
        free += sum(int(getattr(a, "nbytes", 0)) for a in list(_SCRATCH.values()))
    if free is not None and need > free:
        raise DVRInputError(
            f"backend: the cuda analysis needs {need / 2**30:.2f} GiB on the GPU but "
            f"{free / 2**30:.2f} GiB are free; use backend='numba' (bricked), build_cache=False "
            "or a smaller image"
        )
