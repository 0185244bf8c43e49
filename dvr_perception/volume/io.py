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

import gzip
import os
import re
import shutil
import tempfile
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np

from dvr_perception.errors import DVRInputError, DVRWarning
from dvr_perception.volume._limits import (
    HEADER_MAX,
    check_budget,
    check_ratio,
    check_size,
    check_spacing,
    parse_float,
    parse_int,
    resolve_data_file,
    shown,
)
from dvr_perception.volume._nrrd import nrrd_axes, nrrd_header, nrrd_space, read_nrrd, write_nrrd
from dvr_perception.volume._vtk_headers import check_legacy_vtk, check_vti
from dvr_perception.volume.orient import from_axes, ras_to_lps
from dvr_perception.volume.volume import Volume

__all__ = ["header_axes", "load_volume", "save_volume"]


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
_META_DIRECTIONS = ("transformmatrix", "rotation", "orientation")
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
    else:
        if ext in (".mha", ".mhd"):
            fields = _check_meta(path)
            oriented = any(k in fields for k in _META_DIRECTIONS)
        elif ext in (".nii", ".nii.gz"):
            _check_nifti(path, ext)
        elif ext == ".vti":
            oriented = check_vti(path)
        elif ext == ".vtk":
            check_legacy_vtk(path)
            oriented = False  # legacy structured points have no direction
        reader = {
            ".mha": _vtk.vtkMetaImageReader,
            ".mhd": _vtk.vtkMetaImageReader,
            ".vti": _vtk.vtkXMLImageDataReader,
            ".vtk": _vtk.vtkDataSetReader,
            ".nii": _vtk.vtkNIFTIImageReader,
            ".nii.gz": _vtk.vtkNIFTIImageReader,
        }[ext]()
        vol = _read_vtk(reader, path, vname, oriented=oriented)
        if ext in (".mha", ".mhd"):
            vol = _meta_geometry(fields, vol, path)
        return vol
    if data.size == 0:
        raise DVRInputError(f"{path}: the volume is empty (shape (z, y, x) = {data.shape})")
    where = str(path)
    return from_axes(data, axes, origin, name=vname, source=where, where=where, oriented=oriented)


def header_axes(path) -> np.ndarray | None:
    """Return a NRRD, MetaImage or ``.vti`` file's axis vectors (LPS columns) from its header.

    ``None`` for other formats.  For callers that must not read the data, e.g. the MPI path
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
        fields, _ = nrrd_header(path)
        axes = nrrd_axes(fields, path)
        space = nrrd_space(fields, path)
        if space == "ras":
            axes, _ = ras_to_lps(axes, np.zeros(3))
        elif space == "las":
            axes = axes * [[-1.0], [1.0], [1.0]]
        return axes
    if ext in (".mha", ".mhd"):
        fields, _ = _meta_header(path)
        spacing = np.ones(3)
        for key in ("elementspacing", "elementsize"):
            if key in fields:
                spacing = np.array([parse_float(v, path, key) for v in fields[key].split()[:3]])
                break
        for key in _META_DIRECTIONS:
            if key in fields:
                vals = [parse_float(v, path, "TransformMatrix") for v in fields[key].split()]
                if len(vals) == 9:
                    return np.array(vals).reshape(3, 3).T * spacing
        return np.diag(spacing)
    if ext == ".vti":
        from dvr_perception.volume._vtk_headers import vti_axes

        return vti_axes(path)
    return None


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
    from dvr_perception.rays import memory

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


def _meta_geometry(fields: dict[str, str], vol: Volume, path: Path) -> Volume:
    """Apply a MetaImage header's ``TransformMatrix`` (one axis direction per triple)."""
    for key in _META_DIRECTIONS:
        if key in fields:
            vals = [parse_float(v, path, "TransformMatrix") for v in fields[key].split()]
            if len(vals) != 9:
                raise DVRInputError(
                    f"{path}: field 'TransformMatrix': expected 9 numbers, got {len(vals)}"
                )
            directions = np.array(vals).reshape(3, 3).T  # column k: index axis k
            break
    else:
        return vol
    origin = np.zeros(3)
    for key in ("offset", "position", "origin"):
        if key in fields:
            origin = np.array([parse_float(v, path, "Offset") for v in fields[key].split()[:3]])
            break
    axes = directions * np.asarray(vol.spacing)
    where = f"{path}: MetaImage TransformMatrix"  # (vol.oriented: the matrix records it)
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


_META_TYPES = {
    "MET_CHAR": 1, "MET_UCHAR": 1, "MET_SHORT": 2, "MET_USHORT": 2, "MET_INT": 4,
    "MET_UINT": 4, "MET_LONG": 4, "MET_ULONG": 4, "MET_LONG_LONG": 8, "MET_ULONG_LONG": 8,
    "MET_FLOAT": 4, "MET_DOUBLE": 8,
}  # fmt: skip


def _meta_header(path: Path) -> tuple[dict[str, str], int]:
    """Return the MetaImage header's fields (keys lower case) and the data offset."""
    with open(path, "rb") as f:
        head = f.read(HEADER_MAX)
    fields: dict[str, str] = {}
    offset = 0
    for raw in head.split(b"\n"):
        if offset + len(raw) >= len(head) and len(head) == HEADER_MAX:
            raise DVRInputError(f"{path}: the MetaImage header is longer than {HEADER_MAX} bytes")
        offset += len(raw) + 1
        line = raw.decode("latin-1").strip()
        if not line:
            continue
        key, sep, value = line.partition("=")
        if not sep:
            raise DVRInputError(f"{path}: malformed MetaImage header line {shown(line)}")
        fields[key.strip().lower()] = value.strip()
        if key.strip().lower() == "elementdatafile":
            break  # the last field; attached data follows
    return fields, min(offset, len(head))


def _check_meta(path: Path) -> dict[str, str]:
    """Check a ``.mha``/``.mhd`` header (data file, sizes, spacing, size) before VTK reads it."""
    fields, offset = _meta_header(path)

    def need(key: str, name: str) -> str:
        if key not in fields:
            raise DVRInputError(f"{path}: MetaImage header has no {name!r} field")
        return fields[key]

    if need("ndims", "NDims") != "3":
        raise DVRInputError(f"{path}: field 'NDims': expected 3, got {shown(fields['ndims'])}")
    tokens = need("dimsize", "DimSize").split()
    if len(tokens) != 3:
        raise DVRInputError(f"{path}: field 'DimSize': expected 3 integers, got {shown(tokens)}")
    dims = tuple(parse_int(t, path, "DimSize") for t in tokens)
    etype = need("elementtype", "ElementType").upper()
    if etype not in _META_TYPES:
        raise DVRInputError(
            f"{path}: field 'ElementType': unsupported type {shown(etype)}; expected one of "
            f"{', '.join(_META_TYPES)}"
        )
    channels = fields.get("elementnumberofchannels", "1")
    channels = parse_int(channels, path, "ElementNumberOfChannels")
    for key, name in (("elementspacing", "ElementSpacing"), ("elementsize", "ElementSize")):
        if key in fields:
            vals = fields[key].split()
            if len(vals) != 3:
                raise DVRInputError(
                    f"{path}: field {name!r}: expected 3 numbers, got {shown(vals)}"
                )
            check_spacing([parse_float(v, path, name) for v in vals], path, name)
    for key, name in (("offset", "Offset"), ("position", "Position"), ("origin", "Origin")):
        for v in fields.get(key, "").split()[:3]:
            parse_float(v, path, name)
    expected = check_budget(path, (*dims, channels), np.dtype(f"u{_META_TYPES[etype]}"), "DimSize")
    data_file = need("elementdatafile", "ElementDataFile")
    if data_file.upper() == "LOCAL":
        src = path
    else:
        if data_file.split()[:1] == ["LIST"] or "%" in data_file:
            raise DVRInputError(f"{path}: field 'ElementDataFile': file lists are not supported")
        src, offset = resolve_data_file(path, data_file, "ElementDataFile"), 0
    header_size = parse_int(fields.get("headersize", "0"), path, "HeaderSize", lo=-1)
    available = src.stat().st_size - offset - max(header_size, 0)
    where = f"{path} (data file {src.name})" if src != path else str(path)
    if fields.get("compresseddata", "false").lower() == "true":
        check_ratio(where, available, expected)
    elif available < expected:
        raise DVRInputError(
            f"{where}: truncated: expected {expected} bytes, found {max(available, 0)} "
            f"(DimSize {tuple(dims)})"
        )
    return fields


def _check_nifti(path: Path, ext: str) -> None:
    """Refuse a NIfTI-1 header whose sizes cannot fit the memory limit (before VTK reads it)."""
    try:
        with gzip.open(path, "rb") if ext == ".nii.gz" else open(path, "rb") as f:
            head = f.read(348)
    except (OSError, EOFError) as exc:
        raise DVRInputError(f"{path}: cannot read the NIfTI header ({exc})") from None
    if len(head) < 348:
        raise DVRInputError(f"{path}: truncated: the NIfTI header needs 348 bytes")
    for order in "<>":
        if int(np.frombuffer(head[:4], order + "i4")[0]) == 348:
            break
    else:
        return  # not NIfTI-1: VTK's reader decides
    dim = np.frombuffer(head[40:56], order + "i2").astype(np.int64)
    bitpix = int(np.frombuffer(head[72:74], order + "i2")[0])
    if not 1 <= dim[0] <= 7 or bitpix <= 0 or np.any(dim[1 : dim[0] + 1] < 0):
        raise DVRInputError(f"{path}: NIfTI field 'dim': invalid sizes {dim.tolist()}")
    check_budget(path, [int(d) for d in dim[1 : dim[0] + 1]], f"u{max(bitpix // 8, 1)}", "dim")


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
