"""Outlier handling: the paper's robust algorithm (section 4.2), the Huynh et al.
baseline, the Ke & Kanade L1 baseline and an oracle told the true outliers.

All strategies work on the augmented rank-(3k+1) factorization, need no registration,
and return a :class:`~jaxnrsfm.factorize.Factorization` whose ``inliers`` say which
observed entries were kept. They are pure and jit-compiled; a batch vmaps them.

**Residual scale.** The paper detects outliers from the reprojection error of each
entry, ``|e_ij|`` (eq. 16); its reference for the threshold (Wang et al., CRV 2013) is
not available, so the choice here is the principled one of ``ALGORITHMS.md``: under
Gaussian image noise of standard deviation ``sigma`` per coordinate, ``|e_ij|`` is
Rayleigh distributed, whose median is ``sigma sqrt(2 ln 2)``. The scale is estimated as
``sigma_hat = median(|e_ij|) / sqrt(2 ln 2)``, first over all observed entries (valid
while fewer than half are outliers, but inflated by them: by 19% with 20% outliers),
then over the entries that first estimate keeps.

**Threshold.** An entry is an outlier when ``|e_ij| > threshold * sigma_hat``. By
default the multiple is the Bayes decision boundary between the two populations, as
in MLESAC (Torr & Zisserman 2000): inliers Rayleigh with scale ``sigma_hat``, outliers
uniform on ``[0, max |e|]``, the outlier fraction ``eps`` the one found so far. That is
the ``x`` with ``(1 - eps) x exp(-x^2 / 2) = eps sigma_hat / max|e|``, kept in
``[3, 6]``: about 3.4 with 20% outliers at ``sigma = 5``, 3.9 with 10% at ``sigma = 2``,
4.2 with 5% at ``sigma = 1`` on the paper's cube, where an inlier is lost with
probability ``exp(-x^2 / 2)``, 0.3% to 0.01%. A fixed ``threshold`` overrides it.

**Weights (step 5).** Entries are weighted by a per-frame and per-point model of the
residual variance, ``sigma_ij = sigma_i sigma_j / sigma_hat`` with ``sigma_i``,
``sigma_j`` the RMS inlier residuals of frame ``i`` and point ``j``: weight
``sigma_hat^2 / (sigma_i sigma_j)``, clipped to ``[1/10, 10]`` so that a frame or point with
few inliers cannot dominate. With homogeneous noise the weights are all near one.
"""

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from .factorize import Factorization, finish, initial_fit, least_squares_fit, masked_als
from .implicit import attach
from .l1 import ke_kanade as ke_kanade_l1
from .linalg import svd_factors
from .metrics import entry_errors
from .objective import L1_DELTA, robust_factorize
from .tracks import row_mask

RAYLEIGH_MEDIAN = float(np.sqrt(2 * np.log(2.0)))
"""Median of a Rayleigh variable of unit scale: ``|e|`` for ``e ~ N(0, I_2)``."""

BOUNDS = (3.0, 6.0)
"""Range of the automatic threshold multiple (see the module docstring)."""

SCHEDULE = 3.0
"""The first rejection pass's threshold is this many times the final one, falling
geometrically: the first fit is pulled by every outlier, and each cleaner fit earns a
tighter threshold."""

RIGID_RANK = 4
"""The rank the robust algorithm starts from: a rigid object's augmented rank."""

PASS_RTOL = 1e-6
"""Convergence tolerance of the rejection passes' fits (the final fit uses the caller's):
a pass only sets the next weights. On the cube (sigma 2, 20% outliers) 1e-6 instead of
1e-10 took a third of the ALS sweeps and changed at most 2 of 25200 final inlier labels."""

ANCHOR = 1e-4
"""Weight an entry rejected as an outlier keeps in the final fit. Dropped outright, it
becomes missing data, and an entry whose neighbours were rejected too (a frame's whole
moving part, say) has a prediction nothing constrains; ``1e-4`` pins it while an
outlier 100 units away pulls like an inlier 1 unit away."""


def robust_scale(errors: Float[Array, "m n"], mask: Bool[Array, "m n"]) -> Float[Array, ""]:
    """``sigma_hat = median(|e_ij|) / sqrt(2 ln 2)`` over the entries in ``mask``."""
    return jnp.nanmedian(jnp.where(mask, errors, jnp.nan)) / RAYLEIGH_MEDIAN


def bayes_threshold(
    errors: Float[Array, "m n"], visible: Bool[Array, "m n"], inliers: Bool[Array, "m n"], sigma: Float[Array, ""]
) -> Float[Array, ""]:
    """The threshold multiple ``x`` where a Rayleigh inlier and a uniform outlier are
    equally likely (module docstring), given the outlier fraction ``1 - inliers/visible``."""
    eps = 1.0 - inliers.sum() / jnp.maximum(visible.sum(), 1)
    largest = jnp.max(jnp.where(visible, errors, 0.0))
    c = eps * sigma / jnp.maximum((1.0 - eps) * largest, jnp.finfo(errors.dtype).tiny)
    c = jnp.maximum(c, jnp.finfo(errors.dtype).tiny)
    # Fixed point of x = sqrt(2 ln(x / c)) on the decreasing branch (x > 1): it contracts
    # there, and ten steps from the upper bound settle it to far below the bounds' width.
    x = jnp.array(BOUNDS[1], errors.dtype)
    for _ in range(10):
        x = jnp.sqrt(2.0 * jnp.log(jnp.maximum(x / c, 1.0)))
    return jnp.clip(x, *BOUNDS)


def classify(
    W: Float[Array, "2m n"],
    fit: Float[Array, "2m n"],
    visible: Bool[Array, "m n"],
    threshold: float | None = None,
    kept: Bool[Array, "m n"] | None = None,
) -> tuple[Bool[Array, "m n"], Float[Array, ""], Float[Array, ""]]:
    """Observed entries whose ``|e_ij|`` is within the threshold, the final scale
    ``sigma_hat`` and the multiple used. The scale is estimated (module docstring) over
    the entries ``kept`` by an earlier pass or, without one, twice: over all observed
    entries, then over those the first estimate keeps."""
    errors = entry_errors(W, fit)
    first = kept
    if first is None:
        first = visible & (errors <= (threshold or BOUNDS[1]) * robust_scale(errors, visible))
    sigma = robust_scale(errors, first)
    factor = bayes_threshold(errors, visible, first, sigma) if threshold is None else jnp.asarray(threshold, W.dtype)
    return visible & (errors <= factor * sigma), sigma, factor


MISFIT = 0.12
"""Largest Kolmogorov--Smirnov distance between the kept residuals and the Rayleigh
model that :func:`rayleigh_misfit` accepts. Measured: on the cube, fits that found the
outliers 0.005--0.02 (fitted residuals are a little smaller than the noise); on the real
dinosaur tracks (heavier tailed than Gaussian) 0.07--0.10 for k = 2..5; with 50% and 60%
outliers on the cube, where the median scale breaks down, 0.17 and 0.14 -- but 0.09
with 70%, which therefore goes unflagged: past the breakdown point the outliers are
the majority, and the residuals alone cannot always tell which population is which."""


def rayleigh_misfit(
    W: Float[Array, "2m n"], fit: Float[Array, "2m n"], inliers: Bool[Array, "m n"]
) -> Float[Array, ""]:
    """Kolmogorov--Smirnov distance between the kept ``|e_ij| / sigma_hat`` and a unit
    Rayleigh law: the check that the entries called inliers look like Gaussian noise.
    When the outliers outnumber what the median scale can absorb, the "inliers" are a
    mixture and the distance is large; the pipeline then reports ``too_many_outliers``."""
    errors = entry_errors(W, fit)
    x = jnp.sort(jnp.where(inliers, errors / robust_scale(errors, inliers), jnp.inf).ravel())
    count = jnp.maximum(inliers.sum(), 1)
    rank = jnp.arange(1, x.size + 1, dtype=W.dtype)
    model = 1.0 - jnp.exp(-0.5 * jnp.where(jnp.isfinite(x), x, 0.0) ** 2)
    gap = jnp.maximum(jnp.abs(model - rank / count), jnp.abs(model - (rank - 1) / count))
    return jnp.max(jnp.where(rank <= count, gap, 0.0))


def _zero_translations(W):
    return jnp.zeros((W.shape[0] // 2, 2), W.dtype)


def rank_schedule(rank: int, passes: int) -> tuple[int, ...]:
    """Ranks of the rejection passes: from the rigid rank up by two to ``rank``, then at
    ``rank`` until there are ``passes`` passes in all."""
    start = min(RIGID_RANK, rank)
    ranks = (*range(start, rank, 2), rank)
    return ranks + (rank,) * max(0, passes - len(ranks))


def _grow(W, weights, M, S, rank):
    # New directions for a higher-rank pass: the leading left singular vectors of the
    # weighted residual, i.e. what the lower-rank model leaves unexplained in the data
    # it currently trusts.
    add = rank - M.shape[1]
    if add == 0:
        return M
    U, s, _ = jnp.linalg.svd(row_mask(weights) * (W - M @ S), full_matrices=False)
    return jnp.concatenate([M, U[:, :add] * s[:add]], axis=1)


def wang(
    W: Float[Array, "2m n"],
    visible: Bool[Array, "m n"],
    *,
    rank: int,
    complete: bool,
    threshold: float | None = None,
    passes: int = 3,
    weighted: bool = True,
    max_steps: int = 500,
    rtol: float = 1e-10,
) -> Factorization:
    """The paper's robust nonrigid factorization (section 4.2, steps 1--5).

    1. an augmented factorization of all observed entries;
    2. residuals ``|e_ij|``, the robust scale and a threshold;
    3. the entries beyond it down-weighted, the factorization re-estimated as a
       weighted missing-data problem (masked ALS, warm-started);
    4. residuals of *all* observed entries against the new fit, a new threshold (a
       wrongly rejected entry comes back). Steps 3--4 repeat over the passes of
       :func:`rank_schedule`, with a threshold falling from ``SCHEDULE`` times the final
       one; then the final inliers by :func:`classify`;
    5. a weighted factorization of the inliers (if ``weighted``).

    Steps 6--7 (metric upgrade, per-frame structure) follow in the pipeline.

    Gradients: the passes run on ``stop_gradient(W)``; their decisions -- the inlier set
    and step 5's weights -- are constants, and the final weighted fit is re-attached to
    ``W`` by :func:`jaxnrsfm.implicit.attach`.

    Two departures from a literal reading, both measured on the paper's cube, both
    needed to match the oracle there:

    - **The rank grows over the passes** (rigid rank 4, then +2 per pass up to
      ``rank``). The cube's three weakest deformation modes lie below the noise (and far
      below the outliers' singular values), so a full-rank first fit spends those
      dimensions on the tracks of the few points with the most outliers and reproduces
      them exactly: their outliers have zero residual and are never found. A low-rank
      fit has no spare dimension to absorb them; the higher ranks are added once most
      outliers are down-weighted.
    - **Rejection is soft during the passes**: an entry has weight
      ``1 / (1 + (|e| / (f sigma_hat))^2)`` (Cauchy), not 0 or 1. A low-rank pass
      misfits genuine deformation; hard rejection then dropped a frame's whole moving
      part, and nothing brought it back.
    """
    W_in, W = W, jax.lax.stop_gradient(W)  # the passes' decisions are constants to the gradient
    ranks = rank_schedule(rank, passes)
    factors = (threshold or 4.0) * np.geomspace(SCHEDULE, 1.0, len(ranks))
    budget = dict(max_steps=max_steps, rtol=max(rtol, PASS_RTOL))
    M, S, _, _ = initial_fit(W, visible, ranks[0], complete=complete, **budget)
    weights, kept = visible.astype(W.dtype), visible
    for r, factor in zip(ranks, factors, strict=True):
        if r > M.shape[1]:
            M = _grow(W, weights, M, S, r)
            M, S, _, _ = masked_als(W, weights, M, **budget)
        errors = entry_errors(W, M @ S)
        bound = factor * robust_scale(errors, kept)
        kept = visible & (errors <= bound)
        weights = jnp.where(visible, 1.0 / (1.0 + (errors / bound) ** 2), 0.0)
        M, S, _, _ = masked_als(W, weights, M, **budget)
    inliers, sigma, _ = classify(W, M @ S, visible, threshold, kept)
    weights = inliers.astype(W.dtype)
    if weighted:
        errors = jnp.where(inliers, entry_errors(W, M @ S), 0.0)
        frame = jnp.sqrt(jnp.sum(errors**2, 1) / jnp.maximum(inliers.sum(1), 1))
        point = jnp.sqrt(jnp.sum(errors**2, 0) / jnp.maximum(inliers.sum(0), 1))
        ratio = sigma**2 / jnp.maximum(frame[:, None] * point[None, :], jnp.finfo(W.dtype).tiny)
        weights = jnp.where(inliers, jnp.clip(ratio, 0.1, 10.0), 0.0)
    weights = jnp.where(visible & ~inliers, ANCHOR, weights)
    M, S, steps, converged = masked_als(W, weights, M, max_steps=max_steps, rtol=rtol)
    _, M, S = attach(W_in, weights, M @ S, rank)
    return finish(W_in, inliers, M, S, _zero_translations(W), steps, converged)


def huynh(
    W: Float[Array, "2m n"],
    visible: Bool[Array, "m n"],
    *,
    rank: int,
    complete: bool,
    iterations: int = 10,
    start: float = 6.0,
    end: float = 2.5,
    max_steps: int = 500,
    rtol: float = 1e-10,
) -> Factorization:
    """Huynh, Hartley & Heyden (2003): outlier correction with pseudo observations.

    Each iteration fits the (corrected) tracks by least squares, then replaces every
    observation by a pseudo observation ``w_hat_ij + psi(e_ij)``, where ``psi`` clips the
    residual to length ``c * sigma_hat`` (Huber's influence function), with ``c``
    decreasing geometrically from ``start`` to ``end`` over the ``iterations``. The
    entries it reports as outliers are chosen by :func:`classify`, the rule of
    :func:`wang`, so that detection can be compared.
    """
    factors = jnp.geomspace(start, end, iterations).astype(W.dtype)
    M, S, _, _ = initial_fit(W, visible, rank, complete=complete, max_steps=max_steps, rtol=rtol)
    mask = row_mask(visible)

    def correct(carry, c):
        M, S, _, _, _ = carry
        fit = M @ S
        errors = entry_errors(W, fit)
        bound = c * robust_scale(errors, visible)
        shrink = jnp.minimum(1.0, bound / jnp.maximum(errors, jnp.finfo(W.dtype).tiny))
        pseudo = jnp.where(mask, fit + (W - fit) * row_mask(shrink), 0.0)
        if complete:
            M, S = svd_factors(pseudo, rank)
            steps, converged = jnp.array(0), jnp.array(True)
        else:
            M, S, steps, converged = masked_als(pseudo, visible, M, max_steps=max_steps, rtol=rtol)
        return (M, S, visible & (errors <= bound), steps, converged), None

    init = (M, S, visible, jnp.array(0), jnp.array(True))
    (M, S, _, steps, converged), _ = jax.lax.scan(correct, init, factors)
    inliers, _, _ = classify(W, M @ S, visible)
    return finish(W, inliers, M, S, _zero_translations(W), steps, converged)


def ke_kanade(
    W: Float[Array, "2m n"],
    visible: Bool[Array, "m n"],
    *,
    rank: int,
    complete: bool,
    threshold: float | None = None,
    max_steps: int = 100,
    rtol: float = 1e-4,
) -> Factorization:
    """Ke & Kanade (2005): L1-norm factorization by alternating linear programs
    (:func:`jaxnrsfm.l1.ke_kanade`), started from the least-squares fit, until a sweep
    lowers the L1 cost by less than ``rtol`` of itself (on the cube, ``1e-4`` took 7
    sweeps where ``1e-6`` took 13-15, and moved the error by less than 0.1%). The entries it
    reports as outliers are chosen by :func:`classify`, the rule of :func:`wang`, so
    that detection can be compared."""
    M, _, _, _ = initial_fit(W, visible, rank, complete=complete)
    M, S, steps, converged = ke_kanade_l1(W, visible, M, max_steps=max_steps, rtol=rtol)
    inliers, _, _ = classify(W, M @ S, visible, threshold)
    return finish(W, inliers, M, S, _zero_translations(W), steps, converged)


def huber(
    W: Float[Array, "2m n"],
    visible: Bool[Array, "m n"],
    *,
    rank: int,
    complete: bool,
    delta: float | Float[Array, ""] | None = 1.345,
    threshold: float | None = None,
    max_steps: int = 500,
    rtol: float = 1e-10,
) -> Factorization:
    """The general robust solver (:mod:`jaxnrsfm.objective`) from the least-squares fit:
    Huber loss with ``delta`` robust scales (the classic 1.345, 95% efficient under
    Gaussian noise), or the L1 loss when ``delta`` is ``None``. The scale is
    :func:`classify`'s on the least-squares residuals; the reported outliers are chosen by
    :func:`classify` too. Gradients: LM runs on constants; the least-squares fit (hence
    the scale) and the Huber solution are re-attached to ``W`` and ``delta`` (which may be
    traced) by :func:`jaxnrsfm.implicit.attach`."""
    M, S, _, _ = least_squares_fit(W, visible, rank, complete=complete, max_steps=max_steps, rtol=rtol)
    _, sigma, _ = classify(W, M @ S, visible, threshold)
    d = (L1_DELTA if delta is None else delta) * sigma
    constant = jax.lax.stop_gradient
    M, S, steps, converged = robust_factorize(
        constant(W), visible, constant(M), constant(S), constant(d), max_steps=max_steps, rtol=max(rtol, 1e-8)
    )
    _, M, S = attach(W, visible, M @ S, rank, d)
    inliers, _, _ = classify(W, M @ S, visible, threshold)
    return finish(W, inliers, M, S, _zero_translations(W), steps, converged)


def oracle(
    W: Float[Array, "2m n"],
    visible: Bool[Array, "m n"],
    outliers: Bool[Array, "m n"],
    *,
    rank: int,
    max_steps: int = 500,
    rtol: float = 1e-10,
) -> Factorization:
    """The least-squares factorization told the true ``outliers``: the best any outlier
    rejection can do, the yardstick of the paper's comparison."""
    inliers = visible & ~outliers
    M, S, steps, converged = least_squares_fit(W, inliers, rank, complete=False, max_steps=max_steps, rtol=rtol)
    return finish(W, inliers, M, S, _zero_translations(W), steps, converged)
