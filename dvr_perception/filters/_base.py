"""Shared machinery of the VTK filters: parameters, spec loading and error reporting.

Every filter of :mod:`dvr_perception.filters` wraps the library the same way: the input
``vtkImageData`` becomes a :class:`~dvr_perception.volume.Volume` through
:func:`~dvr_perception.volume.from_vtk_image`, the library computes numpy arrays, and these
become point- or field-data arrays of the output.  :class:`DVRFilterBase` implements the parts
that do not depend on the computation:

* **Parameters** are :class:`Parameter` descriptors: ``f.sigma = 2`` (or ``f.SetSigma(2)``,
  the spelling ParaView's proxies use) validates the value and calls ``Modified()`` when it
  changes, so the pipeline re-executes.
* **Errors** never escape as Python exceptions.  A :class:`~dvr_perception.errors.DVRInputError`
  (or any other exception) raised while a request is processed is reported like C++'s
  ``vtkErrorMacro``: an ``ErrorEvent`` carrying the message when the filter has error
  observers, otherwise an error text on the ``vtkOutputWindow`` (ParaView's *Output Messages*).
  The request then returns 0, so ``Update()`` fails and the output stays empty; the message is
  also kept in :attr:`DVRFilterBase.error_message`.
* **Warnings** (:class:`~dvr_perception.errors.DVRWarning` and other Python warnings raised by
  the library while a request runs) are forwarded the same way as ``WarningEvent`` or warning
  text, and kept in :attr:`DVRFilterBase.warning_messages`.
* The filters need the **whole input** (curvature and rays are not local), so the update extent
  requested upstream is always the input's whole extent; they do not stream.  Under several
  MPI ranks *Perception Measures* and the optimiser can instead have each rank hold its piece
  (their ``distributed`` parameter; :mod:`dvr_perception.distributed`).
"""

from __future__ import annotations

import math
import warnings

import numpy as np

from dvr_perception._vtk import (
    VTKPythonAlgorithmBase,
    numpy_to_vtk,
    vtkCommand,
    vtkDataObject,
    vtkDoubleArray,
    vtkOutputWindow,
    vtkStreamingDemandDrivenPipeline,
    vtkStringArray,
)
from dvr_perception.errors import DVRCancelled, DVRInputError
from dvr_perception.structures.io import load_spec, loads_json, spec_from_dict
from dvr_perception.volume.convert import from_vtk_image

__all__ = ["DVRFilterBase", "Parameter", "check_range", "engine_luminance"]


class Parameter:
    """A filter property that validates its value and marks the filter modified on change.

    Parameters
    ----------
    default : object
        Initial value (not validated).
    convert : callable
        ``convert(value, name) -> value``; raises :class:`DVRInputError` for a bad value.
    setter : str, optional
        Name of the ``SetXxx`` method generated on the owner class (default: CamelCase of the
        attribute name).
    """

    def __init__(self, default, convert, *, setter: str | None = None):
        self.default = default
        self.convert = convert
        self.setter = setter
        self.name = ""

    def __set_name__(self, owner, name: str) -> None:
        self.name = name
        camel = "".join(part.capitalize() for part in name.split("_"))
        attr = self.setter or f"Set{camel}"
        if attr not in owner.__dict__:

            def set_value(obj, *value):
                setattr(obj, name, value[0] if len(value) == 1 else value)

            set_value.__doc__ = f"Set ``{name}`` (ParaView-style setter)."
            set_value.__name__ = attr
            setattr(owner, attr, set_value)

    def __get__(self, obj, owner=None):
        if obj is None:
            return self
        return obj.__dict__.get(self.name, self.default)

    def __set__(self, obj, value) -> None:
        value = self.convert(value, self.name)
        old = obj.__dict__.get(self.name, self.default)
        obj.__dict__[self.name] = value
        if not _same(old, value):
            obj.Modified()


def _same(a, b) -> bool:
    try:
        return bool(a == b) and type(a) is type(b)
    except (TypeError, ValueError):
        return False


# -- converters used by the parameters -----------------------------------------------------------
def as_text(value, name: str) -> str:
    """Accept ``None`` (as ``""``) or a string (or path-like)."""
    if value is None:
        return ""
    if not isinstance(value, str):
        value = getattr(value, "__fspath__", lambda: None)()
        if not isinstance(value, str):
            raise DVRInputError(f"{name}: expected text, got {type(value).__name__}")
    return value


def as_positive_float(value, name: str) -> float:
    """Accept a finite number > 0."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise DVRInputError(f"{name}: expected a positive number, got {value!r}") from None
    if not (math.isfinite(v) and v > 0):
        raise DVRInputError(f"{name}: expected a positive number, got {value!r}")
    return v


def as_positive_int(value, name: str) -> int:
    """Accept an integer >= 1."""
    try:
        v = int(value)
    except (TypeError, ValueError):
        raise DVRInputError(f"{name}: expected a positive integer, got {value!r}") from None
    if v != value or v < 1:
        raise DVRInputError(f"{name}: expected a positive integer, got {value!r}")
    return v


def check_range(value, name: str, low, high, *, integer: bool = False):
    """Return ``value`` if it lies in ``[low, high]`` (an integer when ``integer``).

    The ParaView plugin checks its properties' documented ranges (the ``smdomain`` ranges the
    GUI's sliders use) with this, so a value typed in Python is held to them too.

    Raises
    ------
    DVRInputError
        One line naming ``name`` and the range.

    Examples
    --------
    >>> check_range(32, "Width", 16, 4096, integer=True)
    32
    >>> check_range(5, "Width", 16, 4096, integer=True)
    Traceback (most recent call last):
    ...
    dvr_perception.errors.DVRInputError: Width: expected an integer in [16, 4096], got 5
    """
    what = "an integer" if integer else "a number"
    try:
        v = float(value)
        ok = math.isfinite(v) and low <= v <= high and not isinstance(value, (bool, str))
        ok = ok and (not integer or v == int(v))
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise DVRInputError(f"{name}: expected {what} in [{low:g}, {high:g}], got {value!r}")
    return int(v) if integer else v


def as_flag(value, name: str) -> bool:
    """Accept a bool or 0/1."""
    if isinstance(value, bool) or value in (0, 1):
        return bool(value)
    raise DVRInputError(f"{name}: expected true/false (or 1/0), got {value!r}")


# -- the base class ----------------------------------------------------------------------------
class DVRFilterBase(VTKPythonAlgorithmBase):
    """One ``vtkImageData`` input, one output; library errors become VTK errors.

    Subclasses implement :meth:`execute` (and :meth:`information` when the output geometry
    differs from the input's) and call :meth:`load_input` / :meth:`load_spec_parameters`.

    Attributes
    ----------
    error_message : str
        The last error reported by the filter ("" after a successful update).
    warning_messages : list of str
        Warnings reported during the last update.
    """

    #: point array of the input to analyse ("" = the active scalars)
    input_array = Parameter("", as_text)
    #: path of a structure-spec JSON file (see :mod:`dvr_perception.structures.io`)
    spec_file = Parameter("", as_text)
    #: the structure spec as JSON text (alternative to ``spec_file``)
    spec_json = Parameter("", as_text)

    def __init__(self, output_type: str = "vtkImageData") -> None:
        super().__init__(
            nInputPorts=1, inputType="vtkImageData", nOutputPorts=1, outputType=output_type
        )
        self.error_message = ""
        self.warning_messages: list[str] = []

    # -- pipeline passes (guarded) ------------------------------------------------------------
    def RequestInformation(self, request, in_info, out_info):
        """Pipeline pass: describe the output (see :meth:`information`)."""
        return self._guarded(self.information, in_info, out_info)

    def RequestUpdateExtent(self, request, in_info, out_info):
        """Pipeline pass: always request the whole extent of the input."""
        info = in_info[0].GetInformationObject(0)
        key = vtkStreamingDemandDrivenPipeline
        if info is not None and info.Has(key.WHOLE_EXTENT()):
            info.Set(key.UPDATE_EXTENT(), info.Get(key.WHOLE_EXTENT()), 6)
        return 1

    def RequestData(self, request, in_info, out_info):
        """Pipeline pass: compute the output (see :meth:`execute`)."""
        self.warning_messages = []
        key = vtkDataObject.DATA_OBJECT()
        output = out_info.GetInformationObject(0).Get(key)

        def run():
            image = in_info[0].GetInformationObject(0).Get(key)
            self.execute(image, output)

        status = self._guarded(run)
        if status:
            self.UpdateProgress(1.0)
        elif output is not None:
            output.Initialize()
        return status

    def information(self, in_info, out_info) -> None:
        """Describe the output in ``out_info`` (default: VTK copies the input's geometry)."""

    def execute(self, image, output) -> None:
        """Fill ``output`` from the input ``image``; raise :class:`DVRInputError` on bad input."""
        raise NotImplementedError

    # -- helpers for subclasses ---------------------------------------------------------------
    def progress_range(self, lo: float, hi: float):
        """Return a library ``progress`` callback that moves the bar from ``lo`` to ``hi``.

        The long steps (:func:`~dvr_perception.rays.curvature.curvature_volume`,
        :func:`~dvr_perception.rays.engine.analyze`) report their fraction ``f`` from inside;
        it becomes ``UpdateProgress(lo + (hi - lo) * f)``, so ParaView's progress bar moves
        during the step.  When an abort was requested (``GetAbortExecute``) the callback raises
        :class:`StopIteration`: the step stops with
        :class:`~dvr_perception.errors.DVRCancelled`, reported as the filter's error.

        Parameters
        ----------
        lo, hi : float
            The part of the filter's progress (0 to 1) the step covers.

        Returns
        -------
        callable
            ``progress(fraction)``.
        """

        def progress(fraction: float) -> None:
            self.UpdateProgress(lo + (hi - lo) * fraction)
            if self.GetAbortExecute():
                raise StopIteration("abort requested")

        return progress

    @property
    def label(self) -> str:
        """Name used at the start of the filter's messages."""
        return type(self).__name__

    def load_input(self, image):
        """Return the input image as a :class:`~dvr_perception.volume.Volume`."""
        return from_vtk_image(
            image,
            array=self.input_array or None,
            name="input",
            source=f"{self.label} input",
        )

    def load_spec_parameters(self):
        """Return the :class:`~dvr_perception.structures.spec.StructureSpec` of the parameters.

        Exactly one of ``spec_file`` and ``spec_json`` must be set.
        """
        if self.spec_file and self.spec_json:
            raise DVRInputError(
                f"{self.label}: both spec_file and spec_json are set; set only one of them"
            )
        if self.spec_file:
            return load_spec(self.spec_file)
        if self.spec_json:
            return spec_from_dict(loads_json(self.spec_json, "spec_json"), source="spec_json")
        raise DVRInputError(
            f"{self.label}: no structure spec; set spec_file (a spec JSON file) or spec_json"
        )

    # -- error and warning reporting ------------------------------------------------------------
    def _guarded(self, function, *args) -> int:
        self.error_message = ""
        caught: list = []
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                function(*args)
        except DVRInputError as exc:
            self.report_error(str(exc))
            return 0
        except DVRCancelled as exc:  # ParaView's abort inside a long step
            self.report_error(f"{self.label}: {exc}")
            return 0
        except Exception as exc:  # never let an exception escape into VTK's C++ code
            self.report_error(f"{self.label}: internal error ({type(exc).__name__}: {exc})")
            return 0
        finally:
            for w in caught:
                self.report_warning(str(w.message))
        return 1

    def report_error(self, message: str) -> None:
        """Report ``message`` as ``vtkErrorMacro`` does (``ErrorEvent`` or the output window)."""
        self.error_message = message
        self._emit(vtkCommand.ErrorEvent, "ERROR", message)

    def report_warning(self, message: str) -> None:
        """Report ``message`` as ``vtkWarningMacro`` does."""
        self.warning_messages.append(message)
        self._emit(vtkCommand.WarningEvent, "Warning", message)

    def _emit(self, event: int, kind: str, message: str) -> None:
        if self.HasObserver(event):
            try:
                self.InvokeEvent(event, message)  # the message is the call data (a string)
                return
            except TypeError:  # a VTK without string call data from Python
                self.InvokeEvent(event)
        text = f"{kind}: In {__name__}\n{self.label} ({hex(id(self))}): {message}\n\n"
        window = vtkOutputWindow.GetInstance()
        if event == vtkCommand.ErrorEvent:
            window.DisplayErrorText(text)
        else:
            window.DisplayWarningText(text)


# -- small conversions shared by the filters -----------------------------------------------------
def point_array(values: np.ndarray, name: str):
    """Return a named VTK array holding a copy of ``values`` (``(N,)`` or ``(N, C)``)."""
    values = np.ascontiguousarray(values)
    if values.ndim not in (1, 2):
        raise ValueError(f"point_array {name}: expected 1 or 2 dimensions, got {values.shape}")
    arr = numpy_to_vtk(values, deep=True)
    arr.SetName(name)
    return arr


def double_array(values, name: str):
    """Return a named ``vtkDoubleArray`` with one component and one tuple per value."""
    arr = vtkDoubleArray()
    arr.SetName(name)
    vals = [float(v) for v in values]
    arr.SetNumberOfTuples(len(vals))
    for i, v in enumerate(vals):
        arr.SetValue(i, v)
    return arr


def engine_luminance(rgba, background) -> np.ndarray:
    """Return the luminance of the engine's premultiplied ``rgba`` over ``background``.

    The composite of :func:`~dvr_perception.measures.composite_luminance`,
    ``Y(rgb) + (1 - a) * Y(background)``, without its check that no colour channel exceeds
    its opacity: that check is meant for images of unknown origin.  The engine's image is
    premultiplied by construction, and its colour may legitimately exceed its opacity where
    shading adds a white specular term (VTK's Phong model, which the engine follows, adds
    the highlight on top of the premultiplied colour: emission, up to a few per cent on
    tooth and cthead at their spec views).  Checking it would report every highlight as a
    "not premultiplied" warning in ParaView.

    Examples
    --------
    >>> float(engine_luminance([[0.5, 0.5, 0.5, 0.5]], (1.0, 1.0, 1.0))[0])
    1.0
    """
    from dvr_perception.measures.luminance import LUMA_WEIGHTS

    arr = np.asarray(rgba, np.float64)
    weights = np.asarray(LUMA_WEIGHTS, np.float64)
    bg = float(np.asarray(background, np.float64) @ weights)
    return arr[..., :3] @ weights + (1.0 - arr[..., 3]) * bg


def string_array(values, name: str):
    """Return a named ``vtkStringArray`` of ``values``."""
    arr = vtkStringArray()
    arr.SetName(name)
    for v in values:
        arr.InsertNextValue(str(v))
    return arr
