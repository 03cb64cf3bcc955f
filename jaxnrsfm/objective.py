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

CG is preconditioned by the inverse of the normal matrix's diagonal blocks (`BlockJacobiNormal`):
a residual ``e_ij`` involves only frame ``i``'s two rows of ``M`` and point ``j``'s column of
``S``, so those blocks (``2r x 2r`` a frame, ``r x r`` a point) are exactly what one
alternating least-squares step inverts, and they are read off the operator with ``3r``
products. On the 40-frame cube (sigma 2, 10% outliers, rank 13) it halved the Huber fit's
time (8.2 to 4.0 s) and cut the L1 fit's from 12.0 to 4.7 s, for the same fits; the coupling
of ``M`` and ``S``, which the blocks leave out, is what CG still iterates on.
"""

from typing import Any

import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int

from .tracks import row_mask

L1_DELTA = 0.1
"""``delta``, in robust scales, of the Huber loss that stands in for L1."""

CG_RTOL = 1e-3
"""Relative tolerance of the conjugate-gradient solve of each Levenberg--Marquardt step:
an inexact Newton step, which need only lower the damped model; LM's own test decides
convergence. Measured on the 40-frame cube (10% outliers, the tests' XLA flags), against
``1e-6``: L1 on exact tracks 31.8 -> 25.6 s (62 -> 52 steps), Huber at sigma 2 13.8 -> 10.2
s, L1 at sigma 2 32.4 -> 29.9 s, each with the same fit (RMS against the truth to 6 digits)
and the same outliers found."""


STALL_STEPS = 20
"""Consecutive rejected Levenberg--Marquardt steps after which `robust_factorize` stops at
its last accepted iterate, as converged (`StallingLevenbergMarquardt`)."""


class StallingLevenbergMarquardt(optx.LevenbergMarquardt):
    """``optimistix.LevenbergMarquardt`` that also stops, at its last accepted iterate, once
    `STALL_STEPS` steps in a row were rejected.

    optimistix tests for convergence only on an accepted step. At a minimum that the
    inexact CG steps cannot improve on (the cost's round-off), every step is rejected, and
    the solve ran on to its step limit and reported failure: on the paper's cube (seed 0,
    sigma 2, 10% outliers) the Huber fit under XLA's default options (`reconstruct_batch`)
    was accepted 20 times and then rejected 472 times in a row up to the limit of 500, at
    the cost, to every digit, where the same fit under the single call's options met the test
    after 33 steps (optimistix issue #195). Each rejection shrinks the step by 4 (the trust
    region's factor): after 20, by 10^12, and a point that no step of any of those sizes
    improves is a minimum to round-off.
    """

    def terminate(self, fn, y, args, options, state, tags):
        terminate, result = super().terminate(fn, y, args, options, state, tags)
        return terminate | (state.num_steps_since_acceptance >= STALL_STEPS), result


def _block_inverse(normal: lx.AbstractLinearOperator) -> lx.AbstractLinearOperator:
    """The inverse of the diagonal blocks of the normal matrix ``normal`` on ``(M, S)``:
    frame ``i``'s rows ``2i, 2i + 1`` of ``M`` (coupled by the loss on each entry's
    2-vector residual) and point ``j``'s column of ``S``, as a positive definite operator."""
    M_struct, S_struct = normal.in_structure()
    M_shape, S_shape, dtype = M_struct.shape, S_struct.shape, M_struct.dtype
    (two_m, r), n = M_shape, S_shape[1]
    m = two_m // 2
    eye = jnp.eye(r, dtype=dtype)
    # Probe (c, l): ones in column l of M's rows of parity c; its product's M part holds,
    # in frame i's rows, column (c, l) of that frame's block. Likewise S's row l for the points.
    frame_probes = jnp.zeros((2, r, two_m, r), dtype).at[0, :, 0::2].set(eye[:, None]).at[1, :, 1::2].set(eye[:, None])
    frame_probes = frame_probes.reshape(2 * r, two_m, r)
    point_probes = jnp.broadcast_to(eye[:, :, None], (r, r, n))
    frame = jax.vmap(lambda v: normal.mv((v, jnp.zeros(S_shape, dtype)))[0])(frame_probes)
    point = jax.vmap(lambda v: normal.mv((jnp.zeros(M_shape, dtype), v))[1])(point_probes)
    frame_blocks = frame.reshape(2 * r, m, 2 * r).transpose(1, 2, 0)  # (m, 2r, 2r)
    point_blocks = point.transpose(2, 1, 0)  # (n, r, r)
    # One batched inversion (two independent batched LAPACK calls in one program have
    # deadlocked on a 2-core CPU, README): the point blocks padded to 2r with the identity.
    pad = jnp.zeros((n, 2 * r, 2 * r), dtype).at[:, :r, :r].set(point_blocks).at[:, r:, r:].set(eye)
    blocks = jnp.concatenate([frame_blocks, pad])
    # The damping keeps each block definite; a relative jitter guards the undamped limit.
    jitter = 1e3 * jnp.finfo(dtype).eps * jnp.trace(blocks, axis1=1, axis2=2) / (2 * r)
    inverse = jnp.linalg.inv(blocks + jitter[:, None, None] * jnp.eye(2 * r, dtype=dtype))
    frame_inv, point_inv = inverse[:m], inverse[m:, :r, :r]

    def apply(y):
        dM, dS = y
        dM = jnp.einsum("iab,ib->ia", frame_inv, dM.reshape(m, 2 * r)).reshape(M_shape)
        return dM, jnp.einsum("jab,bj->aj", point_inv, dS)

    return lx.FunctionLinearOperator(apply, normal.in_structure(), lx.positive_semidefinite_tag)


class BlockJacobiNormal(lx.Normal):
    """``lineax.Normal`` around ``lineax.CG``, with CG preconditioned by `_block_inverse` of
    the normal matrix it is given (the module docstring says why). For the operator of
    `robust_factorize`'s Levenberg--Marquardt steps only: it assumes unknowns ``(M, S)``."""

    def init(self, operator: lx.AbstractLinearOperator, options: dict[str, Any]):
        inner_state, tall, transpose, inner_options = super().init(operator, options)
        normal = inner_state[0]  # CG's state: the (linearised) normal operator first
        return inner_state, tall, transpose, {**inner_options, "preconditioner": _block_inverse(normal)}


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
    # optimistix damps the step in the default float dtype: float64 when x64 is enabled,
    # where a float32 problem failed lineax's structure check. Such a problem is solved in
    # float64 and returned in float32.
    dtype = W.dtype
    work = jnp.promote_types(dtype, jax.dtypes.canonicalize_dtype(jnp.float64))
    W, M0, S0, delta = (jnp.asarray(x, work) for x in (W, M0, S0, delta))
    W = jnp.where(row_mask(visible), W, 0.0)

    def residuals(params, _):
        M, S = params
        return huber_residuals(W - M @ S, visible, delta)

    # The normal matrix is ill conditioned (the singular values of W span orders of
    # magnitude, and the gauge is only damped away): CG needs tens to hundreds of
    # iterations, and a CG that stops at its step limit makes the whole solve report
    # failure (a CG that meets its loose CG_RTOL is an inexact step, which LM accepts).
    # In float32 CG could not reach tighter tolerances, and a CG that fails ends the solve
    # at its first step (Huber and L1 returned the least-squares start): they are floored
    # at sqrt(eps) and 1e3 eps of the dtype (float64's are above both; CG_RTOL is above
    # float32's sqrt(eps) too). So is LM's own
    # tolerance, at sqrt(eps) / 2: a relative change d of the parameters near the minimum
    # changes the loss by d^2, so float32 resolves the minimiser to about sqrt(eps) and met
    # 1e-8 only by chance (a Huber solve whose scale moved by round-off wobbled for 500
    # steps at loss 46711.77 +- 0.01; 45 steps at 1e-4). float64's 1e-8 is above it.
    eps = float(np.finfo(work).eps)
    cg = lx.CG(rtol=max(CG_RTOL, np.sqrt(eps)), atol=max(1e-10, 1e3 * eps), max_steps=cg_steps)
    tol = max(rtol, np.sqrt(eps) / 2)
    solver = StallingLevenbergMarquardt(rtol=tol, atol=tol, linear_solver=BlockJacobiNormal(cg))
    sol = optx.least_squares(residuals, solver, (M0, S0), max_steps=max_steps, throw=False)
    M, S = sol.value
    return M.astype(dtype), S.astype(dtype), sol.stats["num_steps"], sol.result == optx.RESULTS.successful
