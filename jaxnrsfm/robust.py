"""Outlier handling: the paper's robust algorithm (section 4.2), the Huynh et al.
baseline, the Ke & Kanade L1 baseline and an oracle told the true outliers.

All strategies work on the augmented rank-(3k+1) factorization, need no registration,
and return a `jaxnrsfm.factorize.Factorization` whose ``inliers`` say which
observed entries were kept. They are pure and jit-compiled; a batch vmaps them.

**Residual model and threshold** (`jaxnrsfm.residuals`): the residual lengths
``|e_ij|`` (eq. 16) are fitted by a mixture of heavy-tailed (Student-t) inliers and
uniform outliers, and an entry is an outlier where the outlier component is the more
likely: the Bayes boundary of MLESAC (Torr & Zisserman 2000) with an inlier law that also
fits the heavy-tailed model misfit of real tracks. Every scale is floored at the tracks'
precision (`jaxnrsfm.residuals.scale_floor`), so that exact tracks have no
numerical "outliers". A fixed ``threshold`` (a multiple of the fitted scale) overrides
the boundary.

**Weights (step 5).** Entries are weighted by a per-frame and per-point model of the
residual variance, ``sigma_ij = sigma_i sigma_j / sigma`` with ``sigma_i``, ``sigma_j``
and ``sigma`` the RMS inlier residuals of frame ``i``, of point ``j`` and of all: weight
``sigma^2 / (sigma_i sigma_j)``, clipped to ``[1/10, 10]`` so that a frame or point with
few inliers cannot dominate. With homogeneous noise the weights are all near one.
"""

from functools import partial
from typing import Literal

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from . import residuals, temporal
from .factorize import (
    Factorization,
    finish,
    initial_fit,
    least_squares_fit,
    masked_als,
    motion_given_structure,
    structure_given_motion,
)
from .implicit import attach
from .l1 import ke_kanade as ke_kanade_l1
from .linalg import leading_directions, svd_factors
from .metrics import entry_errors
from .objective import L1_DELTA, robust_factorize
from .tracks import row_mask

SCHEDULE = 3.0
"""The first rejection pass's threshold is this many times the final one, falling
geometrically: the first fit is pulled by every outlier, and each cleaner fit earns a
tighter threshold."""

PASS_FACTOR = 4.0
"""The rejection passes' final soft-rejection scale, in robust (median) scales: the
passes only set the weights of the next fit; the inliers come from the residual model."""

PASS_DROP = 3.0
"""A pass's soft-rejection bound is at least ``1 / PASS_DROP`` of the previous pass's. On
exact tracks the median scale collapses to the floor once a pass fits the rigid majority
exactly, and a bound at the floor soft-rejects every moving entry before the ranks that
explain the deformation are added: on the cube at sigma 0 with 10% outliers the passes then
settled on a wrong consensus (a frame's moving face rejected) in 3 of 8 trials, and in none
with this limit. With noise (sigma >= 1, the Fig. 5 protocol) it never binds."""

RIGID_RANK = 4
"""The rank the robust algorithm starts from: a rigid object's augmented rank."""

PASS_RTOL = 1e-4
"""Convergence tolerance of the fits that only decide (the final fits use the caller's):
the rejection passes, which set the next weights, and the least-squares fits of the
inliers that take rejected entries back and that `row_column_check` checks. On the cube
(sigma 2, 20% outliers) 1e-6 instead of 1e-10 in the passes took a third of the ALS
sweeps and changed at most 2 of 25200 final inlier labels. 1e-4 in all of them, against
1e-6 in the passes and the caller's 1e-10 in the others, on the paper's cube (20 trials,
seeds 1000-1019, one core, XLA's defaults): the robust fit 165 -> 128 ms a trial at sigma
2 with 10% outliers, its mean error over the oracle's 1.0045 -> 1.0047 (no trial beyond
1.1 times the oracle either way).

A caller who asks for a tighter solve than the default gets tighter decisions too
(`PASS_RTOL_RATIO`): the output of a trial is a function of the tracks through the
decisions' fits (the residual model's scale weighs the rejected entries), and a fit stopped
at 1e-4 stops after a number of sweeps that jumps as the tracks move, which left the output
reproducible only to ~1e-12 relative (the 12-frame cube, sigma 1, 10% outliers, rtol 1e-14:
central differences of step 1e-5 to 1e-3 agreed with the derivatives to 5e-7 - 4e-4, not
monotone in the step; with the deciding fits at 1e-8, to 4e-9 - 3e-7)."""

PASS_RTOL_RATIO = 1e6
"""The deciding fits stop at `PASS_RTOL`, or at this many times the caller's tolerance where
that is tighter (the default 1e-10 gives 1e-4 either way), and never at a tighter one than
the caller's."""


def anchor_weights(
    W: Float[Array, "2m n"], visible: Bool[Array, "m n"], inliers: Bool[Array, "m n"], sigma: Float[Array, ""]
) -> Float[Array, "m n"]:
    """The weights of the hard-inlier fits: 1 for an inlier, ``(sigma / rms)^2`` for a
    rejected entry (``sigma`` the inliers' residual scale, ``rms`` the tracks',
    `jaxnrsfm.residuals.track_rms`), at least ``sqrt(eps)`` of the dtype.

    A rejected entry is not dropped: it stays an observation with the variance of the
    outlier law, which spreads over the image (``rms^2``), where an inlier's is
    ``sigma^2`` -- the weights of least squares under that mixture. Dropped outright (or
    kept with a weight far below that), it becomes missing data, and where a frame's
    outliers outnumber what the rank-``r`` model can spare, nothing bounds the fit's
    prediction there. Measured on the paper's cube (100 frames, 20% outliers, seed 0):
    in trial 15 at sigma 4 one frame with 72 outliers took a direction of the motion space
    for itself (its entries' leverage 0.54, the other frames' at most 0.17); with a
    rejected entry weighing ``1e-4 (sigma / rms)^2``, masked ALS drifted along it for
    1000 sweeps without converging and predicted that frame's rejected entries 2600
    units off (error 19.3 against the oracle's 1.68); with ``(sigma / rms)^2`` it
    converged in 58 sweeps, error 1.91. The pull of an outlier ``e`` away is
    ``(sigma / rms)^2 e``: on the cube (sigma 2, rms ~400) 2.5e-5 of it, 2.5e-3 units for
    an outlier 100 units off. On exact tracks the floor ``sqrt(eps)`` applies; it also
    keeps float32's gradient solve (`jaxnrsfm.implicit`) well conditioned. A
    function of ``sigma``, which is differentiated where it is (`wang`'s final fit)."""
    relative = jnp.maximum((sigma / residuals.track_rms(W, visible)) ** 2, jnp.sqrt(jnp.finfo(W.dtype).eps))
    return jnp.where(inliers, 1.0, jnp.where(visible, relative, 0.0))


def inlier_scale(errors: Float[Array, "m n"], inliers: Bool[Array, "m n"], floor: Float[Array, ""]) -> Float[Array, ""]:
    """The per-coordinate RMS of the inliers' residuals, with ``floor^2`` added to its
    square (smooth, and at least the tracks' precision, on exact tracks)."""
    kept = jnp.where(inliers, errors, 0.0)
    return jnp.sqrt(jnp.sum(kept**2) / (2 * jnp.maximum(inliers.sum(), 1)) + floor**2)


RECLASSIFY = 2
"""Rounds of `wang`'s final classification against the least-squares fit of the
previous round's inliers."""


def step_weights(
    errors: Float[Array, "m n"], inliers: Bool[Array, "m n"], floor: Float[Array, ""]
) -> Float[Array, "m n"]:
    """Step 5's weights of the inliers: ``sigma^2 / (sigma_i sigma_j)`` clipped to
    ``[1/10, 10]`` (module docstring), each RMS taken with ``floor^2`` added to its square,
    so that residuals below the tracks' precision (exact tracks) give uniform weights and
    the weights are smooth functions of the residuals there too."""
    kept = jnp.where(inliers, errors, 0.0)

    def rms(axis):
        return jnp.sqrt(jnp.sum(kept**2, axis) / jnp.maximum(inliers.sum(axis), 1) + floor**2)

    ratio = rms(None) ** 2 / (rms(1)[:, None] * rms(0)[None, :])
    return jnp.where(inliers, jnp.clip(ratio, 0.1, 10.0), 0.0)


def classify(
    W: Float[Array, "2m n"],
    fit: Float[Array, "2m n"],
    visible: Bool[Array, "m n"],
    threshold: float | None = None,
) -> tuple[Bool[Array, "m n"], residuals.ResidualModel]:
    """Observed entries that the residual model (`jaxnrsfm.residuals.fit`) calls
    inliers, and the model; a fixed ``threshold`` multiple of its scale overrides its
    boundary."""
    errors = entry_errors(W, fit)
    model = residuals.fit(errors, visible, residuals.scale_floor(W, visible))
    return visible & (errors <= _boundary(model, threshold)), model


def _boundary(model: residuals.ResidualModel, threshold: float | None) -> Float[Array, ""]:
    """The residual length above which an entry is an outlier: the model's own boundary, or
    ``threshold`` multiples of its scale."""
    return model.threshold if threshold is None else threshold * model.sigma


def _zero_translations(W):
    return jnp.zeros((W.shape[0] // 2, 2), W.dtype)


def rank_schedule(rank: int, passes: int) -> tuple[int, ...]:
    """Ranks of the rejection passes: from the rigid rank up by two to ``rank``, then at
    ``rank`` until there are ``passes`` passes in all."""
    start = min(RIGID_RANK, rank)
    ranks = (*range(start, rank, 2), rank)
    return ranks + (rank,) * max(0, passes - len(ranks))


def _grow(W, weights, M, S, used, add):
    # ``add`` new directions for a higher-rank pass, in columns used..used+add-1 of M (zero
    # until now; ``used`` traced, ``add`` static): the leading left singular vectors of the
    # weighted residual, i.e. what the lower-rank model leaves unexplained in the data it
    # currently trusts. Only a warm start for the pass's fit, so by subspace iteration
    # (linalg.leading_directions), not a full decomposition.
    new = leading_directions(row_mask(weights) * (W - M @ S), add)
    return jax.lax.dynamic_update_slice(M, new, (0, used))


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
       `rank_schedule`, with a threshold falling from ``SCHEDULE`` times the final
       one; then the final inliers by `classify`, and (``RECLASSIFY`` rounds) the
       rejected entries that the least-squares fit of the inliers explains taken back, and
       those that their own track predicts (`jaxnrsfm.temporal`; only where the
       tracks are smooth in time); then the inliers that their frame's or point's
       robust re-fit rejects, where it puts several far beyond the boundary (`row_column_check`);
    5. a weighted factorization of the inliers (if ``weighted``), with the weights of
       `step_weights` from the residuals of the inliers' least-squares fit.

    Steps 6--7 (metric upgrade, per-frame structure) follow in the pipeline.

    Gradients: the passes run on ``stop_gradient(W)``; their decisions -- the inlier set
    and the residual model that weighs the rejected entries in the inliers' least-squares
    fit -- are constants. That fit, step 5's weights and the rejected entries' weight
    computed from it (`anchor_weights`), and the final weighted fit are functions of
    ``W``, re-attached by `jaxnrsfm.implicit.attach` (the final fit, where differentiated,
    with two Newton polish steps: on exact tracks one left the differentiated value
    reproducible only to ~1e-9, too coarse for a finite-difference check; an
    undifferentiated call skips them).

    Two departures from a literal reading, both measured on the paper's cube, both
    needed to match the oracle there (and a limit on how fast the passes' bound falls,
    `PASS_DROP`, needed to be exact on noise-free tracks):

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
    factors = (threshold or PASS_FACTOR) * np.geomspace(SCHEDULE, 1.0, len(ranks))
    floor = residuals.scale_floor(W, visible)
    # The fits whose answer only decides (weights, inlier labels) stop at PASS_RTOL (or
    # tighter, where the caller asks for a tight solve: PASS_RTOL_RATIO).
    deciding = dict(max_steps=max_steps, rtol=min(max(rtol, PASS_RTOL), rtol * PASS_RTOL_RATIO))
    if complete:
        # The passes' start, a rank-RIGID_RANK fit of every entry: its leading subspace by
        # subspace iteration (linalg.leading_directions), not the SVD of the tracks (the
        # paper's cube: 0.6 ms against 7.8), and the structure given it (orthogonal columns).
        M = leading_directions(W, ranks[0])
        norms = jnp.sum(M**2, axis=0)
        S = (M.T @ W) / jnp.where(norms > 0, norms, 1.0)[:, None]
    else:
        M, S, _, _ = initial_fit(W, visible, ranks[0], complete=False, **deciding)
    weights, kept = visible.astype(W.dtype), visible
    last = jnp.zeros((), W.dtype)

    def sweep(adds, carry, step):
        # One pass (new weights from the current fit's residuals, then their fit), or, where
        # the rank grows (by one of ``adds``), the new directions and their fit: a grown
        # rank's first fit keeps the weights.
        M, S, weights, kept, last = carry
        used, pass_rank, factor = step
        reweight = used == pass_rank
        # A branch for a growth by each count in ``adds``, each its own subspace iteration (a
        # growth by one, to an odd rank, is not the first column of a growth by two).
        if adds:
            grow = [partial(_grow, W, kept, M, S, used, add) for add in adds]
            which = jnp.where(reweight, 0, 1 + jnp.searchsorted(jnp.array(adds), pass_rank - used))
            M = jax.lax.switch(which, [lambda: M, *grow])
        errors = entry_errors(W, M @ S)
        bound = jnp.maximum(factor * residuals.median_scale(errors, kept, floor), last / PASS_DROP)
        last = jnp.where(reweight, bound, last)
        kept = jnp.where(reweight, visible & (errors <= bound), kept)
        weights = jnp.where(reweight, jnp.where(visible, 1.0 / (1.0 + (errors / bound) ** 2), 0.0), weights)
        M, S, _, _ = masked_als(W, weights, M, active=jnp.arange(M.shape[1]) < pass_rank, **deciding)
        return (M, S, weights, kept, last), None

    # The schedule's steps (rank before, pass rank, bound factor): each pass, and before the
    # first pass at a higher rank its growth.
    schedule = []
    for r, factor in zip(ranks, factors, strict=True):
        used = schedule[-1][1] if schedule else ranks[0]
        schedule += [(used, r, 1.0), (r, r, factor)] if r > used else [(r, r, factor)]

    # The passes run as one loop for each width of arrays -- the next power of two at least
    # their rank, or the full rank -- the columns beyond a pass's own rank zero (masked_als's
    # ``active``): one copy of the pass's fit in the compiled program for each width, not each
    # rank, and no pass computes with more than twice its rank. On the paper's cube (k = 4:
    # six ranks, three widths; benchmarks/speed.py, 2-core CPU) against a loop for each rank:
    # the batch's program compiled in 7.8 s instead of 9.8 s (a single call's, under its
    # cheaper options, 3.4 s instead of 4.5 s), its trials as fast (76.2 and 77.7 ms), the
    # same fits to round-off (40 trials of the 30-frame cube: the same sweeps and errors).
    # One loop at the full rank halved the passes' compilation, but its trials ran 6% slower.
    def width(r):
        return min(rank, 1 << (r - 1).bit_length())

    for w in sorted({width(r) for _, r, _ in schedule}):
        group = [step for step in schedule if width(step[1]) == w]
        adds = sorted({r - used for used, r, _ in group if r > used})
        M, S = jnp.pad(M, ((0, 0), (0, w - M.shape[1]))), jnp.pad(S, ((0, w - S.shape[0]), (0, 0)))
        used, pass_rank, factor = zip(*group, strict=True)
        xs = (jnp.array(used), jnp.array(pass_rank), jnp.array(factor, W.dtype))
        (M, S, weights, kept, last), _ = jax.lax.scan(partial(sweep, adds), (M, S, weights, kept, last), xs)
    inliers, model = classify(W, M @ S, visible, threshold)
    take_back = _boundary(model, threshold)
    tight = dict(max_steps=max_steps, rtol=rtol)

    def reclassify(_, carry):
        # The passes' fit is soft-weighted and loosely converged: an entry it rejected
        # comes back if the least-squares fit of the inliers explains it (on exact tracks
        # its residual is then round-off), by the passes' residual model. Only back, and
        # by that model: where the hard inliers leave a frame or point undetermined their
        # fit is far off, and a model refitted to it (on the cube at 20% outliers and
        # sigma >= 3) took most outliers back.
        M, inliers = carry
        M, S, _, _ = masked_als(W, anchor_weights(W, visible, inliers, model.sigma), M, **deciding)
        return M, inliers | (visible & (entry_errors(W, M @ S) <= take_back))

    # Loops, not unrolled rounds: one copy of each fit in the compiled program.
    M, inliers = jax.lax.fori_loop(0, RECLASSIFY, reclassify, (M, inliers))
    # A rejected entry that continues its own track is not an outlier (jaxnrsfm.temporal).
    inliers = temporal.take_back(W, visible, inliers, take_back, model.sigma)
    # An inlier that jumps off its own track is an outlier the model kept (jaxnrsfm.temporal).
    inliers = temporal.reject_jumps(W, inliers, model.sigma, take_back / model.sigma, floor)
    # A frame or point with 25-30% outliers absorbs those it kept into its own parameters;
    # its robust re-fit, given the others, does not (row_column_check). It checks the
    # least-squares fit of the inliers, warm-started where the reclassification left it.
    M, S, _, _ = masked_als(W, anchor_weights(W, visible, inliers, model.sigma), M, **deciding)
    inliers = inliers & ~row_column_check(W, visible, inliers, M, S, _boundary(model, threshold), model.sigma)
    # The final weights are continuous functions of the tracks, through the inliers'
    # least-squares fit re-attached to W, and are differentiated as such: step 5's
    # weights of the inliers (if ``weighted``) and the rejected entries' weight, from the
    # inliers' residual scale. That scale is taken from a fit whose own rejected entries
    # weigh by it: the first fit's by the passes' model (a constant to the gradient), the
    # second's by the first fit's scale, so that the constant's part in the gradient is
    # second order (on the 12-frame cube at sigma 1 with one fit: 2.6e-5 relative from
    # finite differences, with two 5.0e-7, and 2.2e-7 at sigma 0).

    def refit(_, carry):
        M, weights, _, steps = carry
        M, S, more, _ = masked_als(W, jax.lax.stop_gradient(weights), M, **tight)
        fit, _, _ = attach(W_in, weights, M, S, rank, steps=0)
        errors = entry_errors(W_in, fit)
        return M, anchor_weights(W_in, visible, inliers, inlier_scale(errors, inliers, floor)), errors, steps + more

    weights = anchor_weights(W, visible, inliers, model.sigma)
    M, weights, errors, steps = jax.lax.fori_loop(0, 2, refit, (M, weights, jnp.zeros_like(weights), jnp.array(0)))
    if weighted:
        weights = jnp.where(inliers, step_weights(errors, inliers, floor), weights)
    M, S, more, converged = masked_als(W, jax.lax.stop_gradient(weights), M, **tight)
    _, M, S = attach(W_in, weights, M, S, rank, steps=2)
    return finish(W_in, inliers, M, S, _zero_translations(W), steps + more, converged)


ROW_COLUMN_GATE = 4
"""`row_column_check` acts on a frame or point only where its robust re-fit puts at least this
many of its inliers beyond `ROW_COLUMN_FAR` times the boundary."""

ROW_COLUMN_FAR = 2.0
"""How far beyond the residual model's boundary, in multiples of it, an inlier's residual
under its frame's or point's robust re-fit must lie to count toward `ROW_COLUMN_GATE`. It
is what tells outliers from model misfit: under the fitted inlier law an entry lies beyond
twice the boundary with probability ~1e-10 (Gaussian, boundary 3.4 scales) to ~4e-4
(Student-t with 3 degrees of freedom, boundary 12 scales, as on motion capture). On the
paper's cube (Fig. 5, 20% outliers, seed 0) the outliers that a frame had absorbed came
back at a median 2.1-5.3 times the boundary (at most 3.8-8.0) under an L1 re-fit, 12-27 of
them a frame; where the re-fit and the least-squares fit differ by chance, 2-3 entries at
most 1.5 times it. On clean motion capture (Akhter's yoga and stretch), whose misfit is
heavy-tailed and gathered on a few points, 5-13 of a point's entries lay beyond the
boundary under the re-fit, at most 1.33 times it: counting those (08b50fe, reverted)
rejected clean entries and raised yoga's e3D from 0.096 to 0.165. Picked on those trials
and sequences; on seed 2 of Fig. 5 (held out) the check took every 20%-outlier setting
within 5% of the oracle (README, "Robust methods")."""


def row_column_check(
    W: Float[Array, "2m n"],
    visible: Bool[Array, "m n"],
    inliers: Bool[Array, "m n"],
    M: Float[Array, "2m r"],
    S: Float[Array, "r n"],
    boundary: Float[Array, ""],
    scale: Float[Array, ""],
    iterations: int = 10,
) -> Bool[Array, "m n"]:
    """Inliers that their frame's or their point's robust re-fit rejects, where it puts at least
    `ROW_COLUMN_GATE` of that frame's or point's inliers beyond `ROW_COLUMN_FAR` times the
    ``boundary``.

    A frame (point) with 25-30% outliers gives the rank-r model 2r (r) free parameters that
    absorb the outliers it kept: on the paper's cube at 20% outliers (Fig. 5) that was the
    tail of trials 1.2-2.4 times the oracle's error, their recall still 0.99, the frame's
    or point's fit several sigma off. Each point's structure given ``M`` and each frame's
    motion given ``S`` is re-fitted over all its observed entries by a convex Huber-type
    loss of the entry lengths, quadratic up to the inlier ``scale`` and linear beyond
    (``iterations`` reweighted least-squares solves from the fit, weights
    ``1 / max(|e|, scale)``), which a minority of outliers cannot pull.

    The floor at ``scale`` keeps every solve well conditioned. Floored at round-off instead
    (least entry lengths, an L1 fit), 10 solves were far from converged and the check
    rejected clean entries (Fig. 5, 20% outliers, sigma 1, seed 0: mean error 0.380 ->
    0.417); it needed 30, 75 ms of a 410 ms `wang` call on the paper's cube. With the
    floor, 10 solves (~20 ms) gave the L1 fit's Fig. 5 figures: at sigma 1, 3, 4, 5 one to
    three trials in 100 moved, by at most 4%."""

    def reweight(errors):
        return jnp.where(visible, 1.0 / jnp.maximum(errors, scale), 0.0)

    def columns(_, S):
        weights = reweight(entry_errors(W, M @ S))
        return structure_given_motion(row_mask(weights) * W, weights, M, 0.0)

    def rows(_, motion):
        weights = reweight(entry_errors(W, motion @ S))
        return motion_given_structure(row_mask(weights) * W, weights, S, 0.0)

    S_robust = jax.lax.fori_loop(0, iterations, columns, S)
    M_robust = jax.lax.fori_loop(0, iterations, rows, M)

    def rejected(errors, axis):
        far = jnp.sum(inliers & (errors > ROW_COLUMN_FAR * boundary), axis, keepdims=True)
        return inliers & (errors > boundary) & (far >= ROW_COLUMN_GATE)

    return rejected(entry_errors(W, M @ S_robust), 0) | rejected(entry_errors(W, M_robust @ S), 1)


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
    entries it reports as outliers are chosen by `classify`, the rule of
    `wang`, so that detection can be compared.
    """
    factors = jnp.geomspace(start, end, iterations).astype(W.dtype)
    floor = residuals.scale_floor(W, visible)
    M, S, _, _ = initial_fit(W, visible, rank, complete=complete, max_steps=max_steps, rtol=rtol)
    mask = row_mask(visible)

    def correct(carry, c):
        M, S, _, _, _ = carry
        fit = M @ S
        errors = entry_errors(W, fit)
        bound = c * residuals.median_scale(errors, visible, floor)
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
    inliers, _ = classify(W, M @ S, visible)
    return finish(W, inliers, M, S, _zero_translations(W), steps, converged)


def ke_kanade(
    W: Float[Array, "2m n"],
    visible: Bool[Array, "m n"],
    *,
    rank: int,
    complete: bool,
    threshold: float | None = None,
    max_steps: int = 100,
    rtol: float = 1e-6,
) -> Factorization:
    """Ke & Kanade (2005): L1-norm factorization by alternating linear programs
    (`jaxnrsfm.l1.ke_kanade`), started from the least-squares fit, until a sweep
    lowers the L1 cost by less than ``rtol`` of itself. On exact tracks with outliers the
    cost is the outliers' and falls slowly in relative terms: ``1e-4`` stopped 2e-6 (Bregler
    k = 2) and 6e-6 (the 40-frame cube, precision 0.98) of the tracks' RMS from exact,
    ``1e-6`` 3e-8 and 3e-7 (precision 1) after 7 and 9 sweeps against 5 and 7; on the noisy
    cube it took 13-15 sweeps against 7 and moved the error by less than 0.1%. The entries it
    reports as outliers are chosen by `classify`, the rule of `wang`, so
    that detection can be compared."""
    M, _, _, _ = initial_fit(W, visible, rank, complete=complete)
    M, S, steps, converged = ke_kanade_l1(W, visible, M, max_steps=max_steps, rtol=rtol)
    inliers, _ = classify(W, M @ S, visible, threshold)
    return finish(W, inliers, M, S, _zero_translations(W), steps, converged)


L1_SHRINK = 0.01
"""Factor by which `_l1_continuation` shrinks the L1 fit's smoothing kink a round."""
L1_ROUNDS = 5
"""Most rounds of `_l1_continuation` after the first fit."""


def _l1_continuation(
    W: Float[Array, "2m n"],
    visible: Bool[Array, "m n"],
    M: Float[Array, "2m r"],
    S: Float[Array, "r n"],
    d: Float[Array, ""],
    sigma: Float[Array, ""],
    converged: Bool[Array, ""],
    *,
    max_steps: int,
    rtol: float,
) -> tuple[Float[Array, "2m r"], Float[Array, "r n"], Float[Array, ""], Array, Bool[Array, ""]]:
    """The L1 fit from its first smoothed fit ``(M, S)`` at kink ``d``, set from the residual
    scale ``sigma``: the kink shrunk by ``L1_SHRINK`` and the fit redone from the last, at
    most ``L1_ROUNDS`` times, while the fit's robust residual scale (floored at the tracks'
    precision) follows the kink down, i.e. fell tenfold since the scale before it.

    The smoothed minimum is off the L1 one by a multiple of the kink. On exact tracks with
    10% outliers (a Bregler sequence, k = 2, and the 40-frame cube) the inliers' fit missed
    the tracks by 6e-4 and 1.3e-3 of their RMS after the first fit, 100 times less each
    round: the first kink was set by the outliers' pull on the least-squares residuals, and
    the inliers' residuals shrink with it (to a tenth of it, not less). On noisy tracks the
    fit's residual scale is the noise's, whatever the kink, and nothing follows (a kink far
    below the noise took Levenberg--Marquardt past its step limit). Returns ``M, S``, the
    kink's total shrink (a constant), the extra steps and whether every fit converged."""
    floor = residuals.scale_floor(W, visible)

    def scale(M, S):
        return residuals.median_scale(entry_errors(W, M @ S), visible, floor)

    def falling(carry):
        *_, rounds, now, before = carry
        return (rounds < L1_ROUNDS) & (now < np.sqrt(L1_SHRINK) * before)

    def fit(carry):
        M, S, shrink, steps, converged, rounds, now, _ = carry
        shrink = shrink * L1_SHRINK
        M, S, more, ok = robust_factorize(W, visible, M, S, d * shrink, max_steps=max_steps, rtol=rtol)
        return M, S, shrink, steps + more, converged & ok, rounds + 1, scale(M, S), now

    init = (M, S, jnp.ones((), W.dtype), jnp.array(0), converged, jnp.array(0), scale(M, S), sigma)
    M, S, shrink, steps, converged, *_ = jax.lax.while_loop(falling, fit, init)
    return M, S, shrink, steps, converged


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
    solver: Literal["auto", "als", "varpro"] = "als",
) -> Factorization:
    """The general robust solver (`jaxnrsfm.objective`) from the least-squares fit:
    Huber loss with ``delta`` robust scales (the classic 1.345, 95% efficient under
    Gaussian noise), or the L1 loss when ``delta`` is ``None``. The scale is
    `classify`'s on the least-squares residuals; the reported outliers are chosen by
    `classify` too. For L1 the kink is only a smoothing, shrunk while the fit's residuals
    follow it down (`_l1_continuation`: on exact tracks, to the tracks' precision).

    Gradients: LM runs on constants; the least-squares fit (hence the scale) and the Huber
    solution are re-attached to ``W`` and ``delta`` (which may be traced) by
    `jaxnrsfm.implicit.attach`; for L1, the number of shrinks is a constant."""
    M, S, _, _ = least_squares_fit(W, visible, rank, complete=complete, max_steps=max_steps, rtol=rtol, solver=solver)
    _, model = classify(W, M @ S, visible, threshold)
    d = (L1_DELTA if delta is None else delta) * model.sigma
    constant = jax.lax.stop_gradient
    fixed = constant(W)
    budget = dict(max_steps=max_steps, rtol=max(rtol, 1e-8))
    M, S, steps, converged = robust_factorize(fixed, visible, constant(M), constant(S), constant(d), **budget)
    if delta is None:
        M, S, shrink, more, converged = _l1_continuation(
            fixed, visible, M, S, constant(d), constant(model.sigma), converged, **budget
        )
        d, steps = d * shrink, steps + more
    _, M, S = attach(W, visible, M, S, rank, d)
    inliers, _ = classify(W, M @ S, visible, threshold)
    return finish(W, inliers, M, S, _zero_translations(W), steps, converged)


def oracle(
    W: Float[Array, "2m n"],
    visible: Bool[Array, "m n"],
    outliers: Bool[Array, "m n"],
    *,
    rank: int,
    max_steps: int = 500,
    rtol: float = 1e-10,
    solver: Literal["auto", "als", "varpro"] = "als",
) -> Factorization:
    """The least-squares factorization told the true ``outliers``: the best any outlier
    rejection can do, the yardstick of the paper's comparison."""
    inliers = visible & ~outliers
    M, S, steps, converged = least_squares_fit(
        W, inliers, rank, complete=False, max_steps=max_steps, rtol=rtol, solver=solver
    )
    return finish(W, inliers, M, S, _zero_translations(W), steps, converged)
