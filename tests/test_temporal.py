"""The temporal witness for rejected entries (jaxnrsfm.temporal): clean entries of smooth
tracks come back, displaced ones do not, and tracks that are not smooth in time are left
alone."""

import jax.numpy as jnp
import numpy as np

from jaxnrsfm.temporal import interpolate, prediction_errors, reject_jumps, smooth, stencil_errors, take_back
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


def test_cubic_tracks_are_interpolated_exactly():
    # Each track a cubic in time: the cubic through two trusted neighbours on each side
    # reproduces it, over gaps of one to three frames; an entry with no trusted neighbour
    # on one side (the sequence's ends) is not interpolated.
    rng = np.random.default_rng(0)
    m, n = 40, 6
    t = np.arange(m)[:, None, None] / m
    X = sum(rng.normal(size=(1, 2, n)) * 50 * t**p for p in range(4))
    trusted = np.ones((m, n), bool)
    trusted[[5, 12, 13, 30, 31, 32], [0, 1, 1, 2, 2, 2]] = False
    trusted[0, 3] = trusted[m - 1, 4] = False
    trusted[1:3, 5] = False  # a single trusted neighbour before: a quadratic, not exact
    W = from_frames(jnp.asarray(X))
    wrong = jnp.where(jnp.repeat(jnp.asarray(trusted), 2, axis=0), W, 0.0)
    filled, interpolated = interpolate(wrong, jnp.asarray(trusted), jnp.asarray(1e3))
    expected = ~trusted
    expected[0, 3] = expected[m - 1, 4] = False
    np.testing.assert_array_equal(np.asarray(interpolated), expected)
    exact = np.repeat(expected & (np.arange(n) < 5), 2, axis=0)
    np.testing.assert_allclose(np.asarray(filled)[exact], np.asarray(W)[exact], rtol=1e-10)
    kept = ~np.repeat(expected, 2, axis=0)
    np.testing.assert_array_equal(np.asarray(filled)[kept], np.asarray(wrong)[kept])


def test_interpolation_spans_follow_the_tracks_smoothness():
    # The ellipses' cubic stencils miss by 0.001, 0.025 and 0.55 units (medians) at spacings
    # 1, 2 and 4: a scale of 0.1 units admits gaps of one and three frames (spans 2 and 4),
    # not of seven (span 8); frames out of temporal order admit none.
    X = _smooth_tracks()
    m, _, n = X.shape
    trusted = np.ones((m, n), bool)
    trusted[10, 0] = False
    trusted[20:23, 1] = False
    trusted[30:37, 2] = False
    W = from_frames(jnp.asarray(X))
    errors = [np.asarray(stencil_errors(W, jnp.asarray(trusted), h)) for h in (2, 4)]
    assert np.median(errors[0][np.isfinite(errors[0])]) < 0.1 < np.median(errors[1][np.isfinite(errors[1])])
    _, interpolated = interpolate(W, jnp.asarray(trusted), jnp.asarray(0.1))
    expected = ~trusted
    expected[30:37, 2] = False
    np.testing.assert_array_equal(np.asarray(interpolated), expected)
    shuffled = from_frames(jnp.asarray(X[np.random.default_rng(1).permutation(m)]))
    assert not bool(interpolate(shuffled, jnp.asarray(trusted), jnp.asarray(0.1))[1].any())


def test_jumps_off_the_track_are_rejected():
    # Displacements of 10 units that a low-rank model kept as inliers: each is the largest
    # prediction error of its track nearby, beyond 10 median scales of those errors; their
    # neighbours, whose predictions pass through them, stay. Clean tracks lose nothing, nor
    # do tracks out of temporal order.
    X = _smooth_tracks()
    m, _, n = X.shape
    jumps = np.zeros((m, n), bool)
    jumps[[5, 17, 30, 31, 44], [0, 3, 7, 8, 11]] = True
    X_out = X.copy()
    X_out[:, 1][jumps] -= 10.0
    everything = jnp.ones((m, n), bool)
    floor = jnp.asarray(1e-6)
    kept = reject_jumps(from_frames(jnp.asarray(X_out)), everything, jnp.asarray(5.0), jnp.asarray(10.0), floor)
    np.testing.assert_array_equal(~np.asarray(kept), jumps)
    assert bool(reject_jumps(from_frames(jnp.asarray(X)), everything, jnp.asarray(5.0), jnp.asarray(10.0), floor).all())
    shuffled = from_frames(jnp.asarray(X_out[np.random.default_rng(1).permutation(m)]))
    assert bool(reject_jumps(shuffled, everything, jnp.asarray(5.0), jnp.asarray(10.0), floor).all())
