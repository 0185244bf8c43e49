"""Quality-map overlay: a colour-mapped measure image on top of the 3D view, with a scalar bar.

The measure image (e.g. a visibility deviation ``delta_v(r)``, one value per pixel of the
analysed camera) is mapped through a colour map to RGBA, made semi-transparent where it is
defined (NaN = not defined = fully transparent), resized to the window by nearest neighbour and
drawn as a 2D image actor in front of the volume.  Resize the window first: the overlay does
not follow later size changes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dvr_perception._deprecation import deprecated_alias
from dvr_perception.errors import DVRInputError

__all__ = ["QualityOverlay", "add_quality_map", "colourize"]


@dataclass(eq=False)
class QualityOverlay:
    """What :func:`add_quality_map` added: the image actor, the scalar bar and the RGBA."""

    image_actor: object
    scalar_bar: object
    rgba: np.ndarray


def _measure_array(measure_image) -> np.ndarray:
    data = getattr(measure_image, "deviation", measure_image)
    try:
        arr = np.asarray(data, dtype=np.float64)
    except (TypeError, ValueError):
        raise DVRInputError(
            f"measure_image: expected an (H, W) array, got {type(measure_image).__name__}"
        ) from None
    if arr.ndim != 2 or min(arr.shape) < 1:
        raise DVRInputError(f"measure_image: expected an (H, W) array, got shape {arr.shape}")
    return arr


def _check_clim(clim, arr) -> tuple[float, float]:
    if clim is None:
        finite = arr[np.isfinite(arr)]
        lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
        return (lo, hi if hi > lo else lo + 1.0)
    try:
        lo, hi = (float(c) for c in clim)
    except (TypeError, ValueError):
        raise DVRInputError(f"clim: expected (min, max), got {clim!r}") from None
    if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
        raise DVRInputError(f"clim: expected finite (min, max) with min < max, got {clim!r}")
    return lo, hi


def colourize(measure_image, *, clim, cmap="viridis", opacity=0.6) -> np.ndarray:
    """Map a measure image to ``uint8`` RGBA (alpha ``opacity`` where finite, 0 where NaN).

    Examples
    --------
    >>> rgba = colourize(np.array([[0.0, np.nan], [0.5, 1.0]]), clim=(0, 1))
    >>> rgba.shape, rgba[0, 1, 3], rgba[0, 0, 3]
    ((2, 2, 4), np.uint8(0), np.uint8(153))
    """
    import matplotlib

    arr = _measure_array(measure_image)
    lo, hi = _check_clim(clim, arr)
    if not 0.0 <= float(opacity) <= 1.0:
        raise DVRInputError(f"opacity: expected a value in [0, 1], got {opacity!r}")
    try:
        cm = matplotlib.colormaps[cmap]
    except (KeyError, TypeError):
        raise DVRInputError(f"cmap: unknown matplotlib colour map {cmap!r}") from None
    norm = np.clip((np.nan_to_num(arr, nan=lo) - lo) / (hi - lo), 0.0, 1.0)
    rgba = (np.asarray(cm(norm)) * 255.0 + 0.5).astype(np.uint8)
    rgba[..., 3] = np.where(np.isfinite(arr), round(255 * float(opacity)), 0)
    return rgba


colorize = deprecated_alias(
    colourize,
    "dvr_perception.plotting.overlay.colorize",
    "dvr_perception.plotting.overlay.colourize",
)


def _resize_nearest(rgba: np.ndarray, height: int, width: int) -> np.ndarray:
    rows = np.minimum((np.arange(height) + 0.5) * rgba.shape[0] / height, rgba.shape[0] - 1)
    cols = np.minimum((np.arange(width) + 0.5) * rgba.shape[1] / width, rgba.shape[1] - 1)
    return rgba[rows.astype(int)][:, cols.astype(int)]


def add_quality_map(
    plotter, measure_image, *, title, clim=None, cmap="viridis", opacity=0.6, name="quality"
) -> QualityOverlay:
    """Overlay a colour-mapped measure image on the plotter's view, with a scalar bar.

    Parameters
    ----------
    plotter : pyvista.Plotter
        Target plotter (its active renderer).
    measure_image : array_like or result
        ``(H, W)`` values, row 0 at the top (NaN = no value); or a measure result with a
        ``deviation`` image.
    title : str
        Scalar-bar title.
    clim : (float, float), optional
        Colour range (default: the finite data range).
    cmap : str, default: "viridis"
        Matplotlib colour map name.
    opacity : float, default: 0.6
        Overlay opacity where the measure is defined.
    name : str, default: "quality"
        Actor name prefix (adding the same name replaces the overlay).

    Returns
    -------
    QualityOverlay

    Examples
    --------
    >>> import pyvista as pv
    >>> pl = pv.Plotter(off_screen=True, window_size=(32, 32))
    >>> ov = add_quality_map(pl, np.eye(8), title="delta_v", clim=(0, 1))
    >>> ov.rgba.shape
    (32, 32, 4)
    >>> pl.close()
    """
    import pyvista as pv
    from vtkmodules.vtkRenderingAnnotation import vtkScalarBarActor
    from vtkmodules.vtkRenderingCore import vtkActor2D, vtkImageMapper

    from dvr_perception import _vtk

    if not isinstance(plotter, pv.Plotter):
        raise DVRInputError(f"plotter: expected a pyvista.Plotter, got {type(plotter).__name__}")
    if not isinstance(title, str):
        raise DVRInputError(f"title: expected a string, got {type(title).__name__}")
    arr = _measure_array(measure_image)
    lo, hi = _check_clim(clim, arr)
    width, height = (int(v) for v in plotter.window_size)
    rgba = _resize_nearest(colourize(arr, clim=(lo, hi), cmap=cmap, opacity=opacity), height, width)
    img = _vtk.vtkImageData()
    img.SetDimensions(width, height, 1)
    scalars = _vtk.numpy_to_vtk(np.ascontiguousarray(rgba[::-1]).reshape(-1, 4), deep=True)
    img.GetPointData().SetScalars(scalars)
    mapper = vtkImageMapper()
    mapper.SetInputData(img)
    mapper.SetColorWindow(255.0)
    mapper.SetColorLevel(127.5)
    actor = vtkActor2D()
    actor.SetMapper(mapper)
    actor.SetPosition(0, 0)
    lut = pv.LookupTable(cmap=cmap)
    lut.scalar_range = (lo, hi)
    bar = vtkScalarBarActor()
    bar.SetLookupTable(lut)
    bar.SetTitle(title)
    bar.SetNumberOfLabels(3)
    bar.SetPosition(0.86, 0.1)
    bar.SetWidth(0.12)
    bar.SetHeight(0.8)
    plotter.add_actor(actor, name=f"{name}_image", reset_camera=False, render=False)
    plotter.add_actor(bar, name=f"{name}_bar", reset_camera=False, render=False)
    return QualityOverlay(actor, bar, rgba)
