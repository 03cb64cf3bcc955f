import jax
import jax.numpy as jnp
import numpy as np

import jaxnrsfm as nr


def e3d_numpy(S_hat, S):
    """A direct NumPy transcription of shared/data/README.md's e3D, on 3F x P arrays."""
    scale = np.mean(np.std(S, axis=1))
    S_hat, S = S_hat / scale, S / scale
    F = S.shape[0] // 3
    X = np.concatenate([f - f.mean(axis=1, keepdims=True) for f in np.split(S_hat, F)], axis=1)
    Y = np.concatenate([f - f.mean(axis=1, keepdims=True) for f in np.split(S, F)], axis=1)
    U, _, Vt = np.linalg.svd(Y @ X.T)
    Q = U @ Vt
    return np.mean(np.linalg.norm(Q @ X - Y, axis=0))


def test_e3d_matches_numpy_transcription():
    rng = np.random.default_rng(0)
    truth = rng.normal(size=(30, 3, 17)) * 5 + 2
    Q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    estimate = np.einsum("ab,ibn->ian", Q, truth) + rng.normal(size=truth.shape) + rng.normal(size=(30, 3, 1))
    expected = e3d_numpy(estimate.reshape(-1, 17), truth.reshape(-1, 17))
    np.testing.assert_allclose(nr.e3d(jnp.asarray(estimate), jnp.asarray(truth)), expected, rtol=1e-12)
    # invariant to one rotation or reflection and to per-frame translation, not to scale
    mirrored = estimate * np.array([1, 1, -1])[:, None]
    np.testing.assert_allclose(nr.e3d(mirrored, truth), expected, rtol=1e-12)
    assert float(nr.e3d(truth, truth)) < 1e-12
    assert float(nr.e3d(2 * truth, truth)) > 0.5


def test_reprojection_errors():
    W = jnp.zeros((4, 3))
    W_hat = W.at[0, 0].set(3.0).at[1, 0].set(4.0).at[2, 1].set(1.0)
    mask = jnp.ones((2, 3), bool)
    np.testing.assert_allclose(nr.entry_errors(W, W_hat), [[5, 0, 0], [0, 1, 0]])
    np.testing.assert_allclose(nr.mean_reprojection_error(W, W_hat, mask), 1.0)
    np.testing.assert_allclose(nr.rms_error(W, W_hat, mask), np.sqrt(26 / 12))
    only_first = mask.at[1].set(False)
    np.testing.assert_allclose(nr.mean_reprojection_error(W, W_hat, only_first), 5 / 3)


def test_statistical_floor_is_what_a_truncated_svd_achieves():
    key_a, key_b, key_n = jax.random.split(jax.random.key(0), 3)
    m, n, r, sigma = 60, 80, 5, 1.5
    clean = jax.random.normal(key_a, (2 * m, r)) @ jax.random.normal(key_b, (r, n)) * 10
    noisy = clean + sigma * jax.random.normal(key_n, clean.shape)
    fit = nr.factorize(noisy, rank=r).W_hat
    err = nr.rms_error(clean, fit, jnp.ones((m, n), bool))
    np.testing.assert_allclose(err, nr.statistical_floor(sigma, m, n, r), rtol=0.05)


def test_outlier_precision_recall():
    true = jnp.array([[True, True, False, False]])
    found = jnp.array([[True, False, True, False]])
    p, r = nr.outlier_precision_recall(found, true)
    assert float(p) == 0.5 and float(r) == 0.5
    p, r = nr.outlier_precision_recall(jnp.zeros_like(true), true)
    assert float(p) == 1.0 and float(r) == 0.0
    mask = jnp.array([[True, False, True, True]])
    p, r = nr.outlier_precision_recall(found, true, mask)
    assert float(p) == 0.5 and float(r) == 1.0
