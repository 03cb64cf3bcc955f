import importlib

import jax.numpy as jnp
import numpy as np
import pytest

import jaxnrsfm as nr

pipeline = importlib.import_module("jaxnrsfm.pipeline")


@pytest.fixture
def W():
    return np.random.default_rng(0).normal(size=(20, 15))


@pytest.fixture(autouse=True)
def no_compilation(monkeypatch):
    """Every error in this file must be raised before the pipeline is traced."""

    def fail(*args, **kwargs):
        raise AssertionError("the pipeline was reached before validation failed")

    monkeypatch.setattr(pipeline, "reconstruct_prepared", fail)


@pytest.mark.parametrize(
    "bad, message",
    [
        (np.zeros(10), "2-D array"),
        (np.zeros((4, 5, 6)), "2-D array"),
        (np.zeros((9, 15)), "even number of rows"),
        (np.zeros((0, 15)), "empty"),
    ],
)
def test_bad_shapes(bad, message):
    with pytest.raises(ValueError, match=message):
        nr.reconstruct(bad, k=1)


def test_visible_shape(W):
    with pytest.raises(ValueError, match=r"visible must have shape \(m, n\) = \(10, 15\)"):
        nr.reconstruct(W, np.ones((10, 14), bool), k=1)


def test_rank_too_large(W):
    # 20 x 15 carries rank 15 at most: k = 5 needs 16 in the augmented form.
    with pytest.raises(ValueError, match=r"k=5 \(augmented rank 16\) is larger than the data allows"):
        nr.reconstruct(W, k=5)
    with pytest.raises(ValueError, match="rank 16 is larger than the data allows"):
        nr.factorize(W, rank=16)


@pytest.mark.parametrize("value", [np.inf, -np.inf])
def test_infinite_observed_value(W, value):
    W[3, 4] = value
    with pytest.raises(ValueError, match="non-finite value.*frame 1, point 4"):
        nr.reconstruct(W, k=1)


def test_nan_marked_visible(W):
    W[[6, 7], 2] = np.nan
    visible = np.ones((10, 15), bool)
    with pytest.raises(ValueError, match="non-finite value.*frame 3, point 2"):
        nr.reconstruct(W, visible, k=1)
    visible[3, 2] = False  # the same NaN, now declared missing, is fine for validation
    nr.prepare_tracks(W, visible, rank=4)


def test_half_missing_entry(W):
    W[6, 2] = np.nan
    with pytest.raises(ValueError, match="one coordinate NaN"):
        nr.reconstruct(W, k=1)


def test_empty_frame_and_point(W):
    visible = np.ones((10, 15), bool)
    visible[4] = False
    with pytest.raises(ValueError, match=r"frame\(s\) \[4\] have no visible points"):
        nr.reconstruct(W, visible, k=1)
    W2 = W.copy()
    W2[:, 7] = np.nan
    with pytest.raises(ValueError, match=r"point\(s\) \[7\] are never visible"):
        nr.reconstruct(W2, k=1)


def test_too_few_visible_for_rank(W):
    visible = np.ones((10, 15), bool)
    visible[2, 3:] = False  # 3 visible points, the rank-4 motion needs 4
    with pytest.raises(ValueError, match="frame 2 has 3 visible points, fewer than the 4"):
        nr.reconstruct(W, visible, k=1)
    visible = np.ones((10, 15), bool)
    visible[1:, 5] = False  # seen in one frame: 2 equations for a rank-4 column
    with pytest.raises(ValueError, match="point 5 is visible in 1 frame"):
        nr.reconstruct(W, visible, k=1)


def test_unknown_method_form_k(W):
    with pytest.raises(ValueError, match="unknown method 'wang2'"):
        nr.reconstruct(W, k=1, method="wang2")
    with pytest.raises(ValueError, match="unknown form"):
        nr.reconstruct(W, k=1, form="projective")
    with pytest.raises(ValueError, match="positive integer"):
        nr.reconstruct(W, k=0)
    with pytest.raises(ValueError, match="form must be"):
        nr.factorize(W, rank=3, form="projective")


def test_prepare_zero_fills_and_masks(W):
    W[[4, 5], 3] = np.nan
    W0, visible = nr.prepare_tracks(W)
    assert not bool(visible[2, 3]) and int(visible.sum()) == 149
    assert bool(jnp.all(jnp.isfinite(W0))) and float(W0[4, 3]) == 0.0


def test_layouts(W):
    X = nr.to_frames(jnp.asarray(W))
    assert X.shape == (10, 2, 15)
    np.testing.assert_array_equal(X[3, 1], W[7])
    np.testing.assert_array_equal(nr.from_frames(X), W)
