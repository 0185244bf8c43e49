"""ParaView reader "DVR Perception volume": volume files in patient LPS, as the CLI reads them.

ParaView's own NRRD, MetaImage, NIfTI and DICOM readers ignore the files' axis directions (the
voxels come in file order), so a volume stored with a negative or permuted axis is shown
mirrored, and the DVR Perception filters then measure a different object than the command line
and PyVista do.  This reader is a shell over ``dvr_perception.filters.VolumeReader``
(:func:`dvr_perception.volume.load_volume`): flips and permutations are applied to the data
order, an oblique rotation becomes the image's direction matrix (ParaView 5.11's volume and
surface representations rotate it; its outline does not).  It reads NRRD/NHDR, NIfTI, MGZ/MGH,
MetaImage, VTI and DICOM (a multi-frame file, or one file of a series: the whole series in its
folder).  ``dvr_perception_plugin.py`` registers it; in pvpython::

    reader = DVRPerceptionvolume(FileName="head.nrrd")
"""

from paraview.util.vtkAlgorithm import VTKPythonAlgorithmBase, smdomain, smhint, smproperty, smproxy

_EXTENSIONS = "nrrd nhdr nii nii.gz mgz mgh mha mhd vti dcm"


@smproxy.reader(
    name="DVRPerceptionVolume",
    label="DVR Perception volume",
    extensions=_EXTENSIONS,
    file_description="DVR Perception volume (patient LPS)",
    support_reload=False,
)
class VolumeReader(VTKPythonAlgorithmBase):
    """Forwards the pipeline passes to a lazily created ``dvr_perception.filters.VolumeReader``."""

    def __init__(self):
        VTKPythonAlgorithmBase.__init__(
            self, nInputPorts=0, nOutputPorts=1, outputType="vtkImageData"
        )
        self._values = {"file_name": "", "series": ""}
        self._impl = None

    def _set(self, name, value):
        value = "" if value is None else str(value)
        if self._values[name] != value:
            self._values[name] = value
            self.Modified()

    def _library_reader(self):
        if self._impl is None:
            from dvr_perception.filters import VolumeReader as Impl

            self._impl = Impl()
        for name, value in self._values.items():
            setattr(self._impl, name, value)
        return self._impl

    @smproperty.stringvector(name="FileName")
    @smdomain.filelist()
    @smhint.filechooser(extensions=_EXTENSIONS, file_description="Volume files")
    def SetFileName(self, value):
        self._set("file_name", value)

    @smproperty.stringvector(name="Series", default_values="", panel_visibility="advanced")
    def SetSeries(self, value):
        """DICOM: the SeriesInstanceUID to read from a folder holding several series."""
        self._set("series", value)

    def RequestInformation(self, request, in_info, out_info):
        return self._library_reader().RequestInformation(request, in_info, out_info)

    def RequestData(self, request, in_info, out_info):
        return self._library_reader().RequestData(request, in_info, out_info)
