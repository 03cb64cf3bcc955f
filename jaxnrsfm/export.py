"""Export of reconstructed shape sequences for 3-D viewers: PLY, OBJ and VRML97, as point
clouds or as triangulated surfaces.

PLY and OBJ hold one static geometry per file, so a sequence is a numbered series,
``shapes_0000.ply``, ``shapes_0001.ply``, ..., the form that viewers (ParaView, MeshLab,
Blender's sequence importers) play frame by frame; trimesh writes them. No maintained
Python library writes VRML97, and its text is short, so the VRML writer is here: ONE file
whose ``CoordinateInterpolator`` morphs a ``PointSet`` (or, with faces, an
``IndexedFaceSet``) through every frame, driven by a looping ``TimeSensor`` (the VRML97
way to animate geometry, no Script node needed); a viewer without animation shows the
first frame.

Surfaces, as the paper draws its reconstructions (wireframes of the cube and the faces):
one triangulation of the points for every frame (:func:`triangulate`, Delaunay in the
reference frame's image plane), so that the mesh deforms with the object.
"""

import os
from pathlib import Path

import numpy as np
from jaxtyping import Float, Int

FORMATS = {".ply": "ply", ".obj": "obj", ".wrl": "vrml", ".vrml": "vrml"}
"""File extensions `export_shapes` understands, and the format each one selects."""


def export_format(path: str | os.PathLike) -> str:
    """The format that ``path``'s extension selects (``"ply"``, ``"obj"`` or ``"vrml"``).

    Checked apart from writing so that a command can refuse a bad name before it computes.

    **Raises:** ``ValueError`` for an extension not in `FORMATS`.
    """
    suffix = Path(path).suffix.lower()
    if suffix not in FORMATS:
        raise ValueError(f"{path}: unknown export format {suffix or '(no extension)'!r}; use {', '.join(FORMATS)}")
    return FORMATS[suffix]


def series_paths(path: str | os.PathLike, frames: int) -> list[Path]:
    """The files of a per-frame series named after ``path``: ``stem_0000.ext``, ...

    Zero-padded (at least four digits) so that sorting by name sorts by frame.
    """
    path = Path(path)
    width = max(4, len(str(frames - 1)))
    return [path.with_name(f"{path.stem}_{i:0{width}d}{path.suffix}") for i in range(frames)]


def triangulate(shapes: Float[np.ndarray, "m 3 n"], frame: int = 0) -> Int[np.ndarray, "f 3"]:
    """Triangles over the points: the Delaunay triangulation (scipy.spatial, Qhull) of
    frame ``frame``'s points in its image plane, the ``x, y`` of a reconstruction's world
    frame, which is the first camera's (:func:`jaxnrsfm.upgrade.canonical_world`). The same
    triangles serve every frame: the surface deforms with the points.

    **Returns:** ``(f, 3)`` point indices, each triangle counter-clockwise in that plane.
    Coincident points are kept as points; only one of them is a vertex of triangles.

    **Raises:** ``ValueError`` if the points span no triangle (fewer than three, or all on a line).
    """
    from scipy.spatial import Delaunay, QhullError

    plane = np.asarray(shapes, dtype=np.float64)[frame, :2].T
    try:
        faces = np.asarray(Delaunay(plane).simplices, dtype=np.int64)
    except (QhullError, ValueError) as err:
        raise ValueError(f"the points of frame {frame} span no triangle in its image plane ({err})") from None
    # Qhull does not orient its simplices: make every triangle counter-clockwise in the plane
    # (its normal towards the camera), so that viewers light them consistently.
    a, b, c = (plane[faces[:, i]] for i in range(3))
    clockwise = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0]) < 0
    faces[clockwise] = faces[clockwise][:, ::-1]
    return faces


def export_shapes(
    path: str | os.PathLike,
    shapes: Float[np.ndarray, "m 3 n"],
    *,
    faces: Int[np.ndarray, "f 3"] | None = None,
    fps: float = 25.0,
    name: str = "jaxnrsfm",
) -> list[Path]:
    """Write a sequence of 3-D shapes (``m`` frames of ``n`` points) in the format chosen
    by ``path``'s extension (`FORMATS`).

    **Arguments:**

    - `path`: ``.ply`` or ``.obj`` (one file per frame, see `series_paths`), or
      ``.wrl``/``.vrml`` (one animated VRML97 file, see `write_vrml`).
    - `shapes`: ``(m, 3, n)``, e.g. `jaxnrsfm.Reconstruction.shapes`.
    - `faces`: optional ``(f, 3)`` point indices of triangles (e.g. :func:`triangulate`),
      the same in every frame: surfaces instead of point clouds.
    - `fps`: playback rate of the VRML animation.
    - `name`: title of the VRML world.

    **Returns:** the files written.

    **Raises:** ``ValueError`` for an unknown extension, a shape array not ``(m, 3, n)``,
    one with non-finite values, or faces that are not triangles of its points.
    """
    fmt = export_format(path)
    shapes = np.asarray(shapes, dtype=np.float64)
    if shapes.ndim != 3 or shapes.shape[1] != 3 or 0 in shapes.shape:
        raise ValueError(f"shapes must be a non-empty (frames, 3, points) array; got shape {shapes.shape}")
    if not np.all(np.isfinite(shapes)):
        # NaN is no number in OBJ or VRML, and no viewer draws it from PLY.
        raise ValueError("the shapes have non-finite values (a failed reconstruction): nothing to export")
    if faces is not None:
        faces = np.asarray(faces)
        if faces.ndim != 2 or faces.shape[1] != 3 or not np.issubdtype(faces.dtype, np.integer):
            raise ValueError(f"faces must be an integer (f, 3) array of point indices; got {faces.dtype} {faces.shape}")
        if faces.size and (faces.min() < 0 or faces.max() >= shapes.shape[2]):
            raise ValueError(f"faces index points outside 0..{shapes.shape[2] - 1}")
    if fmt == "vrml":
        write_vrml(path, shapes, faces=faces, fps=fps, name=name)
        return [Path(path)]
    return write_series(path, shapes, faces=faces)


def write_series(
    path: str | os.PathLike, shapes: Float[np.ndarray, "m 3 n"], *, faces: Int[np.ndarray, "f 3"] | None = None
) -> list[Path]:
    """One PLY or OBJ file per frame (by ``path``'s extension), with trimesh: a point cloud,
    or with ``faces`` a triangle mesh (every point a vertex, in order, none merged).

    trimesh writes PLY as binary float32 vertices, OBJ as text with 8 decimals.
    """
    import trimesh  # only the export needs it

    file_type = export_format(path)
    paths = series_paths(path, shapes.shape[0])
    for points, p in zip(np.swapaxes(shapes, 1, 2), paths, strict=True):
        if faces is None:
            trimesh.PointCloud(points).export(p, file_type=file_type)
        else:
            # process=False: no merging of coincident points, no reordering.
            trimesh.Trimesh(points, faces, process=False).export(p, file_type=file_type)
    return paths


def write_vrml(
    path: str | os.PathLike,
    shapes: Float[np.ndarray, "m 3 n"],
    *,
    faces: Int[np.ndarray, "f 3"] | None = None,
    fps: float = 25.0,
    name: str = "",
) -> None:
    """One VRML97 (VRML 2.0) file that plays the sequence in a loop at ``fps`` frames per
    second: a ``PointSet`` (with ``faces``, an ``IndexedFaceSet`` of those triangles, seen
    from both sides) whose ``Coordinate`` starts at frame 0 and is driven by a
    ``CoordinateInterpolator`` with key ``i / (m - 1)`` at frame ``i``.

    The viewpoint looks down -z at the centroid of all frames from far enough to see every
    point; the points are white (a surface grey) on the default black background.
    """
    if not fps > 0:
        raise ValueError(f"fps must be positive; got {fps}")
    points = np.swapaxes(np.asarray(shapes, dtype=np.float64), 1, 2)  # (m, n, 3)
    m, n, _ = points.shape
    keys = np.linspace(0.0, 1.0, m) if m > 1 else np.zeros(1)
    centre = points.reshape(-1, 3).mean(axis=0)
    radius = float(np.max(np.linalg.norm(points - centre, axis=2))) or 1.0
    # The default field of view is pi/4: a sphere of this radius fills it from 1/tan(pi/8) = 2.4 radii.
    eye = centre + np.array([0.0, 0.0, 3.0 * radius])

    def triples(p: np.ndarray) -> str:
        # SFFloat is single precision; 9 significant digits round-trip float32.
        return ", ".join(f"{x:.9g} {y:.9g} {z:.9g}" for x, y, z in p)

    if faces is None:
        appearance = "material Material { emissiveColor 1 1 1 }"
        geometry = "PointSet {"
    else:
        appearance = "material Material { diffuseColor 0.8 0.8 0.8 }"
        index = ", ".join(f"{a} {b} {c} -1" for a, b, c in faces)
        geometry = f"IndexedFaceSet {{ solid FALSE coordIndex [{index}]"
    # VRML97 allows \" in strings, but some parsers (VTK's) do not: keep the title plain.
    title = " ".join(name.replace('"', "'").replace("\\", "/").split())
    lines = [
        "#VRML V2.0 utf8",
        f"# {m} frames of {n} points, written by jaxnrsfm: a CoordinateInterpolator morphs the geometry",
        "# through the frames in a loop; a viewer without animation shows frame 0.",
        f'WorldInfo {{ title "{title}" info ["frames {m}", "points {n}", "fps {fps:g}"] }}',
        'NavigationInfo { type ["EXAMINE", "ANY"] }',
        f'Viewpoint {{ position {triples(eye[None])} description "front" }}',
        f"DEF clock TimeSensor {{ cycleInterval {m / fps:.9g} loop TRUE }}",
        "DEF frames CoordinateInterpolator {",
        f"  key [{', '.join(f'{k:.9g}' for k in keys)}]",
        "  keyValue [",
        *(f"    {triples(p)}," for p in points),
        "  ]",
        "}",
        "Shape {",
        f"  appearance Appearance {{ {appearance} }}",
        f"  geometry {geometry} coord DEF points Coordinate {{ point [{triples(points[0])}] }} }}",
        "}",
        "ROUTE clock.fraction_changed TO frames.set_fraction",
        "ROUTE frames.value_changed TO points.set_point",
        "",
    ]
    Path(path).write_text("\n".join(lines), encoding="utf-8")
