"""Conversion between :class:`~dvr_perception.volume.Volume` and ``vtkImageData``.

Conventions: a Volume's ``data[z, y, x]`` is VTK's point order (x fastest), so conversion is a
reshape, never a transpose.  ``to_vtk_image`` shares memory with the volume (zero copy; the VTK
array keeps a reference to the numpy buffer), ``from_vtk_image`` copies, so the returned Volume
never points into memory that VTK may free.

This module also holds :func:`vtk_errors`, the context manager that turns the errors VTK
algorithms *print* into one :class:`~dvr_perception.errors.DVRInputError`.
"""

from __future__ import annotations

import contextlib
import re

import numpy as np

from dvr_perception import _vtk
from dvr_perception.errors import DVRInputError
from dvr_perception.volume.volume import Volume

__all__ = [
    "from_vtk_image",
    "has_identity_direction",
    "image_direction",
    "to_vtk_image",
    "vtk_errors",
]


def to_vtk_image(
    volume: Volume, *, name: str = "scalars", with_direction: bool = False
) -> _vtk.vtkImageData:
    """Return a ``vtkImageData`` with the volume's dims, spacing, origin and point scalars.

    Parameters
    ----------
    volume : Volume
        The volume to wrap.
    name : str, optional
        Name of the point-scalar array.
    with_direction : bool, optional
        Also set the image's direction matrix (VTK >= 9.0), for files and displays in patient
        coordinates.  Off by default: the engine, the VTK reference renderer and the displays
        fed by the project render in the volume's frame, where the camera is placed
        (:func:`dvr_perception.rays.camera.patient_view`); an axis-aligned volume's direction
        is the identity anyway.

    Returns
    -------
    vtkImageData
        Shares memory with ``volume.data`` (zero copy); the VTK array holds a reference to it.

    Examples
    --------
    >>> import numpy as np
    >>> from dvr_perception.volume import Volume
    >>> img = to_vtk_image(Volume(np.zeros((2, 3, 4), np.uint8), spacing=(1, 1, 2)))
    >>> img.GetDimensions(), img.GetSpacing()
    ((4, 3, 2), (1.0, 1.0, 2.0))
    """
    if not isinstance(volume, Volume):
        raise DVRInputError(f"to_vtk_image: volume must be a Volume, got {type(volume).__name__}")
    flat = volume.data.reshape(-1)  # C-contiguous (Volume guarantees it): a view, no copy
    arr = _vtk.numpy_to_vtk(flat, deep=False)  # keeps `flat` alive via arr._numpy_reference
    arr.SetName(str(name))
    image = _vtk.vtkImageData()
    image.SetDimensions(*volume.dims)
    image.SetSpacing(*volume.spacing)
    image.SetOrigin(*volume.origin)
    if with_direction and hasattr(image, "SetDirectionMatrix"):
        image.SetDirectionMatrix(*np.asarray(volume.direction).ravel())
    image.GetPointData().SetScalars(arr)
    return image


def from_vtk_image(
    image, *, array: str | None = None, name: str = "volume", source: str = "", oriented=True
) -> Volume:
    """Return a :class:`Volume` holding a copy of one point array of a ``vtkImageData``.

    Parameters
    ----------
    image : vtkImageData
        A 3-D image (every dimension at least 2 points).
    array : str, optional
        Name of the point array to use; default: the active point scalars (or the only
        point array when none is active).
    name : str, optional
        Name of the returned volume.
    source : str, optional
        Where the image came from (used in error messages and stored on the volume).
    oriented : bool, optional
        Stored as ``Volume.oriented``: ``False`` when the image's file records no patient
        orientation (its direction is a default, not a statement).

    Returns
    -------
    Volume
        ``data[z, y, x]`` with the image's spacing and origin (the origin of a non-zero
        extent is shifted to the first point).  A direction matrix (VTK >= 9.0) is honoured:
        flips and permutations are applied to the data order
        (:func:`dvr_perception.volume.orient.canonical`), an oblique rotation is kept in
        ``Volume.direction``.

    Examples
    --------
    >>> import numpy as np
    >>> from dvr_perception.volume import Volume
    >>> vol = Volume(np.arange(24, dtype=np.int16).reshape(2, 3, 4))
    >>> back = from_vtk_image(to_vtk_image(vol))
    >>> bool(np.array_equal(back.data, vol.data)), back.data.dtype
    (True, dtype('int16'))
    """
    where = source or name
    if not isinstance(image, _vtk.vtkImageData):
        raise DVRInputError(
            f"{where}: expected vtkImageData, got "
            f"{image.GetClassName() if hasattr(image, 'GetClassName') else type(image).__name__}"
        )
    pd = image.GetPointData()
    if array is not None:
        arr = pd.GetAbstractArray(str(array))
        if arr is None:
            names = [pd.GetArrayName(i) for i in range(pd.GetNumberOfArrays())]
            raise DVRInputError(f"{where}: no point array named {array!r}; found {names}")
    else:
        arr = pd.GetScalars()
        if arr is None and pd.GetNumberOfArrays() == 1:
            arr = pd.GetAbstractArray(0)
    if arr is None:
        if image.GetCellData().GetNumberOfArrays() > 0:
            raise DVRInputError(
                f"{where}: the image holds only cell data; expected point scalars "
                "(convert with a cell-to-point filter first)"
            )
        n = pd.GetNumberOfArrays()
        raise DVRInputError(
            f"{where}: no point scalars"
            + (f" among {n} point arrays; pass array=NAME" if n else "")
        )
    label = arr.GetName() or "scalars"
    if not hasattr(arr, "GetNumberOfComponents") or arr.GetDataType() in (0, 1, 13):
        raise DVRInputError(f"{where}: point array {label!r} is not numeric")
    ncomp = arr.GetNumberOfComponents()
    if ncomp != 1:
        raise DVRInputError(
            f"{where}: point array {label!r} has {ncomp} components; expected a scalar "
            "(1-component) array"
        )
    x0, x1, y0, y1, z0, z1 = image.GetExtent()
    shape = (z1 - z0 + 1, y1 - y0 + 1, x1 - x0 + 1)
    if min(shape) <= 0 or arr.GetNumberOfTuples() != int(np.prod(shape)):
        raise DVRInputError(
            f"{where}: empty or inconsistent image (extent {image.GetExtent()}, "
            f"{arr.GetNumberOfTuples()} values); expected a non-empty 3-D volume"
        )
    data = np.array(_vtk.vtk_to_numpy(arr), copy=True).reshape(shape)
    spacing = np.asarray(image.GetSpacing(), float)
    direction = _direction(image)
    first = direction @ (np.array([x0, y0, z0], float) * spacing)
    origin = np.asarray(image.GetOrigin(), float) + first
    if not all(np.isfinite(s) and 0 < s <= 1e6 for s in spacing):
        raise DVRInputError(
            f"{where}: volume {name!r}: spacing must be three numbers in (0, 1e6], got "
            f"{tuple(spacing.tolist())}"
        )
    from dvr_perception.volume.orient import from_axes

    try:
        return from_axes(
            data, direction * spacing, origin, name=name, source=source, where=where,
            oriented=oriented,
        )  # fmt: skip
    except DVRInputError as exc:
        if str(exc).startswith(where):
            raise
        raise DVRInputError(f"{where}: {exc}") from None


def has_identity_direction(image) -> bool:
    """Return whether a ``vtkImageData``'s direction matrix is the identity (or absent).

    Examples
    --------
    >>> img = _vtk.vtkImageData()
    >>> has_identity_direction(img)
    True
    >>> img.SetDirectionMatrix(-1, 0, 0, 0, -1, 0, 0, 0, 1)
    >>> has_identity_direction(img)
    False
    """
    return bool(np.array_equal(_direction(image), np.eye(3)))


def image_direction(image) -> np.ndarray:
    """Return a ``vtkImageData``'s 3 x 3 direction matrix (the identity before VTK 9.0)."""
    return _direction(image)


def _direction(image) -> np.ndarray:
    get = getattr(image, "GetDirectionMatrix", None)  # VTK >= 9.0
    if get is None:
        return np.eye(3)
    m = get()
    return np.array([[m.GetElement(i, j) for j in range(3)] for i in range(3)])


@contextlib.contextmanager
def vtk_errors(algorithm, what: str):
    """Turn errors that a VTK algorithm reports while running into one ``DVRInputError``.

    Observers on the algorithm and its executive catch ``ErrorEvent`` (which also stops VTK
    from printing them), and a temporary ``vtkStringOutputWindow`` collects what helper
    objects (XML parsers, legacy readers) print; any text mentioning an error counts.  On
    exit, if an error was seen, ``DVRInputError("{what}: ...")`` is raised with VTK's first
    message.  (MetaIO writes some diagnostics straight to stderr; those cannot be caught.)

    Parameters
    ----------
    algorithm : vtkAlgorithm
        Reader, writer or filter about to be updated inside the ``with`` block.
    what : str
        Prefix of the error message (usually the file path).

    Examples
    --------
    >>> from dvr_perception._vtk import vtkXMLImageDataReader
    >>> reader = vtkXMLImageDataReader()
    >>> reader.SetFileName("/nonexistent.vti")
    >>> try:
    ...     with vtk_errors(reader, "/nonexistent.vti"):
    ...         _ = reader.Update()
    ... except DVRInputError as exc:
    ...     print(str(exc).split(":")[0])
    /nonexistent.vti
    """
    messages: list[str] = []

    def on_error(_obj, _event, data=None):
        messages.append(str(data) if data else "VTK reported an error")

    on_error.CallDataType = "string0"  # VTK passes the message text as call data
    targets = [algorithm]
    executive = algorithm.GetExecutive() if hasattr(algorithm, "GetExecutive") else None
    if executive is not None:
        targets.append(executive)
    tags = [(t, t.AddObserver("ErrorEvent", on_error)) for t in targets]
    previous = _vtk.vtkOutputWindow.GetInstance()
    capture = _vtk.vtkStringOutputWindow()
    _vtk.vtkOutputWindow.SetInstance(capture)
    verbosity = _vtk.vtkLogger.GetCurrentVerbosityCutoff()  # = stderr verbosity without log files
    _vtk.vtkLogger.SetStderrVerbosity(_vtk.vtkLogger.VERBOSITY_OFF)
    try:
        yield messages
    finally:
        _vtk.vtkLogger.SetStderrVerbosity(verbosity)
        _vtk.vtkOutputWindow.SetInstance(previous)
        for t, tag in tags:
            t.RemoveObserver(tag)
    printed = capture.GetOutput() or ""
    if "error" in printed.lower():
        lines = [ln for ln in printed.splitlines() if ln.strip() and "error" in ln.lower()]
        messages.append(lines[-1] if lines else printed)
    if messages:
        first = " ".join(messages[0].split())
        first = re.sub(r"^.*?\(0x[0-9a-fA-F]+\):\s*", "", first)
        raise DVRInputError(f"{what}: VTK could not process the file ({first[:300]})")
