"""The exported files load in VTK, a maintained reader independent of the writers
(trimesh writes PLY and OBJ, jaxnrsfm.export writes VRML97)."""

import re

import numpy as np
import pytest

from jaxnrsfm.export import FORMATS, export_format, export_shapes, series_paths, triangulate

vtk_core = pytest.importorskip("vtkmodules.vtkCommonCore", reason="the readers come from vtk: pip install '.[test]'")
from vtkmodules.vtkIOGeometry import vtkOBJReader  # noqa: E402
from vtkmodules.vtkIOImport import vtkVRMLImporter  # noqa: E402
from vtkmodules.vtkIOPLY import vtkPLYReader  # noqa: E402


def _shapes(m=4, n=7, seed=0):
    shapes = np.random.default_rng(seed).normal(size=(m, 3, n))
    shapes[:, :, 3] = shapes[:, :, 2]  # coincident points must stay two points
    return shapes


def _points(polydata) -> np.ndarray:
    return np.array([polydata.GetPoint(i) for i in range(polydata.GetNumberOfPoints())])


@pytest.fixture
def vtk_messages():
    """What VTK reports through its output window (its errors and warnings)."""
    window = vtk_core.vtkStringOutputWindow()
    previous = vtk_core.vtkOutputWindow.GetInstance()
    vtk_core.vtkOutputWindow.SetInstance(window)
    yield window.GetOutput
    vtk_core.vtkOutputWindow.SetInstance(previous)


@pytest.mark.parametrize(("ext", "reader", "atol"), [(".ply", vtkPLYReader, 1e-6), (".obj", vtkOBJReader, 1e-7)])
def test_point_cloud_series(tmp_path, vtk_messages, ext, reader, atol):
    shapes = _shapes()
    paths = export_shapes(tmp_path / f"shapes{ext}", shapes)
    assert paths == [tmp_path / f"shapes_{i:04d}{ext}" for i in range(4)]
    for path, shape in zip(paths, shapes, strict=True):
        r = reader()
        r.SetFileName(str(path))
        r.Update()
        # PLY: binary float32 vertices; OBJ: 8 decimals.
        np.testing.assert_allclose(_points(r.GetOutput()), shape.T, rtol=1e-6, atol=atol)
    assert vtk_messages() == ""


@pytest.mark.parametrize("m", [1, 5])
def test_vrml(tmp_path, vtk_messages, capfd, m):
    shapes = _shapes(m=m)
    path = tmp_path / "shapes.wrl"
    assert export_shapes(path, shapes, fps=10, name='a "quoted" name') == [path]
    importer = vtkVRMLImporter()
    importer.SetFileName(str(path))
    importer.Update()
    # VTK's VRML parser reports syntax errors on stderr, semantic ones in its output window.
    assert vtk_messages() == "" and "error" not in capfd.readouterr().err.lower()
    actors = importer.GetRenderer().GetActors()
    assert actors.GetNumberOfItems() == 1
    actors.InitTraversal()
    cloud = actors.GetNextActor().GetMapper().GetInput()
    assert cloud.GetNumberOfVerts() == 7  # a PointSet: one vertex cell per point
    np.testing.assert_allclose(_points(cloud), shapes[0].T, rtol=1e-6, atol=1e-7)
    # VTK imports the static scene only: check the animation's data in the text it parsed.
    text = path.read_text()
    assert text.startswith("#VRML V2.0 utf8\n")
    keys = re.search(r"key \[([^\]]*)\]", text).group(1).split(",")
    values = re.search(r"keyValue \[([^\]]*)\]", text).group(1).replace(",", " ").split()
    np.testing.assert_allclose(np.array(keys, float), np.linspace(0, 1, m) if m > 1 else [0.0])
    frames = np.array(values, float).reshape(m, 7, 3)
    np.testing.assert_allclose(frames, shapes.transpose(0, 2, 1), rtol=1e-7, atol=1e-8)
    assert "ROUTE clock.fraction_changed TO frames.set_fraction" in text
    assert "ROUTE frames.value_changed TO points.set_point" in text


def test_formats_and_errors(tmp_path):
    assert {export_format(f"x{ext.upper()}") for ext in FORMATS} == {"ply", "obj", "vrml"}
    with pytest.raises(ValueError, match="unknown export format '.stl'"):
        export_shapes(tmp_path / "x.stl", _shapes())
    with pytest.raises(ValueError, match=r"\(frames, 3, points\)"):
        export_shapes(tmp_path / "x.ply", np.zeros((4, 2, 7)))
    with pytest.raises(ValueError, match="non-finite"):
        export_shapes(tmp_path / "x.wrl", np.full((4, 3, 7), np.nan))
    assert series_paths(tmp_path / "s.ply", 12345)[-1].name == "s_12344.ply"
    assert not list(tmp_path.iterdir())


def _surface(m=4):
    # A bumpy grid seen from the first camera: its Delaunay triangles in the image plane.
    u, v = np.meshgrid(np.linspace(0, 1, 4), np.linspace(0, 1, 3))
    base = np.stack([u.ravel(), v.ravel(), 0.1 * np.sin(3 * u.ravel())])
    shapes = np.stack([base * (1 + 0.1 * i) for i in range(m)])
    return shapes, triangulate(shapes)


def test_triangulate():
    shapes, faces = _surface()
    # a 4 x 3 grid: 3 x 2 cells, two triangles each, covering the unit square once
    assert faces.shape == (12, 3) and faces.dtype == np.int64
    a, b, c = (shapes[0, :2].T[faces[:, i]] for i in range(3))
    area = 0.5 * ((b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0]))
    assert (area > 0).all() and np.isclose(area.sum(), 1.0)
    with pytest.raises(ValueError, match="span no triangle"):
        triangulate(np.zeros((2, 3, 5)))


@pytest.mark.parametrize(("ext", "reader", "atol"), [(".ply", vtkPLYReader, 1e-6), (".obj", vtkOBJReader, 1e-7)])
def test_surface_series(tmp_path, vtk_messages, ext, reader, atol):
    shapes, faces = _surface()
    paths = export_shapes(tmp_path / f"surface{ext}", shapes, faces=faces)
    for path, shape in zip(paths, shapes, strict=True):
        r = reader()
        r.SetFileName(str(path))
        r.Update()
        mesh = r.GetOutput()
        np.testing.assert_allclose(_points(mesh), shape.T, rtol=1e-6, atol=atol)
        assert mesh.GetNumberOfPolys() == len(faces)
        np.testing.assert_array_equal(_triangles(mesh), faces)
    assert vtk_messages() == ""


def test_vrml_surface(tmp_path, vtk_messages, capfd):
    shapes, faces = _surface()
    path = tmp_path / "surface.wrl"
    export_shapes(path, shapes, faces=faces)
    importer = vtkVRMLImporter()
    importer.SetFileName(str(path))
    importer.Update()
    assert vtk_messages() == "" and "error" not in capfd.readouterr().err.lower()
    actors = importer.GetRenderer().GetActors()
    actors.InitTraversal()
    mesh = actors.GetNextActor().GetMapper().GetInput()
    np.testing.assert_allclose(_points(mesh), shapes[0].T, rtol=1e-6, atol=1e-7)
    np.testing.assert_array_equal(_triangles(mesh), faces)
    # the animation morphs the same Coordinate the faces index
    assert "IndexedFaceSet" in path.read_text() and "ROUTE frames.value_changed TO points.set_point" in path.read_text()


def _triangles(polydata) -> np.ndarray:
    cells = polydata.GetPolys()
    ids = vtk_core.vtkIdList()
    cells.InitTraversal()
    triangles = []
    while cells.GetNextCell(ids):
        triangles.append([ids.GetId(i) for i in range(ids.GetNumberOfIds())])
    return np.array(triangles)


def test_bad_faces(tmp_path):
    shapes, faces = _surface()
    with pytest.raises(ValueError, match="integer"):
        export_shapes(tmp_path / "x.ply", shapes, faces=faces.astype(float))
    with pytest.raises(ValueError, match="outside"):
        export_shapes(tmp_path / "x.ply", shapes, faces=faces + 100)
    assert not list(tmp_path.iterdir())
