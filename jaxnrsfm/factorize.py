"""Affine factorization of a tracking matrix: ``W ~ M S`` (+ translations).

Two forms, both from the paper (section 3.2 and 4.1):

* **registered rank-3k** (eq. 8): every frame is registered to its centroid, then the
  centred matrix is factorized at rank ``3k``. Valid only when every point is seen and
  clean, because the centroid is computed from the data itself.
* **augmented rank-(3k+1)** (eq. 12): no registration; the translations are carried by
  an extra column of ``M`` and a row of ones in ``S``. Works with outlying and missing
  data.

Complete data is factorized by a truncated SVD, the least-squares optimum (eq. 13);
data with missing entries by masked alternating least squares (Hartley &
Schaffalitzky's power factorization; its sweeps extrapolated), initialised from the SVD
of the mean-filled matrix. All kernels are pure and jit-compiled; they vmap over trials.
"""

from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .implicit import attach
from .linalg import add_ridge, grams, svd_factors, symmetric_products
from .tracks import prepare_tracks, row_mask, to_frames
from .varpro import varpro

SOLVERS = ("auto", "als", "varpro")
"""Missing-data solvers of `factorize`: masked ALS, ALS finished by variable
projection (`jaxnrsfm.varpro.varpro`), or ``"auto"``: VarPro only where ALS stalls."""


class Factorization(eqx.Module):
    """A low-rank fit ``W_hat = M S + translations``.

    For the augmented form the translations are zero here: they live in ``M``'s last
    column and ``S``'s (approximate) ones row until the metric upgrade separates them.
    """

    M: Float[Array, "2m r"]
    """Motion matrix."""
    S: Float[Array, "r n"]
    """Structure matrix."""
    translations: Float[Array, "m 2"]
    """Per-frame image centroids removed before factorizing (registered form), else 0."""
    W_hat: Float[Array, "2m n"]
    """The fitted tracking matrix, ``M S`` plus the translations."""
    inliers: Bool[Array, "m n"]
    """Entries the fit used: the visible ones, less any a robust method rejected."""
    cost: Float[Array, ""]
    """Sum of squared residuals over the inliers."""
    steps: Int[Array, ""]
    """Alternating least-squares sweeps taken (0 for the SVD)."""
    converged: Bool[Array, ""]
    """False if the iterative solver hit ``max_steps`` before its tolerance."""


def _solve_batched(
    G: Float[Array, "b r r"], rhs: Float[Array, "b r c"], damping: Float[Array, ""] | float = 0.0
) -> Float[Array, "b r c"]:
    # ``damping`` adds a larger ridge than add_ridge's own. The ridged normal matrices are
    # positive definite: a Cholesky factor and two triangular solves. jnp.linalg.solve's
    # pivoted LU (its permutation built by a loop of scatters) made up a third of the
    # compiled robust pipeline (cube, 30 frames: 41379 -> 32279 lines of optimised HLO,
    # compilation 11.5 -> 8.2 s under the tests' flags) and ran slower.
    factor = jax.lax.linalg.cholesky(add_ridge(G, damping), symmetrize_input=False)
    return jax.scipy.linalg.cho_solve((factor, True), rhs)


def structure_given_motion(
    weighted: Float[Array, "2m n"], weights: Float[Array, "m n"], M: Float[Array, "2m r"], damping: Float[Array, ""]
) -> Float[Array, "r n"]:
    """The weighted least-squares structure ``S`` given the motion ``M`` (half an ALS sweep).

    ``weighted`` is the tracks times their ``weights`` (``(m, n)``, one per entry, shared by
    its two coordinates). Each column of ``S`` is an independent ``r x r`` normal equation
    over its weighted entries, one batched solve; ``damping`` adds that fraction of each
    equation's mean diagonal to its diagonal (a ridge)."""
    G = grams(weights.T, symmetric_products(to_frames(M).transpose(1, 2, 0)))
    return _solve_batched(G, (weighted.T @ M)[..., None], damping)[..., 0].T


def motion_given_structure(
    weighted: Float[Array, "2m n"], weights: Float[Array, "m n"], S: Float[Array, "r n"], damping: Float[Array, ""]
) -> Float[Array, "2m r"]:
    """The weighted least-squares motion ``M`` given the structure ``S``, as
    `structure_given_motion`: the two rows of a frame share one ``r x r`` normal equation."""
    G = grams(weights, symmetric_products(S[None]))
    rhs = to_frames(weighted) @ S.T  # (m, 2, r)
    return _solve_batched(G, rhs.transpose(0, 2, 1), damping).transpose(0, 2, 1).reshape(-1, S.shape[0])


DAMPING = 1e-3
"""Ridge of `initial_fit`'s first ALS sweeps, relative to each normal equation's
mean diagonal."""
DAMPED_STEPS = 30
EXTRAPOLATION = (1.0, 1.5, 0.5, 0.25, 8.0)
"""`masked_als`'s extrapolation factor: its start, its growth after an accepted
extrapolation and its shrinkage after a rejected one, and its bounds."""


def masked_als(
    W: Float[Array, "2m n"],
    weights: Float[Array, "m n"],
    M0: Float[Array, "2m r"],
    *,
    max_steps: int = 500,
    rtol: float = 1e-10,
    damped_steps: int | Int[Array, ""] = 0,
    active: Bool[Array, " r"] | None = None,
) -> tuple[Float[Array, "2m r"], Float[Array, "r n"], Int[Array, ""], Bool[Array, ""]]:
    """Minimise ``sum_ij weights_ij |w_ij - M_i s_j|^2`` by alternating least squares from ``M0``.

    ``weights`` is a visibility mask (bool) or non-negative per-entry weights; a zero
    weight is a missing entry. ``active`` (leading ``True`` entries, then ``False``) marks
    the columns of ``M0`` in use, the others being zero: the fit is then one of that lower
    rank, its unused columns of ``M`` and rows of ``S`` kept at zero, so that fits of several
    ranks can share one compiled loop (`jaxnrsfm.robust.wang`'s passes). The first
    ``damped_steps`` sweeps are damped (ridge
    ``DAMPING``, see `initial_fit`); then, undamped, it stops when a sweep lowers
    the cost by less than ``rtol`` of itself, or when the cost is negligible against the
    data.

    Each undamped sweep is extrapolated: the new ``M`` (given the last ``S``) is moved on
    along its change, ``M + beta (M_new - M)``, and kept if the fit with its own ``S``
    costs less than the last iterate; otherwise the plain sweep is taken (one more solve
    for ``S``). ``beta`` grows while extrapolations are kept and shrinks when one is not
    (`EXTRAPOLATION`). Plain ALS crawls through the "swamps" of a missing-data problem:
    on the paper's cube with its outliers missing (rank 13, sigma 2), from the SVD of the
    zero-filled tracks, two of six 30-frame trials took 375 and 323 sweeps to
    ``rtol = 1e-10``, extrapolated 53 and 87 (the same minima to 1e-9), and at the
    rejection passes' 1e-6 plain ALS stopped in the swamp (cost 38177.3 against the
    minimum 38055.7) where the extrapolated sweeps reached 38055.74 in 34; on 100 frames
    68 against 29 sweeps. Where plain ALS converges in a few sweeps, the extrapolated one
    takes about two more.
    """
    weights = jnp.asarray(weights, W.dtype)
    mask = row_mask(weights)
    weighted = mask * W  # the half-sweeps' right-hand sides: formed once, not every sweep
    scale = jnp.sum(mask * W**2)
    floor = jnp.finfo(W.dtype).eps ** 2 * scale
    start, grow, shrink, smallest, largest = EXTRAPOLATION
    inf = jnp.array(jnp.inf, W.dtype)

    def cost(M, S):
        return jnp.sum(mask * (W - M @ S) ** 2)

    def damping(step):
        return jnp.where(step < damped_steps, DAMPING, 0.0)

    def cond(state):
        _, _, c, c_prev, step, _ = state
        progress = (step < damped_steps) | ((c > floor) & (c_prev - c > rtol * c))
        return (step == 0) | ((step < max_steps) & progress)

    def body(state):
        M, S, c, _, step, beta = state
        damped, ridge = step < damped_steps, damping(step)
        new = motion_given_structure(weighted, weights, S, ridge)
        # No extrapolation in a damped sweep (its fixed point is the ridge's, not the
        # cost's) nor from the start, whose cost is not yet known.
        plain = damped | (step == 0)
        far = new + jnp.where(plain, 0.0, beta) * (new - M)
        S_far = structure_given_motion(weighted, weights, far, ridge)
        c_far = cost(far, S_far)
        keep = plain | (c_far < c)

        # Under vmap the cond runs both branches, and two batched LAPACK calls that XLA's
        # CPU runtime may run concurrently have deadlocked it (see `initial_fit`): the
        # ``0 * c`` terms order this solve after S_far's, and the QR below after it.
        def sweep(_):
            S_new = structure_given_motion(weighted, weights, new + 0.0 * c_far, ridge)
            return new, S_new, cost(new, S_new)

        M, S, c_new = jax.lax.cond(keep, lambda _: (far, S_far, c_far), sweep, None)
        beta = jnp.where(
            plain, beta, jnp.where(keep, jnp.minimum(grow * beta, largest), jnp.maximum(shrink * beta, smallest))
        )
        # Keep M orthonormal so the gauge cannot drift towards an ill-conditioned pair.
        Q, R = jnp.linalg.qr(M + 0.0 * c_new)
        # Unused columns of M are zero, and so are their rows of R (they trail): only Q's
        # columns there are arbitrary. (The solves keep them at zero: a zero column of M or
        # row of S has a zero right-hand side and no coupling to the others.)
        Q = Q if active is None else jnp.where(active, Q, 0.0)
        # A damped sweep's cost is no reference for the convergence test: damped ALS
        # stalls at its own (ridge-biased) fixed point, which the undamped sweeps must leave.
        return Q, R @ S, c_new, jnp.where(damped, inf, c), step + 1, beta

    S0 = structure_given_motion(weighted, weights, M0, damping(0))
    M, S, c, c_prev, steps, _ = jax.lax.while_loop(
        cond, body, (M0, S0, inf, inf, jnp.array(0), jnp.array(start, W.dtype))
    )
    converged = (c <= floor) | (c_prev - c <= rtol * c)
    return M, S, steps, converged


def mean_fill(W: Float[Array, "2m n"], visible: Bool[Array, "m n"]) -> Float[Array, "2m n"]:
    """Replace missing entries by the mean of their row's visible entries."""
    mask = row_mask(visible)
    mean = jnp.sum(jnp.where(mask, W, 0.0), axis=1) / jnp.maximum(mask.sum(axis=1), 1)
    return jnp.where(mask, W, mean[:, None])


def centroids(W: Float[Array, "2m n"], visible: Bool[Array, "m n"]) -> Float[Array, "m 2"]:
    """Per-frame image centroid of the visible points (eq. 4's registration)."""
    vis = visible[:, None, :]
    return jnp.sum(jnp.where(vis, to_frames(W), 0.0), axis=2) / jnp.maximum(vis.sum(axis=2), 1)


def initial_fit(
    W: Float[Array, "2m n"],
    weights: Float[Array, "m n"],
    rank: int,
    *,
    complete: bool,
    max_steps: int = 500,
    rtol: float = 1e-10,
) -> tuple[Float[Array, "2m r"], Float[Array, "r n"], Int[Array, ""], Bool[Array, ""]]:
    """Least-squares rank-``rank`` fit: the truncated SVD when ``complete`` (static) and
    the weights are uniform, else masked ALS started from the SVD of the mean-filled matrix.

    With missing data the least-squares cost has local minima, and ALS runs twice from
    that start: plainly, and with its first ``DAMPED_STEPS`` sweeps damped (a ridge);
    the fit of lower cost wins. Neither start is always the better: on 150 frames of
    Akhter's yoga with 30% missing, rank 7, plain ALS stopped at RMS 0.00277 on the
    visible entries and 0.58 on the hidden ones (the tracks' RMS is 0.45), the damped
    start at 0.00221 and 0.00315 (any damping from 1e-4 to 1e-1 led there); on a
    noise-free 12-frame deformable cube with 30% missing and too low a rank, the plain
    start found the lower minimum. The sweeps after the damped ones are undamped, so
    both answers are stationary points of the least-squares cost itself. ``steps``
    counts the sweeps of both runs."""
    if complete:
        M, S = svd_factors(W, rank)
        return M, S, jnp.array(0), jnp.array(True)
    M0, _ = svd_factors(mean_fill(W, weights > 0), rank)
    mask = row_mask(weights).astype(W.dtype)

    def run(damped):
        M, S, steps, converged = masked_als(W, weights, M0, max_steps=max_steps, rtol=rtol, damped_steps=damped)
        return M, S, steps, converged, jnp.sum(mask * (W - M @ S) ** 2)

    # The two runs go one after the other through ``lax.map``: written as two independent
    # while loops in one compiled function, their batched solves deadlocked XLA's CPU
    # runtime on a 2-core machine (jaxlib 0.10).
    M, S, steps, converged, cost = jax.lax.map(run, jnp.array([0, min(DAMPED_STEPS, max_steps // 2)]))
    best = jnp.argmin(cost)
    return M[best], S[best], steps.sum(), converged[best]


def least_squares_fit(
    W: Float[Array, "2m n"],
    weights: Float[Array, "m n"],
    rank: int,
    *,
    complete: bool,
    max_steps: int = 500,
    rtol: float = 1e-10,
    solver: Literal["auto", "als", "varpro"] = "als",
) -> tuple[Float[Array, "2m r"], Float[Array, "r n"], Int[Array, ""], Bool[Array, ""]]:
    """`initial_fit`, differentiable with respect to ``W`` and ``weights``: the
    truncated SVD directly, the missing-data fit through the implicit function theorem
    (`jaxnrsfm.implicit.attach`; the factors come back balanced).

    ``solver`` (static) chooses the missing-data fit: ``"als"``; ``"varpro"``, ALS then
    variable projection from its answer; ``"auto"``, VarPro only when ALS stopped at its
    step limit, the mark of the slow "swamps" where it stalls short of a minimum (on the
    Oxford dinosaur, rank 4: ALS stopped at RMS 1.3538 after 1000 sweeps, VarPro from
    there reached the best known 1.084673 in 285 steps; on the paper's cube with 30%
    missing ALS converged in 54 sweeps and VarPro from there changed nothing). A
    ``lax.cond``: under ``jax.vmap`` it becomes a select and VarPro runs for every
    member. VarPro needs a visibility mask (``bool`` weights)."""
    if complete:
        return initial_fit(W, weights, rank, complete=True)
    if solver not in SOLVERS:
        raise ValueError(f"solver must be one of {SOLVERS}; got {solver!r}")
    if solver != "als" and weights.dtype != bool:
        raise ValueError(f"solver={solver!r} needs a visibility mask, not real weights")
    constant = jax.lax.stop_gradient
    W0 = constant(W)
    M, S, steps, converged = initial_fit(W0, constant(weights), rank, complete=False, max_steps=max_steps, rtol=rtol)

    def finish_by_varpro(M, S, steps, converged):
        M, S, more, converged = varpro(W0, weights, M, rtol=rtol)
        return M, S, steps + more, converged

    # VarPro's answer is stationary to its tolerance: no Newton polish (attach) after it.
    polish = True
    if solver == "varpro":
        M, S, steps, converged = finish_by_varpro(M, S, steps, converged)
        polish = False
    elif solver == "auto":
        stalled = jnp.logical_not(converged)
        M, S, steps, converged = jax.lax.cond(stalled, finish_by_varpro, lambda *x: x, M, S, steps, converged)
        polish = jnp.logical_not(stalled)
    _, M, S = attach(W, weights, M, S, rank, polish=polish, polish_value=True)
    return M, S, steps, converged


def finish(
    W: Float[Array, "2m n"],
    inliers: Bool[Array, "m n"],
    M: Float[Array, "2m r"],
    S: Float[Array, "r n"],
    t: Float[Array, "m 2"],
    steps: Int[Array, ""],
    converged: Bool[Array, ""],
) -> Factorization:
    """Assemble a `Factorization`, with its cost over the inliers."""
    fit = M @ S + t.reshape(-1)[:, None]
    cost = jnp.sum(jnp.where(row_mask(inliers), W - fit, 0.0) ** 2)
    return Factorization(M, S, t, fit, inliers, cost, steps, converged)


@eqx.filter_jit
def factorize_prepared(
    W: Float[Array, "2m n"],
    visible: Bool[Array, "m n"],
    *,
    rank: int,
    register: bool,
    complete: bool,
    max_steps: int = 500,
    rtol: float = 1e-10,
    solver: Literal["auto", "als", "varpro"] = "als",
) -> Factorization:
    """`factorize` on already validated, zero-filled tracks (jit-compiled, vmappable).

    ``complete`` is static: ``True`` uses the SVD alone, ``False`` refines the SVD of the
    mean-filled matrix by the missing-data ``solver`` of `least_squares_fit`
    (``"als"`` here, the pipeline's: a vmapped sweep would run VarPro in every trial).
    """
    t = centroids(W, visible) if register else jnp.zeros((W.shape[0] // 2, 2), W.dtype)
    Wc = jnp.where(row_mask(visible), W - t.reshape(-1)[:, None], 0.0)
    M, S, steps, converged = least_squares_fit(
        Wc, visible, rank, complete=complete, max_steps=max_steps, rtol=rtol, solver=solver
    )
    return finish(W, visible, M, S, t, steps, converged)


def factorize(
    W: ArrayLike,
    visible: ArrayLike | None = None,
    *,
    rank: int,
    form: Literal["augmented", "registered"] = "augmented",
    max_steps: int = 500,
    rtol: float = 1e-10,
    solver: Literal["auto", "als", "varpro"] = "auto",
) -> Factorization:
    """Low-rank affine factorization of a tracking matrix.

    **Arguments:**

    - `W`: tracks ``(2m, n)``, rows ``2i, 2i+1`` = u, v of frame ``i``; NaN = missing.
    - `visible`: optional ``(m, n)`` boolean mask of observed entries.
    - `rank`: rank of ``M S``: ``3k + 1`` for the augmented form of a ``k``-basis
      nonrigid object (``4`` for a rigid one), ``3k`` for the registered form.
    - `form`: ``"augmented"`` (eq. 12, no registration) or ``"registered"`` (eq. 8,
      each frame centred on its visible centroid first).
    - `max_steps`, `rtol`: the alternating least-squares budget when data is missing.
    - `solver`: the missing-data solver (`least_squares_fit`): ``"auto"`` (masked
      ALS, finished by variable projection when ALS stalls at ``max_steps``), ``"als"``
      or ``"varpro"`` (ALS, then VarPro always). ``steps`` counts both.

    **Returns:** a `Factorization`.
    """
    if form not in ("augmented", "registered"):
        raise ValueError(f"form must be 'augmented' or 'registered'; got {form!r}")
    if solver not in SOLVERS:
        raise ValueError(f"solver must be one of {SOLVERS}; got {solver!r}")
    W0, vis = prepare_tracks(W, visible, rank=rank)
    complete = not isinstance(vis, jax.core.Tracer) and bool(vis.all())
    return factorize_prepared(
        W0,
        vis,
        rank=rank,
        register=form == "registered",
        complete=complete,
        max_steps=max_steps,
        rtol=rtol,
        solver=solver,
    )
