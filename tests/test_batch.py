"""reconstruct_batch: its three strategies map the same single-sequence pipeline."""

import jax
import numpy as np
import pytest

import jaxnrsfm as nr


def test_strategies_agree():
    seqs = jax.vmap(lambda key: nr.bregler_sequence(key, k=1, n_frames=12, n_points=20, noise=0.5, outlier_ratio=0.1))(
        jax.random.split(jax.random.key(7), 3)
    )
    recs = {s: nr.reconstruct_batch(seqs.W, k=1, method="wang", strategy=s) for s in nr.batch.STRATEGIES}
    # Two at a time: a whole batch and one padded with a copy of the last trial.
    recs["vmap2"] = nr.reconstruct_batch(seqs.W, k=1, method="wang", strategy="vmap", batch_size=2)
    assert recs["vmap2"].W_hat.shape == seqs.W.shape and (recs["vmap2"].status == nr.Status.success).shape == (3,)
    for strategy in ("map", "vmap", "vmap2"):
        np.testing.assert_array_equal(recs[strategy].inliers, recs["loop"].inliers)
        np.testing.assert_allclose(recs[strategy].W_hat, recs["loop"].W_hat, rtol=1e-7, atol=1e-7)
    one = nr.reconstruct(seqs.W[1], k=1, method="wang")
    np.testing.assert_allclose(recs["loop"].W_hat[1], one.W_hat, rtol=1e-9, atol=1e-9)


def test_per_trial_stage_arrays():
    # The oracle's mask is an array field: one per trial, mapped with the tracks.
    seqs = jax.vmap(lambda key: nr.bregler_sequence(key, k=1, n_frames=10, n_points=15, noise=0.5, outlier_ratio=0.1))(
        jax.random.split(jax.random.key(8), 2)
    )
    oracle = nr.Oracle(seqs.outliers)
    recs = {s: nr.reconstruct_batch(seqs.W, k=1, method=oracle, shapes="upgrade", strategy=s) for s in ("loop", "map")}
    for t in range(2):
        np.testing.assert_array_equal(recs["loop"].inliers[t], seqs.visible[t] & ~seqs.outliers[t])
        np.testing.assert_allclose(recs["map"].W_hat[t], recs["loop"].W_hat[t], rtol=1e-8, atol=1e-8)
    with pytest.raises(ValueError, match="leading axis of 2 trials"):
        nr.reconstruct_batch(seqs.W, k=1, method=nr.Oracle(seqs.outliers[0]))


def test_bad_batches():
    with pytest.raises(ValueError, match="shape \\(T, 2m, n\\)"):
        nr.reconstruct_batch(np.zeros((12, 20)), k=1)
    with pytest.raises(ValueError, match="unknown strategy"):
        nr.reconstruct_batch(np.zeros((2, 12, 20)), k=1, strategy="pmap")
    for strategy, size in (("map", 2), ("vmap", 0)):
        with pytest.raises(ValueError, match="batch_size must be a positive integer"):
            nr.reconstruct_batch(np.zeros((2, 12, 20)), k=1, strategy=strategy, batch_size=size)
