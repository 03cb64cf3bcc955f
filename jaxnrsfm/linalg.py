"""Decompositions whose derivatives need only a spectral gap.

JAX differentiates ``svd`` and ``eigh`` through every pair of singular values or
eigenvalues: ``1 / (s_i^2 - s_j^2)``. A noise-free tracking matrix has ``min(2m, n) - r``
(numerically) zero singular values, so those pairs are ``inf`` or huge and the gradient
turns NaN, although no output that the pipeline uses depends on how the null space is
spanned. The versions here return only the leading (or trailing) part and differentiate
it through the pairs that cross the gap between the kept and the discarded part: the
derivative is finite whenever the kept part is separated from the rest.

Beside them, the small dense pieces the solvers share: ridged normal matrices and their
Cholesky solve, the normal matrices of many weighted problems with one design (`grams`),
and the nearest orthonormal rows.
"""

import math
from functools import partial

import jax
import jax.flatten_util
import jax.numpy as jnp
import lineax as lx
import numpy as np
from jaxtyping import Array, Float


@partial(jax.custom_jvp, nondiff_argnums=(1,))
def truncated_svd(
    A: Float[Array, "p q"], rank: int
) -> tuple[Float[Array, "p r"], Float[Array, " r"], Float[Array, "r q"]]:
    """The leading ``rank`` singular triplets ``U_r, s_r, Vt_r`` of ``A``.

    Differentiable (forward and reverse mode) wherever ``s_1 > ... > s_r > s_{r+1}``:
    the discarded singular values may be zero and repeated.
    """
    U, s, Vt = jnp.linalg.svd(A, full_matrices=False)
    return U[:, :rank], s[:rank], Vt[:rank]


@truncated_svd.defjvp
def _truncated_svd_jvp(rank, primals, tangents):
    (A,), (dA,) = primals, tangents
    U, s, Vt = jnp.linalg.svd(A, full_matrices=False)
    V = Vt.T
    Ur, sr, Vr = U[:, :rank], s[:rank], V[:, :rank]
    # First-order perturbation of triplet i < rank: along u_j (resp. v_j) for every other
    # j, (s_i C_ji + s_j C_ij) / (s_i^2 - s_j^2) with C = U^T dA V; beyond the thin
    # bases (s_j = 0), the projection of dA v_i / s_i (resp. dA^T u_i / s_i). Pairs
    # with both j, i >= rank never occur.
    C = U.T @ dA @ V
    C_ji, C_ij = C[:, :rank], C[:rank, :].T
    same = jnp.arange(s.shape[0])[:, None] == jnp.arange(rank)[None, :]
    gap = jnp.where(same, 1.0, sr[None, :] ** 2 - s[:, None] ** 2)
    X = jnp.where(same, 0.0, (sr[None, :] * C_ji + s[:, None] * C_ij) / gap)
    Y = jnp.where(same, 0.0, (sr[None, :] * C_ij + s[:, None] * C_ji) / gap)
    dU = U @ X + (dA @ Vr - U @ C_ji) / sr
    dV = V @ Y + (dA.T @ Ur - V @ C_ij) / sr
    return (Ur, sr, Vr.T), (dU, jnp.diagonal(C)[:rank], dV.T)


def leading_directions(A: Float[Array, "p q"], count: int, iterations: int = 3) -> Float[Array, "p count"]:
    """``A``'s leading ``count`` left singular vectors, each times its singular value, by
    subspace iteration (Halko, Martinsson & Tropp 2011, algorithm 4.4): a block of
    ``count + 4`` columns from a fixed Gaussian start, ``iterations`` products with
    ``A A^T`` each followed by a QR factorization, and the SVD of ``A``'s projection on the
    block. Approximate (the error falls as ``(s_{b+1} / s_count)^(2 iterations + 1)``): for
    a warm start, where a full decomposition of ``A`` costs more than the fit it starts
    (the paper's cube, 200 x 252: 0.5-0.6 ms against 4.0 ms for ``eigh`` of ``A A^T``). Not
    differentiated."""
    block = min(count + 4, *A.shape)
    with jax.ensure_compile_time_eval():
        start = jax.random.normal(jax.random.key(0), (A.shape[1], block), A.dtype)

    # Each QR after the product before it (one LAPACK call after the other, README).
    def power(_, Q):
        return jnp.linalg.qr(A @ (A.T @ Q))[0]

    Q = jax.lax.fori_loop(0, iterations, power, jnp.linalg.qr(A @ start)[0])
    u, s, _ = jnp.linalg.svd(Q.T @ A, full_matrices=False)
    return (Q @ u[:, :count]) * s[:count]


def svd_factors(A: Float[Array, "p q"], rank: int) -> tuple[Float[Array, "p r"], Float[Array, "r q"]]:
    """Best rank-``rank`` factors of a complete matrix, balanced as ``U sqrt(s)``, ``sqrt(s) V^T``
    (differentiable wherever ``s_rank > s_rank+1``, `truncated_svd`)."""
    return _balanced(*truncated_svd(A, rank))


def _balanced(U, s, Vt):
    # The factors U sqrt(s), sqrt(s) V^T of an SVD, shared by both ways of computing it.
    root = jnp.sqrt(s)
    return U * root, root[:, None] * Vt


def product_factors(M: Float[Array, "p r"], S: Float[Array, "r q"]) -> tuple[Float[Array, "p r"], Float[Array, "r q"]]:
    """The balanced factors of `svd_factors` of the product ``M S`` (rank at most ``r``),
    from the factors alone: a QR factorization of each and the SVD of the ``r x r`` product
    of their triangles. On the paper's cube (200 x 252, r = 13) a fraction of a
    millisecond, where the SVD of the product took 8-9 ms. Not differentiated (the fits it
    serves are constants to the gradient, `jaxnrsfm.implicit.attach`)."""
    # One LAPACK call after the other (the ``0 *`` terms): two independent batched LAPACK
    # calls (under vmap) that XLA's CPU runtime ran concurrently have deadlocked it
    # (README), and a QR is two calls (the factorization, then its Q).
    Qm, Rm = jnp.linalg.qr(M)
    Qs, Rs = jnp.linalg.qr(S.T + 0.0 * Qm[0, 0])
    u, s, vt = jnp.linalg.svd(Rm @ Rs.T + 0.0 * Qs[0, 0])
    return _balanced(Qm @ u, s, vt @ Qs.T)


@partial(jax.custom_jvp, nondiff_argnums=(1,))
def lowest_eigenvectors(G: Float[Array, "d d"], k: int) -> Float[Array, "d k"]:
    """Eigenvectors of the ``k`` smallest eigenvalues of the symmetric ``G``.

    Differentiable wherever ``lambda_k < lambda_{k+1}``. The ``k`` eigenvalues may
    coincide: the derivative then leaves the basis of their subspace unturned, which is
    exact for every output that depends on the subspace alone.
    """
    return jnp.linalg.eigh(G)[1][:, :k]


@lowest_eigenvectors.defjvp
def _lowest_eigenvectors_jvp(k, primals, tangents):
    (G,), (dG,) = primals, tangents
    lam, V = jnp.linalg.eigh(G)
    C = V.T @ dG @ V
    inside = jnp.arange(lam.shape[0]) < k
    gap = jnp.where(inside[:, None], 1.0, lam[None, :k] - lam[:, None])
    X = jnp.where(inside[:, None], 0.0, C[:, :k] / gap)
    return V[:, :k], V @ X


def polar_rows(A: Float[Array, "... 2 3"]) -> Float[Array, "... 2 3"]:
    """The orthonormal pair of rows nearest to each ``2 x 3`` block: ``(A A^T)^(-1/2) A``.

    Written with the closed-form square root of a 2x2 SPD matrix,
    ``sqrt(P) = (P + sqrt(det P) I) / sqrt(tr P + 2 sqrt(det P))``, because the SVD's
    derivative is infinite where the two singular values coincide -- which is exactly
    the case of interest, a scaled rotation.
    """
    P = A @ jnp.swapaxes(A, -1, -2)
    a, b, d = P[..., 0, 0], P[..., 0, 1], P[..., 1, 1]
    root_det = jnp.sqrt(a * d - b * b)
    norm = jnp.sqrt(a + d + 2 * root_det)
    # sqrt(P) = (P + s I) / norm with s = sqrt(det P), inverted in closed form (no LAPACK
    # call): det(P + s I) = s (a + d + 2 s) = s norm^2.
    adjugate = jnp.stack([jnp.stack([d + root_det, -b], -1), jnp.stack([-b, a + root_det], -1)], -2)
    return (adjugate @ A) / (root_det * norm)[..., None, None]


def add_ridge(G: Float[Array, "... r r"], damping: Float[Array, ""] | float = 0.0) -> Float[Array, "... r r"]:
    """``G`` plus a ridge of ``max(1e-12, 100 eps) + damping`` times its mean diagonal.

    A relative ridge keeps an (almost) unconstrained unknown finite instead of NaN; at
    1e-12 it is far below the noise of any real problem. In float32 it must also exceed
    the round-off of G's eigenvalues (~eps |G|), or an unknown that only tiny weights
    constrain gets a singular, even indefinite, system: 100 eps there.
    """
    r = G.shape[-1]
    relative = max(1e-12, 100 * float(jnp.finfo(G.dtype).eps)) + damping
    ridge = relative * jnp.trace(G, axis1=-2, axis2=-1)[..., None, None] / r + jnp.finfo(G.dtype).tiny
    return G + ridge * jnp.eye(r, dtype=G.dtype)


def symmetric_products(A: Float[Array, "p r n"]) -> Float[Array, "q n"]:
    """The ``q = r(r+1)/2`` distinct entries of ``sum_p a_pj a_pj^T`` for each column ``j``
    (ALS's ``p = 2`` coordinates of an entry share its weight, and are summed here): what
    `grams` weighs. Formed once for a design shared by many weighted problems (a
    half-sweep's ``M`` or ``S``), each problem's normal matrix is then one row of a matrix
    product."""
    rows, cols = np.triu_indices(A.shape[1])
    return jnp.sum(A[:, rows] * A[:, cols], axis=0)


def grams(weights: Float[Array, "*b n"], products: Float[Array, "q n"]) -> Float[Array, "*b r r"]:
    """``G = sum_j weights_j sum_p a_pj a_pj^T`` for each row of ``weights``, from the
    `symmetric_products` of ``a``: the normal matrices of weighted least-squares problems
    that share their design. Each is symmetric, so one matrix product forms the
    ``r(r+1)/2`` distinct entries of all of them, which a gather spreads into place: about
    half the work of all ``r^2`` entries, and no ``(b, n, r)`` tensor of weighted rows
    (which an ``einsum("nr,bn,ns->brs")`` formed)."""
    r = (math.isqrt(8 * products.shape[0] + 1) - 1) // 2
    rows, cols = np.triu_indices(r)
    index = np.zeros((r, r), int)
    index[rows, cols] = index[cols, rows] = np.arange(rows.size)
    return (weights @ products.T)[..., index]


class RidgeCholesky(lx.Cholesky):
    """lineax's Cholesky solve of a positive semidefinite system with a relative ridge,
    ``(A + lambda I) x = b``, the ridge of `add_ridge`.

    For the normal equations of a rank-deficient least-squares problem with more residuals
    than unknowns, ``lx.Normal(RidgeCholesky())`` fits like the pseudo-inverse: ``J x`` is
    ``J J^+ r`` to round-off, at the cost of a Cholesky factor, a fraction of the SVD of ``J``
    (`jaxnrsfm.upgrade.rotation_triple`). Its ``x`` is not the minimum-norm one: the
    round-off of ``J^T r`` in ``J``'s null space is divided by ``lambda`` (2e-4 relative on a
    30 x 12 matrix of rank 9), a move along directions that change no residual. With more
    unknowns than residuals (``J J^T``), that round-off reaches ``J x`` (6e-5 relative on a
    9 x 30 matrix of rank 6): a Gauss--Newton step still, not an exact one. A ridge of
    ``sqrt(eps)`` fits the null space better and the range worse (8e-8 relative in ``J x``),
    and it changed the rotation triple Akhter's yoga converged to.
    """

    def init(self, operator, options):
        del options
        factor, _ = jax.scipy.linalg.cho_factor(add_ridge(operator.as_matrix()))
        return factor

    def compute(self, state, vector, options):
        del options
        flat, unflatten = jax.flatten_util.ravel_pytree(vector)
        return unflatten(jax.scipy.linalg.cho_solve((state, False), flat)), lx.RESULTS.successful, {}

    def transpose(self, state, options):
        return state, options

    def conj(self, state, options):
        return state, options
