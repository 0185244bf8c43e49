"""Take the patient orientation out of a file VTK just wrote, for a volume without one.

VTK's writers always record an orientation: ``vtkXMLImageDataWriter`` a ``Direction``,
``vtkMetaImageWriter`` a ``TransformMatrix``, ``vtkNIFTIImageWriter`` a q-form with its code
set.  A volume whose file recorded none (``Volume.oriented`` is false: its axes were only
*taken* as L, P, S) must not come back from a re-saved copy claiming one, so
:func:`drop_orientation` removes that field from the header again, leaving the data untouched.
"""

from __future__ import annotations

import gzip
import re
import shutil
from pathlib import Path

__all__ = ["drop_orientation"]

#: How much of a header is searched for the field (VTK writes it in the first few lines).
_HEAD = 4096

_NIFTI_FORM_CODES = slice(252, 256)  # qform_code, sform_code (two int16)


def drop_orientation(path: Path, ext: str) -> None:
    """Remove the orientation field from a ``.vti``, ``.mha``/``.mhd`` or ``.nii[.gz]`` file.

    Parameters
    ----------
    path : pathlib.Path
        The header VTK wrote (in the writer's temporary folder; rewritten in place).
    ext : str
        Its format: ``".vti"``, ``".mha"``, ``".mhd"``, ``".nii"`` or ``".nii.gz"``.

    Notes
    -----
    A NIfTI file gets both form codes 0 (NIfTI's "no orientation"); the format keeps no
    origin without a form, so the origin is then not stored (it reads back as 0).
    """
    if ext in (".nii", ".nii.gz"):
        _nifti_codes_off(path, ext)
        return
    if ext == ".vti":
        pattern = re.compile(rb'(<ImageData\b[^>]*?)\s+Direction="[^"]*"')
    else:
        pattern = re.compile(rb"(\n)TransformMatrix = [^\n]*\n")
    with open(path, "rb") as f:
        head = f.read(_HEAD)
    end = head.find(b"ElementDataFile") if ext in (".mha", ".mhd") else head.find(b"<Piece")
    new, count = pattern.subn(rb"\1", head[: max(end, 0)], count=1)
    if count == 0:  # nothing recorded (an older VTK): nothing to take out
        return
    tmp = path.with_name(path.name + ".part")
    with open(path, "rb") as src, open(tmp, "wb") as dst:
        src.seek(end)
        dst.write(new)
        shutil.copyfileobj(src, dst, 1 << 20)
    tmp.replace(path)


def _nifti_codes_off(path: Path, ext: str) -> None:
    if ext == ".nii":
        with open(path, "r+b") as f:
            f.seek(_NIFTI_FORM_CODES.start)
            f.write(b"\0\0\0\0")
        return
    tmp = path.with_name(path.name + ".part")
    with gzip.open(path, "rb") as src, gzip.open(tmp, "wb", compresslevel=6) as dst:
        head = bytearray(src.read(348))
        head[_NIFTI_FORM_CODES] = b"\0\0\0\0"
        dst.write(bytes(head))
        shutil.copyfileobj(src, dst, 1 << 20)
    tmp.replace(path)
