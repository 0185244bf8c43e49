"""ParaView Python state: tooth with the dvr_perception Perception Measures filter.

Written by plugin/make_state_files.py (ParaView 5.11.0); the body below is ParaView's own
Python state.  Run it in pvpython (``PYTHONPATH=dvr_perception/paraview/pvsite``),
with ``exec``/``runpy`` and a global ``data_directory``, or load it in the GUI (*File > Load
State*, Python state).  The volume is looked up in ``data_directory``, else
``$DVR_SHARED_DATA``, else ``<repo>/../shared/data``.
"""

import os

import paraview
from paraview.simple import *

paraview.compatibility.major = 5
paraview.compatibility.minor = 11

try:
    _repo = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
except NameError:  # run without a file name (e.g. pasted into the Python shell)
    _repo = os.getcwd()
data_directory = (
    globals().get("data_directory")
    or os.environ.get("DVR_SHARED_DATA")
    or os.path.join(os.path.dirname(_repo), "shared", "data")
)
if "PerceptionMeasures" not in globals():
    LoadPlugin(os.path.join(_repo, "dvr_perception", "paraview", "dvr_perception_plugin.py"),
               ns=globals())

#### disable automatic camera reset on 'Show'
paraview.simple._DisableFirstRenderCameraReset()

# Create a new 'Render View'
renderView1 = CreateView('RenderView')
renderView1.ViewSize = [256, 256]
renderView1.AxesGrid = 'GridAxes3DActor'
renderView1.OrientationAxesVisibility = 0
renderView1.StereoType = 0
renderView1.CameraPosition = [51.0, 454.72452732580035, 79.99999999999997]
renderView1.CameraFocalPoint = [51.0, 46.5, 80.0]
renderView1.CameraViewUp = [-1.2246467991473532e-16, 6.123233995736766e-17, 1.0]
renderView1.CameraFocalDisk = 1.0
renderView1.CameraParallelScale = 1.0
renderView1.UseColorPaletteForBackground = 0
renderView1.Background = [0.0, 0.0, 0.0]

# Create a new 'Render View'
renderView2 = CreateView('RenderView')
renderView2.InteractionMode = '2D'
renderView2.AxesGrid = 'GridAxes3DActor'
renderView2.OrientationAxesVisibility = 0
renderView2.StereoType = 0
renderView2.CameraPosition = [127.5, 127.5, 696.6729559300638]
renderView2.CameraFocalPoint = [127.5, 127.5, 0.0]
renderView2.CameraFocalDisk = 1.0
renderView2.CameraParallelScale = 180.31222920256963

# Create a new 'SpreadSheet View'
spreadSheetView1 = CreateView('SpreadSheetView')
spreadSheetView1.ColumnToSort = ''
spreadSheetView1.BlockSize = 1024
spreadSheetView1.FieldAssociation = 'Field Data'

SetActiveView(None)

# ----------------------------------------------------------------
# setup view layouts
# ----------------------------------------------------------------

# create new layout object 'tooth'
tooth = CreateLayout(name='tooth')
tooth.SplitHorizontal(0, 0.500000)
tooth.AssignView(1, renderView1)
tooth.SplitVertical(2, 0.600000)
tooth.AssignView(5, renderView2)
tooth.AssignView(6, spreadSheetView1)
tooth.SetSize(657, 801)

# ----------------------------------------------------------------
# restore active view
SetActiveView(renderView1)
# ----------------------------------------------------------------

# ----------------------------------------------------------------
# setup the data processing pipelines
# ----------------------------------------------------------------

# create a new 'Nrrd Reader'
toothnhdr = NrrdReader(registrationName='tooth.nhdr', FileName=os.path.join(data_directory, 'tooth.nhdr'))

# create a new 'Perception Measures'
perceptionMeasures = PerceptionMeasures(registrationName='Perception Measures', Input=toothnhdr,
    SpecFile='')
perceptionMeasures.Height = 256
perceptionMeasures.ScalarArray = 'ImageFile'
perceptionMeasures.SpecJSON = '{"version":1,"background":[0.0,0.0,0.0],"structures":[{"name":"dentin","range":[145.0,180.0],"importance":0.4,"color":[0.95,0.88,0.7],"edge":0.1,"lighting":{"ambient":0.2,"diffuse":0.8,"specular":0.2,"specular_power":16.0}},{"name":"enamel","range":[200.0,250.0],"importance":0.85,"color":[0.85,0.92,1.0],"edge":0.1,"lighting":{"ambient":0.2,"diffuse":0.8,"specular":0.2,"specular_power":16.0}}],"rendering":{"shade":true,"light_direction":[0.0,0.0,1.0],"light_intensity":1.0},"view":[180.0,90.0,1.0]}'
perceptionMeasures.Width = 256

# ----------------------------------------------------------------
# setup the visualization in view 'renderView1'
# ----------------------------------------------------------------

# show data from toothnhdr
toothnhdrDisplay = Show(toothnhdr, renderView1, 'UniformGridRepresentation')

# get 2D transfer function for 'ImageFile'
imageFileTF2D = GetTransferFunction2D('ImageFile')
imageFileTF2D.ScalarRangeInitialized = 1
imageFileTF2D.Range = [0.0, 255.0, 0.0, 1.0]

# get color transfer function/color map for 'ImageFile'
imageFileLUT = GetColorTransferFunction('ImageFile')
imageFileLUT.AutomaticRescaleRangeMode = 'Never'
imageFileLUT.TransferFunction2D = imageFileTF2D
imageFileLUT.RGBPoints = [145.062255859375, 0.95, 0.88, 0.7, 179.937744140625, 0.95, 0.88, 0.7, 200.062255859375, 0.85, 0.92, 1.0, 249.937744140625, 0.85, 0.92, 1.0]
imageFileLUT.ColorSpace = 'RGB'
imageFileLUT.ScalarRangeInitialized = 1.0

# get opacity transfer function/opacity map for 'ImageFile'
imageFilePWF = GetOpacityTransferFunction('ImageFile')
imageFilePWF.Points = [145.0, 0.0, 0.5, 0.0, 148.5, 0.4, 0.5, 0.0, 176.5, 0.4, 0.5, 0.0, 180.0, 0.0, 0.5, 0.0, 200.0, 0.0, 0.5, 0.0, 205.0, 0.85, 0.5, 0.0, 245.0, 0.85, 0.5, 0.0, 250.0, 0.0, 0.5, 0.0]
imageFilePWF.ScalarRangeInitialized = 1

# trace defaults for the display properties.
toothnhdrDisplay.Representation = 'Volume'
toothnhdrDisplay.ColorArrayName = ['POINTS', 'ImageFile']
toothnhdrDisplay.LookupTable = imageFileLUT
toothnhdrDisplay.Specular = 0.2
toothnhdrDisplay.SpecularPower = 16.0
toothnhdrDisplay.Ambient = 0.2
toothnhdrDisplay.Diffuse = 0.8
toothnhdrDisplay.SelectTCoordArray = 'None'
toothnhdrDisplay.SelectNormalArray = 'None'
toothnhdrDisplay.SelectTangentArray = 'None'
toothnhdrDisplay.OSPRayScaleArray = 'ImageFile'
toothnhdrDisplay.OSPRayScaleFunction = 'PiecewiseFunction'
toothnhdrDisplay.SelectOrientationVectors = 'None'
toothnhdrDisplay.ScaleFactor = 16.0
toothnhdrDisplay.SelectScaleArray = 'ImageFile'
toothnhdrDisplay.GlyphType = 'Arrow'
toothnhdrDisplay.GlyphTableIndexArray = 'ImageFile'
toothnhdrDisplay.GaussianRadius = 0.8
toothnhdrDisplay.SetScaleArray = ['POINTS', 'ImageFile']
toothnhdrDisplay.ScaleTransferFunction = 'PiecewiseFunction'
toothnhdrDisplay.OpacityArray = ['POINTS', 'ImageFile']
toothnhdrDisplay.OpacityTransferFunction = 'PiecewiseFunction'
toothnhdrDisplay.DataAxesGrid = 'GridAxesRepresentation'
toothnhdrDisplay.PolarAxes = 'PolarAxesRepresentation'
toothnhdrDisplay.ScalarOpacityFunction = imageFilePWF
toothnhdrDisplay.TransferFunction2D = imageFileTF2D
toothnhdrDisplay.OpacityArrayName = ['POINTS', 'ImageFile']
toothnhdrDisplay.ColorArray2Name = ['POINTS', 'ImageFile']
toothnhdrDisplay.VolumeRenderingMode = 'Ray Cast Only'
toothnhdrDisplay.Shade = 1
toothnhdrDisplay.IsosurfaceValues = [127.5]
toothnhdrDisplay.SliceFunction = 'Plane'
toothnhdrDisplay.Slice = 80
toothnhdrDisplay.SelectInputVectors = [None, '']
toothnhdrDisplay.WriteLog = ''

# init the 'PiecewiseFunction' selected for 'ScaleTransferFunction'
toothnhdrDisplay.ScaleTransferFunction.Points = [0.0, 0.0, 0.5, 0.0, 255.0, 1.0, 0.5, 0.0]

# init the 'PiecewiseFunction' selected for 'OpacityTransferFunction'
toothnhdrDisplay.OpacityTransferFunction.Points = [0.0, 0.0, 0.5, 0.0, 255.0, 1.0, 0.5, 0.0]

# init the 'Plane' selected for 'SliceFunction'
toothnhdrDisplay.SliceFunction.Origin = [51.0, 46.5, 80.0]

# ----------------------------------------------------------------
# setup the visualization in view 'renderView2'
# ----------------------------------------------------------------

# show data from perceptionMeasures
perceptionMeasuresDisplay = Show(perceptionMeasures, renderView2, 'UniformGridRepresentation')

# get 2D transfer function for 'rgba'
rgbaTF2D = GetTransferFunction2D('rgba')
rgbaTF2D.ScalarRangeInitialized = 1
rgbaTF2D.Range = [0.0, 1.9993321073354926, 0.0, 1.0]

# get color transfer function/color map for 'rgba'
rgbaLUT = GetColorTransferFunction('rgba')
rgbaLUT.TransferFunction2D = rgbaTF2D
rgbaLUT.RGBPoints = [0.0, 0.231373, 0.298039, 0.752941, 0.9996660536677463, 0.865003, 0.865003, 0.865003, 1.9993321073354926, 0.705882, 0.0156863, 0.14902]
rgbaLUT.ScalarRangeInitialized = 1.0

# get opacity transfer function/opacity map for 'rgba'
rgbaPWF = GetOpacityTransferFunction('rgba')
rgbaPWF.Points = [0.0, 0.0, 0.5, 0.0, 1.9993321073354926, 1.0, 0.5, 0.0]
rgbaPWF.ScalarRangeInitialized = 1

# trace defaults for the display properties.
perceptionMeasuresDisplay.Representation = 'Slice'
perceptionMeasuresDisplay.ColorArrayName = ['POINTS', 'rgba']
perceptionMeasuresDisplay.LookupTable = rgbaLUT
perceptionMeasuresDisplay.MapScalars = 0
perceptionMeasuresDisplay.SelectTCoordArray = 'None'
perceptionMeasuresDisplay.SelectNormalArray = 'None'
perceptionMeasuresDisplay.SelectTangentArray = 'None'
perceptionMeasuresDisplay.OSPRayScaleArray = 'rgba'
perceptionMeasuresDisplay.OSPRayScaleFunction = 'PiecewiseFunction'
perceptionMeasuresDisplay.SelectOrientationVectors = 'None'
perceptionMeasuresDisplay.ScaleFactor = 25.5
perceptionMeasuresDisplay.SelectScaleArray = 'None'
perceptionMeasuresDisplay.GlyphType = 'Arrow'
perceptionMeasuresDisplay.GlyphTableIndexArray = 'rgba'
perceptionMeasuresDisplay.GaussianRadius = 1.2750000000000001
perceptionMeasuresDisplay.SetScaleArray = ['POINTS', 'rgba']
perceptionMeasuresDisplay.ScaleTransferFunction = 'PiecewiseFunction'
perceptionMeasuresDisplay.OpacityArray = ['POINTS', 'rgba']
perceptionMeasuresDisplay.OpacityTransferFunction = 'PiecewiseFunction'
perceptionMeasuresDisplay.DataAxesGrid = 'GridAxesRepresentation'
perceptionMeasuresDisplay.PolarAxes = 'PolarAxesRepresentation'
perceptionMeasuresDisplay.ScalarOpacityUnitDistance = 8.967988815980597
perceptionMeasuresDisplay.ScalarOpacityFunction = rgbaPWF
perceptionMeasuresDisplay.TransferFunction2D = rgbaTF2D
perceptionMeasuresDisplay.OpacityArrayName = ['POINTS', 'rgba']
perceptionMeasuresDisplay.ColorArray2Name = ['POINTS', 'rgba']
perceptionMeasuresDisplay.IsosurfaceValues = [0.5]
perceptionMeasuresDisplay.SliceFunction = 'Plane'
perceptionMeasuresDisplay.SelectInputVectors = [None, '']
perceptionMeasuresDisplay.WriteLog = ''

# init the 'Plane' selected for 'SliceFunction'
perceptionMeasuresDisplay.SliceFunction.Origin = [127.5, 127.5, 0.0]

# ----------------------------------------------------------------
# setup the visualization in view 'spreadSheetView1'
# ----------------------------------------------------------------

# show data from perceptionMeasures
perceptionMeasuresDisplay_1 = Show(perceptionMeasures, spreadSheetView1, 'SpreadSheetRepresentation')

# trace defaults for the display properties.
perceptionMeasuresDisplay_1.Assembly = ''

# ----------------------------------------------------------------
# setup color maps and opacity mapes used in the visualization
# note: the Get..() functions create a new object, if needed
# ----------------------------------------------------------------

# ----------------------------------------------------------------
# restore active source
SetActiveSource(perceptionMeasures)
# ----------------------------------------------------------------
