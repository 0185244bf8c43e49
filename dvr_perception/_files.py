"""Atomic output files: PNG images, JSON documents and ``.npz`` buffer archives.

Every writer goes through :func:`atomic_path`: the data is written to a hidden temporary file
in the target's directory and moved over the target with :func:`os.replace` only when writing
succeeded, so an interrupted or failed write never leaves a partial file behind.
"""

from __future__ import annotations

import json
import math
import os
import secrets
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from dvr_perception import _vtk
from dvr_perception.errors import DVRInputError

__all__ = ["atomic_path", "json_ready", "read_png", "write_json", "write_npz", "write_png"]


@contextmanager
def atomic_path(path) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; move it onto ``path`` if the block succeeds.

    The temporary file does not exist when the block starts; the caller creates it.  If the
    block raises, the temporary file (if any) is removed and ``path`` is left untouched.

    Parameters
    ----------
    path : str or os.PathLike
        The final file.  Its directory must exist.

    Yields
    ------
    pathlib.Path
        A hidden file name in the same directory, with the same suffix as ``path``.

    Raises
    ------
    DVRInputError
        If the directory of ``path`` does not exist or ``path`` is a directory.

    Examples
    --------
    >>> import tempfile
    >>> target = Path(tempfile.mkdtemp()) / "hello.txt"
    >>> with atomic_path(target) as tmp:
    ...     _ = tmp.write_text("hi")
    >>> target.read_text()
    'hi'
    """
    final = Path(path)
    parent = final.parent
    if not parent.is_dir():
        raise DVRInputError(f"output file {final}: directory {parent} does not exist")
    if final.is_dir():
        raise DVRInputError(f"output file {final}: is a directory; expected a file name")
    tmp = parent / f".{final.name}.{secrets.token_hex(4)}.tmp{final.suffix}"
    try:
        yield tmp
        if not tmp.exists():
            raise OSError(f"output file {final}: nothing was written")
        os.replace(tmp, final)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _to_uint8_image(image) -> np.ndarray:
    arr = np.asarray(image)
    if arr.ndim != 3 or arr.shape[2] not in (3, 4) or arr.shape[0] < 1 or arr.shape[1] < 1:
        raise DVRInputError(
            f"write_png: image must have shape (height, width, 3 or 4), got {arr.shape}"
        )
    if arr.dtype == np.uint8:
        return np.ascontiguousarray(arr)
    if arr.dtype.kind not in "fb":
        raise DVRInputError(
            f"write_png: image must be uint8 or floating point in [0, 1], got dtype {arr.dtype}"
        )
    arr = arr.astype(np.float64)
    if not np.all(np.isfinite(arr)):
        raise DVRInputError("write_png: image contains NaN or infinite values")
    if arr.min() < -1e-6 or arr.max() > 1 + 1e-6:
        raise DVRInputError(
            f"write_png: float image values must lie in [0, 1], got range "
            f"[{arr.min():.4g}, {arr.max():.4g}]"
        )
    return np.round(np.clip(arr, 0.0, 1.0) * 255.0).astype(np.uint8)


def write_png(path, image) -> Path:
    """Write an RGB or RGBA image as a PNG file (atomically).

    Parameters
    ----------
    path : str or os.PathLike
        Output file.
    image : array_like
        ``(height, width, 3)`` or ``(height, width, 4)`` array, either ``uint8`` or floating
        point in ``[0, 1]``.  Row 0 is the **top** of the picture.

    Returns
    -------
    pathlib.Path
        The written path.

    Examples
    --------
    >>> import tempfile
    >>> out = Path(tempfile.mkdtemp()) / "red.png"
    >>> _ = write_png(out, np.tile([1.0, 0.0, 0.0], (2, 3, 1)))
    >>> read_png(out).shape
    (2, 3, 3)
    """
    pixels = _to_uint8_image(image)
    h, w, c = pixels.shape
    # VTK images start at the bottom row
    flat = np.ascontiguousarray(pixels[::-1]).reshape(h * w, c)
    img = _vtk.vtkImageData()
    img.SetDimensions(w, h, 1)
    vtk_arr = _vtk.numpy_to_vtk(flat, deep=True)
    vtk_arr.SetName("rgba" if c == 4 else "rgb")
    img.GetPointData().SetScalars(vtk_arr)
    with atomic_path(path) as tmp:
        writer = _vtk.vtkPNGWriter()
        writer.SetFileName(str(tmp))
        writer.SetInputData(img)
        writer.Write()
        if writer.GetErrorCode() != 0 or not tmp.is_file():
            raise OSError(
                f"output file {path}: could not write PNG (VTK error code {writer.GetErrorCode()})"
            )
    return Path(path)


def read_png(path) -> np.ndarray:
    """Read a PNG file into a ``(height, width, channels)`` uint8 array, row 0 at the top.

    Parameters
    ----------
    path : str or os.PathLike
        PNG file to read.

    Returns
    -------
    numpy.ndarray
        The pixels, ``uint8``.
    """
    p = Path(path)
    if not p.is_file():
        raise DVRInputError(f"PNG file {p}: not found")
    reader = _vtk.vtkPNGReader()
    if not reader.CanReadFile(str(p)):
        raise DVRInputError(f"PNG file {p}: not a readable PNG image")
    reader.SetFileName(str(p))
    reader.Update()
    out = reader.GetOutput()
    w, h, _ = out.GetDimensions()
    scalars = _vtk.vtk_to_numpy(out.GetPointData().GetScalars())
    return np.ascontiguousarray(scalars.reshape(h, w, -1)[::-1]).astype(np.uint8, copy=False)


def json_ready(obj):
    """Convert ``obj`` into plain JSON types.

    NumPy scalars and arrays become Python numbers and lists, tuples become lists, paths become
    strings, and non-finite floats become ``None`` (JSON has no NaN).

    Examples
    --------
    >>> json_ready({"a": np.float32(0.5), "b": np.arange(2), "c": float("nan")})
    {'a': 0.5, 'b': [0, 1], 'c': None}
    """
    if isinstance(obj, Mapping):
        return {str(k): json_ready(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_ready(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return json_ready(obj.tolist())
    if isinstance(obj, np.generic):
        return json_ready(obj.item())
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    if obj is None or isinstance(obj, (bool, int, str)):
        return obj
    raise DVRInputError(f"JSON output: cannot convert a {type(obj).__name__} value to JSON")


def write_json(path, obj) -> Path:
    """Write ``obj`` as indented JSON (atomically), converting NumPy types first.

    Parameters
    ----------
    path : str or os.PathLike
        Output file.
    obj : object
        Anything :func:`json_ready` accepts.

    Returns
    -------
    pathlib.Path
        The written path.
    """
    text = json.dumps(json_ready(obj), indent=2) + "\n"
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)


def write_npz(path, **arrays) -> Path:
    """Write arrays into an uncompressed ``.npz`` archive (atomically).

    Parameters
    ----------
    path : str or os.PathLike
        Output file; it is written exactly there (no ``.npz`` is appended).
    **arrays : array_like
        Named arrays.  Strings are stored as NumPy unicode arrays; object arrays are refused
        because reading them back would need ``allow_pickle``.

    Returns
    -------
    pathlib.Path
        The written path.
    """
    converted = {}
    for name, value in arrays.items():
        arr = np.asarray(value)
        if arr.dtype.kind == "O":
            raise DVRInputError(
                f"write_npz: array {name!r} has dtype object; expected numbers or strings"
            )
        converted[name] = arr
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.savez(fh, **converted)
    return Path(path)
