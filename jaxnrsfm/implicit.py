"""Derivatives of the low-rank fits by the implicit function theorem.

Every factorization the pipeline differentiates is a stationary point of a weighted or
Huber reprojection loss, ``sum_ij c_ij rho(|w_ij - l_ij|)`` over rank-``r`` matrices ``L``
(``c``: per-entry weights, 0 where missing). The solvers that find it -- masked ALS,
Levenberg--Marquardt -- iterate in ``lax.while_loop`` and see only constants
(``stop_gradient``); their answer is then re-attached to the inputs here.

The attachment writes stationarity as a fixed point of the majorisation (EM) map of
Srebro & Jaakkola's weighted low-rank approximation,

    ``Z = T(Z) = L(Z) + Omega(E) * E``,  ``L(Z)`` = best rank-``r`` fit of ``Z``,  ``E = W - L(Z)``,

with ``Omega = c psi(|e|) / |e|`` scaled into ``[0, 1]`` (``psi``: the loss's influence
function; ``psi(a) / a = 1`` for least squares, ``min(1, delta / a)`` for Huber). At a
fixed point ``Z - L = Omega E`` is orthogonal to the rank-``r`` manifold at ``L``: exactly
the stationarity of the loss. The implicit function theorem on ``F(Z) = T(Z) - Z = 0`` (a
``jax.custom_jvp``: ``dZ = -(dF/dZ)^-1 dF/dargs dargs``, solved by matrix-free GMRES with
lineax; reverse mode transposes that solve) then differentiates ``L`` with respect to the
tracks, the weights and ``delta`` -- no unrolling, and the gauge of ``(M, S)`` never
enters, because ``L`` has none. ``L(Z)`` is `jaxnrsfm.linalg.truncated_svd`, finite
on noise-free data. The forward pass returns the solver's own fit, which is ``L(Z)`` to
the solver's tolerance, without an SVD: the polish, ``L(Z)`` and the tangent solve are
compiled and run only where the result is differentiated.
"""

from functools import partial

import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
from jaxtyping import Array, Bool, Float

from .linalg import product_factors, svd_factors
from .tracks import row_mask


def _gmres(dtype) -> lx.GMRES:
    # The linear solver of the Newton polish and of the tangent (and cotangent) solves.
    # A tighter rtol than sqrt(eps) stagnates at round-off on some cotangents; in float64
    # it leaves the gradients right to about 1e-7 (against finite differences).
    rtol = float(np.sqrt(np.finfo(dtype).eps))
    return lx.GMRES(rtol=rtol, atol=rtol * 1e-4, max_steps=2000, restart=50, stagnation_iters=100)


def lowrank(
    Z: Float[Array, "2m n"], rank: int
) -> tuple[Float[Array, "2m n"], Float[Array, "2m r"], Float[Array, "r n"]]:
    """The best rank-``rank`` fit ``L = M S`` of a complete matrix, with the balanced
    factors of `jaxnrsfm.linalg.svd_factors`."""
    M, S = svd_factors(Z, rank)
    return M @ S, M, S


def influence_weights(E: Float[Array, "2m n"], delta: Float[Array, ""]) -> Float[Array, "m n"]:
    """``psi(a) / a`` of each entry's residual length ``a``: 1 within ``delta``,
    ``delta / a`` beyond (Huber); ``delta = inf`` is least squares."""
    sq = E[0::2] ** 2 + E[1::2] ** 2
    far = sq > delta**2
    # Double where: the far branch must not see a = 0 (or delta = inf) in its gradient.
    return jnp.where(far, delta / jnp.sqrt(jnp.where(far, sq, 1.0)), 1.0)


def _em_from_fit(L, args):
    # T's value at any Z whose rank-r projection is L.
    W, weights, delta = args
    E = W - L
    return L + row_mask(weights * influence_weights(E, delta)) * E


def _stationarity(Z, args, *, rank):
    return _em_from_fit(lowrank(Z, rank)[0], args) - Z


@partial(jax.custom_jvp, nondiff_argnums=(0, 1))
def _root(rank: int, steps: int, Z: Float[Array, "2m n"], args, when: Bool[Array, ""] | None) -> Float[Array, "2m n"]:
    """``Z``, a root of `_stationarity` at ``args``, as a function of ``args``.

    Undifferentiated, ``Z`` itself: the solver's answer, stationary to its tolerance.
    Differentiated, ``Z`` after `_polish` (``steps`` Newton steps, where ``when``), and the
    tangents at that point: the polish serves only the derivative, so only a differentiated
    call pays for it (`attach`)."""
    return Z


@_root.defjvp
def _root_jvp(rank, steps, primals, tangents):
    # The implicit function theorem: F(Z(args), args) = 0, so dF/dZ dZ = -dF/dargs dargs.
    Z, args, when = primals
    _, t_args, _ = tangents
    stationarity = partial(_stationarity, rank=rank)
    Z = _polish(rank, steps, Z, args, when)
    _, rhs = jax.jvp(lambda args: stationarity(Z, args), (args,), (t_args,))
    operator = lx.JacobianLinearOperator(stationarity, Z, args)
    return Z, -lx.linear_solve(operator, rhs, _gmres(Z.dtype)).value


def _newton_step(stationarity, Z: Float[Array, "2m n"], fixed) -> Float[Array, "2m n"]:
    # One Newton step on the stationarity equation. GMRES works on the linearisation, so
    # a product costs matrix products, not an SVD; and its restart is short, because
    # lineax's GMRES pays per step for its restart length (restart 50 took 0.2 s a solve
    # on the cube, 10 a quarter of that).
    F, tangent = jax.linearize(lambda Z: stationarity(Z, fixed), Z)
    rtol = float(np.sqrt(np.finfo(Z.dtype).eps))
    gmres = lx.GMRES(rtol=rtol, atol=rtol * 1e-4, max_steps=500, restart=10, stagnation_iters=50)
    operator = lx.FunctionLinearOperator(tangent, jax.eval_shape(lambda: Z))
    polished = Z + lx.linear_solve(operator, -F, gmres, throw=False).value
    # A step whose linear solve failed could land anywhere: keep it only if it helped.
    size = lambda F: jnp.max(jnp.abs(F))  # noqa: E731
    return jnp.where(size(stationarity(polished, fixed)) < size(F), polished, Z)


def _polish(rank: int, steps: int, Z: Float[Array, "2m n"], args, when: Bool[Array, ""] | None) -> Float[Array, "2m n"]:
    # ``steps`` Newton steps on Z; ``when`` (traced) chooses at run time, None: always.
    # A static "never" is steps = 0, so that its GMRES is not even compiled.
    if steps == 0:
        return Z
    stationarity = partial(_stationarity, rank=rank)

    def newton(Z):
        for _ in range(steps):
            Z = _newton_step(stationarity, Z, args)
        return Z

    return newton(Z) if when is None else jax.lax.cond(when, newton, lambda Z: Z, Z)


def attach(
    W: Float[Array, "2m n"],
    weights: Float[Array, "m n"],
    M: Float[Array, "2m r"],
    S: Float[Array, "r n"],
    rank: int,
    delta: Float[Array, ""] | float = jnp.inf,
    *,
    steps: int = 1,
    polish: bool | Bool[Array, ""] = True,
    polish_value: bool = False,
) -> tuple[Float[Array, "2m n"], Float[Array, "2m r"], Float[Array, "r n"]]:
    """The rank-``rank`` fit ``L = M S`` that a solver found, returned as a differentiable
    function of ``W``, ``weights`` and ``delta``.

    ``weights`` are the loss's per-entry weights (a mask, or non-negative reals; they
    matter only up to scale); ``delta`` the Huber parameter in image units (``inf``:
    least squares).

    Where the result is differentiated, ``steps`` Newton steps on the stationarity equation
    first polish ``L``, and the value and its tangents are those of the polished point:
    ALS stops where its cost stalls, which on missing data can leave ``L`` about 1e-4
    (relative) from stationary, and one step reaches about 1e-9, so that the tangents are
    those of the exact stationary point and agree with finite differences of the
    (differentiated) values. Where it is not, ``L`` comes back as the solver left it: the
    polish only serves the derivative, and it was two thirds of the forward time of
    `jaxnrsfm.robust.wang` (30-frame cube: 667 ms a trial with it, 217 without; the
    reconstruction differs by the solver's tolerance). As with optimistix's implicit
    adjoint, the derivative is the exact solution's; a differentiated call also returns
    the polished value, so that value and tangents belong to one point. ``polish``
    (possibly traced) skips the steps for an ``L`` already stationary to its solver's
    tolerance (variable projection's): on the Oxford dinosaur a Newton step there took
    5 s, its GMRES stalling on the nearly singular tangent system of 77% missing data,
    and moved ``L`` by 7e-4. ``polish_value`` (static) polishes an undifferentiated
    result too, for a fit whose value is promised to be the optimum
    (`jaxnrsfm.factorize.least_squares_fit`: the oracle is exact on noise-free tracks,
    2e-12 units off the clean cube, where masked ALS alone stopped 7e-9 off). Returns
    ``(L, M, S)`` with balanced factors.

    Undifferentiated (and unpolished), ``L`` is the solver's ``M S`` and its balanced
    factors come from ``M`` and ``S`` (`jaxnrsfm.linalg.product_factors`), not from an
    SVD of the ``2m x n`` fixed point: the robust method's three attachments took three
    such SVDs in every forward pass (about 10% of a paper-size trial).
    """
    M, S = jax.lax.stop_gradient((M, S))  # the solver's answer: a constant to the gradient
    weights = weights.astype(W.dtype)
    # L depends on the weights only up to scale: a constant normaliser is exact.
    weights = weights / jax.lax.stop_gradient(jnp.maximum(jnp.max(weights), jnp.finfo(W.dtype).tiny))
    args = (W, weights, jnp.asarray(delta, W.dtype))
    Z = jax.lax.stop_gradient(_em_from_fit(M @ S, args))  # the fixed point, if M S is stationary
    if isinstance(polish, bool):
        steps, when = (steps if polish else 0), None
    else:
        when = polish
    if polish_value:
        Z = _polish(rank, steps, Z, jax.lax.stop_gradient(args), when)
        return lowrank(_root(rank, 0, Z, args, when), rank)
    return _attached(rank, steps, (M, S), Z, args, when)


@partial(jax.custom_jvp, nondiff_argnums=(0, 1))
def _attached(rank: int, steps: int, factors, Z: Float[Array, "2m n"], args, when: Bool[Array, ""] | None):
    # Undifferentiated: the solver's fit M S and its balanced factors, no SVD of Z.
    # Differentiated: the rank-r fit of Z as a function of args (`_root`: polished, then
    # the implicit function theorem), value and tangents at that one point.
    M, S = product_factors(*factors)
    return M @ S, M, S


@_attached.defjvp
def _attached_jvp(rank, steps, primals, tangents):
    _, Z, args, when = primals
    _, _, t_args, _ = tangents
    return jax.jvp(lambda args: lowrank(_root(rank, steps, Z, args, when), rank), (args,), (t_args,))
