import numpy as np
import pytest
import scipy.io

import jaxnrsfm as nr
from jaxnrsfm import datasets


def _find_data():
    try:
        return datasets.data_dir()
    except FileNotFoundError:
        return None


DATA = _find_data()
needs_data = pytest.mark.skipif(
    DATA is None, reason="real data absent: set $JAXNRSFM_DATA or provide ../shared/data next to the repository"
)

AKHTER_SIZES = {"drink": (1102, 41), "pickup": (357, 41), "yoga": (307, 41), "stretch": (370, 41), "dance": (264, 75)}


@needs_data
@pytest.mark.parametrize("name", datasets.AKHTER_SEQUENCES)
def test_akhter(name):
    seq = datasets.load_akhter(name)
    F, P = AKHTER_SIZES[name]
    assert seq.name == name
    assert seq.W.shape == (2 * F, P) and seq.visible.shape == (F, P) and seq.visible.all()
    assert seq.shapes.shape == (F, 3, P)
    if name == "dance":  # the file has neither rotations nor a skeleton
        assert seq.rotations is None and seq.edges is None
        return
    R = seq.rotations
    assert R.shape == (F, 3, 3)
    np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape), atol=1e-8)
    # W = blockdiag(Rs) S after centring (shared/data/README.md)
    proj = np.einsum("fab,fbp->fap", R[:, :2], seq.shapes)
    proj -= proj.mean(axis=2, keepdims=True)
    W = nr.to_frames(seq.W)
    np.testing.assert_allclose(proj, W - W.mean(axis=2, keepdims=True), atol=1e-9)
    # edges: 0-based point indices
    assert seq.edges.ndim == 2 and seq.edges.shape[1] == 2
    assert seq.edges.min() == 0 and seq.edges.max() < P


@needs_data
def test_nonrigid_dinosaur():
    seq = datasets.load_nonrigid_dinosaur()
    X = scipy.io.loadmat(DATA / "nonrigid" / "dinosaur_real.mat")["X"]
    assert seq.W.shape == (462, 49) and seq.visible.all()
    np.testing.assert_array_equal(seq.W[0::2], X[0].T)  # row 2f = x of frame f
    np.testing.assert_array_equal(seq.W[1::2], X[1].T)
    assert seq.shapes is None and seq.rotations is None


@needs_data
def test_lrmf_dino():
    seq = datasets.load_lrmf_dino()
    assert seq.W.shape == (72, 319) and seq.visible.shape == (36, 319)
    assert 2 * int(seq.visible.sum()) == 5302  # observed coordinates (shared/data/README.md)
    observed = np.repeat(seq.visible, 2, axis=0)
    assert np.isfinite(seq.W[observed]).all() and np.isnan(seq.W[~observed]).all()
    W0, vis = nr.prepare_tracks(seq.W, seq.visible, rank=4)
    assert W0.shape == (72, 319) and bool((vis == seq.visible).all())


@needs_data
def test_sequence_as_path():
    seq = datasets.load_akhter(DATA / "akhter" / "yoga.mat")
    assert seq.name == "yoga" and seq.W.shape == (614, 41)


def test_data_dir_argument_and_environment(tmp_path, monkeypatch):
    assert datasets.data_dir(tmp_path) == tmp_path
    with pytest.raises(FileNotFoundError, match="does not exist"):
        datasets.data_dir(tmp_path / "nowhere")
    monkeypatch.setenv("JAXNRSFM_DATA", str(tmp_path))
    assert datasets.data_dir() == tmp_path
    monkeypatch.setenv("JAXNRSFM_DATA", str(tmp_path / "nowhere"))
    with pytest.raises(FileNotFoundError, match=r"\$JAXNRSFM_DATA=.*nowhere is not a directory"):
        datasets.data_dir()


def test_data_dir_default_missing(tmp_path, monkeypatch):
    monkeypatch.delenv("JAXNRSFM_DATA", raising=False)
    monkeypatch.setattr(datasets, "__file__", str(tmp_path / "repo" / "jaxnrsfm" / "datasets.py"))
    monkeypatch.chdir(tmp_path)
    with pytest.raises(FileNotFoundError, match=r"JAXNRSFM_DATA is not set and neither .*shared.data"):
        datasets.data_dir()
    # from the working directory: a clone beside shared/, with the package installed elsewhere
    (tmp_path / "shared" / "data").mkdir(parents=True)
    (tmp_path / "clone").mkdir()
    monkeypatch.chdir(tmp_path / "clone")
    assert datasets.data_dir() == tmp_path / "shared" / "data"


def test_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="data file not found"):
        datasets.load_akhter("drink", root=tmp_path)


def test_mat_lacking_variable(tmp_path):
    (tmp_path / "akhter").mkdir()
    scipy.io.savemat(tmp_path / "akhter" / "fake.mat", {"W": np.zeros((4, 3))})
    with pytest.raises(ValueError, match="lacks the variable 'S' \\(it has: W\\)"):
        datasets.load_akhter("fake", root=tmp_path)
    scipy.io.savemat(tmp_path / "dino.mat", {"M": np.zeros((4, 3))})
    with pytest.raises(ValueError, match="lacks the variable 'W'"):
        datasets.load_lrmf_dino(tmp_path / "dino.mat")
    with pytest.raises(ValueError, match="lacks the variable 'X'"):
        datasets.load_nonrigid_dinosaur(tmp_path / "dino.mat")


def test_lrmf_mask_rows_disagree(tmp_path):
    mask = np.ones((4, 3), np.uint8)
    mask[1, 2] = 0  # only the v coordinate of frame 0, point 2 hidden
    scipy.io.savemat(tmp_path / "bad.mat", {"M": np.ones((4, 3)), "W": mask})
    with pytest.raises(ValueError, match="only one coordinate of frame 0, point 2"):
        datasets.load_lrmf_dino(tmp_path / "bad.mat")


def test_npz(tmp_path):
    W = np.arange(24.0).reshape(4, 6)
    W[2:4, 1] = np.nan  # frame 1, point 1 missing
    visible = np.ones((2, 6), bool)
    visible[0, 5] = False
    np.savez(tmp_path / "t.npz", W=W, visible=visible)
    t = datasets.load_tracks(tmp_path / "t.npz")
    expected = np.ones((2, 6), bool)
    expected[1, 1] = expected[0, 5] = False
    np.testing.assert_array_equal(t.visible, expected)
    assert t.name == "t" and np.isnan(t.W[0:2, 5]).all() and t.W[0, 0] == 0.0
    np.savez(tmp_path / "plain.npz", W=np.ones((4, 3)))
    assert datasets.load_npz(tmp_path / "plain.npz").visible.all()


def test_npz_errors(tmp_path):
    np.savez(tmp_path / "a.npz", tracks=np.ones((4, 3)))
    with pytest.raises(ValueError, match="lacks the array 'W' \\(it has: tracks\\)"):
        datasets.load_npz(tmp_path / "a.npz")
    np.savez(tmp_path / "b.npz", W=np.ones((5, 3)))
    with pytest.raises(ValueError, match="even number of rows"):
        datasets.load_npz(tmp_path / "b.npz")
    np.savez(tmp_path / "c.npz", W=np.ones((4, 3)), visible=np.ones((2, 4), bool))
    with pytest.raises(ValueError, match=r"visible has shape \(2, 4\); expected \(m, n\) = \(2, 3\)"):
        datasets.load_npz(tmp_path / "c.npz")
    W = np.ones((4, 3))
    W[0, 1] = np.nan
    np.savez(tmp_path / "d.npz", W=W)
    with pytest.raises(ValueError, match="frame 0, point 1.* one coordinate missing"):
        datasets.load_npz(tmp_path / "d.npz")
    W[0, 1] = np.inf
    W[1, 1] = 0.0
    np.savez(tmp_path / "e.npz", W=W)
    with pytest.raises(ValueError, match="infinite values"):
        datasets.load_npz(tmp_path / "e.npz")


def test_csv(tmp_path):
    (tmp_path / "t.csv").write_text("1,2,3\n4,5,6\n7,,nan\n8, ,NaN\n")
    t = datasets.load_tracks(tmp_path / "t.csv")
    assert t.W.shape == (4, 3) and t.name == "t"
    np.testing.assert_array_equal(t.visible, [[True, True, True], [True, False, False]])
    np.testing.assert_array_equal(t.W[:2], [[1, 2, 3], [4, 5, 6]])


@pytest.mark.parametrize(
    "text, message",
    [
        ("1,2\n3\n", "different numbers of columns"),
        ("1,2\n3,x\n", "line 2: not a number"),
        ("u,v\n1,2\n", "line 1: not a number"),
        ("1,2\n3,4\n5,6\n", "even number of rows"),
        ("", "no data"),
    ],
)
def test_csv_errors(tmp_path, text, message):
    (tmp_path / "bad.csv").write_text(text)
    with pytest.raises(ValueError, match=message):
        datasets.load_csv(tmp_path / "bad.csv")


def test_unknown_suffix(tmp_path):
    with pytest.raises(ValueError, match="unknown track file type '.txt'"):
        datasets.load_tracks(tmp_path / "t.txt")
