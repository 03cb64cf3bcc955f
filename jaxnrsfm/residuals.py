"""The residual model that tells outliers from inliers: a heavy-tailed law for the
inliers' reprojection errors, uniform outliers, and the decision between them.

The paper detects outliers from the length ``a = |e_ij|`` of each entry's 2-vector
residual (eq. 16); its reference for the threshold (Wang et al., CRV 2013) is not
available. The model here is a two-component mixture fitted to the observed lengths,

    ``p(a) = (1 - eps) p_in(a) + eps / A``,   ``A = max a``,

with uniform outliers (as in MLESAC, Torr & Zisserman 2000) and inliers whose 2-vector
residual is Student-t with scale ``sigma`` and ``nu`` degrees of freedom:

    ``p_in(a) = (a / sigma^2) (1 + a^2 / (nu sigma^2))^(-(nu + 2) / 2)``

(``nu = inf``: the Rayleigh law of Gaussian image noise). ``(eps, sigma)`` are fitted by
maximum likelihood (EM with Newton steps) for the ``nu`` of `NU` that `fit`'s search visits,
and the ``nu`` of highest likelihood is kept. An entry is an inlier where the inlier component is the more
likely, ``(1 - eps) p_in(a) >= eps / A``, on the decreasing branch of ``p_in``: that is
one threshold ``a <= T``.

Why a heavy-tailed inlier law: on the paper's cube the noise is Gaussian, the fitted
``nu`` is large, and ``T`` is the Bayes boundary between Rayleigh inliers and uniform
outliers (3.4--4.2 ``sigma`` there). On real motion capture the rank-(3k+1) model misfit
is heavy-tailed: at ``sigma`` from the median, the 99.9% quantile of the clean residuals
is 7--9 ``sigma`` and the largest 8--16 ``sigma`` on the Akhter sequences (choose_k's k),
so a Rayleigh threshold (at most 6 ``sigma``) rejected 5--10% of the clean entries; the
injected outliers of the benchmark (2.5--12.5% of the tracks' extent) are 17--32 ``sigma``.
The fitted ``nu`` (2--4 there) puts ``T`` in that gap.

Why a floor on the scale: on exact tracks (noise-free synthetic data, a sweep starting at
``sigma = 0``) the residuals are the solver's round-off, and a median scale of them makes
every numerical residual an outlier. ``sigma`` is therefore at least
`scale_floor`, ``sqrt(eps)`` of the tracks' RMS in their dtype: the precision to
which a least-squares fit determines its values.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

RAYLEIGH_MEDIAN = float(np.sqrt(2 * np.log(2.0)))
"""Median of a Rayleigh variable of unit scale: ``|e|`` for ``e ~ N(0, I_2)``."""

NU = (3.0, 4.0, 6.0, 10.0, 20.0, 50.0, float("inf"))
"""Degrees of freedom of the inlier law tried by `fit`; ``inf`` is Rayleigh. All
above 2: the inliers are fitted by least squares, which presumes a finite variance (with
``nu = 1`` or 2 the inlier tail also explained the outliers: on Akhter's stretch with 10%
outliers the fit took ``nu = 1``, a threshold of 56 ``sigma`` and a recall of 0.87)."""

FIT_STEPS = 25
"""Most steps of the fit per ``nu``, each a safeguarded Newton step on ``(log sigma,
logit eps)`` or, where it is refused, an EM step. A fit stops earlier, once a step moves
them by less than ``sqrt(eps)`` of the dtype: 6 steps on the paper's cube, 5-16 on the
Akhter sequences' rank-6 residuals. Plain EM crawls on motion capture, where the
likelihood is flat in the outlier fraction: 40 EM steps (the earlier fixed count) left
the threshold of the rank-3k residuals of the Akhter sequences (k = 2, 3) up to 22% from
its limit (dance, k = 2), 80 steps up to 11%; now all ten agree with 20000 EM steps to
the 4 digits compared. Rayleigh residuals with lognormal per-frame and per-point scales
are such a case too (`tests/test_robust.py`)."""

MIN_FACTOR = 3.0
"""Smallest threshold multiple ``T / sigma``: below it an inlier is lost with probability
``exp(-9/2) = 1.1%`` even under Gaussian noise."""

MIN_EPS = 1e-6
"""Smallest outlier fraction of the fit (keeps the logarithms finite on clean data)."""


class ResidualModel(eqx.Module):
    """The fitted mixture of `fit`."""

    sigma: Float[Array, ""]
    """Scale of the inlier law (image units), at least `scale_floor`."""
    nu: Float[Array, ""]
    """Degrees of freedom of the inlier law (``inf``: Rayleigh)."""
    eps: Float[Array, ""]
    """Outlier fraction."""
    threshold: Float[Array, ""]
    """``T``: residual lengths up to it are inliers."""
    exact: Bool[Array, ""]
    """True when the residuals are below the precision floor: exact tracks."""


def track_rms(W: Float[Array, "2m n"], visible: Bool[Array, "m n"]) -> Float[Array, ""]:
    """The RMS of the observed coordinates (a positive scale of the tracks' numbers)."""
    mask = jnp.repeat(visible, 2, axis=0)
    rms = jnp.sqrt(jnp.sum(jnp.where(mask, W, 0.0) ** 2) / jnp.maximum(mask.sum(), 1))
    return jnp.maximum(rms, jnp.finfo(W.dtype).tiny)


def scale_floor(W: Float[Array, "2m n"], visible: Bool[Array, "m n"]) -> Float[Array, ""]:
    """``sqrt(eps)`` of the RMS of the observed tracks, in their dtype (module docstring)."""
    return jnp.sqrt(jnp.finfo(W.dtype).eps) * track_rms(W, visible)


def sorted_lengths(a: Float[Array, "..."]) -> Float[Array, " N"]:
    """The lengths ``a`` (non-negative, ``inf`` and NaN allowed), flattened and sorted in
    ascending order, NaN last: as ``jnp.sort``, by sorting their bit patterns as integers,
    which orders non-negative IEEE floats alike. XLA:CPU sorts integers with a plain
    comparison and floats with a total-order comparator: 25200 float64 lengths (the paper's
    cube) in 1.4 ms instead of 8.3 ms, and a robust trial sorts 16 times."""
    integer = jnp.dtype(f"int{8 * a.dtype.itemsize}")
    bits = jax.lax.bitcast_convert_type(jnp.abs(a).ravel(), integer)  # abs: -0.0 sorts as 0.0
    return jax.lax.bitcast_convert_type(jnp.sort(bits), a.dtype)


def masked_median(a: Float[Array, "..."], mask: Bool[Array, "..."]) -> Float[Array, ""]:
    """The median of the lengths ``a`` in ``mask``, NaN ones left out (NaN where none is
    left): ``jnp.nanmedian(jnp.where(mask, a, nan))``, computed alike from `sorted_lengths`."""
    valid = mask & ~jnp.isnan(a)
    x = sorted_lengths(jnp.where(valid, a, jnp.inf))
    count = valid.sum().astype(a.dtype)
    # As jnp.nanmedian: linear interpolation between the two middle values.
    q = 0.5 * (count - 1)
    low, high = jnp.floor(q), jnp.ceil(q)

    def at(i):
        return x[jnp.clip(i, 0, x.size - 1).astype(int)]

    below, above = at(low), at(high)
    middle = jnp.where(low == high, below, below * (1 - (q - low)) + above * (q - low))
    return jnp.where(count > 0, middle, jnp.nan)


def median_scale(errors: Float[Array, "m n"], mask: Bool[Array, "m n"], floor: Float[Array, ""]) -> Float[Array, ""]:
    """``max(median(|e_ij|) / sqrt(2 ln 2), floor)`` over the entries in ``mask``: the
    Rayleigh scale of Gaussian residuals, robust to fewer than half outliers."""
    return jnp.maximum(masked_median(errors, mask) / RAYLEIGH_MEDIAN, floor)


def log_inlier_density(a: Float[Array, "..."], sigma: Float[Array, ""], nu: Float[Array, ""]) -> Float[Array, "..."]:
    """``log p_in(a)`` of the residual length (module docstring); ``nu = inf`` is Rayleigh."""
    return _log_length(a) - 2 * jnp.log(sigma) + _log_tail((a / sigma) ** 2, nu)


def _log_length(a):
    # log a, finite at a = 0.
    return jnp.log(jnp.maximum(a, jnp.finfo(a.dtype).tiny))


def _log_tail(z, nu):
    # The part of log p_in that depends on z = (a / sigma)^2.
    finite = jnp.isfinite(nu)
    nu_ = jnp.where(finite, nu, 1.0)  # the Rayleigh branch must not see inf (double where)
    return jnp.where(finite, -(nu_ + 2) / 2 * jnp.log1p(z / nu_), -z / 2)


def _em(x, data, nu, mask):
    # One EM step for (eps, sigma) at fixed nu from x = (log sigma, logit eps); the
    # log-likelihood at x, its gradient and its Hessian in x (in closed form: no nested
    # autodiff to trace). A t-distributed 2-vector is Gaussian given a Gamma-distributed
    # precision; its expected value u = (nu + 2) / (nu + a^2/sigma^2) down-weights the tail
    # in the scale update (1 for Rayleigh).
    finite = jnp.isfinite(nu)
    nu_ = jnp.where(finite, nu, 1.0)  # the Rayleigh branch must not see inf (double where)
    a, log_a, A, floor = data
    sigma, eps = jnp.exp(x[0]), jax.nn.sigmoid(x[1])
    z = (a / sigma) ** 2
    # The log-odds of inlier against outlier, and from them the responsibility
    # (sigmoid) and the log-likelihood (log_out + softplus) with one exponential.
    log_out = jnp.log(eps) - jnp.log(A)
    odds = jnp.log1p(-eps) + log_a - 2 * x[0] + _log_tail(z, nu) - log_out
    small = jnp.exp(-jnp.abs(odds))
    r = jnp.where(mask, jnp.where(odds >= 0, 1.0, small) / (1.0 + small), 0.0)
    log_likelihood = jnp.sum(jnp.where(mask, log_out + jnp.maximum(odds, 0.0) + jnp.log1p(small), 0.0))
    u = jnp.where(finite, (nu_ + 2) / (nu_ + z), 1.0)
    count = jnp.maximum(mask.sum(), 1)
    # d odds / d log sigma = u z - 2 and d odds / d logit eps = -1, so with
    # r (1 - r) = small / (1 + small)^2 and d(u z)/d log sigma = -2 z w:
    slope = u * z - 2
    spread = jnp.where(mask, small / (1.0 + small) ** 2, 0.0)
    w = jnp.where(finite, u * nu_ / (nu_ + z), 1.0)
    gradient = jnp.stack([jnp.sum(r * slope), count * (1 - eps) - jnp.sum(r)])
    cross = -jnp.sum(spread * slope)
    hessian = jnp.array(
        [
            [jnp.sum(spread * slope**2 - 2 * r * w * z), cross],
            [cross, jnp.sum(spread) - count * eps * (1 - eps)],
        ]
    )
    sigma = jnp.sqrt(jnp.sum(r * u * a**2) / jnp.maximum(2 * jnp.sum(r), 1.0))
    eps = jnp.clip(1.0 - jnp.sum(r) / count, MIN_EPS, 0.5)
    return _unconstrained(jnp.maximum(sigma, floor), eps), log_likelihood, gradient, hessian


@jax.custom_jvp
def _at_fixed_point(x, data, nu, mask):
    # x, EM's fixed point x = F(x, data) (`_em`), as a function of data: in value x itself;
    # its derivative by the implicit function theorem, dx = (I - F_x)^-1 F_data ddata, not
    # through the loop that found it (which reverse mode cannot differentiate). Huber's
    # scale is differentiated. A rule, so that an undifferentiated fit does not pay for it:
    # F_x's two forward-mode passes ran in every fit (then seven laws a fit; now it applies
    # to the kept law alone, see `fit`).
    return x


@_at_fixed_point.defjvp
def _at_fixed_point_jvp(primals, tangents):
    x, data, nu, mask = primals
    _, t_data, _, _ = tangents
    _, F_data = jax.jvp(lambda data: _em(x, data, nu, mask)[0], (data,), (t_data,))
    I_minus_J = jnp.eye(2, dtype=x.dtype) - jax.jacfwd(lambda x: _em(x, data, nu, mask)[0])(x)
    # A singular system (EM's map with a unit eigenvalue) would make the tangent NaN.
    singular = I_minus_J[0, 0] * I_minus_J[1, 1] == I_minus_J[0, 1] * I_minus_J[1, 0]
    return x, _solve2(jnp.where(singular, jnp.eye(2, dtype=x.dtype), I_minus_J), F_data)


def _fit_nu(fixed, mask, sigma0, eps0, nu):
    # (log sigma, logit eps) at fixed nu by EM with Newton steps (`_em`), and the
    # log-likelihood there; no derivative (`fit` attaches it to the law it keeps).
    def em(x, data):
        return _em(x, data, nu, mask)

    a = fixed[0]
    tol = jnp.sqrt(jnp.finfo(a.dtype).eps)
    slack = 100 * jnp.finfo(a.dtype).eps

    # The floor on sigma and eps in [MIN_EPS, 1/2], in those coordinates.
    low = jnp.stack([jnp.log(fixed[3]), jnp.log(jnp.asarray(MIN_EPS, a.dtype)) - jnp.log1p(-MIN_EPS)])
    bounds = low, jnp.array([jnp.inf, 0.0], a.dtype)

    def newton(x0, here):
        # The Newton step from x0 (its EM pass ``here``), and whether it may be taken: the
        # Hessian negative definite and the step finite.
        _, _, gradient, H = here
        x2 = jnp.clip(x0 - _solve2(H, gradient), *bounds)
        return x2, (H[0, 0] < 0) & (H[0, 0] * H[1, 1] > H[0, 1] * H[1, 0]) & jnp.all(jnp.isfinite(x2))

    def cycle(carry):
        # A Newton step on the likelihood, kept where it may be taken and the likelihood
        # did not fall beyond its round-off; otherwise an EM step (which never lowers it).
        # EM alone crawls where the likelihood is flat in eps; so did SQUAREM, tried first:
        # its extrapolations overshot there and were refused (1.7% off the threshold after
        # 25 cycles, lognormal scales). The carry holds the EM pass at the current point: a
        # kept Newton step's pass is the next cycle's, and only a refused one costs a third.
        x0, here, cycles, _ = carry
        x2, sound = newton(x0, here)
        there = em(x2, fixed)
        take = sound & (there[1] >= here[1] - slack * jnp.abs(here[1]))
        x = jnp.where(take, x2, here[0])
        return x, jax.lax.cond(take, lambda: there, lambda: em(here[0], fixed)), cycles + 1, jnp.max(jnp.abs(x - x0))

    def converged(carry):
        # A Newton step below the tolerance: quadratic convergence puts the point after it
        # at round-off from the fixed point, so it is taken without the EM pass that would
        # only confirm it (one pass in five of a fit on the paper's cube).
        x0, here, _, _ = carry
        x2, sound = newton(x0, here)
        return sound & (jnp.max(jnp.abs(x2 - x0)) <= tol), x2

    def going(carry):
        _, _, cycles, change = carry
        return (cycles < FIT_STEPS) & (change > tol) & ~converged(carry)[0]

    x0 = jax.lax.stop_gradient(_unconstrained(sigma0.astype(a.dtype), eps0.astype(a.dtype)))
    start = (x0, em(x0, fixed), 0, jnp.asarray(jnp.inf, a.dtype))
    # The loop's carry holds the EM pass at its last x, and with it the log-likelihood there
    # (at a final Newton step below the tolerance, its change is of second order).
    last = jax.lax.while_loop(going, cycle, start)
    done, x2 = converged(last)
    x, (_, log_likelihood, _, _), _, _ = last
    return jnp.where(done, x2, x), jnp.where(jnp.isfinite(log_likelihood), log_likelihood, -jnp.inf)


def _best_law(fixed, mask, sigma0, eps0, nus):
    # The nu of highest likelihood among `nus` (increasing), and its (log sigma, logit eps),
    # without fitting every law: both ends first, then inward from the better end while the
    # likelihood rises. The likelihood's profile in nu had its maximum where this search
    # stops in all 127 fits tried (the paper's cube at sigma 0.5-5 with 0-40% outliers, the
    # five Akhter sequences clean, with 10% outliers and with 30% missing; one profile had
    # two maxima, its highest at nu = 3 and the other at 50), at 3.4 laws a fit, not 7: on
    # the cube the search stops after nu = 3, inf, 50 (and 20), on motion capture after
    # 3, inf, 4. One law after the other in one loop (one copy of the fit in the program),
    # not vmapped in lockstep: each fit stops at its own convergence, and its cycle's cond
    # skips an EM pass where the Newton step is kept.
    n = len(nus)

    def visit(carry):
        count, i, step, best, _ = carry
        x, ll = _fit_nu(fixed, mask, sigma0, eps0, nus[i])
        rises = (ll > best[2]) | (count == 0)
        best = jax.tree.map(lambda new, old: jnp.where(rises, new, old), (i, x, ll), best)
        # After both ends (count 1), the walk starts from the better one; it ends before the
        # far end, which lies below the start and so below anything after it.
        step = jnp.where(count == 1, jnp.where(rises, -1, 1), step)
        following = jnp.where(count == 1, best[0], i) + step
        more = (count == 0) | (((count == 1) | rises) & (following != jnp.where(step > 0, n - 1, 0)))
        return count + 1, jnp.where(count == 0, n - 1, following), step, best, more

    dtype = fixed[0].dtype
    nowhere = (jnp.array(0), jnp.zeros(2, dtype), jnp.asarray(-jnp.inf, dtype))
    start = (jnp.array(0), jnp.array(0), jnp.array(1), nowhere, jnp.array(True))
    _, _, _, (i, x, _), _ = jax.lax.while_loop(lambda carry: carry[4], visit, start)
    return nus[i], x


def _solve2(A, b):
    # A 2 x 2 system in closed form: no LAPACK call (two independent batched LAPACK calls
    # in one program have deadlocked on a 2-core CPU, README).
    det = A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]
    return jnp.stack([A[1, 1] * b[0] - A[0, 1] * b[1], A[0, 0] * b[1] - A[1, 0] * b[0]]) / det


def _unconstrained(sigma, eps):
    # (log sigma, logit eps): the coordinates of the Newton steps, in which any point is a
    # valid scale and fraction.
    return jnp.stack([jnp.log(sigma), jnp.log(eps) - jnp.log1p(-eps)])


def _threshold(sigma, nu, eps, A):
    # The length T beyond the inlier law's mode where (1 - eps) p_in(T) = eps / A, by
    # bisection on a logarithmic scale (p_in decreases there). None such below A: all in.
    finite = jnp.isfinite(nu)
    nu_ = jnp.where(finite, nu, 1.0)  # double where: no inf in the unused branch's gradient
    mode = sigma * jnp.where(finite, jnp.sqrt(nu_ / (nu_ + 1)), 1.0)
    target = jnp.log(eps) - jnp.log(A) - jnp.log1p(-eps)

    def bisect(_, bounds):
        lo, hi = bounds
        mid = jnp.sqrt(lo * hi)
        inside = log_inlier_density(mid, sigma, nu) >= target
        return jnp.where(inside, mid, lo), jnp.where(inside, hi, mid)

    hi = jnp.maximum(A, mode) * 2
    lo, _ = jax.lax.fori_loop(0, 60, bisect, (mode, hi))
    return jnp.maximum(lo, MIN_FACTOR * sigma)


def fit(errors: Float[Array, "m n"], visible: Bool[Array, "m n"], floor: Float[Array, ""]) -> ResidualModel:
    """Fit the mixture of the module docstring to the observed residual lengths.

    **Arguments:**

    - `errors`: ``|e_ij|``, ``(m, n)``.
    - `visible`: the entries to model (observed ones).
    - `floor`: the smallest scale, `scale_floor` of the tracks.

    **Returns:** a `ResidualModel`; inliers are ``visible & (errors <= threshold)``.
    """
    data, sigma0, eps0 = _start(errors, visible, floor)
    nus = jnp.asarray(NU, errors.dtype)
    nu, x = _best_law(jax.lax.stop_gradient(data), visible, sigma0, eps0, nus)
    x = _at_fixed_point(x, data, nu, visible)
    sigma, eps = jnp.exp(x[0]), jax.nn.sigmoid(x[1])
    exact = masked_median(errors, visible) / RAYLEIGH_MEDIAN < floor
    return ResidualModel(sigma, nu, eps, _threshold(sigma, nu, eps, data[2]), exact)


def _start(errors, visible, floor):
    # What every law's fit is given: the data of `_em` (the lengths, their logarithm, the
    # outliers' range A and the floor) and the start (sigma0, eps0): the median scale and
    # the fraction of lengths beyond 6 of it.
    a = jnp.where(visible, errors, 0.0)
    A = jnp.maximum(jnp.max(a), floor)
    sigma0 = median_scale(errors, visible, floor)
    eps0 = jnp.clip(jnp.sum(visible & (errors > 6 * sigma0)) / jnp.maximum(visible.sum(), 1), 1e-3, 0.5)
    # log p_in(a) = log a - 2 log sigma + tail (log_inlier_density), with log a computed once.
    return (a, _log_length(a), A, floor), sigma0, eps0


def inlier_cdf(a: Float[Array, "..."], sigma: Float[Array, ""], nu: Float[Array, ""]) -> Float[Array, "..."]:
    """Cumulative distribution of the inlier law's lengths: ``1 - (1 + a^2/(nu sigma^2))^(-nu/2)``
    (``1 - exp(-a^2 / (2 sigma^2))`` for Rayleigh)."""
    z = (a / sigma) ** 2
    finite = jnp.isfinite(nu)
    nu_ = jnp.where(finite, nu, 1.0)
    return jnp.where(finite, -jnp.expm1(-nu_ / 2 * jnp.log1p(z / nu_)), -jnp.expm1(-z / 2))


def misfit(errors: Float[Array, "m n"], inliers: Bool[Array, "m n"], model: ResidualModel) -> Float[Array, ""]:
    """Kolmogorov--Smirnov distance between the kept residual lengths and the fitted
    inlier law truncated at the threshold: the check that the entries called inliers
    are one population. Zero for exact tracks (their residuals are round-off)."""
    x = sorted_lengths(jnp.where(inliers, errors, jnp.inf))
    count = jnp.maximum(inliers.sum(), 1)
    rank = jnp.arange(1, x.size + 1, dtype=errors.dtype)
    cut = inlier_cdf(model.threshold, model.sigma, model.nu)
    law = inlier_cdf(jnp.where(jnp.isfinite(x), x, 0.0), model.sigma, model.nu) / cut
    gap = jnp.maximum(jnp.abs(law - rank / count), jnp.abs(law - (rank - 1) / count))
    return jnp.where(model.exact, 0.0, jnp.max(jnp.where(rank <= count, gap, 0.0)))
