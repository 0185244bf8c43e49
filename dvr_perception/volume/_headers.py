"""One parse of a MetaImage, VTK XML image data or legacy VTK header, then our own read.

A check in front of another program's reader is only as good as the agreement between the two
parsers, and every difference is a way through (a key in another case, a repeated key, an XML
comment, a later ``DIMENSIONS`` line).  So for MetaImage (``.mha``/``.mhd``), ``.vti`` and
legacy structured points (``.vtk``) the header is parsed *once*, here, into a :class:`Layout`
(sizes, type, byte order, encoding, which file and where its data lies, geometry), and the
voxels are read by :func:`read_layout` from that layout alone: VTK never opens the file.

The parse is also strict, so that a header it accepts means the same to VTK's readers (which
ParaView's MPI ranks still use, see ``dvr-perception pvbatch --ranks``): a key repeated in any
case, a known MetaImage key in another case, two synonyms of one field, a legacy keyword twice
or one the structured-points reader does not take, an XML comment, processing instruction,
``DOCTYPE`` or ``CDATA`` section, a second piece, a DataArray of unknown type or format, and an
unsupported compressor are each refused with one :class:`~dvr_perception.errors.DVRInputError`
naming the file and the field.

Data must be complete: a file (or a compressed stream) that holds fewer bytes than the header
claims is refused, and a buffer is only handed on once every byte of it has been written.
Every array a VTK reader would allocate counts against the memory limit.
"""

from __future__ import annotations

from dvr_perception.volume._layout import Layout, read_layout
from dvr_perception.volume._legacy_vtk import LEGACY_TYPES, legacy_layout
from dvr_perception.volume._metaimage import META_TYPES, meta_fields, meta_layout
from dvr_perception.volume._nifti import NIFTI_TYPES, check_nifti
from dvr_perception.volume._vti import XML_TYPES, vti_layout

__all__ = [
    "LEGACY_TYPES",
    "META_TYPES",
    "NIFTI_TYPES",
    "XML_TYPES",
    "Layout",
    "check_nifti",
    "legacy_layout",
    "meta_fields",
    "meta_layout",
    "read_layout",
    "vti_layout",
]
