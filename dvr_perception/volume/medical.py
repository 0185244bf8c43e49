"""DICOM (pydicom) and FreeSurfer MGH/MGZ (nibabel) readers: the ``medical`` extra.

``pip install 'dvr-perception[medical]'`` installs pydicom, its JPEG/JPEG 2000/JPEG-LS/RLE
pixel-data plug-ins (pylibjpeg) and nibabel.  Without them a DICOM folder falls back to
VTK's reader (no patient orientation) and a DICOM file or ``.mgz`` is refused with an error
naming the extra.

DICOM geometry: ``ImageOrientationPatient`` gives the row (index x) and column (index y)
directions, their cross product the slice normal; slices (files of a series, or frames of a
multi-frame file) are sorted by ``ImagePositionPatient`` projected on that normal -- never by
file name or instance number -- and the slice spacing is the step between those positions.
Pixel values go through ``RescaleSlope``/``RescaleIntercept`` (per frame in enhanced files;
``DoseGridScaling`` for RT dose), so a CT comes out in Hounsfield units.  Headers are read
first and checked (one series, grey-scale, sizes against the memory limit) before any pixel
data is decoded.

A folder is searched recursively (at most :data:`MAX_FILES` files, :data:`MAX_DEPTH` folder
levels, symbolic links not followed); several series in it are listed with the sub-folder each
lies in.  The files of the series read must total at most the memory limit (as VTK's DICOM
reader's folder is bounded in :mod:`dvr_perception.volume.io`).  Colour images (RGB, YBR) are
refused with one error: a DICOM colour image is a photograph or a rendering, not a measured
scalar, and a luminance made up from it has no unit that a transfer function's ranges could
mean.  A tilted-gantry series (slice positions stepping off the slice normal) is resampled
onto the regular grid along the normal, as 3D Slicer's acquisition-geometry regularisation
does: each slice is shifted in its plane by linear interpolation, with a warning naming the
tilt.
"""

from __future__ import annotations

import contextlib
import importlib.util
import math
import os
import warnings
from pathlib import Path

import numpy as np

from dvr_perception.errors import DVRInputError, DVRWarning
from dvr_perception.volume._limits import check_budget
from dvr_perception.volume.orient import from_axes, ras_to_lps
from dvr_perception.volume.volume import Volume

__all__ = ["available", "read_dicom", "read_mgh", "require"]

_EXTRA = "pip install 'dvr-perception[medical]'"
#: Most files a DICOM folder (with its sub-folders) may hold (headers are read one by one).
MAX_FILES = 20000
#: Deepest sub-folder level searched below a DICOM folder.
MAX_DEPTH = 8


def available(module: str = "pydicom") -> bool:
    """Return whether ``module`` (a package of the ``medical`` extra) can be imported."""
    return importlib.util.find_spec(module) is not None


def require(what: str, module: str = "pydicom") -> None:
    """Raise the one error that names the missing extra."""
    if not available(module):
        raise DVRInputError(
            f"{what} need the optional package {module!r}: install it with {_EXTRA}"
        )


def read_mgh(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return ``(data[z, y, x], axes, origin)`` (LPS) of a FreeSurfer ``.mgh``/``.mgz`` file."""
    require(f"{path}: FreeSurfer .mgz/.mgh files", "nibabel")
    import nibabel

    try:
        img = nibabel.load(str(path))
        shape = tuple(int(s) for s in img.shape)
        dtype = img.get_data_dtype()
    except Exception as exc:  # nibabel raises many types for a bad header
        raise DVRInputError(f"{path}: not a readable MGH/MGZ file ({str(exc)[:200]})") from None
    if len(shape) == 4 and shape[3] == 1:
        shape = shape[:3]
    if len(shape) != 3:
        raise DVRInputError(f"{path}: MGH field 'dims': expected a 3-D volume, got {shape}")
    check_budget(path, shape, dtype, "dims")
    try:
        data = np.asarray(img.dataobj).reshape(shape)
    except Exception as exc:
        raise DVRInputError(f"{path}: cannot read the voxel data ({str(exc)[:200]})") from None
    affine = np.asarray(img.affine, float)
    axes, origin = ras_to_lps(affine[:3, :3], affine[:3, 3])
    return np.ascontiguousarray(data.transpose(2, 1, 0)), axes, origin


# -- DICOM -----------------------------------------------------------------------------------


def _floats(ds, keyword: str, n: int, where: str) -> np.ndarray:
    value = getattr(ds, keyword, None)
    try:
        out = np.array([float(v) for v in value], float)
    except (TypeError, ValueError):
        out = np.zeros(0)
    if out.shape != (n,) or not np.all(np.isfinite(out)):
        raise DVRInputError(
            f"{where}: DICOM field {keyword!r}: expected {n} numbers, got {str(value)[:80]}"
        )
    return out


def _headers(path: Path) -> list[tuple[Path, object]]:
    import pydicom
    from pydicom.errors import InvalidDicomError

    if path.is_dir():
        files = _walk(path)
        if not files:
            raise DVRInputError(f"{path}: the directory holds no files (expected a DICOM series)")
    else:
        files = [path]
    out = []
    for f in files:
        try:
            # large elements (private blobs) stay on disk; pixel data is not read here
            ds = pydicom.dcmread(f, stop_before_pixels=True, defer_size="1 MB")
            image = "Rows" in ds and "Columns" in ds
        except InvalidDicomError as exc:
            if path.is_dir():
                continue  # not a DICOM file: other files may sit beside a series
            raise DVRInputError(f"{f}: not a DICOM file ({str(exc)[:200]})") from None
        except Exception as exc:  # a corrupt header: pydicom raises many types
            raise DVRInputError(f"{f}: unreadable DICOM header ({str(exc)[:200]})") from None
        if image:
            out.append((f, ds))
    if not out:
        raise DVRInputError(f"{path}: no DICOM image files found")
    return out


def _walk(root: Path) -> list[Path]:
    """Return the regular files below ``root`` (sorted), at most :data:`MAX_FILES`."""
    files: list[Path] = []
    for folder, dirs, names in os.walk(root, followlinks=False):
        depth = len(Path(folder).relative_to(root).parts)
        if depth >= MAX_DEPTH:
            dirs[:] = []  # not deeper
        dirs.sort()
        for name in sorted(names):
            f = Path(folder) / name
            if name == "DICOMDIR" or not f.is_file() or f.is_symlink():
                continue
            files.append(f)
            if len(files) > MAX_FILES:
                raise DVRInputError(
                    f"{root}: more than {MAX_FILES} files in the folder and its sub-folders; "
                    "point to the folder of one study or series"
                )
    return sorted(files)


def _check_series_bytes(path: Path, files) -> None:
    """Refuse a series whose files (read whole) hold more bytes than the memory limit."""
    from dvr_perception import _memory as memory

    total = sum(f.stat().st_size for f in files)
    cap = memory.limit()
    if total > cap:
        raise DVRInputError(
            f"{path}: the series' {len(files)} DICOM files hold {total / 2**20:.0f} MiB, more "
            f"than the memory limit of {cap / 2**20:.0f} MiB; raise it with --memory-limit "
            f"(or {memory.ENV})"
        )


def _pick_series(path: Path, headers, series: str | None):
    groups: dict[str, list] = {}
    for f, ds in headers:
        groups.setdefault(str(getattr(ds, "SeriesInstanceUID", "")), []).append((f, ds))
    if series is not None:
        if series not in groups:
            raise DVRInputError(
                f"{path}: --series {series[:80]!r} not found; the folder holds "
                f"{_describe(groups, path)}"
            )
        return groups[series]
    if len(groups) > 1:
        raise DVRInputError(
            f"{path}: the folder holds {len(groups)} DICOM series; choose one with --series "
            f"UID: {_describe(groups, path)}"
        )
    return next(iter(groups.values()))


def _describe(groups, root: Path) -> str:
    parts = []
    for uid, items in sorted(groups.items()):
        ds = items[0][1]
        desc = str(getattr(ds, "SeriesDescription", "") or getattr(ds, "Modality", ""))
        where = ""
        if root.is_dir():
            folders = sorted({str(f.parent.relative_to(root)) for f, _ in items})
            shown = ", ".join(folders[:3]) + (", ..." if len(folders) > 3 else "")
            where = f" in {shown}" if folders != ["."] else ""
        parts.append(
            f"{uid or '(no UID)'} ({len(items)} file(s){where}{', ' + desc if desc else ''})"
        )
    return "; ".join(parts)


def _pixel_dtype(ds, where: str) -> np.dtype:
    bits = int(getattr(ds, "BitsAllocated", 0) or 0)
    samples = int(getattr(ds, "SamplesPerPixel", 1) or 1)
    photometric = str(getattr(ds, "PhotometricInterpretation", "") or "").strip()
    if samples != 1 or photometric.startswith(("RGB", "YBR", "PALETTE")):
        raise DVRInputError(
            f"{where}: a colour DICOM image (DICOM field 'SamplesPerPixel' is {samples}, "
            f"'PhotometricInterpretation' {photometric or 'missing'}); expected 1 sample per "
            "pixel, grey-scale (MONOCHROME1/2): volume rendering needs measured scalar values"
        )
    if bits not in (8, 16, 32):
        raise DVRInputError(f"{where}: DICOM field 'BitsAllocated' is {bits}; expected 8, 16, 32")
    signed = int(getattr(ds, "PixelRepresentation", 0) or 0) == 1
    return np.dtype(f"{'i' if signed else 'u'}{bits // 8}")


def _int(ds, keyword: str, where: str) -> int:
    try:
        return int(getattr(ds, keyword))
    except (TypeError, ValueError, AttributeError):
        raise DVRInputError(
            f"{where}: DICOM field {keyword!r}: expected an integer, got "
            f"{str(getattr(ds, keyword, None))[:40]}"
        ) from None


def _check_sizes(where: str, ds, frames: int) -> None:
    """Refuse Rows x Columns x frames x BitsAllocated beyond the memory limit (pre-pixels)."""
    dt = _pixel_dtype(ds, where)
    rows, cols = _int(ds, "Rows", where), _int(ds, "Columns", where)
    if rows < 1 or cols < 1 or frames < 1:
        raise DVRInputError(f"{where}: DICOM fields 'Rows'/'Columns': empty image {rows}x{cols}")
    check_budget(where, (cols, rows, frames), dt, "Rows x Columns x NumberOfFrames x BitsAllocated")
    # the decoded float volume (rescaled values) also has to fit
    check_budget(where, (cols, rows, frames), np.float32, "Rows x Columns x NumberOfFrames")


def _pixels(f: Path, where: str):
    import pydicom

    try:
        ds = pydicom.dcmread(f)
        arr = ds.pixel_array
    except Exception as exc:  # decoders raise many types (missing plug-in, corrupt stream)
        ts = ""
        with contextlib.suppress(Exception):
            ts = f" (transfer syntax {ds.file_meta.TransferSyntaxUID.name})"
        why = " ".join(str(exc).split())[:300]
        raise DVRInputError(
            f"{where}: cannot decode the pixel data{ts}: {why}; {_plugins_hint()}"
        ) from None
    return ds, np.asarray(arr)


#: pydicom's JPEG plug-ins (the ``medical`` extra and ``paraview/pvdeps-requirements.txt``).
JPEG_PLUGINS = ("pylibjpeg", "libjpeg", "openjpeg")


def _plugins_hint() -> str:
    """Which JPEG plug-ins are missing and how to install them here (pip or ParaView)."""
    import sys

    names = {"pylibjpeg": "pylibjpeg", "libjpeg": "pylibjpeg-libjpeg",
             "openjpeg": "pylibjpeg-openjpeg"}  # fmt: skip
    missing = [names[m] for m in JPEG_PLUGINS if not available(m)]
    have = f"missing here: {', '.join(missing)}" if missing else "all installed here"
    how = (
        "in ParaView they come from .pvdeps: run make paraview-setup"
        if "paraview" in sys.modules
        else f"install them with {_EXTRA}"
    )
    return (
        "compressed files need pydicom's plug-ins pylibjpeg with pylibjpeg-libjpeg (JPEG, "
        f"JPEG-LS) and pylibjpeg-openjpeg (JPEG 2000) ({have}; {how})"
    )


def _rescale(ds, where: str) -> tuple[float, float]:
    slope = float(getattr(ds, "RescaleSlope", 1) or 1)
    inter = float(getattr(ds, "RescaleIntercept", 0) or 0)
    if "DoseGridScaling" in ds:
        slope *= float(ds.DoseGridScaling)
    if not (np.isfinite(slope) and np.isfinite(inter)) or slope == 0:
        raise DVRInputError(f"{where}: DICOM fields 'RescaleSlope'/'RescaleIntercept' invalid")
    return slope, inter


def _apply(frames: list[np.ndarray], scales: list[tuple[float, float]]) -> np.ndarray:
    """Stack the frames with their rescale, into one pre-allocated array of the output type.

    Integer slopes and intercepts keep integers (int16 when the values fit, else int32);
    others give float32.  No whole-volume intermediate of a wider type is made.
    """
    shape = (len(frames), *frames[0].shape)
    if all(s == (1.0, 0.0) for s in scales):
        out = np.empty(shape, frames[0].dtype)
        for k, f in enumerate(frames):
            out[k] = f
        return out
    whole = frames[0].dtype.kind in "ui" and all(
        float(s).is_integer() and float(i).is_integer() for s, i in scales
    )
    dtype: type = np.float32
    if whole:
        ends = [v * s + i for f, (s, i) in zip(frames, scales, strict=True)
                for v in (int(f.min()), int(f.max()))]  # fmt: skip
        lo, hi = min(ends), max(ends)
        fits = [
            dt for dt in (np.int16, np.int32) if np.iinfo(dt).min <= lo <= hi <= np.iinfo(dt).max
        ]
        dtype = fits[0] if fits else np.float32
    out = np.empty(shape, dtype)
    for k, (f, (s, i)) in enumerate(zip(frames, scales, strict=True)):
        if dtype is np.float32:
            out[k] = f * np.float32(s) + np.float32(i)
        else:
            out[k] = f.astype(np.int64) * int(s) + int(i)
    return out


def _item(seq_owner, keyword: str):
    seq = getattr(seq_owner, keyword, None)
    return seq[0] if seq else None


def _frame_geometry(ds, index: int, where: str):
    """(position, orientation, pixel spacing, rescale) of frame ``index`` of an enhanced file."""
    shared = _item(ds, "SharedFunctionalGroupsSequence")
    per = ds.PerFrameFunctionalGroupsSequence[index]

    def find(group: str):
        for owner in (per, shared):
            if owner is not None and _item(owner, group) is not None:
                return _item(owner, group)
        return None

    pos = find("PlanePositionSequence")
    ori = find("PlaneOrientationSequence")
    pix = find("PixelMeasuresSequence")
    if pos is None or ori is None or pix is None:
        raise DVRInputError(
            f"{where}: enhanced DICOM frame {index + 1} lacks its plane position, orientation "
            "or pixel measures"
        )
    trans = find("PixelValueTransformationSequence")
    scale = _rescale(trans, where) if trans is not None else _rescale(ds, where)
    return (
        _floats(pos, "ImagePositionPatient", 3, where),
        _floats(ori, "ImageOrientationPatient", 6, where),
        _floats(pix, "PixelSpacing", 2, where),
        scale,
    )


def read_dicom(path: Path, *, name: str, series: str | None = None) -> Volume:
    """Read a DICOM series folder or a multi-frame DICOM file into a canonical LPS volume.

    Parameters
    ----------
    path : pathlib.Path
        A folder of single-frame files (one series, or pick one with ``series``) or one
        multi-frame file (enhanced, or legacy with ``GridFrameOffsetVector`` as RT dose).
    name : str
        Volume name.
    series : str, optional
        SeriesInstanceUID to read from a folder that holds several series.

    Raises
    ------
    DVRInputError
        Several series without ``series`` (the message lists them), missing or inconsistent
        geometry, colour images, sizes beyond the memory limit, undecodable pixel data.
    """
    require(f"{path}: DICOM files")
    try:
        return _read(path, name=name, series=series)
    except DVRInputError:
        raise
    except MemoryError:
        raise
    except Exception as exc:  # pydicom parses elements lazily: a corrupt
        # value raises on first access (ValueError, NotImplementedError for an unknown VR,
        # struct.error, ...) in a field the checks above do not name one by one
        raise DVRInputError(
            f"{path}: malformed DICOM header value ({type(exc).__name__}: {str(exc)[:200]})"
        ) from None


def _read(path: Path, *, name: str, series: str | None) -> Volume:
    headers = _pick_series(path, _headers(path), series)
    if len(headers) == 1:
        return _read_multiframe(*headers[0], name=name, source=str(path))
    first = headers[0][1]
    _check_sizes(str(path), first, len(headers))
    _check_series_bytes(path, [f for f, _ in headers])
    entries = []
    for f, ds in headers:
        where = str(f)
        _pixel_dtype(ds, where)  # every file grey-scale, not only the first
        if int(getattr(ds, "NumberOfFrames", 1) or 1) != 1:
            raise DVRInputError(f"{where}: a multi-frame file inside a series; read it alone")
        if (int(ds.Rows), int(ds.Columns)) != (int(first.Rows), int(first.Columns)):
            raise DVRInputError(
                f"{where}: DICOM fields 'Rows'/'Columns' {ds.Rows}x{ds.Columns} differ from the "
                f"series' {first.Rows}x{first.Columns}"
            )
        entries.append(
            (
                _floats(ds, "ImagePositionPatient", 3, where),
                _floats(ds, "ImageOrientationPatient", 6, where),
                _floats(ds, "PixelSpacing", 2, where),
                f,
            )
        )
    order, axes, origin, shear = _stack_geometry([(p, o, s) for p, o, s, _ in entries], str(path))
    frames, scales = [], []
    for i in order:
        f = entries[i][3]
        ds, arr = _pixels(f, str(f))
        if arr.shape != (int(first.Rows), int(first.Columns)):
            raise DVRInputError(f"{f}: decoded pixel data has shape {arr.shape}")
        frames.append(arr)
        scales.append(_rescale(ds, str(f)))
    data = _regularise(_apply(frames, scales), shear)
    return from_axes(data, axes, origin, name=name, source=str(path), where=str(path))


def _read_multiframe(f: Path, ds, *, name: str, source: str) -> Volume:
    where = str(f)
    n = _int(ds, "NumberOfFrames", where) if ds.get("NumberOfFrames") else 1
    if n < 2:
        raise DVRInputError(
            f"{where}: a single 2-D image (NumberOfFrames {n}); expected a series folder or a "
            "multi-frame file"
        )
    _check_sizes(where, ds, n)
    if "PerFrameFunctionalGroupsSequence" in ds:
        geo = [_frame_geometry(ds, i, where) for i in range(n)]
        scales = [g[3] for g in geo]
        order, axes, origin, shear = _stack_geometry([g[:3] for g in geo], where)
    elif "GridFrameOffsetVector" in ds:
        ipp = _floats(ds, "ImagePositionPatient", 3, where)
        iop = _floats(ds, "ImageOrientationPatient", 6, where)
        ps = _floats(ds, "PixelSpacing", 2, where)
        offsets = _floats(ds, "GridFrameOffsetVector", n, where)
        normal = np.cross(iop[:3], iop[3:])
        slices = [(ipp + off * normal, iop, ps) for off in offsets]
        order, axes, origin, shear = _stack_geometry(slices, where)
        scales = [_rescale(ds, where)] * n
    else:
        raise DVRInputError(
            f"{where}: multi-frame DICOM without per-frame positions "
            "(PerFrameFunctionalGroupsSequence or GridFrameOffsetVector)"
        )
    _full, arr = _pixels(f, where)
    if arr.shape != (n, int(ds.Rows), int(ds.Columns)):
        raise DVRInputError(f"{where}: decoded pixel data has shape {arr.shape}")
    data = _regularise(_apply([arr[i] for i in order], [scales[i] for i in order]), shear)
    return from_axes(data, axes, origin, name=name, source=source, where=where)


def _stack_geometry(slices, where: str):
    """Sort slices along their normal; return ``(order, axes, origin, shear)``.

    ``slices`` holds ``(ImagePositionPatient, ImageOrientationPatient, PixelSpacing)``.
    ``shear`` is ``None`` when the positions lie on a line along the normal; for a tilted
    gantry (positions stepping evenly off the normal) it is the in-plane step per slice in
    pixels, ``(rows, columns)``, that :func:`_regularise` undoes.
    """
    _pos0, iop, ps = slices[0]
    for _p, o, s in slices[1:]:
        if not (np.allclose(o, iop, atol=1e-4) and np.allclose(s, ps, rtol=1e-4)):
            raise DVRInputError(
                f"{where}: DICOM fields 'ImageOrientationPatient'/'PixelSpacing' differ between "
                "slices; expected one regular grid"
            )
    row, col = iop[:3], iop[3:]
    normal = np.cross(row, col)
    if not np.isclose(np.linalg.norm(normal), 1.0, atol=1e-3):
        raise DVRInputError(
            f"{where}: DICOM field 'ImageOrientationPatient' {iop.tolist()} is not two "
            "orthonormal vectors"
        )
    depth = np.array([float(np.dot(p, normal)) for p, _, _ in slices])
    order = np.argsort(depth, kind="stable")
    steps = np.diff(depth[order])
    if np.any(steps <= 1e-6 * max(1.0, float(np.abs(depth).max()))):
        raise DVRInputError(
            f"{where}: two slices share the position {float(depth[order][np.argmin(steps)]):g} "
            "mm along the slice normal (ImagePositionPatient); expected one slice per position"
        )
    dz = float(np.median(steps))
    if np.max(np.abs(steps - dz)) > 0.01 * dz + 1e-4:
        raise DVRInputError(
            f"{where}: slice spacing varies from {steps.min():g} to {steps.max():g} mm "
            "(ImagePositionPatient); expected evenly spaced slices"
        )
    first = slices[order[0]][0]
    # in-plane offset of each slice (in sorted order) from the first one
    offsets = np.array([slices[i][0] - first for i in order])
    offsets -= np.outer(offsets @ normal, normal)
    tol = 1e-3 * max(1.0, dz)
    axes = np.column_stack([row * ps[1], col * ps[0], normal * dz])
    if np.all(np.abs(offsets) <= tol):
        return [int(i) for i in order], axes, first, None
    step = offsets[-1] / (len(order) - 1)
    linear = offsets - np.outer(np.arange(len(order)), step)
    if np.any(np.abs(linear) > tol):
        raise DVRInputError(
            f"{where}: the slices' ImagePositionPatient lie neither on one line along the slice "
            "normal nor on one evenly tilted line (a varying gantry tilt or table shift); "
            "expected one regular grid"
        )
    tilt = math.degrees(math.atan2(float(np.linalg.norm(step)), dz))
    warnings.warn(
        f"{where}: tilted gantry ({tilt:.2f} degrees: the slices step {np.linalg.norm(step):.3g} "
        "mm off the slice normal); resampled onto the regular grid along the normal",
        DVRWarning,
        stacklevel=4,
    )
    # pixels per slice (rounded: a whole-pixel step must move pixels exactly)
    shear = (round(float(step @ col) / ps[0], 6), round(float(step @ row) / ps[1], 6))
    return [int(i) for i in order], axes, first, shear


def _regularise(data: np.ndarray, shear) -> np.ndarray:
    """Shift slice ``k`` of a tilted-gantry stack by ``k * shear`` pixels (linear, in place).

    Output voxel ``(i, j, k)`` lies at ``first + i*row + j*col + k*dz*normal``; in the
    acquired slice ``k`` that point is pixel ``(j, i) - k * shear``.  Pixels shifted in from
    outside the slice get the volume's minimum; integer data are rounded back.
    """
    if shear is None:
        return data
    from scipy import ndimage

    fill = float(data.min())
    for k in range(1, data.shape[0]):
        moved = ndimage.shift(
            data[k].astype(np.float64),
            (k * shear[0], k * shear[1]),
            order=1,
            mode="grid-constant",
            cval=fill,
        )
        data[k] = np.rint(moved) if data.dtype.kind in "ui" else moved
    return data
