"""The temporal witness for rejected entries (jaxnrsfm.temporal): clean entries of smooth
tracks come back, displaced ones do not, and tracks that are not smooth in time are left
alone."""

import jax.numpy as jnp
import numpy as np

from jaxnrsfm.temporal import prediction_errors, smooth, take_back
from jaxnrsfm.tracks import from_frames


def _smooth_tracks(m=60, n=12, seed=0):
    # Points on ellipses traversed at their own speeds: smooth in time, far from low rank
    # in no particular way, 100 units across.
    rng = np.random.default_rng(seed)
    t = np.arange(m)[:, None] / m
    radius, speed, phase = rng.uniform(20, 50, n), rng.uniform(0.5, 2.0, n), rng.uniform(0, 2 * np.pi, n)
    angle = 2 * np.pi * speed * t + phase
    return np.stack([radius * np.cos(angle), 0.5 * radius * np.sin(angle)], axis=1)  # (m, 2, n)


def test_clean_entries_come_back_and_displaced_ones_do_not():
    X = _smooth_tracks()
    m, _, n = X.shape
    visible = jnp.ones((m, n), bool)
    outlier = np.zeros((m, n), bool)
    outlier[[5, 17, 30], [0, 3, 7]] = True  # single jumps off the track
    outlier[40:46, 9] = True  # a run displaced by one jump, then following the track
    X_out = X.copy()
    X_out[:, 0][outlier] += 30.0
    rejected = outlier.copy()
    rejected[10, 2] = rejected[50, 5] = True  # clean entries the model rejected
    rejected[20:26, 4] = True  # a clean run
    rejected[0, 1] = rejected[m - 1, 6] = True  # clean entries at the sequence's ends
    # Bound and scale 5 units: the tracks move up to ~2.2 units from the linear predictions.
    inliers = take_back(from_frames(jnp.asarray(X_out)), visible, jnp.asarray(~rejected), 5.0, 5.0)
    np.testing.assert_array_equal(~np.asarray(inliers), outlier)


def test_frames_out_of_temporal_order_take_nothing_back():
    # The same tracks with their frames shuffled: the tracks predict nothing, so the gate
    # (smooth) is off, and the clean rejected entries stay rejected.
    X = _smooth_tracks()[np.random.default_rng(1).permutation(60)]
    W = from_frames(jnp.asarray(X))
    rejected = np.zeros(X[:, 0].shape, bool)
    rejected[10, 2] = rejected[33, 5] = True
    inliers = jnp.asarray(~rejected)
    assert not bool(smooth(W, inliers, 5.0))
    np.testing.assert_array_equal(np.asarray(take_back(W, jnp.ones_like(inliers), inliers, 5.0, 5.0)), ~rejected)


def test_prediction_errors_use_trusted_neighbours_only():
    X = _smooth_tracks(m=8, n=2)
    trusted = np.ones((8, 2), bool)
    trusted[3, 0] = False
    errors = np.asarray(prediction_errors(from_frames(jnp.asarray(X)), jnp.asarray(trusted)))
    assert np.all(np.isfinite(errors))  # every entry has a prediction with both frames trusted
    trusted[:, 1] = False
    errors = np.asarray(prediction_errors(from_frames(jnp.asarray(X)), jnp.asarray(trusted)))
    assert np.all(np.isinf(errors[:, 1]))
