"""Reference renderings with VTK's own volume mappers: the ground truth our engine must match.

:func:`render_vtk` renders a :class:`~dvr_perception.volume.Volume` with a
:class:`~dvr_perception.structures.spec.StructureSpec` through
``vtkFixedPointVolumeRayCastMapper`` (exact still render: ``AutoAdjustSampleDistances`` off,
``ImageSampleDistance`` 1) or ``vtkOpenGLGPUVolumeRayCastMapper``, with our
:class:`~dvr_perception.rays.camera.Camera` and one light that follows the camera.  What the
fixed-point mapper computes is written down in ``docs/vtk_conventions.md``.

The accumulated opacity is recovered from two renders, over black and over white:
``alpha = 1 - (white - black)``, which works for any mapper.
"""

from __future__ import annotations

import contextlib
import functools
import math
import subprocess
import sys
import time
from dataclasses import dataclass

import numpy as np

from dvr_perception import _vtk
from dvr_perception.errors import DVRInputError
from dvr_perception.export.vtk import to_vtk_property
from dvr_perception.rays import _tables
from dvr_perception.rays._grid import clipping_range
from dvr_perception.rays.camera import Camera
from dvr_perception.structures.spec import StructureSpec
from dvr_perception.volume.convert import to_vtk_image
from dvr_perception.volume.volume import Volume

__all__ = [
    "MAPPERS",
    "VTKRender",
    "compare_images",
    "render_vtk",
    "time_vtk_frames",
    "vtk_clipping_range",
    "vtk_frame_timer",
]

MAPPERS = ("fixed_point", "gpu")


@dataclass(frozen=True, eq=False)
class VTKRender:
    """One VTK rendering.

    Attributes
    ----------
    image : numpy.ndarray
        ``(H, W, 3)`` float32 in [0, 1], composited over ``spec.background``, row 0 at the top.
    alpha : numpy.ndarray
        ``(H, W)`` float32 accumulated opacity.
    seconds : float
        Render time of one warm frame (excluding first-render set-up).
    mapper : str
        ``"fixed_point"`` or ``"gpu"``.
    clipping_range : tuple of float
        The camera clipping range VTK used (the fixed-point sample phase starts at the near
        plane; see ``docs/vtk_conventions.md``).
    """

    image: np.ndarray
    alpha: np.ndarray
    seconds: float
    mapper: str
    clipping_range: tuple[float, float]


def vtk_clipping_range(volume: Volume, camera: Camera) -> tuple[float, float]:
    """Clipping range ``vtkRenderer.ResetCameraClippingRange()`` gives for this volume and camera.

    Pure-numpy restatement of VTK's rule (expansion 0.5, near-plane tolerance 0.001 as for a
    24-bit depth buffer), so the engine can anchor its sample phase without VTK.

    Examples
    --------
    >>> vol = Volume(np.zeros((11, 16, 16), np.uint8))
    >>> cam = Camera(position=(7.5, 7.5, 50), focal_point=(7.5, 7.5, 5),
    ...              parallel_projection=True, parallel_scale=10, width=8, height=8)
    >>> [round(x, 6) for x in vtk_clipping_range(vol, cam)]
    [34.6, 58.2]
    """
    return clipping_range(camera, volume.bounds)


@functools.cache
def _probe(kind: str) -> tuple[bool, str]:
    """Check in a subprocess that VTK can render (``kind="basic"``) or run the GPU mapper."""
    if kind == "basic":
        return _vtk.can_render()
    code = (
        "import numpy as np\n"
        "from dvr_perception._vtk import rendering, vtkImageData, numpy_to_vtk\n"
        "from dvr_perception._vtk import vtkVolumeProperty, vtkPiecewiseFunction\n"
        "r = rendering(); img = vtkImageData(); img.SetDimensions(4, 4, 4)\n"
        "img.GetPointData().SetScalars(numpy_to_vtk(np.arange(64, dtype=np.uint8), deep=True))\n"
        "f = vtkPiecewiseFunction(); f.AddPoint(0, 0); f.AddPoint(63, 1)\n"
        "p = vtkVolumeProperty(); p.SetScalarOpacity(f)\n"
        "m = r.vtkOpenGLGPUVolumeRayCastMapper(); m.SetInputData(img)\n"
        "v = r.vtkVolume(); v.SetMapper(m); v.SetProperty(p)\n"
        "ren = r.vtkRenderer(); ren.AddVolume(v); w = r.vtkRenderWindow()\n"
        "w.SetOffScreenRendering(1); w.SetSize(16, 16); w.AddRenderer(ren); ren.ResetCamera()\n"
        "w.Render(); print('ok' if m.IsRenderSupported(w, p) else 'unsupported')\n"
    )
    try:
        proc = subprocess.run(
            [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=False
        )
    except (OSError, subprocess.TimeoutExpired) as exc:
        return False, f"could not start a GPU render check: {exc}"
    if proc.returncode == 0 and proc.stdout.strip().endswith("ok"):
        return True, ""
    return False, f"GPU volume mapper check failed (exit code {proc.returncode})"


class _VTKPipeline:
    """A VTK off-screen window with one volume, our camera and one camera light."""

    def __init__(self, volume, spec, camera, mapper, opacities, shade):
        r = _vtk.rendering()
        prop = to_vtk_property(spec, volume, opacities=opacities, shade=shade)
        rs = spec.rendering
        sd = float(min(volume.spacing)) if rs.sample_distance is None else rs.sample_distance
        if not (math.isfinite(sd) and sd > 0):
            raise DVRInputError(f"rendering.sample_distance must be positive, got {sd}")
        sd = _tables.min_step(float(sd), volume)
        if mapper == "fixed_point":
            m = r.vtkFixedPointVolumeRayCastMapper()
            m.SetImageSampleDistance(1.0)
        else:
            m = r.vtkOpenGLGPUVolumeRayCastMapper()
            m.SetUseJittering(0)
        m.SetAutoAdjustSampleDistances(0)
        m.SetSampleDistance(sd)
        m.SetInputData(to_vtk_image(volume))
        self.vol = r.vtkVolume()
        self.vol.SetMapper(m)
        self.vol.SetProperty(prop)
        self.ren = r.vtkRenderer()
        self.ren.AddVolume(self.vol)
        self.ren.SetAutomaticLightCreation(0)
        light = r.vtkLight()
        light.SetLightTypeToCameraLight()
        light.SetPosition(*(float(c) for c in rs.light_direction))
        light.SetFocalPoint(0.0, 0.0, 0.0)
        light.SetColor(1.0, 1.0, 1.0)
        light.SetAmbientColor(1.0, 1.0, 1.0)
        light.SetIntensity(float(rs.light_intensity))
        self.ren.AddLight(light)
        cam = self.ren.GetActiveCamera()
        cam.SetPosition(*camera.position)
        cam.SetFocalPoint(*camera.focal_point)
        cam.SetViewUp(*camera.view_up)
        cam.SetViewAngle(camera.view_angle)
        cam.SetParallelProjection(int(camera.parallel_projection))
        cam.SetParallelScale(camera.parallel_scale)
        self.ren.ResetCameraClippingRange()
        self.cam = cam
        self.win = r.vtkRenderWindow()
        self.win.SetOffScreenRendering(1)
        self.win.SetSize(camera.width, camera.height)
        self.win.AddRenderer(self.ren)
        self._w2i = r.vtkWindowToImageFilter
        self.size = (camera.height, camera.width)

    def render(self, background) -> float:
        self.ren.SetBackground(*(float(c) for c in background))
        t0 = time.perf_counter()
        self.win.Render()
        return time.perf_counter() - t0

    def read(self) -> np.ndarray:
        f = self._w2i()
        f.SetInput(self.win)
        f.SetInputBufferTypeToRGB()
        f.ReadFrontBufferOff()
        f.Update()
        h, w = self.size
        arr = _vtk.vtk_to_numpy(f.GetOutput().GetPointData().GetScalars())
        return arr.reshape(h, w, 3)[::-1].astype(np.float32) / 255.0

    def close(self) -> None:
        self.ren.RemoveVolume(self.vol)
        self.win.Finalize()
        del self.win, self.ren, self.vol, self.cam


def _prepare(volume, spec, camera, mapper) -> None:
    if not isinstance(volume, Volume):
        raise DVRInputError(f"volume: expected a Volume, got {type(volume).__name__}")
    if not isinstance(spec, StructureSpec):
        raise DVRInputError(f"spec: expected a StructureSpec, got {type(spec).__name__}")
    if not isinstance(camera, Camera):
        raise DVRInputError(f"camera: expected a Camera, got {type(camera).__name__}")
    if mapper not in MAPPERS:
        raise DVRInputError(f"mapper: expected one of {MAPPERS}, got {mapper!r}")
    ok, why = _probe("basic")
    if not ok:
        raise DVRInputError(f"VTK cannot render here: {why}")
    if mapper == "gpu":
        ok, why = _probe("gpu")
        if not ok:
            raise DVRInputError(
                f"mapper='gpu': VTK's GPU volume mapper cannot render here ({why}); "
                "use mapper='fixed_point'"
            )


def render_vtk(
    volume: Volume,
    spec: StructureSpec,
    camera: Camera,
    *,
    mapper: str = "fixed_point",
    opacities=None,
    shade: bool | None = None,
) -> VTKRender:
    """Render a volume with VTK as the reference image.

    Parameters
    ----------
    volume : Volume
        The scalar volume.
    spec : StructureSpec
        Structures (range structures only), background and render settings.
    camera : Camera
        View and image size.
    mapper : {"fixed_point", "gpu"}
        ``vtkFixedPointVolumeRayCastMapper`` or ``vtkOpenGLGPUVolumeRayCastMapper``.
    opacities : sequence of float, optional
        Rendering opacity per structure (default: each structure's ``render_opacity``).
    shade : bool, optional
        Override ``spec.rendering.shade``.

    Returns
    -------
    VTKRender
    """
    _prepare(volume, spec, camera, mapper)
    pipeline = _VTKPipeline(volume, spec, camera, mapper, opacities, shade)
    try:
        pipeline.render((0.0, 0.0, 0.0))  # first frame: gradients, tables, shaders
        pipeline.render((0.0, 0.0, 0.0))
        black = pipeline.read()
        seconds = pipeline.render((1.0, 1.0, 1.0))
        white = pipeline.read()
        clip = tuple(float(c) for c in pipeline.cam.GetClippingRange())
    finally:
        pipeline.close()
    diff = np.clip(white - black, 0.0, 1.0)
    bg = np.asarray(spec.background, dtype=np.float32)
    image = np.clip(black + diff * bg, 0.0, 1.0).astype(np.float32)
    alpha = (1.0 - diff.mean(axis=-1)).astype(np.float32)
    return VTKRender(image, alpha, float(seconds), mapper, clip)


def time_vtk_frames(
    volume: Volume, spec: StructureSpec, camera: Camera, *, frames: int = 3
) -> float:
    """Median seconds of ``frames`` warm frames of the fixed-point mapper (set-up excluded).

    Examples
    --------
    >>> from dvr_perception.structures.spec import Structure
    >>> vol = Volume(np.arange(8 ** 3, dtype=np.uint16).reshape(8, 8, 8) % 200)
    >>> spec = StructureSpec((Structure("a", 0.5, (1, 1, 1), range=(50, 150)),))
    >>> cam = Camera.from_view(vol.bounds, width=16, height=16)
    >>> time_vtk_frames(vol, spec, cam, frames=2) > 0  # doctest: +SKIP
    True
    """
    if int(frames) != frames or frames < 1:
        raise DVRInputError(f"frames: expected a positive integer, got {frames!r}")
    with vtk_frame_timer(volume, spec, camera) as frame:
        times = sorted(frame() for _ in range(int(frames)))
    n = len(times)
    return 0.5 * (times[(n - 1) // 2] + times[n // 2])


@contextlib.contextmanager
def vtk_frame_timer(volume: Volume, spec: StructureSpec, camera: Camera):
    """Yield a function that renders one warm frame of the fixed-point mapper, returning seconds.

    The render window stays open inside the ``with`` block, so frames can be interleaved with
    other work (``dvr-perception bench`` alternates them with our engine's frames).

    Examples
    --------
    >>> from dvr_perception.structures.spec import Structure
    >>> vol = Volume(np.arange(8 ** 3, dtype=np.uint16).reshape(8, 8, 8) % 200)
    >>> spec = StructureSpec((Structure("a", 0.5, (1, 1, 1), range=(50, 150)),))
    >>> cam = Camera.from_view(vol.bounds, width=16, height=16)
    >>> with vtk_frame_timer(vol, spec, cam) as frame:  # doctest: +SKIP
    ...     frame() > 0
    True
    """
    _prepare(volume, spec, camera, "fixed_point")
    pipeline = _VTKPipeline(volume, spec, camera, "fixed_point", None, None)
    try:
        pipeline.render(spec.background)  # first render: set-up, not timed

        def frame() -> float:
            pipeline.cam.Modified()
            return pipeline.render(spec.background)

        yield frame
    finally:
        pipeline.close()


def compare_images(a, b) -> dict:
    """SSIM and mean absolute difference of two ``(H, W, 3)`` images in [0, 1].

    Examples
    --------
    >>> x = np.zeros((8, 8, 3), np.float32)
    >>> compare_images(x, x)["mean_abs_diff"]
    0.0
    """
    from skimage.metrics import structural_similarity

    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.shape != b.shape or a.ndim != 3 or a.shape[-1] != 3:
        raise DVRInputError(
            f"compare_images: expected two (H, W, 3) images of the same shape, "
            f"got {a.shape} and {b.shape}"
        )
    if min(a.shape[:2]) < 7:
        raise DVRInputError(f"compare_images: images must be at least 7x7, got {a.shape[:2]}")
    ssim = structural_similarity(a, b, channel_axis=-1, data_range=1.0)
    return {"ssim": float(ssim), "mean_abs_diff": float(np.mean(np.abs(a - b)))}
