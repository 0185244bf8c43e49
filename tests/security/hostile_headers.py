"""Hostile volume headers of issue 29: one builder per case, shared by the CLI and app tests.

Each builder writes its file into ``folder`` (next to a :data:`SECRET` file one level up,
outside the folder) and returns ``(path, needles)``: the words the single error must hold
besides the file's name.  :data:`SECRET` must never be read as voxels.
"""

from __future__ import annotations

import base64
import struct
import zlib
from pathlib import Path

import numpy as np

#: Bytes of the file outside the volume's folder; never to appear in any loaded data.
SECRET = b"root:x:0:0:root:/root:/bin/bash\n" * 64
META = "ObjectType = Image\nNDims = 3\nDimSize = 4 4 4\nElementType = MET_UCHAR\n"


def write_secret(folder: Path) -> Path:
    """Write :data:`SECRET` beside ``folder`` (in its parent) and return its path."""
    path = folder.parent / "secret.bin"
    path.write_bytes(SECRET)
    return path


def _write(path: Path, blob) -> Path:
    path.write_bytes(blob if isinstance(blob, bytes) else blob.encode("latin-1"))
    return path


# -- MetaImage -------------------------------------------------------------------------------


def meta_key_case(folder: Path):
    """The probe's case: a LOCAL data file in another case, then the real key naming a file."""
    text = META + "Elementdatafile = LOCAL\nElementDataFile = ../secret.bin\n"
    return _write(folder / "case.mha", text + "\0" * 64), ["'Elementdatafile'", "case-sensitive"]


def meta_later_data_file(folder: Path):
    """The two keys the other way round, in one case: the second is a repeat."""
    text = META + "ElementDataFile = ../secret.bin\nelementDataFile = LOCAL\n"
    return _write(folder / "later.mha", text), ["'ElementDataFile'", "outside the header's folder"]


def meta_repeated_dims(folder: Path):
    """``DimSize`` then ``dimsize``: one sized small, the other huge."""
    text = META + "dimsize = 1024 1024 1024\nElementDataFile = LOCAL\n"
    return _write(folder / "dims.mha", text + "\0" * 64), ["'dimsize'", "twice"]


def meta_repeated_compressed(folder: Path):
    """``CompressedData`` given both ways."""
    text = META + "CompressedData = False\ncompresseddata = True\nElementDataFile = LOCAL\n"
    return _write(folder / "comp.mha", text + "\0" * 64), ["'compresseddata'", "twice"]


def meta_header_size_local(folder: Path):
    """``HeaderSize`` choosing an offset into attached data."""
    text = META + "HeaderSize = 3\nElementDataFile = LOCAL\n"
    return _write(folder / "hs.mha", text + "\0" * 64), ["'HeaderSize'"]


def meta_header_size_outside(folder: Path):
    """``HeaderSize`` reaching into a file outside the folder."""
    text = META + "HeaderSize = 32\nElementDataFile = /etc/passwd\n"
    return _write(folder / "hs2.mhd", text), ["'ElementDataFile'", "outside the header's folder"]


def meta_synonyms(folder: Path):
    """``Offset`` and ``Origin`` (MetaIO's synonyms) both given."""
    text = META + "Offset = 0 0 0\nOrigin = 5 5 5\nElementDataFile = LOCAL\n"
    return _write(folder / "syn.mha", text + "\0" * 64), ["'Offset' and 'Origin'", "synonyms"]


def meta_truncated(folder: Path):
    """Attached data shorter than ``DimSize`` claims."""
    text = META + "ElementDataFile = LOCAL\n"
    return _write(folder / "short.mha", text + "\0" * 63), ["truncated"]


def meta_truncated_zlib(folder: Path):
    """Compressed data that expands to fewer bytes than ``DimSize`` claims."""
    text = META + "CompressedData = True\nElementDataFile = LOCAL\n"
    return _write(folder / "shortz.mha", text.encode() + zlib.compress(bytes(60))), ["truncated"]


def meta_zlib_bomb(folder: Path):
    """A small compressed stream expanding to 256 MiB behind a 64-byte header."""
    text = META + "CompressedData = True\nElementDataFile = LOCAL\n"
    bomb = zlib.compress(b"\0" * (256 << 20), 9)
    return _write(folder / "bomb.mha", text.encode() + bomb), ["expands to more"]


# -- VTK XML image data ----------------------------------------------------------------------

_VTI_HEAD = '<VTKFile type="ImageData" version="1.0" byte_order="LittleEndian" header_type="UInt32"'


def _vti(extent: str, arrays: str, appended: bytes | None = None, root_extra: str = "") -> bytes:
    text = (
        f'<?xml version="1.0"?>\n{_VTI_HEAD}{root_extra}>\n'
        f'<ImageData WholeExtent="{extent}" Origin="0 0 0" Spacing="1 1 1">\n'
        f'<Piece Extent="{extent}">\n<PointData Scalars="s">\n{arrays}</PointData>\n'
        "</Piece>\n</ImageData>\n"
    ).encode()
    if appended is not None:
        text += b'<AppendedData encoding="raw">\n_' + appended + b"\n</AppendedData>\n"
    return text + b"</VTKFile>\n"


def vti_comment_before_root(folder: Path):
    """An XML comment carrying a small ``WholeExtent`` before the real (huge) element."""
    comment = b'<!-- <ImageData WholeExtent="0 1 0 1 0 1"> -->\n'
    arr = '<DataArray type="Float64" Name="s" format="appended" offset="0"/>\n'
    body = _vti("0 2047 0 2047 0 2047", arr, struct.pack("<I", 64) + bytes(64))
    return _write(folder / "comment.vti", comment + body), ["XML comment"]


def vti_truncated_appended(folder: Path):
    """Appended raw data shorter than the extent (VTK filled the rest from the heap)."""
    arr = '<DataArray type="UInt8" Name="s" format="appended" offset="0"/>\n'
    blob = _vti("0 7 0 7 0 7", arr, struct.pack("<I", 512) + bytes(100))
    return _write(folder / "short.vti", blob), ["truncated"]


def vti_truncated_inline(folder: Path):
    """Inline base64 data shorter than the extent."""
    data = base64.b64encode(struct.pack("<I", 512) + bytes(100)).decode()
    arr = f'<DataArray type="UInt8" Name="s" format="binary">{data}</DataArray>\n'
    return _write(folder / "short64.vti", _vti("0 7 0 7 0 7", arr)), ["truncated"]


def vti_many_arrays(folder: Path, count: int = 40, edge: int = 64):
    """``count`` Float64 arrays sharing one appended offset (each fits, all do not)."""
    arrays = "".join(
        f'<DataArray type="Float64" Name="{"s" if i == 0 else f"a{i}"}" format="appended" '
        'offset="0"/>\n'
        for i in range(count)
    )
    nbytes = edge**3 * 8
    blob = _vti(f"0 {edge - 1} 0 {edge - 1} 0 {edge - 1}", arrays,
                struct.pack("<I", nbytes) + bytes(nbytes))  # fmt: skip
    return _write(folder / "many.vti", blob), ["'WholeExtent'", f"({count} arrays)"]


def vti_zlib_bomb(folder: Path):
    """``compressor`` with white space around ``=``: one block claiming 512 bytes, expanding
    to 64 MiB."""
    packed = zlib.compress(b"\0" * (64 << 20), 9)
    header = struct.pack("<4I", 1, 512, 512, len(packed))
    arr = '<DataArray type="UInt8" Name="s" format="appended" offset="0"/>\n'
    extra = ' compressor \n = \n "vtkZLibDataCompressor"'
    blob = _vti("0 7 0 7 0 7", arr, header + packed, root_extra=extra)
    return _write(folder / "zbomb.vti", blob), ["expands to more"]


def vti_unknown_compressor(folder: Path):
    """A compressor we do not decode: refused, never handed to VTK."""
    arr = '<DataArray type="UInt8" Name="s" format="appended" offset="0"/>\n'
    blob = _vti("0 1 0 1 0 1", arr, bytes(40), root_extra=' compressor=" vtkLZ4DataCompressor"')
    return _write(folder / "lz4.vti", blob), ["'compressor'", "not supported"]


# -- legacy VTK ------------------------------------------------------------------------------

_LEGACY = "# vtk DataFile Version 3.0\nt\nBINARY\nDATASET STRUCTURED_POINTS\n"


def legacy_later_dimensions(folder: Path):
    """A second ``DIMENSIONS`` line after 45 blank and spacing-free lines."""
    text = _LEGACY + "DIMENSIONS 2 2 2\n" + "\n" * 45 + "DIMENSIONS 1024 1024 1024\n"
    text += "POINT_DATA 8\nSCALARS s unsigned_char\nLOOKUP_TABLE default\n"
    return _write(folder / "later.vtk", text + "\0" * 8), ["'DIMENSIONS'", "twice"]


def legacy_dimensions_after_data(folder: Path):
    """Another header after the data (VTK would read a second array)."""
    text = _LEGACY + "DIMENSIONS 2 2 2\nPOINT_DATA 8\nSCALARS s unsigned_char\n"
    text += "LOOKUP_TABLE default\n" + "\0" * 8 + "\nSCALARS b double\nLOOKUP_TABLE default\n"
    return _write(folder / "after.vtk", text), ["after the voxel data"]


def legacy_truncated(folder: Path):
    """Binary data shorter than ``DIMENSIONS``."""
    text = _LEGACY + "DIMENSIONS 4 4 4\nPOINT_DATA 64\nSCALARS s short\nLOOKUP_TABLE default\n"
    return _write(folder / "short.vtk", text + "\0" * 100), ["truncated"]


# -- NIfTI -----------------------------------------------------------------------------------


def nifti1(dims, datatype: int, bitpix: int, *, data: bytes = b"", vox: float = 352.0) -> bytes:
    """A little-endian NIfTI-1 single file (``n+1``)."""
    head = bytearray(352)
    struct.pack_into("<i", head, 0, 348)
    struct.pack_into("<8h", head, 40, len(dims), *dims, *([1] * (7 - len(dims))))
    struct.pack_into("<hh", head, 70, datatype, bitpix)
    struct.pack_into("<8f", head, 76, 1, 1, 1, 1, 1, 1, 1, 1)
    struct.pack_into("<f", head, 108, vox)
    head[344:348] = b"n+1\0"
    return bytes(head) + data


def nifti2(dims, datatype: int, bitpix: int, *, data: bytes = b"") -> bytes:
    """A little-endian NIfTI-2 single file (``n+2``), 540-byte header + 4 extension bytes."""
    head = bytearray(544)
    struct.pack_into("<i", head, 0, 540)
    head[4:12] = b"n+2\0\r\n\x1a\n"
    struct.pack_into("<hh", head, 12, datatype, bitpix)
    struct.pack_into("<8q", head, 16, len(dims), *dims, *([1] * (7 - len(dims))))
    struct.pack_into("<8d", head, 104, 1, 1, 1, 1, 1, 1, 1, 1)
    struct.pack_into("<q", head, 168, 544)
    return bytes(head) + data


def nifti2_huge(folder: Path):
    """NIfTI-2 (size 540, skipped by the old check) claiming 2000**3 int16 voxels."""
    return _write(folder / "huge2.nii", nifti2((2000, 2000, 2000), 4, 16)), ["'dim'", "limit"]


def nifti1_datatype_not_bitpix(folder: Path):
    """``bitpix`` 8 (16 MiB) but ``datatype`` float64 (128 MiB): the type VTK uses counts."""
    blob = nifti1((256, 256, 256), 64, 8)
    return _write(folder / "bitpix.nii", blob), ["'dim'", "float64", "limit"]


def nifti_truncated(folder: Path):
    """4x4x4 int16 with 100 of its 128 data bytes."""
    return _write(folder / "short.nii", nifti1((4, 4, 4), 4, 16, data=bytes(100))), ["truncated"]


def nifti_analyze(folder: Path):
    """An Analyze 7.5 header (no NIfTI magic): not read."""
    blob = bytearray(nifti1((2, 2, 2), 2, 8, data=bytes(8)))
    blob[344:348] = bytes(4)
    return _write(folder / "analyze.nii", bytes(blob)), ["'magic'"]


#: Every case: name -> builder.
CASES = {
    f.__name__: f
    for f in (
        meta_key_case, meta_later_data_file, meta_repeated_dims, meta_repeated_compressed,
        meta_header_size_local, meta_header_size_outside, meta_synonyms, meta_truncated,
        meta_truncated_zlib, meta_zlib_bomb, vti_comment_before_root, vti_truncated_appended,
        vti_truncated_inline, vti_many_arrays, vti_zlib_bomb, vti_unknown_compressor,
        legacy_later_dimensions, legacy_dimensions_after_data, legacy_truncated, nifti2_huge,
        nifti1_datatype_not_bitpix, nifti_truncated, nifti_analyze,
    )
}  # fmt: skip


def as_array(blob: bytes) -> np.ndarray:
    """The bytes as uint8 (for searching loaded data)."""
    return np.frombuffer(blob, np.uint8)
