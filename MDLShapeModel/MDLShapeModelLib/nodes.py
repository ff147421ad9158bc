"""The module's helpers between MRML nodes and the library's files: inputs written by Slicer's
storage nodes, meshes and tables read into nodes, the subject hierarchy, colours.

Coordinates: Slicer's world is RAS; the library's physical space is LPS, like the image files
SimpleITK reads (:func:`toRas` maps one to the other).
"""

from __future__ import annotations

import os
import pathlib
import re

import slicer
import vtk

# The node types a build takes as inputs.
INPUT_NODE_TYPES = ("vtkMRMLSegmentationNode", "vtkMRMLLabelMapVolumeNode", "vtkMRMLModelNode")


def segmentNames(text: str) -> list:
    """Segment names written as text: separated by commas (names may hold spaces)."""
    return [name.strip() for name in text.split(",") if name.strip()]


def fileSafe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("._") or "case"


def caseName(item) -> str:
    """The case name a build gives an input: a file's name without its suffix, a node's name
    made safe for a file name (exportInputs also makes node names unique)."""
    if isinstance(item, (str, os.PathLike)):
        from mdlshapemodel.prepare.io import case_name

        return case_name(item)
    return fileSafe(item.GetName() or item.GetID())


def uniqueName(name: str, used: set) -> str:
    candidate, k = name, 1
    while candidate.lower() in used:
        k += 1
        candidate = f"{name}_{k}"
    used.add(candidate.lower())
    return candidate


def checkData(node):
    """A volume's or model's data checked before a storage node reads it to write the file, as
    the library checks VTK data: an image's scalars against its extent, a mesh's cells against
    its points (a storage node would read past a shorter array). ValueError with the reason."""
    from mdlshapemodel.errors import InputError
    from mdlshapemodel.prepare import io

    try:
        if node.IsA("vtkMRMLVolumeNode"):
            io.image_values(node.GetImageData())
        elif node.GetPolyData() is None or node.GetPolyData().GetNumberOfPoints() == 0:
            raise InputError("the model has no mesh")
        else:
            io.require_valid_cells(node.GetPolyData())
    except InputError as error:
        raise ValueError(str(error)) from None


def writeNode(node, path: pathlib.Path, storageClass: str) -> pathlib.Path:
    storage = slicer.mrmlScene.CreateNodeByClass(storageClass)
    if storage is None:     # a class the scene has not registered (markups outside Slicer)
        storage = getattr(slicer, storageClass)()
    else:
        storage.UnRegister(None)
    storage.SetFileName(str(path))
    if not storage.WriteData(node):
        raise ValueError(f"could not be written to {path}")
    return path


def writeSegmentation(node, segments, value: int, path: pathlib.Path) -> pathlib.Path:
    from vtk.util.numpy_support import vtk_to_numpy

    segmentation = node.GetSegmentation()
    ids = [segmentation.GetNthSegmentID(i) for i in range(segmentation.GetNumberOfSegments())]
    if segments:
        byName = {segmentation.GetSegment(i).GetName(): i for i in ids}
        missing = [s for s in segments if s not in byName]
        if missing:
            raise ValueError(f"no segment named {missing[0]!r} (it has "
                             f"{', '.join(sorted(byName)) or 'none'})")
        ids = [byName[s] for s in segments]
    if not ids:
        raise ValueError("the segmentation has no segments")
    chosen = vtk.vtkStringArray()
    for i in ids:
        chosen.InsertNextValue(i)
    hasGeometry = bool(segmentation.GetConversionParameter("Reference image geometry"))
    extent = (slicer.vtkSegmentation.EXTENT_REFERENCE_GEOMETRY if hasGeometry
              else slicer.vtkSegmentation.EXTENT_UNION_OF_EFFECTIVE_SEGMENTS)
    labelmap = slicer.mrmlScene.AddNewNodeByClass("vtkMRMLLabelMapVolumeNode")
    try:
        if not slicer.vtkSlicerSegmentationsModuleLogic.ExportSegmentsToLabelmapNode(
                node, chosen, labelmap, None, extent) or labelmap.GetImageData() is None:
            raise ValueError("its segments could not be exported as a label map")
        voxels = vtk_to_numpy(labelmap.GetImageData().GetPointData().GetScalars())
        if not voxels.any():
            raise ValueError("the chosen segments are empty")
        voxels[voxels != 0] = value   # the union of the chosen segments
        labelmap.GetImageData().Modified()
        return writeNode(labelmap, path, "vtkMRMLVolumeArchetypeStorageNode")
    finally:
        slicer.mrmlScene.RemoveNode(labelmap)


def subjectHierarchy():
    return slicer.vtkMRMLSubjectHierarchyNode.GetSubjectHierarchyNode(slicer.mrmlScene)


def placeInFolder(node, folder: int):
    hierarchy = subjectHierarchy()
    item = hierarchy.GetItemByDataNode(node)
    if item:
        hierarchy.SetItemParent(item, folder)
    else:
        hierarchy.CreateItem(folder, node)


def temporaryFolder() -> pathlib.Path:
    """A new folder under Slicer's temporary folder (for a table node written as CSV)."""
    import tempfile

    base = pathlib.Path(slicer.app.temporaryPath)
    base.mkdir(parents=True, exist_ok=True)
    return pathlib.Path(tempfile.mkdtemp(prefix="MDLShapeModel-", dir=base))


def colorNode(colormap: str):
    """A colour node of the matplotlib colour map ``colormap`` (the colours of the library's
    report pages), made once per scene."""
    name = f"MDLShapeModel {colormap}"
    existing = slicer.mrmlScene.GetFirstNodeByName(name)
    if existing is not None:
        return existing
    import matplotlib

    node = slicer.mrmlScene.AddNewNodeByClass("vtkMRMLColorTableNode", name)
    node.SetTypeToUser()          # a lookup table: the display's scalar range spreads over it
    node.SetNumberOfColors(256)
    samples = matplotlib.colormaps[colormap]
    for k in range(256):
        red, green, blue, _ = samples(k / 255)
        node.SetColor(k, f"{k}", red, green, blue, 1.0)
    node.SetAttribute("Category", "MDLShapeModel")
    return node


def colorLegend(displayNode, title: str):
    """The colour legend of a display node (the Colors module's default one), titled."""
    legend = slicer.modules.colors.logic().AddDefaultColorLegendDisplayNode(displayNode)
    legend.SetTitleText(title)
    return legend


def toRas(points):
    """LPS <-> RAS (the same map both ways): x and y negated. (n, 3) array-like -> array."""
    import numpy as np

    return np.asarray(points, dtype=np.float64) * np.array([-1.0, -1.0, 1.0])


def addPointArray(polydata, name: str, values):
    import numpy as np
    from vtk.util.numpy_support import numpy_to_vtk

    array = numpy_to_vtk(np.ascontiguousarray(values, dtype=np.float64), deep=True)
    array.SetName(name)
    polydata.GetPointData().AddArray(array)


def addModel(name: str, points, triangles):
    """A model node of points (RAS) and triangles, with display nodes."""
    from mdlshapemodel.prepare.surface import arrays_to_polydata

    node = slicer.mrmlScene.AddNewNodeByClass("vtkMRMLModelNode", name)
    node.SetAndObservePolyData(arrays_to_polydata(points, triangles))
    node.CreateDefaultDisplayNodes()
    return node


def readModel(path: pathlib.Path, name: str):
    """A model node read by Slicer's model storage node (which honours the file's SPACE)."""
    node = slicer.mrmlScene.AddNewNodeByClass("vtkMRMLModelNode", name)
    storage = slicer.mrmlScene.AddNewNodeByClass("vtkMRMLModelStorageNode")
    storage.SetFileName(str(path))
    if not storage.ReadData(node):
        raise OSError(f"{path}: could not be read as a model")
    node.SetAndObserveStorageNodeID(storage.GetID())
    node.CreateDefaultDisplayNodes()
    return node


def tableNode(name: str, columns: dict):
    """A table node of named columns (str or float values, all of one length)."""
    node = slicer.mrmlScene.AddNewNodeByClass("vtkMRMLTableNode", name)
    table = node.GetTable()
    for title, values in columns.items():
        numeric = all(isinstance(v, (int, float)) for v in values)
        array = vtk.vtkDoubleArray() if numeric else vtk.vtkStringArray()
        array.SetName(title)
        for v in values:
            array.InsertNextValue(float(v) if numeric else str(v))
        table.AddColumn(array)
    node.Modified()
    return node


def metricsTable(build, name: str):
    """The build's measures per mode with their standard errors (``BuildFolder.measures``) as
    a table node; None without them."""
    columns = build.measures()
    return None if columns is None else tableNode(f"{name} measures", columns)


def scoresTable(build, name: str):
    """The cases' scores per mode (``BuildFolder.scores``) as a table node; None without them."""
    from mdlshapemodel.folders import score_header

    scores = build.scores()
    if scores is None:
        return None
    names, values = scores
    columns = {"case": list(names)}
    for k, title in enumerate(score_header(values.shape[1])[1:]):
        columns[title] = [float(v) for v in values[:, k]]
    return tableNode(f"{name} scores", columns)
