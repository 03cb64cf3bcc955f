"""Loaders for real tracking data: the standard NRSfM and matrix-factorization benchmarks
(MATLAB files, read with ``scipy.io.loadmat``) and the user's own tracks (``.npz``, ``.csv``).

Every loader returns a `Tracks`: the tracking matrix in the library's layout
(``2m x n``, rows ``2i, 2i+1`` = u, v of frame ``i``, NaN where missing), its visibility
mask, and whatever ground truth the file carries. Arrays are NumPy float64, as stored:
converting them to JAX arrays is left to the caller, who decides on float64
(``jax_enable_x64``) or float32. Files are described in ``shared/data/README.md``:

* ``akhter/{drink,pickup,yoga,stretch,dance}.mat``: CMU motion capture, orthographic tracks
  with ground-truth shapes and rotations (Akhter, Sheikh, Khan & Kanade, "Trajectory space:
  a dual representation for nonrigid structure from motion", PAMI 2011).
* ``nonrigid/dinosaur_real.mat``: the nonrigid dinosaur tracks of the robust-factorization
  paper (G. Wang), complete.
* ``lrmf/dino_trimmed.mat``: the Oxford dinosaur with missing data, the low-rank
  factorization benchmark (Buchanan & Fitzgibbon, CVPR 2005; Hong & Fitzgibbon, ICCV 2015).
"""

import csv
import os
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal

import numpy as np
import scipy.io
from jaxtyping import Bool, Float, Int

AKHTER_SEQUENCES = ("drink", "pickup", "yoga", "stretch", "dance")
"""The Akhter et al. sequences in ``akhter/``."""

DATA_ENV = "JAXNRSFM_DATA"
"""Environment variable naming the data directory."""


@dataclass(frozen=True)
class Tracks:
    """A tracking matrix, its missing entries, and any ground truth."""

    W: Float[np.ndarray, "2m n"]
    """Tracks: rows ``2i, 2i+1`` are u, v of frame ``i``; NaN at missing entries."""
    visible: Bool[np.ndarray, "m n"]
    """Observed (frame, point) entries."""
    name: str
    """Where the tracks came from (sequence name or file stem)."""
    shapes: Float[np.ndarray, "m 3 n"] | None = None
    """Ground-truth 3-D shape of every frame, if known."""
    rotations: Float[np.ndarray, "m 3 3"] | None = None
    """Ground-truth camera rotations, if known; the camera of frame ``i`` is
    ``rotations[i, :2]`` (the third row is their cross product)."""
    edges: Int[np.ndarray, "e 2"] | None = None
    """Skeleton edges as 0-based point index pairs, for drawing, if known."""
    frame: Literal["world", "camera"] = "world"
    """The frame ``shapes`` are given in: ``"world"`` (compare a reconstruction's
    ``shapes``) or ``"camera"``, each frame's camera coordinates (compare
    ``camera_shapes``, ``R_i S_i``): see `ground_truth_frame`."""


def ground_truth_frame(W: np.ndarray, shapes: np.ndarray) -> Literal["world", "camera"]:
    """``"camera"`` when one fixed orthographic camera sees every frame of the ground truth
    (a static camera, as in Akhter's dance: ``W_i = R[:2] S_i`` for one ``R``), else
    ``"world"``.

    A factorization gives the object's rigid turning to the cameras ``R_i`` whatever the
    real camera did, so under a static camera the true shapes are comparable with the
    reconstructed shapes in each frame's camera coordinates, ``R_i S_i`` -- what the
    published PTA and BMM scripts score on dance (``rotateStruct``, flag ``rotStruct = 1``).
    Decided by the least-squares fit of one ``2 x 3`` projection to all centred frames:
    its relative reprojection error is round-off (below ``1e-6``) for a static camera.
    """
    m = shapes.shape[0]
    X = shapes - shapes.mean(axis=2, keepdims=True)
    frames = W.reshape(m, 2, -1)
    Y = frames - frames.mean(axis=2, keepdims=True)
    A = np.concatenate(list(X), axis=1).T  # (m n, 3)
    B = np.concatenate(list(Y), axis=1).T  # (m n, 2)
    P, *_ = np.linalg.lstsq(A, B, rcond=None)
    misfit = np.linalg.norm(A @ P - B) / max(np.linalg.norm(B), np.finfo(float).tiny)
    return "camera" if misfit < 1e-6 else "world"


def data_dir(path: str | os.PathLike | None = None) -> Path:
    """The data directory: ``path`` if given, else the ``JAXNRSFM_DATA`` environment
    variable, else ``../shared/data`` relative to the repository root (the parent of the
    package directory, for an editable install) or to the working directory, the first
    that exists.

    **Raises:** ``FileNotFoundError`` naming what was tried when the directory is missing.
    """
    if path is not None:
        if not Path(path).is_dir():
            raise FileNotFoundError(f"data directory {path} does not exist")
        return Path(path)
    defaults = [Path(__file__).resolve().parents[2] / "shared" / "data", Path.cwd().parent / "shared" / "data"]
    env = os.environ.get(DATA_ENV)
    if env:
        # An explicit choice is never silently replaced by the default.
        if not Path(env).is_dir():
            raise FileNotFoundError(f"${DATA_ENV}={env} is not a directory (unset it to use ../shared/data)")
        return Path(env)
    for default in defaults:
        if default.is_dir():
            return default
    raise FileNotFoundError(
        f"no data directory: ${DATA_ENV} is not set and neither {defaults[0]} (../shared/data from the "
        f"repository root) nor {defaults[1]} (from the working directory) exists"
    )


def _resolve(name: str | os.PathLike, subdir: str, root: str | os.PathLike | None) -> Path:
    # A bare sequence name is looked up in the data directory; anything else is a path.
    path = Path(name)
    if path.suffix != ".mat":
        path = data_dir(root) / subdir / f"{name}.mat"
    if not path.is_file():
        raise FileNotFoundError(f"data file not found: {path}")
    return path


def _loadmat(path: Path, variables: tuple[str, ...]) -> dict[str, np.ndarray]:
    contents = scipy.io.loadmat(path)
    present = sorted(k for k in contents if not k.startswith("__"))
    for v in variables:
        if v not in contents:
            raise ValueError(f"{path} lacks the variable {v!r} (it has: {', '.join(present) or 'nothing'})")
    return contents


def _check_tracks(W: np.ndarray, source: str) -> None:
    if W.ndim != 2 or W.shape[0] % 2 or W.size == 0:
        raise ValueError(
            f"{source}: tracks must be a non-empty 2-D array with an even number of rows "
            f"(u and v of each frame); got shape {W.shape}"
        )


def _visible_from_nan(W: np.ndarray, source: str) -> np.ndarray:
    nan = np.isnan(W.reshape(W.shape[0] // 2, 2, W.shape[1]))
    if np.any(nan[:, 0] != nan[:, 1]):
        i, j = np.argwhere(nan[:, 0] != nan[:, 1])[0]
        raise ValueError(f"{source}: entry (frame {i}, point {j}) has one coordinate missing and the other not")
    return ~nan[:, 0]


def load_akhter(sequence: str | os.PathLike, *, root: str | os.PathLike | None = None) -> Tracks:
    """An Akhter et al. motion-capture sequence with its ground truth.

    **Arguments:**

    - `sequence`: one of `AKHTER_SEQUENCES`, or the path of a ``.mat`` file.
    - `root`: the data directory (default: `data_dir`).

    **Returns:** `Tracks` with ``shapes`` (``F x 3 x P``, from ``S``), ``rotations``
    (from ``Rs``; ``None`` for dance, which has none), ``edges`` (from ``list``, made
    0-based; ``None`` where absent) and ``frame`` (`ground_truth_frame`: ``"camera"``
    for dance, filmed by a static camera). ``W`` is complete and on the scale of ``S``.
    """
    path = _resolve(sequence, "akhter", root)
    d = _loadmat(path, ("W", "S"))
    W = np.asarray(d["W"], np.float64)
    _check_tracks(W, str(path))
    F, P = W.shape[0] // 2, W.shape[1]
    if d["S"].shape != (3 * F, P):
        raise ValueError(f"{path}: S has shape {d['S'].shape}; expected (3F, P) = ({3 * F}, {P})")
    shapes = np.asarray(d["S"], np.float64).reshape(F, 3, P)
    rotations = None
    if "Rs" in d:
        R2 = np.asarray(d["Rs"], np.float64).reshape(F, 2, 3)
        rotations = np.concatenate([R2, np.cross(R2[:, 0], R2[:, 1])[:, None]], axis=1)
    edges = np.asarray(d["list"], np.int64) - 1 if "list" in d else None
    frame = ground_truth_frame(W, shapes)
    return Tracks(W, _visible_from_nan(W, str(path)), Path(path).stem, shapes, rotations, edges, frame)


def load_nonrigid_dinosaur(
    path: str | os.PathLike = "dinosaur_real", *, root: str | os.PathLike | None = None
) -> Tracks:
    """The nonrigid dinosaur tracks (231 frames, 49 points, complete).

    The file's ``X`` is ``3 x 49 x 231`` (coordinate, point, frame); rows x and y are the
    tracks. The z row is not trusted ground truth and is not returned.
    """
    path = _resolve(path, "nonrigid", root)
    X = np.asarray(_loadmat(path, ("X",))["X"], np.float64)
    if X.ndim != 3 or X.shape[0] < 2:
        raise ValueError(f"{path}: X has shape {X.shape}; expected (3, points, frames)")
    W = X[:2].transpose(2, 0, 1).reshape(2 * X.shape[2], X.shape[1])
    return Tracks(W, _visible_from_nan(W, str(path)), Path(path).stem)


def load_lrmf_dino(path: str | os.PathLike = "dino_trimmed", *, root: str | os.PathLike | None = None) -> Tracks:
    """The Oxford dinosaur with missing data (36 frames, 319 points, rank 4 affine).

    ``M`` holds the tracks (NaN where missing) and ``W`` the per-coordinate visibility
    mask; both rows of a frame must agree, and every visible coordinate must be finite.
    The best known rank-4 fit has RMS 1.084673 over the 5302 observed coordinates (Hong &
    Fitzgibbon, ICCV 2015).
    """
    path = _resolve(path, "lrmf", root)
    d = _loadmat(path, ("M", "W"))
    tracks = np.asarray(d["M"], np.float64)
    _check_tracks(tracks, str(path))
    mask = np.asarray(d["W"]) != 0
    if mask.shape != tracks.shape:
        raise ValueError(f"{path}: mask W has shape {mask.shape}, tracks M {tracks.shape}")
    rows = mask.reshape(-1, 2, mask.shape[1])
    if np.any(rows[:, 0] != rows[:, 1]):
        i, j = np.argwhere(rows[:, 0] != rows[:, 1])[0]
        raise ValueError(f"{path}: the mask W marks only one coordinate of frame {i}, point {j} as observed")
    if not np.all(np.isfinite(tracks[mask])):
        raise ValueError(f"{path}: M has non-finite values at entries that W marks as observed")
    return Tracks(np.where(mask, tracks, np.nan), rows[:, 0], Path(path).stem)


def load_mat(path: str | os.PathLike, variable: str = "W") -> Tracks:
    """Tracks from any MATLAB (v4-v7) file: the ``2m x n`` matrix ``variable``, in the
    library's layout (NaN where missing), as in Akhter's files.

    Ground truth comes along when the file has it in Akhter's layout: ``S`` (``3m x n``)
    becomes ``shapes`` and ``Rs`` (``2m x 3``) ``rotations``; a ``S`` or ``Rs`` of another
    shape is not taken for ground truth and is ignored.

    **Raises:** ``ValueError`` for a file that is not a MATLAB file, a missing or
    non-numeric variable, or a malformed tracking matrix.
    """
    path = Path(path)
    try:
        d = _loadmat(path, (variable,))
    except (scipy.io.matlab.MatReadError, NotImplementedError) as err:
        # v7.3 files are HDF5 and raise NotImplementedError in scipy.
        raise ValueError(f"{path}: not a readable MATLAB v4-v7 file ({err})") from None
    raw = np.asarray(d[variable])
    if not (np.issubdtype(raw.dtype, np.number) or raw.dtype == bool) or np.iscomplexobj(raw):
        raise ValueError(f"{path}: variable {variable!r} is not a real numeric matrix (it holds {raw.dtype} data)")
    W = raw.astype(np.float64)
    _check_tracks(W, f"{path}, variable {variable!r}")
    F, P = W.shape[0] // 2, W.shape[1]
    shapes = rotations = None
    if "S" in d and np.shape(d["S"]) == (3 * F, P):
        shapes = np.asarray(d["S"], np.float64).reshape(F, 3, P)
    if "Rs" in d and np.shape(d["Rs"]) == (2 * F, 3):
        R2 = np.asarray(d["Rs"], np.float64).reshape(F, 2, 3)
        rotations = np.concatenate([R2, np.cross(R2[:, 0], R2[:, 1])[:, None]], axis=1)
    tracks = _tracks(W, None, path)
    frame = "world"
    if shapes is not None and tracks.visible.all():
        frame = ground_truth_frame(W, shapes)
    return replace(tracks, shapes=shapes, rotations=rotations, frame=frame)


def load_npz(path: str | os.PathLike) -> Tracks:
    """Tracks from a ``.npz`` file: array ``W`` (``2m x n``, NaN where missing) and an
    optional boolean ``visible`` (``m x n``) that marks further entries missing."""
    path = Path(path)
    with np.load(path) as f:
        if "W" not in f:
            raise ValueError(f"{path} lacks the array 'W' (it has: {', '.join(f.files) or 'nothing'})")
        W = np.asarray(f["W"], np.float64)
        visible = np.asarray(f["visible"]) if "visible" in f else None
    return _tracks(W, visible, path)


def load_csv(path: str | os.PathLike) -> Tracks:
    """Tracks from a comma-separated ``2m x n`` numeric table without a header; an empty
    cell or ``nan`` is a missing coordinate."""
    path = Path(path)
    rows = []
    with open(path, newline="") as f:
        for i, line in enumerate(csv.reader(f)):
            if not line:
                continue
            try:
                rows.append([float(c) if c.strip() and c.strip().lower() != "nan" else np.nan for c in line])
            except ValueError as err:
                raise ValueError(f"{path}, line {i + 1}: not a number ({err})") from None
    if not rows:
        raise ValueError(f"{path}: no data")
    if len({len(r) for r in rows}) > 1:
        raise ValueError(f"{path}: rows have different numbers of columns ({sorted({len(r) for r in rows})})")
    return _tracks(np.array(rows, np.float64).reshape(len(rows), -1), None, path)


def load_tracks(path: str | os.PathLike, variable: str = "W") -> Tracks:
    """Tracks from a ``.npz``, ``.csv`` or ``.mat`` file (see `load_npz`,
    `load_csv`, `load_mat`; ``variable`` names the ``.mat`` file's matrix)."""
    suffix = Path(path).suffix.lower()
    if suffix == ".npz":
        return load_npz(path)
    if suffix == ".csv":
        return load_csv(path)
    if suffix == ".mat":
        return load_mat(path, variable)
    raise ValueError(f"{path}: unknown track file type {suffix!r}; expected .npz, .csv or .mat")


def _tracks(W: np.ndarray, visible: np.ndarray | None, path: Path) -> Tracks:
    _check_tracks(W, str(path))
    observed = _visible_from_nan(W, str(path))
    if visible is not None:
        if visible.shape != observed.shape:
            raise ValueError(f"{path}: visible has shape {visible.shape}; expected (m, n) = {observed.shape}")
        observed &= visible.astype(bool)
    if not np.all(np.isfinite(W[np.repeat(observed, 2, axis=0)])):
        raise ValueError(f"{path}: W has infinite values at observed entries")
    return Tracks(np.where(np.repeat(observed, 2, axis=0), W, np.nan), observed, path.stem)
