import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxnrsfm as nr
from jaxnrsfm import datasets
from jaxnrsfm.factorize import masked_als, mean_fill, svd_factors
from jaxnrsfm.tracks import prepare_tracks, row_mask
from jaxnrsfm.varpro import _upper_inverse, varpro

DINO_OPTIMUM = 1.084673  # best known RMS, Hong & Fitzgibbon (ICCV 2015)


def low_rank(key, m=20, n=50, r=4, missing=0.3, noise=0.0, dtype=jnp.float64):
    """A rank-r 2m x n matrix, its visibility mask and the zero-filled observed tracks."""
    k1, k2, k3, k4 = jax.random.split(key, 4)
    clean = (jax.random.normal(k1, (2 * m, r)) @ jax.random.normal(k2, (r, n))).astype(dtype)
    visible = jax.random.uniform(k3, (m, n)) >= missing
    W = clean + noise * jax.random.normal(k4, clean.shape, dtype)
    W0, visible = prepare_tracks(np.asarray(W), np.asarray(visible), rank=r)  # checks every factor is determined
    return clean, W0.astype(dtype), visible


def relative_error(M, S, clean):
    return float(jnp.linalg.norm(M @ S - clean) / jnp.linalg.norm(clean))


@pytest.mark.parametrize("jacobian, ridge", [("approximate", 0.04), ("full", 0.04), ("approximate", 0.0)])
def test_noise_free_recovery(key, jacobian, ridge):
    clean, W, visible = low_rank(key)
    M0 = jax.random.normal(jax.random.key(1), (40, 4))
    M, S, steps, converged = varpro(W, visible, M0, jacobian=jacobian, ridge=ridge)
    assert bool(converged) and int(steps) < 1000
    # every entry, the missing 30% included
    assert relative_error(M, S, clean) < 1e-9
    np.testing.assert_allclose(M.T @ M, np.eye(4), atol=1e-12)  # the retraction keeps M orthonormal


def test_float32(key):
    clean, W, visible = low_rank(key, dtype=jnp.float32)
    M0 = jax.random.normal(jax.random.key(1), (40, 4), jnp.float32)
    M, S, steps, converged = varpro(W, visible, M0)
    assert M.dtype == S.dtype == jnp.float32
    assert bool(converged)
    assert relative_error(M, S, clean) < 1e-4


def test_agrees_with_masked_als(key):
    # An easy case (10% missing, mild noise, SVD start): both methods find the same optimum.
    clean, W, visible = low_rank(key, missing=0.1, noise=0.05)
    M0, _ = svd_factors(mean_fill(W, visible), 4)
    mask = row_mask(visible)
    M, S, _, converged = varpro(W, visible, M0)
    Ma, Sa, _, converged_als = masked_als(W, visible, M0, max_steps=2000, rtol=1e-13)
    assert bool(converged) and bool(converged_als)

    def cost(M, S):
        return float(jnp.sum(jnp.where(mask, W - M @ S, 0.0) ** 2))

    assert cost(M, S) <= cost(Ma, Sa) * (1 + 1e-8)
    np.testing.assert_allclose(M @ S, Ma @ Sa, atol=1e-5 * float(jnp.abs(clean).max()))


def test_vmap_over_starts(key):
    clean, W, visible = low_rank(key, m=10, n=30, r=3)
    M0 = jax.random.normal(jax.random.key(2), (3, 20, 3))
    Ms, Ss, _, converged = jax.vmap(lambda m0: varpro(W, visible, m0))(M0)
    assert bool(converged.all())
    M, S, _, _ = varpro(W, visible, M0[1])
    np.testing.assert_allclose(Ms[1] @ Ss[1], M @ S, atol=1e-10)
    assert max(relative_error(m, s, clean) for m, s in zip(Ms, Ss, strict=True)) < 1e-9


def test_upper_inverse():
    R = jnp.triu(jax.random.normal(jax.random.key(3), (5, 6, 6))) + 3 * jnp.eye(6)
    np.testing.assert_allclose(_upper_inverse(R), np.linalg.inv(np.asarray(R)), rtol=1e-12, atol=1e-12)


def test_bad_jacobian(key):
    _, W, visible = low_rank(key, m=5, n=10)
    with pytest.raises(ValueError, match="jacobian must be"):
        varpro(W, visible, jnp.ones((10, 4)), jacobian="exact")


def _dino():
    try:
        return datasets.load_lrmf_dino()
    except FileNotFoundError:
        return None


@pytest.mark.skipif(
    _dino() is None, reason="lrmf/dino_trimmed.mat absent: set $JAXNRSFM_DATA or provide ../shared/data"
)
def test_dino_reaches_best_known_optimum():
    # The benchmark (benchmarks/lrmf_dino.py) runs 20 starts; three keep this test short.
    dino = _dino()
    W, visible = prepare_tracks(dino.W, dino.visible, rank=4)
    mask = row_mask(visible)
    M0 = jax.random.normal(jax.random.key(0), (3, 72, 4))

    def rms(m0):
        M, S, _, converged = varpro(W, visible, m0)
        return jnp.sqrt(jnp.sum(jnp.where(mask, W - M @ S, 0.0) ** 2) / mask.sum()), converged

    errors, converged = jax.lax.map(rms, M0)
    assert bool(converged.all())
    assert int(mask.sum()) == 5302
    hits = np.abs(np.asarray(errors) - DINO_OPTIMUM) < 1e-5
    assert hits.sum() >= 2, f"RMS of the starts: {np.asarray(errors)}"
    assert float(errors.min()) > DINO_OPTIMUM - 1e-5  # nothing below the best known optimum


@pytest.mark.skipif(
    _dino() is None, reason="lrmf/dino_trimmed.mat absent: set $JAXNRSFM_DATA or provide ../shared/data"
)
def test_factorize_default_reaches_dino_optimum():
    # The default missing-data solver: masked ALS stalls on the dinosaur (its step limit),
    # and "auto" finishes by variable projection from there.
    dino = _dino()
    mask = row_mask(jnp.asarray(dino.visible))

    def rms(fac):
        W = jnp.where(mask, jnp.nan_to_num(jnp.asarray(dino.W)), 0.0)
        return float(jnp.sqrt(jnp.sum(jnp.where(mask, W - fac.W_hat, 0.0) ** 2) / mask.sum()))

    default = nr.factorize(dino.W, dino.visible, rank=4)
    assert abs(rms(default) - DINO_OPTIMUM) < 1e-5 and bool(default.converged)
    als = nr.factorize(dino.W, dino.visible, rank=4, solver="als")
    assert not bool(als.converged) and rms(als) > DINO_OPTIMUM + 0.1


def test_factorize_solver_errors():
    W = np.random.default_rng(0).normal(size=(12, 20))
    with pytest.raises(ValueError, match="solver must be one of"):
        nr.factorize(W, rank=4, solver="lm")
