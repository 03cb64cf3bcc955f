import jax
import lineax as lx
import numpy as np

from jaxnrsfm.linalg import RidgeCholesky, product_factors, svd_factors


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


def test_product_factors_are_the_svd_factors_of_the_product():
    # The balanced factors of M S from M and S alone (what an undifferentiated
    # implicit.attach returns): the same product, and the SVD's factors up to each
    # column's sign, against NumPy's SVD of the 2m x n product.
    M = jax.random.normal(jax.random.key(0), (40, 7))
    S = jax.random.normal(jax.random.key(1), (7, 30)) * np.geomspace(1.0, 1e-3, 7)[:, None]
    Mb, Sb = map(np.asarray, product_factors(M, S))
    L = np.asarray(M @ S)
    np.testing.assert_allclose(Mb @ Sb, L, rtol=0, atol=1e-12 * np.abs(L).max())
    U, s, Vt = np.linalg.svd(L, full_matrices=False)
    sign = np.sign(np.sum(Mb * U[:, :7], axis=0))
    np.testing.assert_allclose(Mb, sign * U[:, :7] * np.sqrt(s[:7]), rtol=0, atol=1e-10)
    np.testing.assert_allclose(Sb, (sign * np.sqrt(s[:7]))[:, None] * Vt[:7], rtol=0, atol=1e-10)
    # and svd_factors of the product (the SVD the forward pass no longer takes) agrees too
    Ms, Ss = map(np.asarray, svd_factors(M @ S, 7))
    np.testing.assert_allclose(np.abs(Mb), np.abs(Ms), rtol=0, atol=1e-10)
    np.testing.assert_allclose(np.abs(Sb), np.abs(Ss), rtol=0, atol=1e-10)
