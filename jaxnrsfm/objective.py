"""The framework's general robust solver: the factorization ``W ~ M S`` under a Huber or
L1 loss on the reprojection residuals, minimised with optimistix.

The loss is on the length ``a = |e_ij|`` of each entry's 2-vector residual, so both image
coordinates of an outlier are discounted together:

    ``rho(a) = a^2 / 2`` for ``a <= delta``,  ``delta (a - delta / 2)`` beyond (Huber).

As ``delta -> 0``, ``rho / delta -> a``: the L1 loss is the Huber loss with a ``delta``
far below the noise (``L1_DELTA`` robust scales), which keeps it smooth enough for a
Gauss--Newton model. optimistix's least-squares solvers need residuals whose squares sum
to the loss: ``r_ij = e_ij sqrt(2 rho(a)) / a``, written with the double-``where`` so that
its gradient stays finite at ``a = 0`` (``ALGORITHMS.md``).

The unknowns are ``(M, S)`` together; the Jacobian is never formed (it would be
``2mn x r(2m + n)``, gigabytes at the paper's size): Levenberg--Marquardt solves its damped
normal equations by conjugate gradients on Jacobian-vector products (``lineax.Normal``
around ``lineax.CG``). The ``r^2``-dimensional gauge ``(M G, G^-1 S)`` leaves the normal
matrix singular; the damping makes it definite and CG never needs more.
"""

import jax.numpy as jnp
import lineax as lx
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int

from .tracks import row_mask

L1_DELTA = 0.1
"""``delta``, in robust scales, of the Huber loss that stands in for L1."""


def huber_residuals(E: Float[Array, "2m n"], mask: Bool[Array, "m n"], delta: Float[Array, ""]) -> Float[Array, "2m n"]:
    """``r`` with ``sum r^2 = 2 sum_visible rho(|e_ij|)``: each entry's residual shrunk to
    carry the Huber loss of its length (module docstring); zero where not visible."""
    ex, ey = E[0::2], E[1::2]
    sq = ex**2 + ey**2
    far = sq > delta**2
    # Double where: the branch for far entries must not see a = 0, or its gradient is NaN.
    a = jnp.sqrt(jnp.where(far, sq, 4 * delta**2))
    shrink = jnp.where(far, jnp.sqrt(2 * delta * a - delta**2) / a, 1.0)
    return row_mask(mask) * E * row_mask(shrink)


def huber_loss(E: Float[Array, "2m n"], mask: Bool[Array, "m n"], delta: Float[Array, ""]) -> Float[Array, ""]:
    """``sum_visible rho(|e_ij|)``."""
    return 0.5 * jnp.sum(huber_residuals(E, mask, delta) ** 2)


def robust_factorize(
    W: Float[Array, "2m n"],
    visible: Bool[Array, "m n"],
    M0: Float[Array, "2m r"],
    S0: Float[Array, "r n"],
    delta: Float[Array, ""],
    *,
    max_steps: int = 200,
    rtol: float = 1e-8,
    cg_steps: int = 1000,
) -> tuple[Float[Array, "2m r"], Float[Array, "r n"], Int[Array, ""], Bool[Array, ""]]:
    """Minimise ``sum_visible rho_delta(|w_ij - M_i s_j|)`` over ``(M, S)`` from
    ``(M0, S0)`` by Levenberg--Marquardt with a matrix-free CG solve.

    ``delta`` is in image units (the callers scale it by the robust residual scale).
    Returns ``M, S``, the steps taken and whether the solver met its tolerance; it never
    raises, so one bad trial in a batch cannot abort the others (``throw=False``).
    """
    W = jnp.where(row_mask(visible), W, 0.0)

    def residuals(params, _):
        M, S = params
        return huber_residuals(W - M @ S, visible, delta)

    # The normal matrix is ill conditioned (the singular values of W span orders of
    # magnitude, and the gauge is only damped away): CG needs hundreds of iterations, and
    # a CG that stops short makes the whole solve report failure.
    cg = lx.CG(rtol=1e-6, atol=1e-10, max_steps=cg_steps)
    solver = optx.LevenbergMarquardt(rtol=rtol, atol=rtol, linear_solver=lx.Normal(cg))
    sol = optx.least_squares(residuals, solver, (M0, S0), max_steps=max_steps, throw=False)
    M, S = sol.value
    return M, S, sol.stats["num_steps"], sol.result == optx.RESULTS.successful
