"""Pinhole / parallel camera with VTK's conventions, and the ``--view`` helper.

Conventions (shared by our engine and the VTK reference renderer):

* ``view_angle`` is the vertical field of view in degrees (``vtkCamera.GetViewAngle``).
* ``parallel_scale`` is half the image height in world units (``vtkCamera.GetParallelScale``).
* Images are ``(height, width, ...)`` arrays with row 0 at the **top** (as in a PNG).
* A pixel's ray passes through the pixel centre.
* The default view (azimuth 0, elevation 0, zoom 1) is ParaView's "reset camera": looking down
  -z at the volume centre, +y up, at the distance that fits the bounding sphere in a 30° view.
* Cameras live in the volume's frame (``origin + spacing * index``), which is patient LPS
  unless the volume is oblique.  :func:`patient_view` sets up a named view (``anterior`` ...
  ``inferior``) in patient terms and rotates it into that frame; :meth:`Camera.in_volume_frame`
  does the same for any world camera.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from dvr_perception.errors import DVRInputError

__all__ = [
    "MAX_IMAGE",
    "PATIENT_VIEWS",
    "Camera",
    "default_camera",
    "parse_patient_view",
    "parse_view",
    "patient_angles",
]

#: Named views in patient (LPS) terms: where the camera sits, seen from the volume centre,
#: and the view-up.  Anterior/posterior/left/right views have the head (superior) up; the
#: superior and inferior views have the face (anterior) up.
PATIENT_VIEWS = {
    "anterior": ((0.0, -1.0, 0.0), (0.0, 0.0, 1.0)),
    "posterior": ((0.0, 1.0, 0.0), (0.0, 0.0, 1.0)),
    "left": ((1.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
    "right": ((-1.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
    "superior": ((0.0, 0.0, 1.0), (0.0, -1.0, 0.0)),
    "inferior": ((0.0, 0.0, -1.0), (0.0, -1.0, 0.0)),
}

#: Largest image width or height from any source (``--size``, a camera file, the API).
MAX_IMAGE = 16384


def _unit(v: np.ndarray, what: str) -> np.ndarray:
    n = float(np.linalg.norm(v))
    if not math.isfinite(n) or n == 0:
        raise DVRInputError(f"camera: {what} must be a non-zero finite vector, got {v.tolist()}")
    return v / n


@dataclass(frozen=True)
class Camera:
    """A camera and an image size.

    Examples
    --------
    >>> cam = Camera(position=(0, 0, 10), focal_point=(0, 0, 0), width=4, height=2)
    >>> origins, dirs = cam.rays()
    >>> dirs.shape
    (2, 4, 3)
    >>> bool(np.allclose(np.linalg.norm(dirs, axis=-1), 1))
    True
    """

    position: tuple[float, float, float] = (0.0, 0.0, 1.0)
    focal_point: tuple[float, float, float] = (0.0, 0.0, 0.0)
    view_up: tuple[float, float, float] = (0.0, 1.0, 0.0)
    view_angle: float = 30.0
    parallel_projection: bool = False
    parallel_scale: float = 1.0
    width: int = 512
    height: int = 512

    def __post_init__(self) -> None:
        for name in ("position", "focal_point", "view_up"):
            v = tuple(float(c) for c in getattr(self, name))
            if len(v) != 3 or not all(math.isfinite(c) for c in v):
                raise DVRInputError(f"camera: {name} must be three finite numbers, got {v}")
            object.__setattr__(self, name, v)
        for name in ("width", "height"):
            val = getattr(self, name)
            try:
                ok = not isinstance(val, bool) and int(val) == val
            except (TypeError, ValueError, OverflowError):
                ok = False
            if not ok or not 1 <= int(val) <= MAX_IMAGE:
                shown = repr(val) if len(repr(val)) < 40 else f"{repr(val)[:30]}..."
                raise DVRInputError(
                    f"camera: image {name} must be an integer in 1..{MAX_IMAGE}, got {shown}"
                )
            object.__setattr__(self, name, int(val))
        if not 0 < float(self.view_angle) < 180:
            raise DVRInputError(
                f"camera: view_angle must be in (0, 180) degrees, got {self.view_angle}"
            )
        if not float(self.parallel_scale) > 0:
            raise DVRInputError(
                f"camera: parallel_scale must be positive, got {self.parallel_scale}"
            )
        object.__setattr__(self, "view_angle", float(self.view_angle))
        object.__setattr__(self, "parallel_scale", float(self.parallel_scale))
        object.__setattr__(self, "parallel_projection", bool(self.parallel_projection))
        self.basis()  # validates direction and view-up

    # -- geometry ---------------------------------------------------------------------------
    def basis(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Return unit ``(forward, right, up)`` vectors (right-handed, as VTK)."""
        fwd = _unit(np.subtract(self.focal_point, self.position), "focal_point - position")
        up0 = _unit(np.asarray(self.view_up, float), "view_up")
        right = np.cross(fwd, up0)
        if np.linalg.norm(right) < 1e-9:
            raise DVRInputError("camera: view_up is parallel to the viewing direction")
        right = _unit(right, "right")
        up = np.cross(right, fwd)
        return fwd, right, up

    @property
    def distance(self) -> float:
        """Distance from position to focal point."""
        return float(np.linalg.norm(np.subtract(self.focal_point, self.position)))

    def rays(self) -> tuple[np.ndarray, np.ndarray]:
        """Return per-pixel ray origins and unit directions, each ``(height, width, 3)``."""
        fwd, right, up = self.basis()
        w, h = self.width, self.height
        # normalised device coordinates of pixel centres, y up, row 0 at the top
        xs = (2.0 * (np.arange(w) + 0.5) / w - 1.0)[None, :, None]
        ys = (1.0 - 2.0 * (np.arange(h) + 0.5) / h)[:, None, None]
        aspect = w / h
        pos = np.asarray(self.position, float)
        if self.parallel_projection:
            s = self.parallel_scale
            origins = pos + xs * (s * aspect) * right + ys * s * up
            dirs = np.broadcast_to(fwd, (h, w, 3)).copy()
        else:
            t = math.tan(math.radians(self.view_angle) / 2.0)
            dirs = fwd + xs * (t * aspect) * right + ys * t * up
            dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
            origins = np.broadcast_to(pos, (h, w, 3)).copy()
        return np.ascontiguousarray(origins), np.ascontiguousarray(dirs)

    def with_size(self, width: int, height: int) -> Camera:
        """Return the same camera with another image size."""
        return replace(self, width=width, height=height)

    def in_volume_frame(self, volume) -> Camera:
        """Return this camera, given in world (patient LPS) coordinates, in ``volume``'s frame.

        The engine renders in the frame ``origin + spacing * index``; for an oblique volume
        (``volume.oblique``) a world camera -- e.g. ParaView's, which displays the image with
        its direction matrix -- is rotated into it.  The identity for axis-aligned volumes.
        """
        if not getattr(volume, "oblique", False):
            return self
        d = np.asarray(volume.direction)
        return replace(
            self,
            position=tuple(volume.to_frame(self.position)),
            focal_point=tuple(volume.to_frame(self.focal_point)),
            view_up=tuple(np.asarray(self.view_up) @ d),
        )

    # -- serialisation ------------------------------------------------------------------------
    def to_dict(self) -> dict:
        """JSON-ready dictionary (the ``--camera CAM.json`` format)."""
        return {
            "position": list(self.position),
            "focal_point": list(self.focal_point),
            "view_up": list(self.view_up),
            "view_angle": self.view_angle,
            "parallel_projection": self.parallel_projection,
            "parallel_scale": self.parallel_scale,
            "width": self.width,
            "height": self.height,
        }

    @classmethod
    def from_dict(cls, d: dict, *, source: str = "camera") -> Camera:
        """Build from :meth:`to_dict` output; unknown keys are an error naming ``source``."""
        if not isinstance(d, dict):
            raise DVRInputError(f"{source}: expected a JSON object, got {type(d).__name__}")
        known = set(cls.__dataclass_fields__)
        extra = set(d) - known
        if extra:
            names = sorted(str(e)[:40] for e in extra)
            more = f" and {len(names) - 5} more" if len(names) > 5 else ""
            raise DVRInputError(f"{source}: unknown camera field(s) {names[:5]}{more}")
        try:
            return cls(**d)
        except (TypeError, ValueError, OverflowError) as exc:
            if isinstance(exc, DVRInputError):
                raise DVRInputError(f"{source}: {exc}") from None
            raise DVRInputError(f"{source}: invalid camera ({str(exc)[:120]})") from None

    @classmethod
    def from_view(
        cls,
        bounds: tuple[float, float, float, float, float, float],
        *,
        azimuth: float = 0.0,
        elevation: float = 0.0,
        zoom: float = 1.0,
        width: int = 512,
        height: int = 512,
        view_angle: float = 30.0,
    ) -> Camera:
        """Orbit camera around the centre of ``bounds`` (ParaView's reset camera, then rotate).

        ``azimuth`` rotates about the view-up axis and ``elevation`` about the right axis, both
        in degrees, as ``vtkCamera.Azimuth``/``Elevation``; ``zoom`` > 1 moves closer
        (``vtkCamera.Dolly``).

        Examples
        --------
        >>> cam = Camera.from_view((0, 10, 0, 10, 0, 10), width=64, height=64)
        >>> [round(c, 3) for c in cam.focal_point]
        [5.0, 5.0, 5.0]
        """
        b = np.asarray(bounds, float)
        if b.shape != (6,) or not np.all(np.isfinite(b)):
            raise DVRInputError(f"view: bounds must be 6 finite numbers, got {bounds}")
        if not (math.isfinite(zoom) and zoom > 0):
            raise DVRInputError(f"view: ZOOM must be a positive number, got {zoom}")
        center = np.array([(b[0] + b[1]) / 2, (b[2] + b[3]) / 2, (b[4] + b[5]) / 2])
        radius = 0.5 * float(np.linalg.norm(b[1::2] - b[0::2]))
        radius = radius if radius > 0 else 0.5
        dist = radius / math.sin(math.radians(view_angle) / 2.0) / zoom
        az, el = math.radians(azimuth), math.radians(elevation)
        # start: looking down -z, +y up; rotate about y (azimuth) then about right (elevation)
        offset = np.array([math.sin(az) * math.cos(el), math.sin(el), math.cos(az) * math.cos(el)])
        up = np.array([-math.sin(az) * math.sin(el), math.cos(el), -math.cos(az) * math.sin(el)])
        return cls(
            position=tuple(center + dist * offset),
            focal_point=tuple(center),
            view_up=tuple(up),
            view_angle=view_angle,
            width=width,
            height=height,
        )


def _orbit(center, back, up, *, dist, azimuth, elevation):
    """Position and view-up after vtkCamera Azimuth then Elevation from ``center + dist*back``."""
    back = np.asarray(back, float)
    up = np.asarray(up, float)
    right = np.cross(-back, up)
    az, el = math.radians(azimuth), math.radians(elevation)
    offset = math.sin(az) * math.cos(el) * right + math.sin(el) * up
    offset = offset + math.cos(az) * math.cos(el) * back
    new_up = -math.sin(az) * math.sin(el) * right + math.cos(el) * up
    new_up = new_up - math.cos(az) * math.sin(el) * back
    return np.asarray(center, float) + dist * offset, new_up


def patient_view(
    volume,
    name: str,
    *,
    azimuth: float = 0.0,
    elevation: float = 0.0,
    zoom: float = 1.0,
    width: int = 512,
    height: int = 512,
    view_angle: float = 30.0,
) -> Camera:
    """Camera for a named patient view of ``volume``, in the volume's frame.

    The view is set up in world (patient LPS) coordinates -- e.g. ``"anterior"`` looks at the
    face from in front, head up -- then ``azimuth``/``elevation`` turn it as
    ``vtkCamera.Azimuth``/``Elevation`` and ``zoom`` dollies in, as in
    :meth:`Camera.from_view`.  The result is mapped into the frame the engine renders in
    (``Volume.to_frame``; the identity unless the volume is oblique).

    Parameters
    ----------
    volume : Volume
        The volume (its bounds, origin and direction are used).
    name : str
        One of :data:`PATIENT_VIEWS`.

    Examples
    --------
    >>> from dvr_perception.volume import Volume
    >>> v = Volume(np.zeros((2, 2, 2), np.uint8))
    >>> cam = patient_view(v, "anterior", width=8, height=8)
    >>> [round(float(c), 3) for c in cam.basis()[0]], cam.view_up
    ([0.0, 1.0, 0.0], (0.0, 0.0, 1.0))
    """
    if name not in PATIENT_VIEWS:
        raise DVRInputError(
            f"--view: unknown view {str(name)[:40]!r}; expected one of {', '.join(PATIENT_VIEWS)}"
        )
    if not (math.isfinite(zoom) and zoom > 0):
        raise DVRInputError(f"view: ZOOM must be a positive number, got {zoom}")
    b = np.asarray(volume.bounds, float)
    radius = 0.5 * float(np.linalg.norm(b[1::2] - b[0::2])) or 0.5
    dist = radius / math.sin(math.radians(view_angle) / 2.0) / zoom
    center = volume.to_world(volume.center)
    back, up = PATIENT_VIEWS[name]
    pos, new_up = _orbit(center, back, up, dist=dist, azimuth=azimuth, elevation=elevation)
    d = np.asarray(volume.direction)
    return Camera(
        position=tuple(volume.to_frame(pos)),
        focal_point=tuple(volume.to_frame(center)),
        view_up=tuple(new_up @ d),
        view_angle=view_angle,
        width=width,
        height=height,
    )


def default_camera(volume, view=None, *, width: int = 512, height: int = 512) -> Camera:
    """Return the camera a volume is first seen from.

    ``view`` (a spec's ``(azimuth, elevation, zoom)``) is relative to the down -z, +y up view
    (:meth:`Camera.from_view`), as ``--view A,E,Z`` is.  Without one, a volume whose patient
    orientation is known (``Volume.oriented``) is seen from the front, head up
    (:func:`patient_view` ``"anterior"``); a file without orientation keeps the down -z view.

    Examples
    --------
    >>> from dvr_perception.volume import Volume
    >>> v = Volume(np.zeros((2, 2, 2), np.uint8))
    >>> default_camera(v, width=8, height=8).view_up
    (0.0, 0.0, 1.0)
    >>> [abs(c) for c in default_camera(Volume(v.data, oriented=False)).view_up]
    [0.0, 1.0, 0.0]
    """
    if view is None and getattr(volume, "oriented", False):
        return patient_view(volume, "anterior", width=width, height=height)
    az, el, zoom = view if view is not None else (0.0, 0.0, 1.0)
    return Camera.from_view(
        volume.bounds, azimuth=az, elevation=el, zoom=zoom, width=width, height=height
    )


def patient_angles(volume, camera, name: str) -> tuple[float, float]:
    """Return the azimuth and elevation of ``camera`` from the patient view ``name``.

    The inverse of :func:`patient_view` for the camera's direction: a camera made by
    ``patient_view(volume, name, azimuth=a, elevation=e)`` gives ``(a, e)`` (for
    ``-90 < e < 90``), whatever ``volume``'s direction matrix.  Azimuth in ``(-180, 180]``.

    Examples
    --------
    >>> from dvr_perception.volume import Volume
    >>> v = Volume(np.zeros((4, 4, 4), np.uint8))
    >>> cam = patient_view(v, "left", azimuth=30.0, elevation=-10.0, width=8, height=8)
    >>> [round(a, 6) for a in patient_angles(v, cam, "left")]
    [30.0, -10.0]
    """
    if name not in PATIENT_VIEWS:
        raise DVRInputError(
            f"view {str(name)[:40]!r}: unknown patient view; expected one of "
            f"{', '.join(PATIENT_VIEWS)}"
        )
    d = np.asarray(camera.position, float) - np.asarray(camera.focal_point, float)
    # the camera is in the volume's frame; its direction in world (patient LPS) terms
    d = _unit(d @ np.asarray(volume.direction, float).T, "camera position - focal point")
    back, up = (np.asarray(v, float) for v in PATIENT_VIEWS[name])
    right = np.cross(up, back)
    el = math.degrees(math.asin(max(-1.0, min(1.0, float(d @ up)))))
    az = math.degrees(math.atan2(float(d @ right), float(d @ back)))
    return az, el


def parse_patient_view(text: str) -> tuple[str | None, float, float, float]:
    """Parse ``--view``: ``NAME[,A,E[,Z]]`` (a patient view) or ``A,E[,Z]``.

    Returns ``(name, azimuth, elevation, zoom)``; ``name`` is ``None`` for the numeric form
    (angles relative to the volume's default view, :meth:`Camera.from_view`).

    Examples
    --------
    >>> parse_patient_view("anterior")
    ('anterior', 0.0, 0.0, 1.0)
    >>> parse_patient_view("left,30,-10,2")
    ('left', 30.0, -10.0, 2.0)
    >>> parse_patient_view("30,-10")
    (None, 30.0, -10.0, 1.0)
    """
    head, _, rest = str(text).partition(",")
    name = head.strip().lower()
    try:
        float(name)
        numeric = True
    except ValueError:
        numeric = False
    if name and not numeric:
        if name not in PATIENT_VIEWS:
            raise DVRInputError(
                f"--view: unknown view {head.strip()[:40]!r}; expected A,E[,Z] or one of "
                f"{', '.join(PATIENT_VIEWS)} (optionally followed by ,A,E[,Z])"
            )
        if not rest.strip():
            return name, 0.0, 0.0, 1.0
        az, el, zoom = parse_view(rest)
        return name, az, el, zoom
    az, el, zoom = parse_view(text)
    return None, az, el, zoom


def parse_view(text: str) -> tuple[float, float, float]:
    """Parse ``"AZIMUTH,ELEVATION[,ZOOM]"``.

    Examples
    --------
    >>> parse_view("30,-10")
    (30.0, -10.0, 1.0)
    """
    parts = [p.strip() for p in str(text).split(",")]
    try:
        vals = [float(p) for p in parts]
    except ValueError:
        vals = []
    if len(vals) not in (2, 3) or not all(math.isfinite(v) for v in vals):
        raise DVRInputError(f"--view: expected AZIMUTH,ELEVATION[,ZOOM] numbers, got {text!r}")
    if len(vals) == 2:
        vals.append(1.0)
    if vals[2] <= 0:
        raise DVRInputError(f"--view: ZOOM must be positive, got {vals[2]}")
    return vals[0], vals[1], vals[2]
