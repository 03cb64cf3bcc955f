import jax
import lineax as lx
import numpy as np

from jaxnrsfm.linalg import RidgeCholesky


def test_ridge_cholesky_fits_a_rank_deficient_system_like_the_pseudo_inverse():
    # More residuals than unknowns and rank-deficient (the rotation constraints' Jacobian
    # in jaxnrsfm.upgrade.rotation_triple), a right-hand side outside the range: the fit
    # J x is the pseudo-inverse's to round-off; x differs only in the null space of J.
    A = jax.random.normal(jax.random.key(0), (30, 9)) @ jax.random.normal(jax.random.key(1), (9, 12))
    b = jax.random.normal(jax.random.key(2), (30,))
    x = np.asarray(lx.linear_solve(lx.MatrixLinearOperator(A), b, lx.Normal(RidgeCholesky())).value)
    A, expected = np.asarray(A), np.linalg.pinv(np.asarray(A)) @ np.asarray(b)
    np.testing.assert_allclose(A @ x, A @ expected, rtol=1e-9, atol=1e-9 * np.abs(A @ expected).max())
    row_space = np.linalg.pinv(A) @ A
    np.testing.assert_allclose(row_space @ x, expected, rtol=1e-8, atol=1e-8 * np.abs(expected).max())
