"""``VolumeReader``: a VTK source that reads a volume file the way the command line does.

ParaView's own readers (NRRD, MetaImage, NIfTI, DICOM) give the voxels in file order with no
patient orientation, so a volume stored with a negative or permuted axis appears mirrored in
ParaView while the engine, the CLI and PyVista show it in patient LPS.  This source reads with
:func:`dvr_perception.volume.load_volume` (every format it knows, DICOM folders and multi-frame
files, ``.mgz``) and outputs ``vtkImageData`` in patient LPS:

* flips and permutations of the file's axes are applied to the data order
  (:func:`dvr_perception.volume.orient.canonical`), so an axis-aligned volume has the identity
  direction and every VTK/ParaView display (volume, outline, slice) shows it the right way
  round;
* an oblique volume keeps its rotation as the image's direction matrix (ParaView 5.11's volume
  and surface representations rotate it; its outline representation does not: it draws the
  unrotated box of ``origin + spacing * extent``).

The output has one point-scalar array, ``scalars``.  The source answers a request for a piece
(sub-extent) with that piece of the whole volume, which it reads once and keeps until the file,
``file_name`` or ``series`` changes.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from dvr_perception._vtk import (
    VTKPythonAlgorithmBase,
    numpy_to_vtk,
    vtkAlgorithm,
    vtkDataObject,
    vtkImageData,
    vtkStreamingDemandDrivenPipeline,
)
from dvr_perception.errors import DVRInputError
from dvr_perception.filters._base import DVRFilterBase, Parameter, as_text

__all__ = ["ARRAY_NAME", "VolumeReader"]

#: Name of the output's point-scalar array.
ARRAY_NAME = "scalars"


class VolumeReader(DVRFilterBase):
    """VTK source: the volume of ``file_name`` as ``vtkImageData`` in patient LPS.

    Attributes
    ----------
    file_name : str
        A volume file (``.nrrd``, ``.nhdr``, ``.nii``, ``.nii.gz``, ``.mgz``, ``.mha``,
        ``.mhd``, ``.vti``, ...), a DICOM folder or a DICOM file.  A single-frame DICOM file
        stands for its series: the folder it lies in, restricted to its SeriesInstanceUID.
    series : str
        DICOM only: the SeriesInstanceUID to read from a folder holding several series.

    Examples
    --------
    >>> import os, tempfile
    >>> import numpy as np
    >>> from dvr_perception.volume import Volume, save_volume
    >>> path = os.path.join(tempfile.mkdtemp(), "v.nrrd")
    >>> data = np.arange(24, dtype=np.uint8).reshape(2, 3, 4)
    >>> save_volume(Volume(data, direction=np.diag([-1.0, -1.0, 1.0])), path)
    >>> r = VolumeReader()
    >>> r.file_name = path
    >>> r.Update()
    True
    >>> out = r.GetOutputDataObject(0)
    >>> out.GetDimensions(), out.GetOrigin(), out.GetPointData().GetScalars().GetValue(0)
    ((4, 3, 2), (-3.0, -2.0, 0.0), 11)
    """

    file_name = Parameter("", as_text)
    series = Parameter("", as_text)

    def __init__(self) -> None:
        VTKPythonAlgorithmBase.__init__(
            self, nInputPorts=0, nOutputPorts=1, outputType="vtkImageData"
        )
        self.error_message = ""
        self.warning_messages: list[str] = []
        self._key = None
        self._volume = None

    @property
    def label(self) -> str:
        """Name used at the start of the reader's messages."""
        return "DVR Perception volume"

    # -- reading ----------------------------------------------------------------------------------
    def volume(self):
        """Return the :class:`~dvr_perception.volume.Volume` (read once per file change)."""
        if not self.file_name.strip():
            raise DVRInputError(f"{self.label}: FileName: no file or DICOM folder set")
        path = Path(self.file_name)
        try:
            st = path.stat()
            stamp = (st.st_mtime_ns, st.st_size)
        except OSError:
            stamp = None
        key = (str(path), self.series, stamp)
        if key != self._key or self._volume is None:
            self._volume = None
            self._volume = _read(path, self.series.strip() or None)
            self._key = key
        return self._volume

    # -- pipeline passes --------------------------------------------------------------------------
    def information(self, in_info, out_info) -> None:
        """Declare the whole extent, spacing, origin and direction of the volume."""
        vol = self.volume()
        nx, ny, nz = vol.dims
        info = out_info.GetInformationObject(0)
        key = vtkStreamingDemandDrivenPipeline
        info.Set(key.WHOLE_EXTENT(), (0, nx - 1, 0, ny - 1, 0, nz - 1), 6)
        info.Set(vtkDataObject.SPACING(), *vol.spacing)
        info.Set(vtkDataObject.ORIGIN(), *vol.origin)
        if hasattr(vtkDataObject, "DIRECTION"):  # VTK >= 9.0
            info.Set(vtkDataObject.DIRECTION(), tuple(np.asarray(vol.direction).ravel()), 9)
        info.Set(vtkAlgorithm.CAN_PRODUCE_SUB_EXTENT(), 1)

    def RequestUpdateExtent(self, request, in_info, out_info):
        """Pipeline pass: a source has no input to ask for anything."""
        return 1

    def RequestData(self, request, in_info, out_info):
        """Pipeline pass: fill the output with the requested piece of the volume."""
        self.warning_messages = []
        info = out_info.GetInformationObject(0)
        output = info.Get(vtkDataObject.DATA_OBJECT())
        status = self._guarded(self._fill, info, output)
        if status:
            self.UpdateProgress(1.0)
        elif output is not None:
            output.Initialize()
        return status

    def _fill(self, info, output) -> None:
        vol = self.volume()
        nx, ny, nz = vol.dims
        key = vtkStreamingDemandDrivenPipeline
        ext = info.Get(key.UPDATE_EXTENT()) if info.Has(key.UPDATE_EXTENT()) else None
        whole = (0, nx - 1, 0, ny - 1, 0, nz - 1)
        ext = tuple(int(e) for e in ext) if ext else whole
        pairs = enumerate(zip(ext, whole, strict=True))
        x0, x1, y0, y1, z0, z1 = (max(e, w) if i % 2 == 0 else min(e, w) for i, (e, w) in pairs)
        if x1 < x0 or y1 < y0 or z1 < z0:  # an empty piece
            output.Initialize()
            return
        block = np.ascontiguousarray(vol.data[z0 : z1 + 1, y0 : y1 + 1, x0 : x1 + 1])
        image = vtkImageData()
        image.SetExtent(x0, x1, y0, y1, z0, z1)
        image.SetSpacing(*vol.spacing)
        image.SetOrigin(*vol.origin)
        if hasattr(image, "SetDirectionMatrix"):
            image.SetDirectionMatrix(*np.asarray(vol.direction).ravel())
        # the whole extent shares the kept volume's memory (no second copy of a large volume);
        # the VTK array holds a reference to the numpy buffer
        arr = numpy_to_vtk(block.reshape(-1), deep=False)
        arr.SetName(ARRAY_NAME)
        image.GetPointData().SetScalars(arr)
        output.ShallowCopy(image)


def _read(path: Path, series: str | None):
    """``load_volume`` with a single-frame DICOM file read as the series it belongs to."""
    from dvr_perception.volume import load_volume

    if path.is_file() and path.suffix.lower() in (".dcm", "") and series is None:
        uid = _single_frame_series(path)
        if uid is not None:
            name = path.parent.name or "dicom"
            return load_volume(path.parent, name=name, series=uid)
    return load_volume(path, series=series)


def _single_frame_series(path: Path) -> str | None:
    """Return the SeriesInstanceUID of a single-frame DICOM image file (else ``None``)."""
    from dvr_perception.volume import medical

    if not medical.available():
        return None
    import pydicom

    try:
        ds = pydicom.dcmread(path, stop_before_pixels=True, defer_size="1 KB")
        frames = int(ds.get("NumberOfFrames", 1) or 1)
        uid = str(ds.get("SeriesInstanceUID", "") or "")
    except Exception:  # not DICOM (or unreadable): load_volume reports it
        return None
    return uid if frames == 1 and uid and os.path.isdir(path.parent) else None
