"""The shape step's helpers on synthetic tracks: which directions are signal, and the
nuclear-norm shapes of noisy tracks."""

import jax
import jax.numpy as jnp
import numpy as np

import jaxnrsfm as nr
from jaxnrsfm.refine import GAP, above_noise, above_noise_part, nuclear_shapes


def test_above_noise_keeps_the_signal():
    # Motion capture's exact projections: a smooth decay (at most 4.3 between neighbours on
    # the Akhter sequences and their halves), kept down to the Marchenko-Pastur edge of
    # the smallest.
    smooth = 100.0 * 1.3 ** -np.arange(40.0)
    kept = np.asarray(above_noise(jnp.asarray(smooth), (300, 40)))
    assert kept[:30].all() and not kept[-1]
    # Exact rank-12 tracks with a filled-in tail: the fit's error (1e-8 of the tracks),
    # spread over decades, is cut at the gap however it is spread; so is round-off.
    for tail in (np.geomspace(2e-6, 3e-7, 28), np.geomspace(1e-13, 1e-16, 28)):
        s = jnp.asarray(np.concatenate([np.linspace(160.0, 150.0, 12), tail]))
        assert np.asarray(above_noise(s, (80, 40))).sum() == 12
    # Neighbours more than GAP apart end the signal; a little less do not.
    for factor, signal in ((0.9, 4), (1.1, 2)):
        s = jnp.asarray([10.0, 9.0, 9.0 / (factor * GAP), 4.5 / (factor * GAP), 1e-12])
        assert np.asarray(above_noise(s, (1000, 5))).tolist() == [True] * signal + [False] * (5 - signal)


def test_nuclear_shapes_of_noisy_tracks_fit_their_signal():
    # Given the true rotations, the shapes that reproject onto the noise are half as
    # accurate again as those of the tracks' part above the noise (0.027 against 0.015).
    seq = nr.bregler_sequence(jax.random.key(0), k=2, n_frames=40, n_points=30, noise=1.0)
    frames = nr.to_frames(seq.W)
    frames = frames - frames.mean(axis=2, keepdims=True)
    signal = above_noise_part(frames, 6)
    raw = float(nr.e3d(nuclear_shapes(frames, seq.rotations), seq.shapes))
    denoised = float(nr.e3d(nuclear_shapes(signal, seq.rotations), seq.shapes))
    assert denoised < 0.7 * raw
    # The signal's part is the projection onto the 3k directions of the shapes.
    assert np.linalg.matrix_rank(np.asarray(nr.from_frames(signal)), tol=1e-6 * float(jnp.abs(signal).max())) == 6
