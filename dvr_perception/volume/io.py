"""Read and write volumes: NRRD/NHDR, MetaImage, VTI, legacy VTK, NIfTI, MGZ, DICOM, raw.

:func:`load_volume` picks the reader from the file extension (a directory is read as a DICOM
series) and :func:`save_volume` the writer.  Every failure is one
:class:`~dvr_perception.errors.DVRInputError` that names the file.

NRRD is parsed and written by :mod:`dvr_perception.volume._nrrd` (not with ``vtkNrrdReader``,
which reads a short first axis as vector components).
Headerless raw files follow the shared-data naming ``NAME_XxYxZ_DTYPE.raw`` (little-endian,
x fastest).  DICOM and MGZ go through pydicom and nibabel (:mod:`dvr_perception.volume.medical`,
the ``medical`` extra), the other formats through VTK's readers and writers.

Geometry: every reader yields an origin and one world (patient LPS) vector per index axis;
:func:`dvr_perception.volume.orient.from_axes` applies flips and permutations to the data order,
so volumes come out axis-aligned unless the file's grid is oblique.

Headers are untrusted (:mod:`dvr_perception.volume._limits`): a detached data file must lie in
the header's folder (or a folder allowed with ``DVR_PERCEPTION_DATA_ROOTS``), and the sizes,
spacing, encoding and file size are checked against each other and the memory limit before
any data is read; compressed data is decompressed with a bound.
"""

from __future__ import annotations

import os
import re
import shutil
import tempfile
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np

from dvr_perception.errors import DVRInputError, DVRWarning
from dvr_perception.volume._headers import (
    Layout,
    check_nifti,
    legacy_layout,
    meta_layout,
    read_layout,
    vti_layout,
)
from dvr_perception.volume._limits import check_budget, check_size, parse_int
from dvr_perception.volume._nrrd import nrrd_axes, nrrd_header, nrrd_space, read_nrrd, write_nrrd
from dvr_perception.volume.orient import from_axes, ras_to_lps
from dvr_perception.volume.volume import Volume

__all__ = ["check_volume_file", "header_axes", "load_volume", "save_volume"]


class _LazyVTK:
    """:mod:`dvr_perception._vtk`, imported when a VTK class is first asked for.

    NRRD, raw and the other formats we parse ourselves load without ``vtkmodules`` (a GPU
    machine without VTK); the VTK readers and writers import it on use.
    """

    def __getattr__(self, name: str):
        from dvr_perception import _vtk as module

        return getattr(module, name)


_vtk = _LazyVTK()


def from_vtk_image(*args, **kwargs):
    """:func:`dvr_perception.volume.convert.from_vtk_image` (imported on use: VTK)."""
    from dvr_perception.volume.convert import from_vtk_image as convert

    return convert(*args, **kwargs)


def to_vtk_image(*args, **kwargs):
    """:func:`dvr_perception.volume.convert.to_vtk_image` (imported on use: VTK)."""
    from dvr_perception.volume.convert import to_vtk_image as convert

    return convert(*args, **kwargs)


def vtk_errors(*args, **kwargs):
    """:func:`dvr_perception.volume.convert.vtk_errors` (imported on use: VTK)."""
    from dvr_perception.volume.convert import vtk_errors as convert

    return convert(*args, **kwargs)


RAW_DTYPES = ("uint8", "int8", "uint16", "int16", "uint32", "int32", "float32", "float64")
_RAW_NAME = re.compile(r"^(?P<name>.+)_(?P<x>\d+)x(?P<y>\d+)x(?P<z>\d+)_(?P<dtype>\w+)\.raw$")
_FORMATS = (".nhdr", ".nrrd", ".mha", ".mhd", ".vti", ".vtk", ".nii", ".nii.gz", ".mgz", ".mgh")
_FORMATS += (".dcm", ".raw")
#: Formats parsed by :mod:`._headers` and read by our own code (VTK never opens them).
_LAYOUTS = {".mha": meta_layout, ".mhd": meta_layout, ".vti": vti_layout, ".vtk": legacy_layout}
_WRITABLE = (".vti", ".nhdr", ".nrrd", ".mha", ".mhd", ".nii", ".nii.gz", ".vtk")


def _ext(path: Path) -> str:
    name = path.name.lower()
    return ".nii.gz" if name.endswith(".nii.gz") else path.suffix.lower()


def _stem(path: Path) -> str:
    if path.is_dir():
        return path.name
    ext = _ext(path)
    stem = path.name[: -len(ext)] if ext else path.name
    m = _RAW_NAME.match(path.name) if ext == ".raw" else None
    return m.group("name") if m else stem


def load_volume(path, *, name: str | None = None, series: str | None = None) -> Volume:
    """Read a volume file (or a DICOM series folder) into a :class:`Volume`.

    Parameters
    ----------
    path : str or os.PathLike
        ``.nhdr`` (detached NRRD, ``data file:`` beside it), ``.nrrd``, ``.mha``/``.mhd``,
        ``.vti``, legacy ``.vtk`` structured points, ``.nii``/``.nii.gz``, ``.mgz``/``.mgh``,
        a ``.dcm`` file (multi-frame DICOM), a folder of DICOM files, or headerless
        ``NAME_XxYxZ_DTYPE.raw``.
    name : str, optional
        Volume name; default the file stem (``cthead.nhdr`` -> ``"cthead"``,
        ``engine_256x256x128_uint8.raw`` -> ``"engine"``).
    series : str, optional
        DICOM only: the SeriesInstanceUID to read from a folder that holds several series.

    Returns
    -------
    Volume
        Data indexed ``[z, y, x]`` in patient LPS coordinates (millimetres): the file's
        origin, spacing and axis directions are honoured, NIfTI/FreeSurfer RAS is converted,
        and axis flips and permutations are applied to the data order
        (:func:`dvr_perception.volume.orient.canonical`), so the direction is the identity
        unless the file's grid is oblique.  A file without orientation (``spacings`` only,
        raw) is taken as LPS-aligned.

    Raises
    ------
    DVRInputError
        Missing file, unknown extension, bad header, truncated data, unsupported type,
        non-finite voxels, multi-component or non-image data, a DICOM file or ``.mgz``
        without the ``medical`` extra installed; the message names the file.

    Examples
    --------
    >>> import numpy as np, tempfile, os
    >>> from dvr_perception.volume import Volume
    >>> d = tempfile.mkdtemp()
    >>> vol = Volume(np.arange(24, dtype=np.uint8).reshape(2, 3, 4), spacing=(1, 1, 2))
    >>> save_volume(vol, os.path.join(d, "demo.nhdr"))
    >>> back = load_volume(os.path.join(d, "demo.nhdr"))
    >>> back.name, back.dims, back.spacing
    ('demo', (4, 3, 2), (1.0, 1.0, 2.0))
    """
    path = Path(os.fspath(path))
    if not path.exists():
        raise DVRInputError(f"{path}: file not found")
    vname = str(name) if name is not None else _stem(path)
    ext = "" if path.is_dir() else _ext(path)
    if series is not None and not (path.is_dir() or ext == ".dcm"):
        raise DVRInputError(f"{path}: --series applies to DICOM only")
    if path.is_dir() or ext == ".dcm":
        return _read_dicom(path, vname, series)
    if ext not in _FORMATS:
        raise DVRInputError(
            f"{path}: unknown volume format {ext or '(no extension)'!r}; expected one of "
            f"{', '.join(_FORMATS)} or a DICOM series directory"
        )
    if path.stat().st_size == 0:
        raise DVRInputError(f"{path}: the file is empty (0 bytes)")
    oriented = True  # whether the file records the patient orientation
    if ext in (".nhdr", ".nrrd"):
        data, axes, origin, oriented = read_nrrd(path)
    elif ext == ".raw":
        data, axes, origin = _read_raw(path), np.eye(3), (0.0, 0.0, 0.0)
        oriented = False
    elif ext in (".mgz", ".mgh"):
        from dvr_perception.volume.medical import read_mgh

        data, axes, origin = read_mgh(path)
    elif ext in _LAYOUTS:
        layout = _LAYOUTS[ext](path)
        data, axes, origin = read_layout(layout), layout.axes, layout.origin
        oriented = layout.oriented
    else:  # NIfTI: checked exactly as VTK's reader parses it, then read by it
        check_nifti(path, ext)
        return _read_vtk(_vtk.vtkNIFTIImageReader(), path, vname, oriented=True)
    if data.size == 0:
        raise DVRInputError(f"{path}: the volume is empty (shape (z, y, x) = {data.shape})")
    where = str(path)
    return from_axes(data, axes, origin, name=vname, source=where, where=where, oriented=oriented)


def header_axes(path) -> np.ndarray | None:
    """Return a NRRD, MetaImage, ``.vti`` or legacy ``.vtk`` file's axis vectors (LPS columns).

    From the header alone, parsed and checked exactly as :func:`load_volume` parses it (sizes
    against the memory limit, the data file inside the allowed folders, attached raw data
    complete), so a file passed here is one VTK's readers read the same way.  ``None`` for
    other formats.  For callers that must not read the data, e.g. the MPI path
    of ``dvr-perception pvbatch``, whose ranks read their pieces with ParaView's readers in
    file order: they need to know whether the file's axes are flipped, permuted or rotated.

    Raises
    ------
    DVRInputError
        A malformed header (the message names the file and field).

    Examples
    --------
    >>> import tempfile, os
    >>> d = tempfile.mkdtemp()
    >>> save_volume(Volume(np.zeros((2, 2, 2), np.uint8), spacing=(1, 1, 2)), f"{d}/v.nrrd")
    >>> np.diag(header_axes(f"{d}/v.nrrd")).tolist()
    [1.0, 1.0, 2.0]
    """
    path = Path(os.fspath(path))
    ext = "" if path.is_dir() else _ext(path)
    if ext in (".nhdr", ".nrrd"):
        read_nrrd(path, check_only=True)  # sizes, budget, data file: as load_volume
        fields, _ = nrrd_header(path)
        axes = nrrd_axes(fields, path)
        space = nrrd_space(fields, path)
        if space == "ras":
            axes, _ = ras_to_lps(axes, np.zeros(3))
        elif space == "las":
            axes = axes * [[-1.0], [1.0], [1.0]]
        return axes
    if ext in _LAYOUTS:
        return _LAYOUTS[ext](path).axes
    return None


def check_volume_file(path, *, limit: int | None = None, hint: str | None = None):
    """Check a volume file's header exactly as :func:`load_volume` reads it; read no voxels.

    The one parse that :func:`load_volume` also uses: sizes and type against ``limit`` (bytes;
    default the memory limit, ``hint`` says how to raise it), the data file inside the allowed
    folders, the data complete.  For the web app's upload check, the ParaView reader and
    ``pvbatch``.

    Returns
    -------
    tuple
        ``(dims, dtype, data_file)``: points along x, y, z, the stored voxel type, and the file
        holding the voxels (``path`` itself for attached data; ``None`` where VTK reads it).

    Raises
    ------
    DVRInputError
        Everything :func:`load_volume` would refuse from the header (the message names the
        file and the field); formats read without a header (raw, DICOM, MGZ) are only
        checked for their existence here.

    Examples
    --------
    >>> import tempfile, os
    >>> d = tempfile.mkdtemp()
    >>> save_volume(Volume(np.zeros((2, 3, 4), np.int16)), f"{d}/v.mha")
    >>> dims, dtype, src = check_volume_file(f"{d}/v.mha")
    >>> dims, dtype.name, src.name
    ((4, 3, 2), 'int16', 'v.mha')
    >>> check_volume_file(f"{d}/v.mha", limit=10, hint="--max-volume-mb")
    Traceback (most recent call last):
    ...
    dvr_perception.errors.DVRInputError: ...v.mha: field 'DimSize': sizes 4 3 2 of int16 need 0.0 MB, more than the limit of 0.0 MB; raise it with --max-volume-mb
    """  # noqa: E501
    path = Path(os.fspath(path))
    if not path.exists():
        raise DVRInputError(f"{path}: file not found")
    ext = "" if path.is_dir() else _ext(path)
    if ext in _LAYOUTS:
        layout: Layout = _LAYOUTS[ext](path, limit=limit, hint=hint)
        return layout.dims, layout.dtype, layout.data_file
    if ext in (".nii", ".nii.gz"):
        dims, dtype = check_nifti(path, ext, limit=limit, hint=hint)
        return dims, dtype, path
    if ext in (".nhdr", ".nrrd"):
        return read_nrrd(path, limit=limit, hint=hint, check_only=True)
    return None, None, None


def _read_dicom(path: Path, name: str, series: str | None) -> Volume:
    from dvr_perception.volume import medical

    if medical.available():
        return medical.read_dicom(path, name=name, series=series)
    if not path.is_dir() or series is not None:
        medical.require("DICOM files and --series")
    warnings.warn(
        f"{path}: read with VTK's DICOM reader (pip install 'dvr-perception[medical]' for "
        "patient orientation, several series, multi-frame and compressed files): rows "
        "bottom-up, slices by position, origin 0",
        DVRWarning,
        stacklevel=3,
    )
    _check_dicom_folder_size(path)
    return _read_vtk(_vtk.vtkDICOMImageReader(), path, name, dicom=True, oriented=False)


def _check_dicom_folder_size(path: Path) -> None:
    """Bound VTK's DICOM reader before it reads: its voxels never outnumber the files' bytes.

    VTK's reader decodes only uncompressed pixel data, so the folder's regular files hold at
    least as many bytes as the volume it makes; their total must fit the memory limit.
    """
    from dvr_perception import _memory as memory

    total = 0
    with os.scandir(path) as entries:
        for entry in entries:
            if entry.is_file(follow_symlinks=False):
                total += entry.stat(follow_symlinks=False).st_size
    cap = memory.limit()
    if total > cap:
        raise DVRInputError(
            f"{path}: the DICOM files hold {total / 2**20:.0f} MiB, more than the memory limit "
            f"of {cap / 2**20:.0f} MiB that VTK's DICOM reader may fill; raise it with "
            f"--memory-limit (or {memory.ENV}), or install the medical extra, which checks "
            "each header first"
        )


def _read_vtk(reader, path: Path, name: str, *, dicom: bool = False, oriented=True) -> Volume:
    if dicom:
        if not any(p.is_file() for p in path.iterdir()):
            raise DVRInputError(f"{path}: the directory holds no files (expected a DICOM series)")
        reader.SetDirectoryName(str(path))
    else:
        reader.SetFileName(str(path))
    with vtk_errors(reader, str(path)):
        reader.Update()
    out = reader.GetOutput()
    if out is None or not out.IsA("vtkImageData"):
        found = out.GetClassName() if out is not None else "nothing"
        raise DVRInputError(f"{path}: holds {found}; expected image data (structured points)")
    if out.GetNumberOfPoints() == 0:
        raise DVRInputError(f"{path}: the volume is empty (dimensions {out.GetDimensions()})")
    if out.GetPointData().GetNumberOfArrays() == 0 and out.GetCellData().GetNumberOfArrays() == 0:
        raise DVRInputError(f"{path}: VTK read no voxel data from the file")
    own_geometry = (_vtk.vtkNIFTIImageReader, _vtk.vtkMetaImageReader)
    if isinstance(reader, own_geometry) and hasattr(out, "SetDirectionMatrix"):
        out.SetDirectionMatrix(1, 0, 0, 0, 1, 0, 0, 0, 1)  # the header is applied below
    vol = from_vtk_image(out, name=name, source=str(path), oriented=oriented)
    if isinstance(reader, _vtk.vtkNIFTIImageReader):
        vol = _nifti_geometry(reader, vol)
    return vol


def _nifti_geometry(reader, vol: Volume) -> Volume:
    # vtkNIFTIImageReader gives data coordinates (origin + spacing * index, with the slice
    # order already reversed when qfac is -1) and the matrix from them to RAS.  The s-form
    # wins when its code is set (as nibabel's best affine), else the q-form.
    m = reader.GetSFormMatrix() or reader.GetQFormMatrix()
    if m is None:  # neither form is set: the file records no orientation
        return replace(vol, oriented=False)
    mat = np.array([[m.GetElement(i, j) for j in range(4)] for i in range(3)])
    rot, shift = mat[:, :3], mat[:, 3]
    axes = rot * np.asarray(vol.spacing)
    origin = rot @ np.asarray(vol.origin) + shift
    axes, origin = ras_to_lps(axes, origin)
    where = f"{vol.source}: NIfTI s-form/q-form"
    return from_axes(vol.data, axes, origin, name=vol.name, source=vol.source, where=where)


def _read_raw(path: Path) -> np.ndarray:
    m = _RAW_NAME.match(path.name)
    if m is None:
        raise DVRInputError(
            f"{path}: a headerless raw file must be named NAME_XxYxZ_DTYPE.raw "
            "(e.g. engine_256x256x128_uint8.raw)"
        )
    dtype = m.group("dtype").lower()
    if dtype not in RAW_DTYPES:
        raise DVRInputError(
            f"{path}: unsupported raw dtype {dtype!r} in the file name; expected one of "
            f"{', '.join(RAW_DTYPES)}"
        )
    dims = tuple(parse_int(m.group(a), path, "file name", lo=0) for a in "xyz")
    if 0 in dims:
        raise DVRInputError(f"{path}: the volume is empty (dims {dims} in the file name)")
    dt = np.dtype(dtype).newbyteorder("<")
    check_size(path, path.stat().st_size, check_budget(path, dims, dt, "file name"), dims)
    return np.fromfile(path, dtype=dt).reshape(dims[::-1]).astype(dt.newbyteorder("="))


def save_volume(volume: Volume, path) -> None:
    """Write a volume; the format follows the extension.

    Parameters
    ----------
    volume : Volume
        The volume to write (data, spacing, origin and direction are stored).  A volume that
        is not ``oriented`` is written without a patient orientation, so it reads back as
        not oriented: NRRD gets ``space dimension: 3`` instead of ``space``, ``.vti`` no
        ``Direction``, MetaImage no ``TransformMatrix``, NIfTI both form codes 0 (NIfTI
        keeps no origin without a form: it reads back as 0).
    path : str or os.PathLike
        Target file: ``.vti``, ``.nhdr`` (plus ``STEM_XxYxZ_DTYPE.raw`` beside it, itself
        readable as headerless raw), ``.nrrd``, ``.mha``, ``.mhd`` (plus ``STEM.raw``),
        ``.nii``, ``.nii.gz`` or legacy ``.vtk`` (binary structured points).

    Notes
    -----
    Writing is atomic per file: everything is first written into a temporary folder next to
    the target and then moved into place with :func:`os.replace` (data file before header),
    so a failure never leaves a partial file under the final name.

    Examples
    --------
    >>> import numpy as np, tempfile, os
    >>> from dvr_perception.volume import Volume
    >>> d = tempfile.mkdtemp()
    >>> save_volume(Volume(np.zeros((2, 2, 2), np.float32)), os.path.join(d, "z.vti"))
    >>> sorted(os.listdir(d))
    ['z.vti']
    """
    if not isinstance(volume, Volume):
        raise DVRInputError(f"save_volume: volume must be a Volume, got {type(volume).__name__}")
    path = Path(os.fspath(path))
    ext = _ext(path)
    if ext not in _WRITABLE:
        raise DVRInputError(
            f"{path}: cannot write format {ext or '(no extension)'!r}; expected one of "
            f"{', '.join(_WRITABLE)}"
        )
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.is_dir():
        raise DVRInputError(f"{path}: the folder {str(parent)!r} does not exist")
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.tmp-", dir=parent))
    try:
        written = _write(volume, tmp / path.name, ext)
        from dvr_perception._files import commit

        # data file and header together (Ctrl-C held back); a non-regular target is refused
        commit([(f, parent / f.name) for f in written])
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _write(volume: Volume, target: Path, ext: str) -> list[Path]:
    if ext in (".nhdr", ".nrrd"):
        return write_nrrd(volume, target, detached=ext == ".nhdr")
    if volume.oblique and ext in (".mha", ".mhd", ".vtk"):
        raise DVRInputError(
            f"{target.name}: this format would lose the volume's oblique direction; write "
            ".nrrd, .nhdr, .vti, .nii or .nii.gz"
        )
    if (
        ext in (".mha", ".mhd")
        and volume.data.dtype.itemsize == 8
        and volume.data.dtype.kind in "iu"
    ):
        raise DVRInputError(
            f"{target.name}: VTK's MetaImage writer cannot store 64-bit integers (it writes "
            "half of them); write .nrrd, .nhdr, .vti or .nii"
        )
    image = to_vtk_image(volume, with_direction=ext == ".vti")
    out = [target]
    if ext == ".vti":
        writer = _vtk.vtkXMLImageDataWriter()
    elif ext in (".mha", ".mhd"):
        writer = _vtk.vtkMetaImageWriter()
        writer.SetCompression(False)
        if ext == ".mhd":
            raw = target.with_suffix(".raw")
            writer.SetRAWFileName(str(raw))
            out = [raw, target]
    elif ext == ".vtk":
        writer = _vtk.vtkStructuredPointsWriter()
        writer.SetFileTypeToBinary()
    else:
        writer = _vtk.vtkNIFTIImageWriter()
        _nifti_matrix(writer, volume)
    writer.SetInputData(image)
    writer.SetFileName(str(target))
    with vtk_errors(writer, str(target.name)):
        writer.Write()
    if not volume.oriented and not volume.oblique and ext != ".vtk":
        from dvr_perception.volume._unoriented import drop_orientation

        drop_orientation(target, ext)  # VTK's writers always record one
    return out


def _nifti_matrix(writer, volume: Volume) -> None:
    """Give the NIfTI writer the q-form/s-form from data coordinates to RAS."""
    d = np.asarray(volume.direction)
    o = np.asarray(volume.origin)
    flip = np.array([-1.0, -1.0, 1.0])
    rot = flip[:, None] * d
    shift = flip * (o - d @ o)  # data coordinates are origin + spacing * index
    m = _vtk.vtkMatrix4x4()
    for i in range(3):
        for j in range(3):
            m.SetElement(i, j, rot[i, j])
        m.SetElement(i, 3, shift[i])
    writer.SetQFormMatrix(m)
    writer.SetSFormMatrix(m)
