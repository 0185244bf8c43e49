"""``StructuralLayers``: classify the voxels of a volume into the structures of a spec.

One ``vtkImageData`` in, one ``vtkImageData`` out with the same geometry and the input's point
arrays, plus three point arrays:

``structure_id`` (int16)
    Index of the voxel's structure in the spec, ``-1`` for none
    (:func:`~dvr_perception.rays.curvature.classify_structures`).
``boundary`` (uint8)
    1 on voxels whose structure differs from one of their 6 neighbours, else 0.
``curvature`` (float32)
    ``|mean curvature|`` of the structure boundaries in 1/world-units, 0 off the boundary
    (:func:`~dvr_perception.rays.curvature.curvature_volume`).

Label structures need a label volume, which a single input image does not carry; a spec with
label structures is therefore reported as an error (the library's "no label volume" message).
Errors (missing or malformed spec, input without point scalars, ...) are reported through
VTK's error mechanism; see :mod:`dvr_perception.filters._base`.

An input with a direction matrix (VTK >= 9) is analysed in patient LPS like a file is
(:func:`~dvr_perception.volume.from_vtk_image` flips/permutes it into canonical order); the three
arrays are put back into the input's own point order
(:func:`~dvr_perception.volume.orient.file_order`), so they lie on the voxels they describe.
"""

from __future__ import annotations

import numpy as np

from dvr_perception.filters._base import DVRFilterBase, Parameter, as_positive_float, point_array
from dvr_perception.rays.curvature import classify_structures, curvature_volume
from dvr_perception.structures.io import attach_labels, check_spec_for_volume
from dvr_perception.volume.convert import image_direction
from dvr_perception.volume.orient import file_order

__all__ = ["StructuralLayers"]


class StructuralLayers(DVRFilterBase):
    """VTK filter: structure id, boundary mask and boundary curvature of every voxel.

    The parameters are attributes, each also settable ParaView-style (``SetSpecFile(path)``,
    ``SetSigma(2.0)``, ...); changing one marks the filter modified.

    Attributes
    ----------
    spec_file : str
        Path of a structure-spec JSON file, or
    spec_json : str
        the spec as JSON text (exactly one of the two).
    sigma : float
        Gaussian scale of the curvature, in units of the smallest voxel spacing (default 1.0).
    input_array : str
        Point array to classify (default "": the active scalars).

    Examples
    --------
    >>> import json
    >>> from dvr_perception.structures.io import spec_to_dict
    >>> from dvr_perception.structures import make_phantom
    >>> from dvr_perception.volume import to_vtk_image
    >>> vol, spec = make_phantom(size=16)
    >>> f = StructuralLayers()
    >>> f.spec_json = json.dumps(spec_to_dict(spec))
    >>> f.SetInputDataObject(to_vtk_image(vol))
    >>> f.Update()
    True
    >>> out = f.GetOutputDataObject(0)
    >>> out.GetDimensions(), out.GetPointData().GetArray("structure_id").GetDataTypeAsString()
    ((16, 16, 16), 'short')
    """

    sigma = Parameter(1.0, as_positive_float)

    def __init__(self) -> None:
        super().__init__("vtkImageData")

    def execute(self, image, output) -> None:
        """Classify the input and add ``structure_id``, ``boundary`` and ``curvature``."""
        self.UpdateProgress(0.0)
        volume = self.load_input(image)
        spec = self.load_spec_parameters()
        volume = attach_labels(volume, spec)  # the spec's label volume, e.g. a .seg.nrrd
        check_spec_for_volume(spec, volume)  # label structures without labels -> error
        self.UpdateProgress(0.1)
        ids = classify_structures(volume, spec)
        self.UpdateProgress(0.2)
        curvature, boundary = curvature_volume(
            volume, spec, sigma=self.sigma, progress=self.progress_range(0.2, 0.9)
        )
        self.UpdateProgress(0.9)
        output.ShallowCopy(image)
        pd = output.GetPointData()
        direction = image_direction(image)  # the canonical order back to the input's

        def put(values, name):
            pd.AddArray(point_array(file_order(values, direction).reshape(-1), name))

        put(ids, "structure_id")
        put(boundary.astype(np.uint8), "boundary")
        put(curvature, "curvature")
